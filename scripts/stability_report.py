"""Stability at the extremes (issue #7 part 4): writes docs/stability.md.

Runs every optical-depth integrator (as single scattering), Hillaire 2020's
multiple-scattering LUT and Bruneton's tables over the extreme grid of
:mod:`skyfit.tools.stability`, in float64 and float32, and reports

* NaN/Inf counts in the radiance and in its gradients w.r.t. beta, H, g and the
  ground albedo, negative radiances, refusals (with their messages) and
  unexpected exceptions, per method and per value of each grid axis;
* the max relative error of each integrator's optical-depth columns against the
  float64 scipy reference (skyfit.tools.reference.column_quad), per scale height,
  observer altitude and kind of segment (view ray / sun ray).

Usage::

    .venv/bin/python scripts/stability_report.py [--out docs/stability.md] [--quick] [--cross]

``--quick`` is the coarse grid of tests/test_extremes.py; ``--cross`` crosses all
100 atmospheres (H x beta x g) instead of sweeping one axis at a time.
Exit status 2 with a one-line message on bad flags.
"""
from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from pathlib import Path

import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from skyfit.tools import stability as S  # noqa: E402
from skyfit.transmittance import INTEGRATORS  # noqa: E402

MULTIPLE = ("hillaire", "bruneton", "bruneton_clamp")
AXES = (
    ("H", "both scale heights"),
    ("beta", "every scattering and extinction coefficient"),
    ("g", "Mie asymmetry"),
    ("altitude", "observer altitude"),
    ("sun zenith", "sun zenith angle [deg]"),
    ("view", "view direction (cosine mu, or the ground's horizon mu_h)"),
)


def _fmt(x: float) -> str:
    if x == 0:
        return "0"
    if x != x or x == float("inf"):
        return "inf"
    return f"{x:.2e}"


def _cell(t: S.Tally) -> str:
    """'values/gradients' non-finite counts; R = refused, E = unexpected exception."""
    if t.rays == 0:
        return "-"
    s = f"{t.bad_values}/{t.bad_grads}"
    if t.negative:
        s += f" neg{t.negative}"
    if t.refused:
        s = "R" if t.refused == t.rays else s + f" R{t.refused}"
    if t.errors:
        s += " E"
    return s


def _values(cells: dict, axis: str) -> list[str]:
    seen = []
    for (_, ax, v) in cells:
        if ax == axis and v not in seen:
            seen.append(v)
    return seen


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=str(REPO / "docs" / "stability.md"), help="markdown report to write")
    ap.add_argument("--quick", action="store_true", help="the coarse grid of tests/test_extremes.py")
    ap.add_argument("--cross", action="store_true", help="all H x beta x g combinations (100 atmospheres)")
    ap.add_argument("--methods", default=",".join(INTEGRATORS + MULTIPLE), help="comma list")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--no-radiance-reference", action="store_true", help="skip the single-scattering comparison with scipy")
    try:
        args = ap.parse_args(argv)
    except SystemExit as e:
        return int(e.code or 0)
    methods = [m for m in args.methods.split(",") if m]
    bad = [m for m in methods if m not in INTEGRATORS + MULTIPLE]
    if bad:
        print(f"stability_report: unknown method(s) {', '.join(bad)}; valid: {', '.join(INTEGRATORS + MULTIPLE)}", file=sys.stderr)
        return 2
    out = Path(args.out)
    if not out.parent.is_dir():
        print(f"stability_report: output folder {out.parent} does not exist", file=sys.stderr)
        return 2
    torch.set_num_threads(args.threads)
    from tqdm import tqdm

    grid = S.COARSE if args.quick else S.Grid()
    if args.cross:
        grid = S.Grid(**{**grid.__dict__, "cross": True})
    settings = S.FAST_SETTINGS if args.quick else S.REPORT_SETTINGS
    t_start = time.process_time()
    n_groups = len(S.atmosphere_cases(grid)) * len(grid.altitudes) * len(grid.sun_zenith_deg) * 2

    radiance: dict[str, dict] = {}
    columns: dict[str, dict] = {}
    ss_errors: dict[str, dict] = {}
    ref_cache: dict = {}
    ref_grid = S.Grid(**{**S.REFERENCE_GRID.__dict__, **({k: getattr(S.COARSE, k) for k in ("scale_heights", "betas", "mie_g")} if args.quick else {})})
    ref_views = 128 if args.quick else RADIANCE_VIEW_SAMPLES
    factory = None if args.no_radiance_reference else _reference_factory()
    cpu: dict[str, float] = {}
    cache: dict = {}
    for m in methods:
        t0 = time.process_time()
        with tqdm(total=n_groups, desc=f"{m} radiance", file=sys.stderr, leave=False, mininterval=5.0) as bar:
            if m == "hillaire":
                mk = S.hillaire_renderer
            elif m == "bruneton":
                mk = S.bruneton_renderer
            elif m == "bruneton_clamp":
                mk = lambda atm: S.bruneton_renderer(atm, below_mu_s_min="clamp")  # noqa: E731
            else:
                mk = lambda atm, m=m: S.single_renderer(m, settings.get(m, {}), atm)  # noqa: E731
            radiance[m] = S.radiance_scene(m, mk, grid, progress=bar.update)
        if m in INTEGRATORS:
            columns[m] = S.column_errors(m, settings.get(m, {}), grid, reference_cache=cache)
            if factory is not None:
                with tqdm(total=len(S.atmosphere_cases(ref_grid)), desc=f"{m} vs scipy", file=sys.stderr, leave=False, mininterval=5.0) as bar:
                    ss_errors[m] = S.radiance_errors(m, settings.get(m, {}), factory, ref_grid, view_samples=ref_views, cache=ref_cache, progress=bar.update)
        cpu[m] = time.process_time() - t0
        print(f"{m}: {cpu[m]:.1f} s CPU", file=sys.stderr)

    lines = _report(args, grid, settings, methods, radiance, columns, cpu, time.process_time() - t_start)
    if ss_errors:
        lines += _radiance_section(ss_errors, settings, ref_grid, ref_views)
    # A hand-written summary between the markers survives regeneration.
    if out.is_file():
        old = out.read_text()
        a, b = old.find(SUMMARY_BEGIN), old.find(SUMMARY_END)
        if 0 <= a < b:
            lines[1:1] = ["", old[a : b + len(SUMMARY_END)]]
    tmp = out.with_suffix(out.suffix + ".tmp")
    tmp.write_text("\n".join(lines) + "\n")
    os.replace(tmp, out)
    print(f"wrote {out}", file=sys.stderr)
    return 0


RADIANCE_VIEW_SAMPLES = 512
SUMMARY_BEGIN, SUMMARY_END = "<!-- summary -->", "<!-- /summary -->"


def _reference_factory():
    """The independent scipy single-scattering reference of tests/test_single_scattering_reference.py."""
    import importlib.util
    import warnings

    path = REPO / "tests" / "test_single_scattering_reference.py"
    spec = importlib.util.spec_from_file_location("_ss_reference", path)
    mod = importlib.util.module_from_spec(spec)
    n = torch.get_num_threads()
    spec.loader.exec_module(mod)
    torch.set_num_threads(n)  # the test module sets its own thread count on import

    def factory(atm):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            return mod.Reference(atm)

    return factory


def _radiance_section(ss_errors: dict, settings: dict, ref_grid, views: int) -> list[str]:
    L = [
        "",
        "## Single-scattering radiance against scipy",
        "",
        "Max relative error of `single_scattering` (each integrator inside, Gauss-Legendre with "
        f"{views} nodes along the view ray so that the outer integral is converged, no sun disk, no ozone) against the "
        "independent float64 scipy reference of `tests/test_single_scattering_reference.py` (adaptive quad for every "
        "optical depth, quad_vec over the view ray with break points at the shadow edge). Geometry: altitudes "
        f"{', '.join(a for a, _ in ref_grid.altitudes)}; sun zenith {', '.join(f'{z:g}' for z in ref_grid.sun_zenith_deg)} deg; "
        f"all the view rays above; the atmospheres of the grid. Errors are relative to max(|ref|, {S.RADIANCE_FLOOR:g} x the "
        "largest reference radiance of that atmosphere), per wavelength.",
        "",
    ]
    first = next(iter(ss_errors.values()))
    for axis, desc in AXES:
        vals = _values(first, axis)
        if not vals:
            continue
        L += [f"### By {axis}", "", "| method | dtype | " + " | ".join(vals) + " |", "|---|---|" + "---|" * len(vals)]
        for m, cells in ss_errors.items():
            for dn in ("float64", "float32"):
                row = []
                for v in vals:
                    c = cells.get((dn, axis, v))
                    if c is None:
                        row.append("-")
                        continue
                    s = _fmt(c["max_rel_err"]) if c["n"] else "-"
                    if c["refused"]:
                        s = ("R" if s == "-" else s + " R") + str(c["refused"])
                    row.append(s)
                L.append(f"| {m} | {dn} | " + " | ".join(row) + " |")
        L.append("")
    L += ["Worst case per method:", ""]
    for m, cells in ss_errors.items():
        for dn in ("float64", "float32"):
            cs = [c for (d, ax, _), c in cells.items() if d == dn and ax == "altitude" and c["worst"]]
            if cs:
                w = max(cs, key=lambda c: c["max_rel_err"])
                L.append(f"- {_label(m, settings)}, {dn}: {_fmt(w['max_rel_err'])} at {w['worst']}")
    return L


def _label(m: str, settings: dict) -> str:
    if m == "hillaire":
        return f"hillaire (LUT {S.HILLAIRE_LUT['size'][0]}x{S.HILLAIRE_LUT['size'][1]}, gauss-16 single)"
    if m == "bruneton":
        return "bruneton (tiny tables, 3 orders)"
    if m == "bruneton_clamp":
        return "bruneton (same, below_mu_s_min='clamp')"
    s = settings.get(m, {})
    return m + (" (" + ", ".join(f"{k}={v}" for k, v in s.items()) + ")" if s else " (defaults)")


def _report(args, grid, settings, methods, radiance, columns, cpu, cpu_total) -> list[str]:
    cmd = "python scripts/stability_report.py" + (" --quick" if args.quick else "") + (" --cross" if args.cross else "")
    L = [
        "# Stability at the extremes",
        "",
        f"Made by `.venv/bin/python {cmd[7:]}` (CPU time {cpu_total:.0f} s, one thread, "
        f"on {platform.machine()} under load from other jobs; torch {torch.__version__}). "
        "The grid and the counting are in `skyfit/tools/stability.py`; `tests/test_extremes.py` runs the ends of every axis "
        "(the `--quick` grid) in under a minute and asserts the same properties.",
        "",
        "## The grid",
        "",
        "Every method is run on every atmosphere, and for each atmosphere on every geometry, in float64 and float32:",
        "",
        f"- observer altitude: {', '.join(a for a, _ in grid.altitudes)} (Earth: bottom 6360 km, top 6420 km; space = 120 km up);",
        f"- sun zenith: {', '.join(f'{z:g}' for z in grid.sun_zenith_deg)} deg (90.27: the disk, radius 0.268 deg, just below the ground's horizon and partly seen from a few metres up);",
        "- view cosine mu: 1, +-1e-3, +-1e-6, 0, -1 and, for raised observers, the ground's horizon mu_h and mu_h +- 1e-6; "
        "each towards and away from the sun's azimuth, plus the view straight at the sun (scattering angle 0, nu = 1);",
        f"- scale height H (both layers): {', '.join(f'{h:g}' for h in grid.scale_heights)} m;",
        f"- beta (Rayleigh scattering, Mie extinction, Mie scattering = {S.MIE_SSA} x extinction): {', '.join(f'{b:g}' for b in grid.betas)} /m;",
        f"- Mie g (Cornette-Shanks): {', '.join(f'{g:g}' for g in grid.mie_g)};",
        "- " + ("all combinations of H, beta and g." if grid.cross else "H, beta and g swept one at a time from Earth's (Bruneton 2017: H = 8 km / 1.2 km, g = 0.8), so 1 + "
                f"{len(grid.scale_heights)} + {len(grid.betas)} + {len(grid.mie_g)} atmospheres."),
        "",
        f"Wavelengths {S.WAVELENGTHS_NM[0]:g} and {S.WAVELENGTHS_NM[1]:g} nm. Single scattering: 16-node Gauss-Legendre along the view ray, "
        "sun disk and Lambertian ground included. Gradients: one backward pass per (atmosphere, altitude, sun zenith) group of "
        "rays, of the summed radiance w.r.t. beta_R, beta_M^s, beta_M^e (per wavelength), H_R, H_M, g and the ground albedo.",
        "",
        "## Non-finite values and gradients",
        "",
        "Cells: `values/gradients`, the number of non-finite radiance entries (ray x wavelength) and of non-finite "
        "gradient entries; `R` = the method refused every ray of the cell with ValueError (its documented regime), "
        "`R<n>` = it refused n rays; `neg<n>` = negative radiances; `E` = an unexpected exception.",
        "",
        "### Totals",
        "",
        "| method | dtype | rays | radiance entries checked | non-finite | negative | gradient entries checked | non-finite | refused rays | unexpected errors |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for m in methods:
        for dn in ("float64", "float32"):
            tot = S.Tally()
            for (d, ax, _), t in radiance[m].items():
                if d == dn and ax == "altitude":
                    tot.add(t)
            L.append(
                f"| {_label(m, settings)} | {dn} | {tot.rays} | {tot.values} | {tot.bad_values} | {tot.negative} | {tot.grads} | {tot.bad_grads} | "
                f"{tot.refused} | {len(tot.errors)} |"
            )
    L += ["", "Refusals (one message per method; the numbers vary with the case):", ""]
    for m in methods:
        msgs = sorted(set().union(*[t.messages for t in radiance[m].values()]))
        errs = sorted(set().union(*[t.errors for t in radiance[m].values()]))
        if msgs:
            L.append(f"- {m}: {len(msgs)} distinct messages, e.g. `{msgs[0]}`")
        if errs:
            L.append(f"- {m}: UNEXPECTED `{errs[0]}`")
    where = [w for m in methods for t in radiance[m].values() for w in t.bad_where]
    if where:
        L += ["", "First non-finite results:", ""] + [f"- {w}" for w in dict.fromkeys(where)][:20]
    for axis, desc in AXES:
        any_cells = next(iter(radiance.values())) if radiance else {}
        vals = _values(any_cells, axis)
        if not vals:
            continue
        L += ["", f"### By {axis} ({desc})", "", "| method | dtype | " + " | ".join(vals) + " |", "|---|---|" + "---|" * len(vals)]
        for m in methods:
            for dn in ("float64", "float32"):
                L.append(f"| {m} | {dn} | " + " | ".join(_cell(radiance[m].get((dn, axis, v), S.Tally())) for v in vals) + " |")
    if columns:
        L += [
            "",
            "## Optical-depth columns against scipy",
            "",
            "Max relative error `|c - ref| / max(ref, 1 mm)` of each integrator's column against "
            "`skyfit.tools.reference.column_quad` (float64 scipy quad, break points at the tangent point), on the grid's view "
            "segments (the part of each view ray inside the atmosphere) and sun rays (observer to the top along "
            "max(mu_s, mu_h), as single scattering uses them), each scale height alone. The reference is evaluated at the "
            "inputs the method received (rounded to its dtype). `R<n>`: n segments refused; non-finite columns or "
            "d column/dH would be listed as `nf`.",
            "",
        ]
        vals_h = _values(next(iter(columns.values())), "H")
        vals_a = _values(next(iter(columns.values())), "altitude")
        for title, axis, vals in (("scale height", "H", vals_h), ("observer altitude (all H)", "altitude", vals_a), ("segment kind (all H)", "segment", ["view", "sun"])):
            L += [f"### By {title}", "", "| method | dtype | " + " | ".join(vals) + " | worst case |", "|---|---|" + "---|" * (len(vals) + 1)]
            for m in columns:
                for dn in ("float64", "float32"):
                    row, worst = [], (0.0, "")
                    for v in vals:
                        c = columns[m].get((dn, axis, v))
                        if c is None:
                            row.append("-")
                            continue
                        s = _fmt(c["max_rel_err"]) if c["n"] else "-"
                        if c["refused"]:
                            s += f" R{c['refused']}"
                        if c["bad_values"] or c["bad_grads"]:
                            s += f" nf{c['bad_values']}/{c['bad_grads']}"
                        row.append(s)
                        if c["n"] and c["max_rel_err"] >= worst[0]:
                            worst = (c["max_rel_err"], c["worst"])
                    L.append(f"| {_label(m, settings)} | {dn} | " + " | ".join(row) + f" | {worst[1]} |")
            L.append("")
    L += ["", "CPU seconds per method (radiance scan + columns, under load): " + ", ".join(f"{m} {cpu[m]:.0f}" for m in methods) + "."]
    return L


if __name__ == "__main__":
    sys.exit(main())
