"""Accuracy and speed of the Gałaj 2021 spline optical depth (docs/spline.md).

Accuracy: every spline kind, grid layout and size against scipy quad (float64,
epsrel 1e-10) on the case grid of tests/test_spline.py (radii at and near the
ground and the top and at 20 km; mu = +-1, +-0.5, +-0.1, +-1e-6, 0 and the
geometric horizon; segments to the ground or the top, half way, and 1 km),
for H = 8000 m and 1200 m. Timing: 1e5 random segments inside the atmosphere,
prepare() and one call, forward and forward+backward, beside other integrators.

Usage:
    .venv/bin/python scripts/spline_accuracy.py [--out docs/spline_table.md]
    .venv/bin/python scripts/spline_accuracy.py --timing [--device cuda] [--threads 2]
"""
from __future__ import annotations

import argparse
import math
import platform
import statistics
import time

import torch
from scipy.integrate import quad

from skyfit.transmittance import make_integrator
from skyfit.transmittance.spline import SPLINE_KINDS

R_B, R_T = 6_360_000.0, 6_420_000.0
SCALE_HEIGHTS = (8000.0, 1200.0)
F64 = torch.float64


def quad_column(r: float, mu: float, length: float, h: float) -> float:
    """The defining integral by scipy quad in float64 (same as tests/test_spline.py)."""
    if length <= 0.0:
        return 0.0

    def f(s: float) -> float:
        return math.exp(-(math.sqrt(max(r * r + 2.0 * r * mu * s + s * s, 0.0)) - R_B) / h)

    pts = [p for p in (-r * mu,) if 0.0 < p < length]
    if pts:
        w = math.sqrt(2.0 * r * h)
        pts += [p for p in (pts[0] - 3 * w, pts[0] + 3 * w) if 0.0 < p < length]
    return quad(f, 0.0, length, epsrel=1e-10, epsabs=0.0, limit=1000, points=sorted(pts) or None)[0]


def length_to_boundary(r: float, mu: float) -> float:
    disc_b = r * r * (mu * mu - 1.0) + R_B * R_B
    if mu < 0.0 and disc_b >= 0.0:
        return max(-r * mu - math.sqrt(disc_b), 0.0)
    return max(-r * mu + math.sqrt(max(r * r * (mu * mu - 1.0) + R_T * R_T, 0.0)), 0.0)


def cases() -> list[tuple[float, float, float]]:
    radii = (R_B, R_B + 1.0, R_B + 1000.0, R_B + 20_000.0, R_T - 1.0, R_T)
    mus = (1.0, 0.5, 0.1, 1e-6, 0.0, -1e-6, -0.1, -0.5, -1.0)
    out = []
    for r in radii:
        mu_h = -math.sqrt(max(1.0 - (R_B / r) ** 2, 0.0))
        for mu in mus + ((mu_h, mu_h + 1e-6) if mu_h < 0 else ()):
            full = length_to_boundary(r, mu)
            for length in {full, 0.5 * full, min(1000.0, full)}:
                out.append((r, mu, length))
    return out


CONFIGS: list[tuple[str, dict]] = (
    [(f"smooth/log, {k}", {"kind": k}) for k in SPLINE_KINDS]
    + [(f"smooth/values, {k}", {"kind": k, "space": "values"}) for k in ("natural_cubic", "hermite")]
    + [("smooth/log, natural_cubic, linear rows", {"distance_interp": "linear"})]
    + [(f"paper (values, bilinear), {k}", {"kind": k, "grid": "paper", "space": "values", "distance_interp": "linear"}) for k in ("natural_cubic", "hermite")]
    + [("paper grid, log space, natural_cubic", {"grid": "paper", "distance_interp": "linear"})]
)
SIZES = ((20, 10), (50, 20), (100, 40), (200, 80))


def accuracy_table() -> str:
    cs = cases()
    r, mu, length = (torch.tensor(v, dtype=F64) for v in zip(*cs))
    ref = torch.tensor([[quad_column(*c, h) for h in SCALE_HEIGHTS] for c in cs], dtype=F64)
    h = torch.tensor(SCALE_HEIGHTS, dtype=F64)
    nz = ref > 0
    lines = [
        f"{len(cs)} segments x 2 layers; relative error |spline - quad| / quad, zero-length segments excluded (exactly 0).",
        "",
        "| layout, kind | N x M | max H=8 km | median H=8 km | max H=1.2 km | median H=1.2 km | worst case (H=1.2 km) |",
        "|---|---|---|---|---|---|---|",
    ]
    for label, kw in CONFIGS:
        for n, m in SIZES:
            integ = make_integrator("spline", height_points=n, distance_points=m, **kw)
            col = integ.prepare(h, R_B, R_T)(r, mu, length)
            err = (col - ref).abs() / torch.where(nz, ref, torch.ones_like(ref))
            cells = []
            for k in range(2):
                e = err[:, k][nz[:, k]]
                cells += [f"{float(e.max()):.1e}", f"{float(e.median()):.1e}"]
            wr, wmu, wl = cs[int(torch.where(nz[:, 1], err[:, 1], torch.zeros_like(err[:, 1])).argmax())]
            worst = f"alt {wr - R_B:.0f} m, mu {wmu:.3g}, L {wl:.0f} m"
            lines.append(f"| {label} | {n} x {m} | {cells[0]} | {cells[1]} | {cells[2]} | {cells[3]} | {worst} |")
    return "\n".join(lines)


def _segments(n: int, device: str, dtype: torch.dtype, seed: int = 0):
    """Random observers (altitude^2-weighted), directions and segment lengths inside the atmosphere."""
    from skyfit.geometry import atmosphere_segment

    g = torch.Generator().manual_seed(seed)
    r = R_B + (R_T - R_B) * torch.rand(n, generator=g, dtype=F64) ** 2
    mu = 2.0 * torch.rand(n, generator=g, dtype=F64) - 1.0
    _, end, _ = atmosphere_segment(r, mu, R_B, R_T)
    length = end * torch.rand(n, generator=g, dtype=F64)
    return (x.to(device=device, dtype=dtype) for x in (r, mu, length))


def _timed(fn, device: str, repeats: int) -> float:
    """Median wall time of ``fn()`` in seconds (CUDA synchronised)."""
    ts = []
    for _ in range(repeats):
        if device.startswith("cuda"):
            torch.cuda.synchronize()
        t0 = time.perf_counter()
        fn()
        if device.startswith("cuda"):
            torch.cuda.synchronize()
        ts.append(time.perf_counter() - t0)
    return statistics.median(ts)


def timing_table(device: str, n: int = 100_000, repeats: int = 7) -> str:
    rows = [("spline", {}), ("spline", {"kind": "hermite"}), ("spline", {"kind": "akima"}), ("spline", {"space": "values"}),
            ("spline", {"grid": "paper", "space": "values", "distance_interp": "linear"}),
            ("taylor", {}), ("gauss", {"samples": 32}), ("trapezoid", {"samples": 64})]
    lines = [
        f"{n} segments, device {device}" + (f" ({torch.cuda.get_device_name()})" if device.startswith("cuda") else f" ({platform.processor() or platform.machine()}, {torch.get_num_threads()} threads)")
        + f", torch {torch.__version__}; median of {repeats}.",
        "",
        "| integrator | settings | dtype | prepare [ms] | forward [ms] | forward+backward [ms] |",
        "|---|---|---|---|---|---|",
    ]
    for dtype in (torch.float32, torch.float64):
        r, mu, length = _segments(n, device, dtype)
        for name, kw in rows:
            integ = make_integrator(name, **kw)
            h = torch.tensor(SCALE_HEIGHTS, dtype=dtype, device=device)
            t_prep = _timed(lambda: integ.prepare(h, R_B, R_T), device, repeats)
            fn = integ.prepare(h, R_B, R_T)
            fn(r, mu, length)  # warm-up (tables cast, kernels compiled)
            t_fwd = _timed(lambda: fn(r, mu, length), device, repeats)
            hg = h.clone().requires_grad_(True)
            rg = r.clone().requires_grad_(True)

            def fwd_bwd():
                integ.prepare(hg, R_B, R_T)(rg, mu, length).sum().backward()

            fwd_bwd()
            t_bwd = _timed(fwd_bwd, device, repeats)
            label = ", ".join(f"{k}={v}" for k, v in kw.items()) or "defaults"
            lines.append(f"| {name} | {label} | {str(dtype).split('.')[-1]} | {t_prep * 1e3:.1f} | {t_fwd * 1e3:.1f} | {t_bwd * 1e3:.1f} |")
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--timing", action="store_true", help="time 1e5 segments instead of the accuracy table")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--out", default=None, help="also write the table to this file")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    table = timing_table(args.device, repeats=args.repeats) if args.timing else accuracy_table()
    print(table)
    if args.out:
        with open(args.out, "w") as fh:
            fh.write(table + "\n")


if __name__ == "__main__":
    main()
