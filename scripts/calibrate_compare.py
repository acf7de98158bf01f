"""Gradient fit vs Gałaj 2021's 101 x 101 grid search of Taylor's (a, b), and the calibrated spline grid and
view samples, for Earth and Mars: writes docs/integrator_calibration.md.

    .venv/bin/python scripts/calibrate_compare.py [--out docs/integrator_calibration.md] [--grid 101] [--quick] [--json-out F]

Every search of one table runs in this one process, on the same objective, one after the other, so
their wall times compare (the machine's load is printed; times on a shared machine vary by ~2x). Text after
MARKER in an existing output file (the hand-written findings) is kept.
"""
from __future__ import annotations

import argparse
import datetime
import json
import os
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from skyfit.atmosphere import load_atmosphere  # noqa: E402
from skyfit.tools.bench import machine_info  # noqa: E402
from skyfit.tools import integrator_calibration as ic  # noqa: E402
from skyfit.tools.reference import column_quad  # noqa: E402
from skyfit.transmittance.taylor import TaylorOpticalDepth  # noqa: E402

WAVELENGTHS = np.arange(400.0, 701.0, 20.0)  # the CLI's default grid


def eval_radiance(atm, rays, ref, a, b) -> tuple[float, float]:
    """(max, RMS) relative radiance error of Taylor (a, b) on the evaluation rays (reference view integral)."""
    rad = ic.render_rays(atm, rays, TaylorOpticalDepth(a, b), ic.REFERENCE_VIEW_SAMPLES, "gauss")
    rel = (rad - ref) / ref
    return float(rel.abs().max()), float(rel.pow(2).mean().sqrt())


def fmt_ab(v: list[float]) -> str:
    return f"{v[0]:.4f}" if len(set(v)) == 1 else " / ".join(f"{x:.4f}" for x in v)


def reference_check(atm, dom, ref, n: int = 200, seed: int = 0) -> dict:
    """Max relative difference of the Gauss-256 reference against Gauss-512 (all points) and scipy quad (n points)."""
    ref512 = ic.reference_columns(dom, atm.scale_heights, samples=512)
    d512 = float(((ref - ref512).abs() / ref512.clamp_min(1e-3)).max())
    rng = np.random.default_rng(seed)
    idx = rng.choice(dom.size, size=min(n, dom.size), replace=False)
    worst = 0.0
    for i in idx:
        for k, H in enumerate(atm.scale_heights.tolist()):
            q = column_quad(float(dom.r[i]), float(dom.mu[i]), float(dom.length[i]), H, atm.bottom_radius, epsrel=1e-12)
            worst = max(worst, abs(float(ref[i, k]) - q) / max(q, 1e-3))
    return {"gauss512": d512, "scipy": worst, "scipy_points": int(len(idx))}


def taylor_rows(atm, metric: str, spacing: str, grid_values, rays, rad_ref, n_d: int, n_t: int) -> tuple[list[dict], dict]:
    """Default, grid search and gradient fits (shared and per layer) on one objective."""
    if metric == "radiance":
        obj = ic.RadianceObjective(atm, ic.radiance_rays(atm, **ic.FIT_RAYS))
        info = {"points": f"{obj.rays.description['rays']} fit rays x {len(WAVELENGTHS)} wavelengths"}
    else:
        dom = ic.galaj_domain(atm.bottom_radius, atm.top_radius, n_d, n_t, spacing)
        obj = ic.TaylorObjective(atm, dom, metric)
        info = {"points": f"{dom.size} (d, t) points" + (f" x {len(WAVELENGTHS)} wavelengths" if metric == "transmittance" else "")}
        if metric == "transmittance" and spacing == "view":
            info["reference"] = reference_check(atm, dom, obj.reference)
    rows = []
    e0, l0 = obj.rms(0.45, 0.45)
    rows.append({"method": "paper default", "a": [0.45], "b": [0.45], "error": e0, "layers": l0, "seconds": None, "evaluations": None})
    g_shared, g_layer, _ = ic.grid_search_taylor(obj, grid_values)
    f_shared = ic.fit_taylor(obj, per_layer=False)
    f_layer = ic.fit_taylor(obj, per_layer=True)
    g = len(grid_values)
    rows.append({"method": f"grid {g}x{g}, shared", **_fit(g_shared)})
    rows.append({"method": "gradient, shared", **_fit(f_shared)})
    if g_layer is not None:
        rows.append({"method": f"grid {g}x{g}, per layer", **_fit(g_layer)})
    rows.append({"method": "gradient, per layer", **_fit(f_layer)})
    for row in rows:
        row["radiance"] = eval_radiance(atm, rays, rad_ref, row["a"] if len(row["a"]) > 1 else row["a"][0],
                                        row["b"] if len(row["b"]) > 1 else row["b"][0])
    return rows, info


def _fit(f: ic.TaylorFit) -> dict:
    return {"a": f.a, "b": f.b, "error": f.error, "layers": f.layer_error, "seconds": f.seconds, "evaluations": f.evaluations}


def table(rows: list[dict]) -> str:
    out = ["| search | a | b | error (RMS) | Rayleigh | Mie | wall time [s] | evaluations | radiance err. max | radiance err. RMS |",
           "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lay = r["layers"] or [None, None]
        f = lambda x, d=4: "–" if x is None else f"{x:.{d}g}"  # noqa: E731
        t = "–" if r["seconds"] is None else f"{r['seconds']:.2f}"
        ev = "–" if r["evaluations"] is None else str(r["evaluations"])
        out.append(f"| {r['method']} | {fmt_ab(r['a'])} | {fmt_ab(r['b'])} | {f(r['error'])} | {f(lay[0])} | {f(lay[1])} | {t} | {ev} | "
                   f"{r['radiance'][0]:.3g} | {r['radiance'][1]:.3g} |")
    return "\n".join(out)


def comparison(summary: dict, g: int) -> str:
    """One line per planet and objective: gradient vs grid, error and wall time."""
    out = ["## Gradient fit vs grid search, side by side\n",
           f"Same objective, same process, one after the other. Error: RMS of the objective (lower is better); "
           f"time: wall seconds of the whole search ({g}x{g} grid evaluations vs the gradient fit's evaluations, "
           f"each with a backward pass).\n",
           "| planet | metric, d spacing | default 0.45/0.45 | grid shared | gradient shared | grid per layer | gradient per layer | "
           "grid time [s] | gradient time shared / per layer [s] |",
           "|---|---|---|---|---|---|---|---|---|"]
    for key, rows in summary.items():
        if key[1] == "calibration":
            continue
        by = {r["method"].split(",")[0].split(" ")[0] + ("_l" if "per layer" in r["method"] else ""): r for r in rows}
        gl = "–" if "grid_l" not in by else f"{by['grid_l']['error']:.4g}"
        out.append(
            f"| {key[0]} | {key[1]}" + (f", {key[2]}" if key[2] else "") + f" | {by['paper']['error']:.4g} | {by['grid']['error']:.4g} | "
            f"{by['gradient']['error']:.4g} | {gl} | "
            f"{by['gradient_l']['error']:.4g} | {by['grid']['seconds']:.1f} | {by['gradient']['seconds']:.2f} / {by['gradient_l']['seconds']:.2f} |")
    return "\n".join(out) + "\n"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=str(Path(__file__).resolve().parents[1] / "docs" / "integrator_calibration.md"))
    ap.add_argument("--grid", type=int, default=101, help="grid points per axis (the paper: 101)")
    ap.add_argument("--quick", action="store_true", help="smoke run: 11x11 grids, 31x30 domains, no spline/view search")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--json-out", help="also write every row and calibration as JSON here")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    t_start = time.perf_counter()
    grid_values = torch.linspace(0.0, 1.0, 11 if args.quick else args.grid, dtype=torch.float64)
    n_d, n_t = (31, 30) if args.quick else (101, 100)
    sections = []
    summary = {}
    # warm-up (autograd and LBFGS set-up), so that the first timed fit does not pay for it
    _atm = load_atmosphere("earth", WAVELENGTHS)
    _obj = ic.TaylorObjective(_atm, ic.galaj_domain(_atm.bottom_radius, _atm.top_radius, 5, 5))
    ic.fit_taylor(_obj, adam_steps=2, lbfgs_iterations=2)
    ic.grid_search_taylor(_obj, torch.linspace(0.0, 1.0, 3, dtype=torch.float64))
    for name in ("earth", "mars"):
        atm = load_atmosphere(name, WAVELENGTHS)
        rays = ic.radiance_rays(atm)
        rad_ref = ic.radiance_reference(atm, rays)
        sec = [f"## {name.capitalize()} (configs/{name}.yaml)\n",
               f"Scale heights {atm.rayleigh_scale_height.item():.0f} m (Rayleigh), {atm.mie_scale_height.item():.0f} m (Mie); "
               f"radii {atm.bottom_radius / 1e3:.1f} / {atm.top_radius / 1e3:.1f} km; sea-level extinction at 400 / 700 nm: "
               f"Rayleigh {atm.rayleigh_scattering[0].item():.3g} / {atm.rayleigh_scattering[-1].item():.3g} 1/m, "
               f"Mie {atm.mie_extinction[0].item():.3g} / {atm.mie_extinction[-1].item():.3g} 1/m.\n"]
        for metric, spacing in (("transmittance", "view"), ("transmittance", "paper"), ("column", "view"), ("radiance", None)):
            print(f"{name}: {metric} {spacing or ''}", file=sys.stderr, flush=True)
            rows, info = taylor_rows(atm, metric, spacing, grid_values, rays, rad_ref, n_d, n_t)
            summary[(name, metric, spacing)] = rows
            title = f"### Taylor (a, b), metric `{metric}`" + (f", d spacing `{spacing}`" if spacing else "")
            sec.append(f"{title}\n\nObjective on {info['points']}.\n")
            if "reference" in info:
                rc = info["reference"]
                sec.append(f"Reference columns (Gauss-Legendre, {ic.REFERENCE_COLUMN_SAMPLES} nodes): max relative difference "
                           f"{rc['gauss512']:.1e} to 512 nodes on all points, {rc['scipy']:.1e} to scipy quad (epsrel 1e-12) on "
                           f"{rc['scipy_points']} random points x 2 layers.\n")
            sec.append(table(rows) + "\n")
        if not args.quick:
            print(f"{name}: spline grid and view samples", file=sys.stderr, flush=True)
            t0 = time.perf_counter()
            cal = ic.calibrate_integrators(atm)
            cal_s = time.perf_counter() - t0
            gauss_view = ic.select_view_samples(atm, rays, rad_ref, 0.5 * cal["tolerance"], "gauss")
            sp, vw = cal["spline"], cal["view"]
            summary[(name, "calibration")] = cal
            nb = "; ".join(f"{n}x{m}: transmittance {te:.2e}, radiance {'–' if re is None else f'{re:.2e}'}" for n, m, te, re, _ in sp["neighbours"])
            sec.append(
                "### Spline grid and view samples (`skyfit calibrate-integrator` defaults)\n\n"
                f"Tolerance {cal['tolerance']:g} relative radiance (max over {cal['rays']['rays']} rays x {len(WAVELENGTHS)} wavelengths), "
                f"half of it for each of the two settings; spline transmittance tolerance {cal['transmittance_tolerance']:g}. "
                f"Reference radiance converged to {cal['reference']['radiance_convergence']:.1e} (vs half its nodes).\n\n"
                f"* spline ({sp['kind']}): **{sp['height_points']} height x {sp['distance_points']} distance points**, "
                f"transmittance error {sp['transmittance_error']:.2e}, radiance error {sp['radiance_error']:.2e}; "
                f"one step smaller: {nb}; {len(sp['evaluated'])} grids evaluated.\n"
                f"* view samples ({vw['rule']}): **{vw['view_samples']}**, radiance error {vw['radiance_error']:.2e} "
                f"(previous candidate {vw['evaluated'][-2][0]}: {vw['evaluated'][-2][1]:.2e}); with the Gauss-Legendre rule "
                f"{gauss_view['view_samples']} ({gauss_view['radiance_error']:.2e}).\n"
                f"* both together (spline + {vw['rule']} {vw['view_samples']}): radiance error {sp.get('combined_radiance_error', float('nan')):.2e}.\n"
                f"* `calibrate-integrator` wall time {cal_s:.1f} s.\n")
        sections.append("\n".join(sec))
    total = time.perf_counter() - t_start
    mach = machine_info("cpu")
    cmd = "python scripts/calibrate_compare.py " + " ".join(sys.argv[1:])
    head = HEADER.format(
        command=cmd.strip(), date=datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
        machine=f"{mach['cpu']}, {mach['logical_cpus']} logical CPUs, torch {mach['torch']} with {args.threads} thread(s), "
                f"load average {os.getloadavg()[0]:.1f} at the end (other jobs shared the machine)",
        total=total, grid=len(grid_values), grid_m1=len(grid_values) - 1,
    )
    out = Path(args.out)
    notes = NOTES
    if out.is_file() and MARKER in out.read_text():  # keep the hand-written findings
        notes = out.read_text().split(MARKER, 1)[1]
    text = head + "\n" + comparison(summary, len(grid_values)) + "\n" + "\n".join(sections) + "\n" + MARKER + notes
    tmp = out.with_name(f".{out.name}.tmp")
    tmp.write_text(text)
    tmp.replace(out)
    if args.json_out:
        Path(args.json_out).write_text(json.dumps(
            {f"{k[0]}/{k[1]}" + (f"/{k[2]}" if len(k) > 2 and k[2] else ""): v for k, v in summary.items()}, indent=1, default=str))
    print(f"wrote {args.out} ({total:.0f} s)", file=sys.stderr)
    return 0


HEADER = """# Integrator calibration: Taylor (a, b), spline grid, view samples

`skyfit calibrate-integrator CONFIG --out integrator.json` (skyfit/tools/integrator_calibration.py) calibrates,
for one atmosphere, the three settings of Gałaj 2021 that depend on it. This page is written by

    {command}

on {date}; {machine}. Whole run {total:.0f} s.

## What is fitted, on what, with which error

**Domain.** Gałaj 2021 Sec. VI.A.2 chose a = b = 0.45 by a grid search over {{0, 0.01, ..., 1}}^2 of the
"cumulative error" of eq. 17 on "a certain number" of d in [0, R] and t in [t_min(d), t_max(d)]. We use
101 line distances d times 100 ends t (k/100 of the way from t_min to t_max, k = 1..100), each point the segment
from t_min(d) (the ground, or the tangent point P_o for d >= r) to t: the integral G of eq. 12 that eqs. 13/14
combine into every column. Two spacings of d: `paper`, uniform on [0, R_top] (for Earth only 1 line in 100 lies
above the ground, where the horizon rays and Taylor's largest errors are), and `view` (the default): half the
lines uniform in the ground zenith cosine (uniform in solid angle over a ground observer's sky), half uniform in
tangent altitude over [0, R_top - R_bottom) (horizon views and sun rays from altitude).

**Reference.** Float64 Gauss-Legendre columns with 256 nodes (checked below against 512 nodes and against
`scipy.integrate.quad`).

**Metrics** (`--metric`):

* `transmittance` (default): RMS over layers k (Rayleigh, Mie), wavelengths (400-700 nm, 20 nm) and domain
  points of exp(-beta_k c~_k) - exp(-beta_k c_k), with beta_k the atmosphere's sea-level extinction. The renderer
  only sees exp(-sum beta c): a 7x error in a Mie column that is opaque anyway, or a 1 mm column at the top, matter
  only as much as they change the transmittance; relative column error weighs them like the zenith column. Per
  layer, so that per-layer fits separate; squared mean, so that the objective is smooth and close to the paper's
  cumulative error.
* `column`: RMS of (c~ - c) / max(c, 1 mm), per layer (independent of beta; docs/accuracy.md's measure).
* `radiance`: RMS relative single-scattering radiance error over 140 fit rays (ground observer; sun zeniths
  20-88 deg, view zeniths 0-90 deg, 4 azimuths) and the wavelengths, against the same render with reference optical
  depth; gradients through the differentiable renderer. Not separable by layer: no per-layer grid (4-D).

**Searches.** Gradient: Adam (30 steps, lr 0.1) then L-BFGS (strong Wolfe) on a = sigmoid(theta_a),
b = sigmoid(theta_b) from (0.45, 0.45), so (a, b) stay in (0, 1) without clamping; the objective is divided by its
starting value. Grid: every (a, b) in {{0, 1/{grid_m1}, ..., 1}}^2 ({grid}x{grid}, Gałaj's search), the same objective,
batched; per layer one pass gives every layer's optimum because the domain metrics separate.

**Radiance columns** of the tables: max and RMS relative single-scattering radiance error of a render with the
row's (a, b) against the reference (Gauss-Legendre optical depth 128 nodes, view integral 256 nodes, float64), on
63 evaluation rays: ground observer, sun zeniths 30/60/85 deg x view zeniths 0/30/60/75/85/88/90 deg x relative
azimuths 0/90/180 deg, 16 wavelengths. These are not the radiance metric's fit rays.
"""

MARKER = "<!-- Everything below this line is written by hand; scripts/calibrate_compare.py keeps it. -->\n"
NOTES = """
## Findings

(to be written by hand)
"""

if __name__ == "__main__":
    sys.exit(main())
