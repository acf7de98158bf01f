"""Accuracy of the Bruneton tables against independent references (docs/multiple_scattering.md).

    python scripts/multiple_accuracy.py                      # default table sizes, CPU
    python scripts/multiple_accuracy.py --device cuda --paths 100000 --workers 16
    python scripts/multiple_accuracy.py --size small --paths 20000   # the sizes of tests/test_multiple.py

Two tables in markdown (and everything in JSON with --json):

1. single scattering from the tables (ozone off) vs the direct renderer
   (skyfit.scattering.single_scattering, Gauss-Legendre optical depth) with the same
   50-interval trapezoid rule (table-resolution error) and with a converged 128-point
   Gauss rule (total error), max |error| / peak radiance over a direction grid;
2. total radiance and orders 2-4 vs the Monte Carlo path tracer
   (skyfit.scattering.multiple_reference), the clear Earth of configs/earth.yaml,
   per sun zenith over five views: table / MC - 1 and the MC standard error.
"""
from __future__ import annotations

import argparse
import json
import multiprocessing
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from skyfit.atmosphere import load_atmosphere  # noqa: E402
from skyfit.scattering import single_scattering  # noqa: E402
from skyfit.scattering.bruneton_tables import TableSizes  # noqa: E402
from skyfit.scattering.multiple import precompute, sky_radiance  # noqa: E402
from skyfit.scattering.multiple_reference import mc_radiance  # noqa: E402
from skyfit.transmittance import make_integrator  # noqa: E402

SUN_ZENITHS = (0, 30, 60, 85, 90, 95)
WAVELENGTHS = (440.0, 550.0, 680.0)
# (altitude m, view zenith deg, azimuth from the sun deg)
VIEWS = ((0.0, 0.0, 0.0), (0.0, 45.0, 0.0), (0.0, 80.0, 180.0), (0.0, 89.0, 90.0), (2000.0, 100.0, 90.0))
SIZES = {
    "default": TableSizes(),
    "small": TableSizes(transmittance_mu=64, transmittance_r=16, irradiance_mu_s=64, irradiance_r=8,
                        scattering_r=8, scattering_mu=32, scattering_mu_s=16, scattering_nu=8),
}


def directions(view_zenith, rel_azimuth, sun_zenith):
    v, a, s = (np.radians(np.asarray(x, dtype=float)) for x in (view_zenith, rel_azimuth, sun_zenith))
    mu = np.cos(v)
    return mu, np.cos(s) + 0 * mu, mu * np.cos(s) + np.sin(v) * np.sin(s) * np.cos(a)


def single_table(sizes: TableSizes, device: str) -> list[dict]:
    atm = load_atmosphere("earth", list(WAVELENGTHS), device=device).replace(ozone_absorption=None)
    tab = precompute(atm, orders=1, sizes=sizes)
    vz = np.array([0, 15, 30, 45, 60, 70, 80, 85, 88, 89.5, 90.5, 92, 100, 120, 150, 180.0])
    az = np.array([0, 30, 60, 90, 120, 150, 180.0])
    V, A = np.meshgrid(vz, az, indexing="ij")
    gauss = make_integrator("gauss", samples=64)
    rows = []
    for sz in SUN_ZENITHS:
        mu, mu_s, nu = (torch.as_tensor(x, dtype=torch.float64, device=device) for x in directions(V, A, sz))
        for alt in (0.0, 10_000.0):
            r = torch.full_like(mu, atm.bottom_radius + alt)
            keep = mu > 0 if alt == 0 else torch.ones_like(mu, dtype=torch.bool)
            got = sky_radiance(tab, None, r, mu, mu_s, nu, ground=False)[keep]
            errs = {}
            for name, n, rule in (("same_rule", 51, "trapezoid"), ("converged", 128, "gauss")):
                ref = single_scattering(atm, r, mu, mu_s, nu, gauss, view_samples=n, rule=rule, ground=False)[keep]
                errs[name] = float(((got - ref).abs() / ref.max(0).values).max())
            rows.append({"sun_zenith": sz, "altitude": alt, **errs})
    return rows


def _mc_case(args):
    (alt, vz, az, sz, paths, seed) = args
    atm = load_atmosphere("earth", list(WAVELENGTHS))
    mu, mu_s, nu = (float(x) for x in directions(vz, az, sz))
    res = mc_radiance(atm, atm.bottom_radius + alt, mu, mu_s, nu, orders=4, paths=paths, seed=seed)
    return res.mean, res.stderr


def mc_table(tab, paths: int, workers: int) -> list[dict]:
    cases = [(alt, vz, az, sz, paths, 1000 + i) for i, (sz, (alt, vz, az)) in
             enumerate((sz, v) for sz in SUN_ZENITHS for v in VIEWS)]
    t0 = time.perf_counter()
    if workers > 1:
        with ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn")) as ex:
            mcs = list(ex.map(_mc_case, cases))
    else:
        mcs = [_mc_case(c) for c in cases]
    print(f"# Monte Carlo: {len(cases)} cases x {paths} paths in {time.perf_counter() - t0:.0f} s", flush=True)
    rows = []
    for (alt, vz, az, sz, _, _), (mean, se) in zip(cases, mcs):
        mu, mu_s, nu = (float(x) for x in directions(vz, az, sz))
        r = tab.atm.bottom_radius + alt
        cum = [sky_radiance(tab, None, r, mu, mu_s, nu, orders=k, below_mu_s_min="clamp").cpu().numpy() for k in (1, 2, 3, 4)]
        per = np.stack([cum[0]] + [cum[k] - cum[k - 1] for k in (1, 2, 3)])
        rows.append({
            "sun_zenith": sz, "altitude": alt, "view_zenith": vz, "azimuth": az,
            "mc_total": mean.sum(0).tolist(), "mc_total_se": np.sqrt((se**2).sum(0)).tolist(),
            "table_total": per.sum(0).tolist(),
            "mc_multiple": mean[1:].sum(0).tolist(), "mc_multiple_se": np.sqrt((se[1:] ** 2).sum(0)).tolist(),
            "table_multiple": per[1:].sum(0).tolist(),
            "mc_orders": mean.tolist(), "mc_orders_se": se.tolist(), "table_orders": per.tolist(),
        })
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--size", choices=sorted(SIZES), default="default")
    ap.add_argument("--irradiance-mu-s", type=int, default=None, help="override the irradiance table's mu_s texels")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--paths", type=int, default=40000)
    ap.add_argument("--workers", type=int, default=1)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    sizes = SIZES[args.size]
    if args.irradiance_mu_s:
        sizes = TableSizes(**{**sizes.__dict__, "irradiance_mu_s": args.irradiance_mu_s})
    print(f"# sizes {sizes}", flush=True)
    out = {"sizes": sizes.__dict__, "wavelengths": WAVELENGTHS}
    out["single"] = single_table(sizes, args.device)
    print("\n| sun zenith | altitude m | error/peak, same rule | error/peak, converged |\n|---|---|---|---|")
    for r in out["single"]:
        print(f"| {r['sun_zenith']} | {r['altitude']:.0f} | {r['same_rule']:.4f} | {r['converged']:.4f} |")
    atm = load_atmosphere("earth", list(WAVELENGTHS), device=args.device)
    t0 = time.perf_counter()
    tab = precompute(atm, orders=4, sizes=sizes, keep_orders=True)
    print(f"\n# precompute (orders 4, keep_orders) {time.perf_counter() - t0:.1f} s", flush=True)
    out["mc"] = mc_table(tab, args.paths, args.workers)
    print("\n| sun zenith | view (alt m, zenith, azimuth) | total: table/MC - 1 (440, 550, 680 nm) | MC se | orders 2-4: table/MC - 1 | MC se |")
    print("|---|---|---|---|---|---|")
    f = lambda v: ", ".join(f"{x:+.3f}" for x in v)  # noqa: E731
    g = lambda v: ", ".join(f"{x:.3f}" for x in v)  # noqa: E731
    for r in out["mc"]:
        tt, mt = np.array(r["table_total"]), np.array(r["mc_total"])
        tm, mm = np.array(r["table_multiple"]), np.array(r["mc_multiple"])
        print(f"| {r['sun_zenith']} | ({r['altitude']:.0f}, {r['view_zenith']:g}, {r['azimuth']:g}) | {f(tt / mt - 1)} | "
              f"{g(np.array(r['mc_total_se']) / mt)} | {f(tm / mm - 1)} | {g(np.array(r['mc_multiple_se']) / mm)} |")
    if args.json:
        args.json.write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
