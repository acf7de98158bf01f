"""`skyfit render`'s defaults against the converged radiance (docs/accuracy.md, "Render defaults").

For every shipped config, sun zenith and observer altitude, renders a set of directions above 5°
elevation (elevations 5-90°, azimuths 0-180° from the sun's, and 1-3° from the sun) the way
``skyfit render`` does without flags (``cli._render_image`` -> ``render_fisheye`` ->
``render.sky.render_vectors`` -> ``scattering.single_scattering``; here ``render_directions``, the
same call below the camera), float32, and compares every pixel and wavelength with a float64
reference: Gauss-Legendre optical depth with 128 nodes and a 512-node Gauss-Legendre view integral,
uniform in distance. The reference's own error is bounded by halving its nodes (64, 256).

Rows: the old defaults (taylor, 32-sample trapezoid, uniform), the new ones
(:data:`skyfit.render.auto.RENDER_DEFAULTS`, also ``skyfit.render``'s now) and ``accuracy=ACCURATE``
(``skyfit.render``'s former default: the cheapest setting measured on the trade study's Earth scenes
with relative RMS error <= 1e-4, :data:`skyfit.api.ACCURATE`). Error: the largest
``|L - L_ref| / L_ref`` over pixels and wavelengths; with the sun more than 3° below the horizon the
shadowed part of the sky is near 0, so there the denominator is ``max(L_ref, 1e-3 max L_ref)``
(noted in the table).

Time: process CPU seconds of a 256 x 256 fisheye (the CLI's default size and wavelengths), old and
new defaults side by side (best of ``--repeat``), one thread. Trade-study row: both defaults on the
trade study's 8 scenes, 40 x 40 sky, 8 wavelengths, earth without ozone, against its reference
(skyfit.tools.trade; docs/benchmarks.md section 5).

    OMP_NUM_THREADS=1 .venv/bin/python scripts/render_defaults_check.py --out docs/render_defaults.json
"""
from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

import numpy as np
import torch

from skyfit.api import ACCURATE
from skyfit.api import render as api_render
from skyfit.atmosphere import DEFAULT_WAVELENGTHS, atmosphere_from_config, parse_wavelengths, read_config
from skyfit.camera import FisheyeCamera, render_fisheye
from skyfit.geometry import zenith_azimuth_to_enu
from skyfit.render import spectral_to_xyz_matrix
from skyfit.render.auto import RENDER_DEFAULTS
from skyfit.render.sky import render_vectors
from skyfit.tools.trade import FULL_TRADE_PLAN, TRADE_SCENES, image_errors
from skyfit.transmittance import parse_integrator

CONFIGS = ("earth", "earth_hazy", "earth_clear_sky_eval", "mars", "kider")
SUN_ZENITHS = (0.0, 30.0, 60.0, 80.0, 89.0, 90.0, 91.0, 93.0, 94.0, 96.0)
ALTITUDES = (0.0, 10000.0)
OLD = {"integrator": "taylor", "view_samples": 32, "rule": "trapezoid", "spacing": "uniform"}
NEW = dict(RENDER_DEFAULTS)
REFERENCE = {"integrator": "gauss:samples=128", "view_samples": 512, "rule": "gauss", "spacing": "uniform"}
HALF = {"integrator": "gauss:samples=64", "view_samples": 256, "rule": "gauss", "spacing": "uniform"}
FLOOR_BELOW_DEG = 93.0
"""Sun zeniths above this use the floored relative error (the sky's shadowed part is near 0). [deg]"""


def atmosphere(name: str, dtype) -> "Atmosphere":  # noqa: F821
    cfg = dict(read_config(name)[0])
    cfg.pop("fit", None)  # kider: the fit's settings, not part of the atmosphere
    return atmosphere_from_config(cfg, parse_wavelengths(DEFAULT_WAVELENGTHS), dtype)


def directions(sun_zenith_deg: float, sun_azimuth_deg: float = 180.0) -> torch.Tensor:
    """Unit view vectors above 5° elevation: a grid in elevation x azimuth from the sun, and next to the sun."""
    z, a = [], []
    for e in (5, 6, 8, 10, 15, 20, 30, 45, 60, 75, 90):
        for d in (0, 5, 15, 30, 60, 90, 120, 150, 180):
            z.append(90.0 - e)
            a.append(sun_azimuth_deg + d)
    for dz in (-3.0, -1.0, 1.0, 3.0):  # 1-3° from the sun, above 5° elevation
        if sun_zenith_deg + dz <= 85.0:
            z.append(max(sun_zenith_deg + dz, 0.0))
            a.append(sun_azimuth_deg)
    return zenith_azimuth_to_enu(torch.deg2rad(torch.tensor(z, dtype=torch.float64)),
                                 torch.deg2rad(torch.tensor(a, dtype=torch.float64)))


def sun_vector(sun_zenith_deg: float, sun_azimuth_deg: float = 180.0) -> torch.Tensor:
    return zenith_azimuth_to_enu(torch.tensor(math.radians(sun_zenith_deg), dtype=torch.float64),
                                 torch.tensor(math.radians(sun_azimuth_deg), dtype=torch.float64))


def render(atm, setting: dict, view, sun, altitude: float) -> torch.Tensor:
    """What ``skyfit render`` computes for these directions with ``setting``, as float64 (N, W)."""
    with torch.no_grad():
        out = render_vectors(atm, view.to(atm.dtype), sun.to(atm.dtype), parse_integrator(setting["integrator"]), altitude,
                             view_samples=setting["view_samples"], rule=setting["rule"], spacing=setting["spacing"])
    return out.double()


def max_relative_error(value: torch.Tensor, ref: torch.Tensor, floor: bool) -> float:
    den = ref.abs()
    if floor:
        den = torch.maximum(den, 1e-3 * den.amax(0))
    err = (value - ref).abs() / den
    err = torch.where((value == 0) & (ref == 0), torch.zeros_like(err), err)
    return float(err.max())


def measure_scene(name: str, sun_zenith: float, altitude: float, api: bool) -> dict:
    a64, a32 = atmosphere(name, torch.float64), atmosphere(name, torch.float32)
    view, sun = directions(sun_zenith), sun_vector(sun_zenith)
    ref = render(a64, REFERENCE, view, sun, altitude)
    half = render(a64, HALF, view, sun, altitude)
    floor = sun_zenith > FLOOR_BELOW_DEG
    row = {"config": name, "sun_zenith_deg": sun_zenith, "altitude_m": altitude, "directions": int(view.shape[0]),
           "floored": floor, "reference_half_nodes": max_relative_error(half, ref, floor),
           "old": max_relative_error(render(a32, OLD, view, sun, altitude), ref, floor),
           "new": max_relative_error(render(a32, NEW, view, sun, altitude), ref, floor)}
    if api and sun_zenith <= 98.0:
        with torch.no_grad():
            sky = api_render(a32, view.float(), sun.float(), altitude=altitude, accuracy=ACCURATE)
        row["accurate_1e-4"] = max_relative_error(sky.radiance.double(), ref, floor)
        row["accurate_1e-4_setting"] = {k: sky.model[k] for k in ("name", "samples", "view_samples", "rule") if k in sky.model}
    return row


def time_defaults(size: int, repeat: int) -> dict:
    """Process CPU seconds of one size x size fisheye (earth, sun zenith 30°), old and new defaults, side by side."""
    atm = atmosphere("earth", torch.float32)
    cam = FisheyeCamera(size)
    best = {"old": math.inf, "new": math.inf}
    for _ in range(repeat):
        for key, st in (("old", OLD), ("new", NEW)):
            t0 = time.process_time()
            with torch.no_grad():
                render_fisheye(atm, cam, 30.0, 180.0, parse_integrator(st["integrator"]), view_samples=st["view_samples"],
                               rule=st["rule"], spacing=st["spacing"])
            best[key] = min(best[key], time.process_time() - t0)
    return {"size": size, "old_cpu_s": best["old"], "new_cpu_s": best["new"], "ratio": best["new"] / best["old"]}


def trade_row() -> dict:
    """Both defaults on the trade study's scenes, sky, wavelengths, atmosphere and reference (docs/benchmarks.md §5)."""
    plan = FULL_TRADE_PLAN
    lam = np.asarray(plan.wavelengths_nm, float)
    xyz = spectral_to_xyz_matrix(torch.as_tensor(lam, dtype=torch.float64)).numpy()
    atms = {dt: atmosphere_from_config(read_config("earth")[0], lam, dt).replace(ozone_absorption=None)
            for dt in (torch.float32, torch.float64)}
    cam = FisheyeCamera(plan.size)
    ref_setting = {"integrator": f"gauss:samples={plan.reference_light}", "view_samples": plan.reference_view,
                   "rule": "gauss", "spacing": "uniform"}
    out = {}
    for key, st in (("old", OLD), ("new", NEW)):
        errs, cost = [], []
        for sc in TRADE_SCENES:
            def img(setting, atm):
                with torch.no_grad():
                    im = render_fisheye(atm, cam, sc.sun_zenith_deg, sc.sun_azimuth_deg, parse_integrator(setting["integrator"]),
                                        altitude=sc.altitude_m, view_samples=setting["view_samples"], rule=setting["rule"],
                                        spacing=setting["spacing"])
                return im.spectral[im.valid].double().numpy()
            ref = img(ref_setting, atms[torch.float64])
            t0 = time.process_time()
            val = img(st, atms[torch.float32])
            cost.append(time.process_time() - t0)
            errs.append(image_errors(ref, val, xyz))
        out[key] = {"cpu_ms": 1e3 * float(np.mean(cost)), "rel": float(np.mean([e["rel_rmse"] for e in errs])),
                    "mean_delta_e": float(np.mean([e["mean_delta_e"] for e in errs])),
                    "max_delta_e": float(np.max([e["mean_delta_e"] for e in errs]))}
    return out


def table(rows: list[dict]) -> str:
    lines = ["| config | observer | sun zenith | old max error | new max error | ACCURATE max error | reference (half nodes) |",
             "|---|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        f = " ¹" if r["floored"] else ""
        lines.append(f"| {r['config']} | {r['altitude_m'] / 1e3:g} km | {r['sun_zenith_deg']:g}° | {r['old']:.3g}{f} | "
                     f"{r['new']:.2g}{f} | {r.get('accurate_1e-4', math.nan):.2g}{f} | {r['reference_half_nodes']:.1g} |")
    return "\n".join(lines)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", type=Path, help="JSON of every measurement")
    p.add_argument("--configs", default=",".join(CONFIGS))
    p.add_argument("--sun-zeniths", default=",".join(f"{z:g}" for z in SUN_ZENITHS))
    p.add_argument("--altitudes", default=",".join(f"{h:g}" for h in ALTITUDES))
    p.add_argument("--size", type=int, default=256, help="fisheye size of the timing [px]")
    p.add_argument("--repeat", type=int, default=3)
    p.add_argument("--no-api", action="store_true", help="skip skyfit.render(accuracy=ACCURATE)")
    p.add_argument("--no-trade", action="store_true", help="skip the trade-study row")
    args = p.parse_args()
    torch.set_num_threads(1)
    rows = []
    for name in args.configs.split(","):
        for h in (float(v) for v in args.altitudes.split(",")):
            for z in (float(v) for v in args.sun_zeniths.split(",")):
                rows.append(measure_scene(name, z, h, not args.no_api))
                print(json.dumps(rows[-1]), flush=True)
    timing = time_defaults(args.size, args.repeat)
    trade = None if args.no_trade else trade_row()
    print(table(rows))
    print(json.dumps({"timing": timing, "trade": trade}, indent=1))
    if args.out:
        args.out.write_text(json.dumps({"old": OLD, "new": NEW, "reference": REFERENCE, "rows": rows, "timing": timing,
                                        "trade": trade}, indent=1))


if __name__ == "__main__":
    main()
