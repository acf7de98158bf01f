"""Ozone in the direct renderer: its effect on the zenith sky, the closed form's accuracy, its cost.

Writes the three tables of docs/ozone.md (markdown on stdout; ``--json FILE`` also saves them):

1. zenith radiance and colour from the ground with vs without the config's ozone (Earth,
   300 DU tent 10-25-40 km), sun zenith 0/60/85/90/95 deg, 380-780 nm every 10 nm: single
   scattering (direct renderer) and single + Hillaire 2020 multiple scattering;
2. the closed-form column (skyfit.transmittance.ozone_column) against scipy quad in float64
   on random and special rays, float64 and float32;
3. the renderer's cost with and without ozone, side by side (interleaved repeats, process
   CPU time, best of ``--repeats``), for three integrators.

    .venv/bin/python scripts/ozone_effect.py [--threads 1] [--size 48] [--rays 1500] [--json out.json]
"""
from __future__ import annotations

import argparse
import json
import math
import os
import time

import numpy as np
import torch
from scipy import integrate
from tqdm import tqdm

from skyfit.atmosphere import load_atmosphere
from skyfit.camera import FisheyeCamera, render_fisheye
from skyfit.render.colour import delta_e_1976, spectral_to_xyz
from skyfit.scattering import single_scattering
from skyfit.scattering.hillaire import hillaire_lut, hillaire_sky_radiance
from skyfit.transmittance import make_integrator, ozone_column

R, R_TOP = 6_360_000.0, 6_420_000.0
SUN_ZENITHS = (0.0, 60.0, 85.0, 90.0, 95.0)


def effect_table(bar) -> list[dict]:
    lam = np.arange(380.0, 781.0, 10.0)
    atm = load_atmosphere("earth", lam)
    no = atm.replace(ozone_absorption=None)
    integ = make_integrator("gauss", samples=32)
    luts = {id(a): hillaire_lut(a, size=(32, 32), directions=64, samples=20) for a in (atm, no)}
    i600 = int(np.argmin(np.abs(lam - 600.0)))
    rows = []
    one = torch.ones(1, dtype=torch.float64)
    for sz in SUN_ZENITHS:
        mu_s = one * math.cos(math.radians(sz))
        args = (torch.full((1,), R, dtype=torch.float64), one, mu_s, mu_s)  # zenith view: nu = mu_s
        row = {"sun_zenith_deg": sz}
        for kind in ("single", "single+hillaire"):
            out = {}
            for name, a in (("ozone", atm), ("none", no)):
                if kind == "single":
                    L = single_scattering(a, *args, integ, view_samples=128, rule="gauss")
                else:
                    L = hillaire_sky_radiance(a, *args, integ, view_samples=128, lut=luts[id(a)], rule="gauss")
                out[name] = (L[0], spectral_to_xyz(L, a.wavelengths)[0].numpy())
            xyz_o, xyz_n = out["ozone"][1], out["none"][1]
            xy = lambda v: (v[0] / v.sum(), v[1] / v.sum())  # noqa: E731
            row[kind] = {
                "L600_ratio": float(out["ozone"][0][i600] / out["none"][0][i600]),
                "Y_ratio": float(xyz_o[1] / xyz_n[1]),
                "xy_ozone": [round(float(v), 4) for v in xy(xyz_o)],
                "xy_none": [round(float(v), 4) for v in xy(xyz_n)],
                # CIELAB (D65) with the ozone-free sky's luminance as white (its L* = 100)
                "delta_e_1976": float(delta_e_1976(xyz_o, xyz_n, float(xyz_n[1]))),
                "Y_none_cd_m2": float(xyz_n[1]),
            }
        rows.append(row)
        bar.update()
    return rows


def _column_quad(r, mu, length, layer=(10e3, 25e3, 40e3)):
    lo, pk, hi = layer
    tent = lambda h: max(0.0, min((h - lo) / (pk - lo), (hi - h) / (hi - pk), 1.0))  # noqa: E731
    b = r * mu
    pts = [-b] if 0 < -b < length else []
    for h in layer:
        disc = b * b - (r * r - (R + h) ** 2)
        if disc >= 0:
            pts += [t for t in (-b - math.sqrt(disc), -b + math.sqrt(disc)) if 0 < t < length]
    f = lambda t: tent(math.sqrt(max(r * r + 2 * b * t + t * t, 0.0)) - R)  # noqa: E731
    return integrate.quad(f, 0.0, length, points=sorted(pts) or None, epsabs=1e-9, epsrel=1e-13, limit=500)[0]


def accuracy_table(n_rays: int, bar) -> dict:
    rng = np.random.default_rng(1)
    r = R + rng.uniform(0.0, 60e3, n_rays)
    mu = np.concatenate([rng.uniform(-1, 1, n_rays - n_rays // 4), rng.uniform(-0.05, 0.05, n_rays // 4)])  # grazing too
    L = np.empty(n_rays)
    for i in range(n_rays):
        bb, cc = r[i] * mu[i], r[i] ** 2 - R * R
        dg = bb * bb - cc
        L[i] = -bb - math.sqrt(dg) if mu[i] < 0 and dg >= 0 else -bb + math.sqrt(bb * bb - (r[i] ** 2 - R_TOP**2))
        L[i] *= rng.choice([1.0, rng.uniform(0, 1)])  # to the boundary (ground or top) or partway
    ref = np.array([_column_quad(*c) for c in zip(r, mu, L)])
    bar.update()
    out = {"rays": n_rays}
    for dt in (torch.float64, torch.float32):
        rr, mm, ll = (np.asarray(v, dtype=np.float32 if dt == torch.float32 else np.float64) for v in (r, mu, L))
        # reference at the inputs the dtype can represent (float32 rounds r to ~0.5 m)
        ref_dt = ref if dt == torch.float64 else np.array([_column_quad(float(a), float(b), float(c)) for a, b, c in zip(rr, mm, ll)])
        got = ozone_column(*(torch.from_numpy(v) for v in (rr, mm, ll)), R, (10e3, 25e3, 40e3)).double().numpy()
        err = np.abs(got - ref_dt)
        big = ref_dt >= 100.0
        out[str(dt).split(".")[-1]] = {"max_abs_m": float(err.max()), "max_rel_ge_100m": float((err[big] / ref_dt[big]).max()),
                                       "max_column_m": float(ref_dt.max()), "rays_ge_100m": int(big.sum())}
        bar.update()
    return out


def cost_table(size: int, repeats: int, bar) -> list[dict]:
    rows = []
    for wl in ((440.0, 550.0, 680.0), tuple(np.arange(380.0, 781.0, 10.0))):
        atm = load_atmosphere("earth", list(wl))
        no = atm.replace(ozone_absorption=None)
        for name, kw in (("gauss", {"samples": 16}), ("chapman", {}), ("taylor", {})):
            integ = make_integrator(name, **kw)
            best = {"ozone": math.inf, "none": math.inf}
            for _ in range(repeats):
                for key, a in (("ozone", atm), ("none", no)):  # interleaved: same load for both
                    t = time.process_time()
                    render_fisheye(a, FisheyeCamera(size), 60.0, 0.0, integ, view_samples=32, rule="gauss")
                    best[key] = min(best[key], time.process_time() - t)
            rows.append({"integrator": name, "W": len(wl), "pixels": int(FisheyeCamera(size).pixel_vectors(torch.float64)[1].sum()),
                         "cpu_s_ozone": best["ozone"], "cpu_s_none": best["none"], "ratio": best["ozone"] / best["none"]})
            bar.update()
    return rows


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--size", type=int, default=48, help="fisheye size of the cost renders [px]")
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--rays", type=int, default=1500, help="random rays of the accuracy table")
    p.add_argument("--json", help="also write the tables to this JSON file")
    a = p.parse_args()
    torch.set_num_threads(a.threads)
    bar = tqdm(total=len(SUN_ZENITHS) + 3 + 6, desc="ozone", file=None, leave=False)
    eff = effect_table(bar)
    acc = accuracy_table(a.rays, bar)
    cost = cost_table(a.size, a.repeats, bar)
    bar.close()

    print("## Zenith sky from the ground, with vs without ozone (Earth, 300 DU)\n")
    print("| sun zenith | model | L(600 nm) ratio | Y ratio | xy with ozone | xy without | ΔE76 | Y without [cd/m²] |")
    print("|---|---|---|---|---|---|---|---|")
    for row in eff:
        for kind in ("single", "single+hillaire"):
            d = row[kind]
            print(f"| {row['sun_zenith_deg']:g} | {kind} | {d['L600_ratio']:.3f} | {d['Y_ratio']:.3f} | "
                  f"({d['xy_ozone'][0]:.4f}, {d['xy_ozone'][1]:.4f}) | ({d['xy_none'][0]:.4f}, {d['xy_none'][1]:.4f}) | "
                  f"{d['delta_e_1976']:.1f} | {d['Y_none_cd_m2']:.4g} |")
    print(f"\n## Closed form vs scipy quad ({acc['rays']} rays)\n")
    print("| dtype | max abs error [m] | max relative error, columns >= 100 m | rays >= 100 m | largest column [m] |")
    print("|---|---|---|---|---|")
    for dt in ("float64", "float32"):
        d = acc[dt]
        print(f"| {dt} | {d['max_abs_m']:.2e} | {d['max_rel_ge_100m']:.2e} | {d['rays_ge_100m']} | {d['max_column_m']:.0f} |")
    print(f"\n## Renderer cost, {a.size}x{a.size} fisheye, 32 Gauss view samples, process CPU s (best of {a.repeats})\n")
    print("| integrator | W | pixels | with ozone [s] | without [s] | ratio |")
    print("|---|---|---|---|---|---|")
    for row in cost:
        print(f"| {row['integrator']} | {row['W']} | {row['pixels']} | {row['cpu_s_ozone']:.3f} | {row['cpu_s_none']:.3f} | {row['ratio']:.2f} |")
    if a.json:
        tmp = a.json + ".tmp"
        with open(tmp, "w") as f:
            json.dump({"effect": eff, "accuracy": acc, "cost": cost, "threads": a.threads}, f, indent=1)
        os.replace(tmp, a.json)


if __name__ == "__main__":
    main()
