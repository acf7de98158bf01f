"""Each optical-depth integrator against scipy quad on the docs/accuracy.md grid.

Usage: .venv/bin/python scripts/accuracy_table.py [--out docs/accuracy.md]
"""
from __future__ import annotations

import argparse
import math
import platform
import sys
import time

import numpy as np
import torch

from skyfit.tools.reference import accuracy_cases, column_quad, relative_column_error
from skyfit.transmittance import make_integrator

BOTTOM, TOP = 6_360_000.0, 6_420_000.0
SCALE_HEIGHTS = (8000.0, 1200.0)

SETTINGS = [
    ("trapezoid", {"samples": 16}),
    ("trapezoid", {"samples": 64}),
    ("trapezoid", {"samples": 256}),
    ("trapezoid", {"samples": 1024}),
    ("midpoint", {"samples": 64}),
    ("midpoint", {"samples": 256}),
    ("simpson", {"samples": 65}),
    ("simpson", {"samples": 257}),
    ("gauss", {"samples": 8}),
    ("gauss", {"samples": 32}),
    ("gauss", {"samples": 128}),
    ("taylor", {}),
    ("spline", {"grid": "paper", "space": "values", "distance_interp": "linear"}),
    ("spline", {}),
    ("spline", {"kind": "linear"}),
    ("spline", {"kind": "catmull_rom"}),
    ("spline", {"kind": "akima"}),
    ("spline", {"kind": "monotone_hermite"}),
    ("spline", {"height_points": 200, "distance_points": 80}),
    ("bruneton_lut", {}),
    ("bruneton_lut", {"mu_size": 1024, "r_size": 256}),
    ("chapman", {}),
]


def evaluate(name, settings, cases, refs, dtype=torch.float64):
    integ = make_integrator(name, **settings)
    r = torch.tensor([c[0] for c in cases], dtype=dtype)
    mu = torch.tensor([c[1] for c in cases], dtype=dtype)
    L = torch.tensor([c[2] for c in cases], dtype=dtype)
    H = torch.tensor(SCALE_HEIGHTS, dtype=dtype)
    t0 = time.perf_counter()
    col = integ.prepare(H, BOTTOM, TOP)(r, mu, L).double().numpy()
    dt = time.perf_counter() - t0
    rel = relative_column_error(col, refs)
    return rel, dt


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("--out", default="docs/accuracy.md")
    args = ap.parse_args(argv)
    torch.set_num_threads(2)
    cases = accuracy_cases(BOTTOM, TOP)
    refs = np.array([[column_quad(r, mu, L, H, BOTTOM) for H in SCALE_HEIGHTS] for r, mu, L, _ in cases])
    rows = []
    worst = {}
    for name, settings in SETTINGS:
        try:
            rel, dt = evaluate(name, settings, cases, refs)
            try:
                rel32 = evaluate(name, settings, cases, refs, torch.float32)[0]
            except RuntimeError as e:  # reported in the table, not hidden
                print(f"{name} {settings} float32: {e}", file=sys.stderr)
                rel32 = np.full_like(rel, np.nan)
        except (ModuleNotFoundError, AttributeError) as e:
            print(f"skip {name}: {e}", file=sys.stderr)
            continue
        except (ValueError, RuntimeError) as e:  # a refusal, or a failure we report rather than hide
            rows.append((name, settings, None, None, None, None, None, f"{type(e).__name__}: {str(e).splitlines()[0]}"))
            continue
        k = int(np.nanargmax(rel.max(1)))
        worst[(name, str(settings))] = cases[k][3]
        rows.append((name, settings, rel[:, 0].max(), np.median(rel[:, 0]), rel[:, 1].max(), np.median(rel[:, 1]), np.max(rel32), cases[k][3]))
        print(name, settings, f"{rel.max():.2e}", file=sys.stderr)
    lines = [
        "# Optical-depth accuracy",
        "",
        "Each integrator's column `int exp(-h/H) ds` against `scipy.integrate.quad` (float64, epsrel 1e-10,",
        "break points at the tangent point) on a fixed grid of "
        f"{len(cases)} segments: observer radius ground, ground + 1 m, ground + 1 km, top - 1 m, top;",
        "mu straight up and down, 0.5, 0.1, -0.1, the horizontal 0 and +-1e-6 around it, the geometric horizon",
        "mu_h = -sqrt(1 - (R/r)^2) and mu_h +- 1e-6; each segment to the ground or the top, and again half way.",
        f"Earth radii {BOTTOM:.0f} / {TOP:.0f} m; Rayleigh H = 8000 m, Mie H = 1200 m. Relative error |c - ref| / max(ref, 1 mm)",
        "(a 1 mm column error changes transmittance by < 1e-5 for beta <= 1e-2 /m; see skyfit.tools.reference).",
        "",
        f"Made by `.venv/bin/python scripts/accuracy_table.py` on {platform.processor() or platform.machine()}, torch {torch.__version__}.",
        "",
        "| method | settings | max rel. err H=8 km | median H=8 km | max rel. err H=1.2 km | median H=1.2 km | max float32 | worst case |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for name, settings, m8, d8, m1, d1, m32, note in rows:
        s = ", ".join(f"{k}={v}" for k, v in settings.items()) or "defaults"
        if m8 is None:
            lines.append(f"| {name} | {s} | failed | | | | | {note} |")
        else:
            f32 = "fails" if np.isnan(m32) else f"{m32:.2e}"
            lines.append(f"| {name} | {s} | {m8:.2e} | {d8:.2e} | {m1:.2e} | {d1:.2e} | {f32} | {note} |")
    lines += [
        "",
        "Notes:",
        "",
        "- `taylor` is Gałaj 2021 eq. 17 with a = b = 0.45: exact for vertical rays, a few percent for the",
        "  Rayleigh layer near the horizon; for the Mie layer (H = 1.2 km) at grazing incidence it is out of",
        "  its regime and the exact bound L exp(-h_low/H) caps it (see skyfit/transmittance/taylor.py).",
        "  `skyfit calibrate-integrator` fits (a, b) per atmosphere and layer (docs/integrator_calibration.md).",
        "- `spline` with `grid=paper, space=values, distance_interp=linear` is the paper's layout taken literally;",
        "  the default is the corrected variant documented in docs/spline.md.",
        "- `bruneton_lut` takes columns as differences of two table lookups (Bruneton 2017 GetTransmittance), so",
        "  short segments near the ground (1 m here) have large *relative* error while the optical-depth error",
        "  stays below ~1e-3 of the larger column (docs/lut_chapman_fog.md).",
        "- `height_fog` (Ishiyama 2018) is flat-Earth and refuses most of this grid; its accuracy inside its",
        "  regime is in docs/lut_chapman_fog.md.",
        "",
    ]
    with open(args.out, "w") as f:
        f.write("\n".join(lines))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
