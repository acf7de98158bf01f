"""Speed and accuracy of the transmittance integrators: Gałaj 2021 Table 3 with our code.

For each optical-depth method and each number of view samples, one run
renders a spectral fisheye sky at several sun zeniths and records

* the wall time (all sun zeniths together, as the paper's cumulative
  "Time"; integrator precomputation is timed apart in ``prepare_s``),
* the RMSE of the spectral radiance over the valid pixels, the wavelengths
  and the images, in mW/(m^2 sr nm),
* the mean CIE 1976 colour difference (Gałaj 2021 eq. 18) over the valid
  pixels and images, each image's XYZ scaled by the reference image's
  ``white_percentile``-th percentile luminance,

against a converged reference: Gauss-Legendre optical depth with many
samples and a Gauss-Legendre view integral with many nodes, in float64. A
second render of the reference at half its samples shows how converged it
is. Rows are rendered in the plan's dtype (float32) with the paper's outer
rule (trapezoid), as a user would render.

Outputs (written atomically into ``out``): ``bench.md`` (table, command,
machine), ``bench.csv``, ``bench.json`` and ``bench_pareto.png`` (time per
image against mean ΔE, the Pareto frontier marked).
"""
from __future__ import annotations

import csv
import dataclasses
import functools
import io
import json
import math
import os
import platform
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from ..io.atomic import write_bytes_atomic
from ..atmosphere import load_atmosphere
from ..camera import FisheyeCamera, render_fisheye
from ..render import delta_e_1976, spectral_to_xyz_matrix
from ..transmittance import INTEGRATORS, integrator_class, make_integrator

SKIPPED_METHODS: dict[str, str] = {
    "height_fog": "skipped: the flat height-fog column refuses full skies (long horizon rays exceed its curvature bound)",
}
"""Registered integrators the bench does not run, with the reason printed in the report."""

QUADRATURE_METHODS = ("trapezoid", "midpoint", "simpson", "gauss")

BENCH_THREADS: int = 2
"""torch intra-op threads of a bench run: the project's machines have 2 cores. With other
processes on the same cores, 2 threads stall on each other (a parallel op waits for a
descheduled thread); tests running in parallel workers therefore use 1."""


@dataclasses.dataclass(frozen=True)
class BenchPlan:
    """What one bench run renders.

    Attributes:
        size: fisheye width and height. [px]
        sun_zeniths_deg: one image per sun zenith. [deg]
        sun_azimuth_deg: [deg]
        view_samples: N of the outer (view-ray) integral, one row per value.
        wavelengths_nm: spectral samples. [nm]
        dtype: dtype of the rows ("float32" or "float64"); the reference is float64.
        rule: outer quadrature rule of the rows (Gałaj 2021 uses the trapezoid rule).
        light_samples: samples of the quadrature optical-depth methods, per method
            (Gałaj 2021 Table 3: 128 for the trapezoid rule); one row set per value.
        reference_light_samples: Gauss-Legendre optical-depth samples of the reference.
        reference_view_samples: Gauss-Legendre view-integral nodes of the reference.
        white_percentile: percentile of the reference luminance used as ΔE white. [%]
        row_budget_s: skip a row (and the larger N of its method) whose time, extrapolated
            linearly in N from the method's previous row, exceeds this; None: no limit. [s]
    """

    size: int
    sun_zeniths_deg: tuple[float, ...]
    sun_azimuth_deg: float
    view_samples: tuple[int, ...]
    wavelengths_nm: tuple[float, ...]
    dtype: str
    rule: str
    light_samples: dict[str, tuple[int, ...]]
    reference_light_samples: int
    reference_view_samples: int
    white_percentile: float = 99.0
    row_budget_s: float | None = None


_WAVELENGTHS = tuple(float(v) for v in np.arange(400.0, 701.0, 20.0))  # 16 samples, the CLI's default grid

FULL_PLAN = BenchPlan(
    size=128,
    sun_zeniths_deg=(30.0, 60.0, 85.0),
    sun_azimuth_deg=180.0,
    view_samples=(8, 16, 32, 64, 128, 256, 512, 1024),
    wavelengths_nm=_WAVELENGTHS,
    dtype="float32",
    rule="trapezoid",
    light_samples={"trapezoid": (128, 16), "midpoint": (32,), "simpson": (32,), "gauss": (32,)},
    reference_light_samples=32,
    reference_view_samples=128,
    row_budget_s=60.0,
)
"""``skyfit bench``: a 128 x 128 sky at three sun zeniths, N = 8 ... 1024 (15-30 minutes on 2 cores; a minute on a GPU)."""

QUICK_PLAN = BenchPlan(
    size=32,
    sun_zeniths_deg=(30.0, 60.0, 85.0),
    sun_azimuth_deg=180.0,
    view_samples=(4, 16, 64),
    wavelengths_nm=_WAVELENGTHS,
    dtype="float32",
    rule="trapezoid",
    light_samples={"trapezoid": (32,), "midpoint": (8,), "simpson": (8,), "gauss": (8,)},
    reference_light_samples=24,
    reference_view_samples=64,
)
"""``skyfit bench --quick``: a reduced table for CI (seconds)."""


@dataclasses.dataclass
class BenchRow:
    """One line of the table; errors are NaN where the method refused the sky."""

    method: str
    settings: str
    light_samples: int | None
    view_samples: int
    rule: str
    dtype: str
    time_s: float
    prepare_s: float
    rmse_mw: float
    mean_delta_e: float
    role: str = "method"  # "reference", "reference check" or "method"
    cpu_s: float = math.nan  # process CPU time of the renders (all threads)
    pareto: bool = False
    note: str = ""

    @property
    def time_per_image_s(self) -> float:
        return self.time_s / self._n_images

    _n_images: int = dataclasses.field(default=1, repr=False)


# -- machine and plan ----------------------------------------------------------
@contextmanager
def torch_threads(n: int) -> Iterator[None]:
    """Run the block with ``n`` torch intra-op threads; the previous count is restored on exit (also on error)."""
    old = torch.get_num_threads()
    torch.set_num_threads(int(n))
    try:
        yield
    finally:
        torch.set_num_threads(old)


def machine_info(device: str) -> dict:
    """CPU model, threads, torch version and the device's name, for the report."""
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    info = {
        "cpu": cpu,
        "logical_cpus": os.cpu_count(),
        "torch_threads": torch.get_num_threads(),
        "torch": torch.__version__,
        "python": platform.python_version(),
        "device": device,
        "load_average_1min": round(os.getloadavg()[0], 2) if hasattr(os, "getloadavg") else None,
    }
    if device.startswith("cuda"):
        info["gpu"] = torch.cuda.get_device_name(torch.device(device))
    return info


def method_settings(plan: BenchPlan) -> tuple[list[tuple[str, dict, int | None]], list[str]]:
    """(name, integrator settings, light samples) for every registered method that imports, and notes.

    Quadrature methods get one entry per light-sample count of the plan; the
    others run with their default settings (closed forms and tables: light samples None).
    """
    entries: list[tuple[str, dict, int | None]] = []
    notes: list[str] = []
    for name in INTEGRATORS:
        if name in SKIPPED_METHODS:
            notes.append(f"{name}: {SKIPPED_METHODS[name]}")
            continue
        try:
            integrator_class(name)
        except (ImportError, AttributeError) as e:
            notes.append(f"{name}: not available ({type(e).__name__}: {e})")
            continue
        if name in QUADRATURE_METHODS:
            if not plan.light_samples.get(name):
                notes.append(f"{name}: not in this plan (no light-sample counts given)")
            for m in plan.light_samples.get(name, ()):
                entries.append((name, {"samples": int(m)}, int(m)))
        else:
            entries.append((name, {}, None))
    return entries, notes


# -- rendering and errors --------------------------------------------------------
def _sync(device: str) -> None:
    if device.startswith("cuda"):
        torch.cuda.synchronize(torch.device(device))


def _prepare(integrator, atm, device: str):
    """The integrator's precomputation for this atmosphere -> (column_fn, seconds)."""
    t0 = time.perf_counter()
    column_fn = integrator.prepare(atm.scale_heights, atm.bottom_radius, atm.top_radius)
    _sync(device)
    return column_fn, time.perf_counter() - t0


def _render_set(atm, integrator, column_fn, plan: BenchPlan, view_samples: int, rule: str, device: str, progress=None):
    """Render every sun zenith -> (spectral radiance of the valid pixels per image as float64 numpy (P, W),
    wall seconds, process CPU seconds)."""
    cam = FisheyeCamera(plan.size)
    images, elapsed, cpu = [], 0.0, 0.0
    for zen in plan.sun_zeniths_deg:
        _sync(device)
        t0, c0 = time.perf_counter(), time.process_time()
        with torch.no_grad():
            img = render_fisheye(atm, cam, zen, plan.sun_azimuth_deg, integrator, view_samples=view_samples,
                                 rule=rule, column_fn=column_fn)
        _sync(device)
        elapsed += time.perf_counter() - t0
        cpu += time.process_time() - c0
        images.append(img.spectral[img.valid].detach().to("cpu", torch.float64).numpy())
        if progress is not None:
            progress.update(1)
    return images, elapsed, cpu


def errors_against(reference: list[np.ndarray], images: list[np.ndarray], wavelengths_nm: np.ndarray,
                   white_percentile: float) -> tuple[float, float]:
    """(RMSE [mW/(m^2 sr nm)], mean CIE 1976 ΔE) of images against the reference.

    Args:
        reference, images: per image, spectral radiance of the valid pixels, shape (P, W). [W/(m^2 sr nm)]
        wavelengths_nm: shape (W,). [nm]
        white_percentile: each image pair is scaled by this percentile of the reference luminance. [%]
    """
    m = spectral_to_xyz_matrix(torch.as_tensor(wavelengths_nm, dtype=torch.float64)).numpy()
    sq, count, de = 0.0, 0, []
    for ref, img in zip(reference, images):
        if not np.all(np.isfinite(img)):
            return math.nan, math.nan
        sq += float(np.sum((img - ref) ** 2))
        count += ref.size
        xyz_ref, xyz_img = ref @ m, img @ m
        white = float(np.percentile(xyz_ref[:, 1], white_percentile))
        de.append(np.asarray(delta_e_1976(xyz_img, xyz_ref, white)).ravel())
    return 1e3 * math.sqrt(sq / max(count, 1)), float(np.mean(np.concatenate(de)))


# -- analysis ----------------------------------------------------------------------
def pareto_front(times: np.ndarray, errors: np.ndarray) -> np.ndarray:
    """Mask of the points no other point beats in both time and error (ties kept)."""
    t, e = np.asarray(times, float), np.asarray(errors, float)
    ok = np.isfinite(t) & np.isfinite(e)
    front = np.zeros(t.shape, bool)
    for i in np.flatnonzero(ok):
        dominated = ok & (t <= t[i]) & (e <= e[i]) & ((t < t[i]) | (e < e[i]))
        front[i] = not dominated.any()
    return front


def speed_ratio_at_equal_error(rows: list[BenchRow], fast: str = "taylor", slow: str = "trapezoid",
                               metric: str = "mean_delta_e", slow_light_samples: int | None = None) -> list[dict]:
    """For each ``fast`` row: the cheapest ``slow`` row with error <= the fast row's, and the time ratio.

    Args:
        metric: ``mean_delta_e`` or ``rmse_mw``.
        slow_light_samples: restrict the slow rows to this light-sample count (None: all).

    Returns:
        One dict per fast row (view samples, times, the matched slow row, ratio slow/fast;
        ratio None where no slow row reaches the fast row's error).
    """
    fast_rows = [r for r in rows if r.role == "method" and r.method == fast and math.isfinite(getattr(r, metric))]
    slow_rows = [r for r in rows if r.role == "method" and r.method == slow and math.isfinite(getattr(r, metric))
                 and (slow_light_samples is None or r.light_samples == slow_light_samples)]
    out = []
    for f in fast_rows:
        err = getattr(f, metric)
        ok = [s for s in slow_rows if getattr(s, metric) <= err]
        best = min(ok, key=lambda s: s.time_s) if ok else None
        out.append({
            "fast_view_samples": f.view_samples, "fast_time_s": f.time_s, "fast_error": err,
            "slow_view_samples": best.view_samples if best else None,
            "slow_light_samples": best.light_samples if best else None,
            "slow_time_s": best.time_s if best else None,
            "slow_error": getattr(best, metric) if best else None,
            "ratio": best.time_s / f.time_s if best else None,
        })
    return out


def _median_ratio(matches: list[dict]) -> float | None:
    r = [m["ratio"] for m in matches if m["ratio"] is not None]
    return float(np.median(r)) if r else None


# -- outputs -------------------------------------------------------------------------
_COLUMNS = ("method", "settings", "light_samples", "view_samples", "rule", "dtype", "time_s", "time_per_image_s",
            "cpu_s", "prepare_s", "rmse_mw", "mean_delta_e", "role", "pareto", "note")


def _row_dict(r: BenchRow) -> dict:
    d = {k: getattr(r, k) for k in _COLUMNS}
    for k in ("time_s", "time_per_image_s", "cpu_s", "prepare_s", "rmse_mw", "mean_delta_e"):
        d[k] = None if not math.isfinite(d[k]) else round(float(d[k]), 6)
    return d


def _fmt(x: float, digits: int = 3) -> str:
    if x is None or not math.isfinite(x):
        return "—"
    return f"{x:.{digits}g}" if abs(x) < 10 ** digits else f"{x:,.0f}"


def markdown_table(rows: list[BenchRow]) -> str:
    """The table in Gałaj 2021 Table 3's layout (method named on its first row), plus our extra columns."""
    head = ("| Method | Settings | Time [s] | Time/image [s] | CPU time [s] | RMSE [mW/(m² sr nm)] | ΔE (CIE 1976) "
            "| No. view samples | No. light samples | Pareto |\n|---|---|---:|---:|---:|---:|---:|---:|---:|:-:|\n")
    lines, last = [], None
    for r in rows:
        key = (r.method, r.settings, r.role)
        name = "" if key == last else (r.method if r.role == "method" else f"{r.method} ({r.role})")
        last = key
        light = "1" if r.light_samples is None else str(r.light_samples)
        if r.note and not math.isfinite(r.mean_delta_e):
            lines.append(f"| {name} | {r.settings} | {r.note.split(':')[0]} | | | — | — | {r.view_samples} | {light} | |")
            continue
        lines.append(
            f"| {name} | {r.settings} | {_fmt(r.time_s)} | {_fmt(r.time_per_image_s)} | {_fmt(r.cpu_s)} | {_fmt(r.rmse_mw)} "
            f"| {_fmt(r.mean_delta_e)} | {r.view_samples} | {light} | {'●' if r.pareto else ''} |"
        )
    return head + "\n".join(lines) + "\n"


def pareto_plot(rows: list[BenchRow], path: Path, title: str) -> None:
    """Time per image against mean ΔE (log-log), one colour per method, the frontier as a step line."""
    # matplotlib stays a local import: heavy, and needed only to draw this plot.
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    pts = [r for r in rows if r.role == "method" and math.isfinite(r.mean_delta_e) and r.mean_delta_e > 0]
    fig = Figure(figsize=(8, 5.5), dpi=120)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    groups: dict[str, list[BenchRow]] = {}
    for r in pts:
        groups.setdefault(f"{r.method} {r.settings}".strip(), []).append(r)
    markers = "osD^v<>pPXh*"
    for k, (label, g) in enumerate(groups.items()):
        g = sorted(g, key=lambda r: r.view_samples)
        ax.plot([r.time_per_image_s for r in g], [r.mean_delta_e for r in g], marker=markers[k % len(markers)],
                ms=5, lw=0.8, alpha=0.85, label=label)
    front = sorted((r for r in pts if r.pareto), key=lambda r: r.time_per_image_s)
    if front:
        ax.step([r.time_per_image_s for r in front], [r.mean_delta_e for r in front], where="post", color="k",
                lw=1.6, zorder=5, label="Pareto frontier")
        ax.scatter([r.time_per_image_s for r in front], [r.mean_delta_e for r in front], s=90, facecolors="none",
                   edgecolors="k", lw=1.4, zorder=6)
        for r in front:
            ax.annotate(f"{r.method} N={r.view_samples}", (r.time_per_image_s, r.mean_delta_e), fontsize=6,
                        xytext=(4, 4), textcoords="offset points")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("time per image [s]")
    ax.set_ylabel("mean ΔE (CIE 1976) vs converged reference")
    ax.set_title(title, fontsize=9)
    ax.grid(True, which="both", alpha=0.25)
    ax.legend(fontsize=7, ncol=2)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    write_bytes_atomic(path, buf.getvalue())


def _ratio_text(summary: dict) -> str:
    lines = []
    for key, label in (("ratio_paper_settings", "trapezoid with the paper's light samples"),
                       ("ratio_all_trapezoid", "any trapezoid setting in the table")):
        block = summary.get(key)
        if not block:
            continue
        med = block["median_ratio"]
        lines.append(f"- Taylor vs {label} ({block['criterion']}): median speed ratio at equal error "
                     f"{'—' if med is None else f'{med:.2f}×'}")
        for m in block["matches"]:
            if m["ratio"] is None:
                lines.append(f"  - Taylor N={m['fast_view_samples']}: no trapezoid setting reaches its error")
            else:
                lines.append(f"  - Taylor N={m['fast_view_samples']} ({m['fast_time_s']:.3g} s) vs trapezoid "
                             f"N={m['slow_view_samples']}, M={m['slow_light_samples']} ({m['slow_time_s']:.3g} s): "
                             f"{m['ratio']:.2f}×")
    same = summary.get("ratio_same_view_samples")
    if same:
        lines.append("- At equal view samples (Gałaj 2021's comparison, trapezoid M = "
                     f"{same['light_samples']}): " + ", ".join(f"N={k}: {v:.2f}×" for k, v in same["ratios"].items()))
    return "\n".join(lines)


# -- entry point -----------------------------------------------------------------------
def run_bench(out: Path, quick: bool = False, device: str = "cpu", as_json: bool = False,
              plan: BenchPlan | None = None, threads: int | None = None) -> dict:
    """Run the bench, write ``bench.md``, ``bench.csv``, ``bench.json``, ``bench_pareto.png`` into ``out``.

    Args:
        out: output folder (created).
        quick: use QUICK_PLAN instead of FULL_PLAN (ignored when ``plan`` is given).
        device: torch device of every render.
        as_json: print the summary as JSON on stdout instead of the Markdown table.
        plan: an explicit plan.
        threads: torch intra-op threads during the run, restored after (default BENCH_THREADS).

    Returns:
        The summary written to ``bench.json``.
    """
    plan = plan or (QUICK_PLAN if quick else FULL_PLAN)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    with torch_threads(BENCH_THREADS if threads is None else threads):
        lam = np.asarray(plan.wavelengths_nm, float)
        dtype = {"float32": torch.float32, "float64": torch.float64}[plan.dtype]
        atm = load_atmosphere("earth", lam, dtype=dtype, device=device)
        atm64 = load_atmosphere("earth", lam, dtype=torch.float64, device=device)
        entries, notes = method_settings(plan)
        machine = machine_info(device)
        n_img = len(plan.sun_zeniths_deg)
        total = n_img * (2 + len(entries) * len(plan.view_samples)) + 1
        rows: list[BenchRow] = []
        with tqdm(total=total, desc="skyfit bench", unit="image", file=sys.stderr, disable=False,
                  mininterval=0.5, dynamic_ncols=True) as bar:
            # Warm-up (allocator, lazy imports, colour tables) outside any timing.
            warm = make_integrator("taylor")
            warm_plan = dataclasses.replace(plan, size=min(plan.size, 16), sun_zeniths_deg=plan.sun_zeniths_deg[:1])
            _render_set(atm, warm, _prepare(warm, atm, device)[0], warm_plan, 8, plan.rule, device)
            bar.update(1)
            bar.set_postfix_str("reference")
            ref_views = (plan.reference_view_samples, max(1, plan.reference_view_samples // 2))
            ref_lights = (plan.reference_light_samples, max(1, plan.reference_light_samples // 2))
            ref = None
            for role, n_view, m in zip(("reference", "reference check"), ref_views, ref_lights):
                integ = make_integrator("gauss", samples=m)
                column_fn, p = _prepare(integ, atm64, device)
                images, t, c = _render_set(atm64, integ, column_fn, plan, n_view, "gauss", device, bar)
                ref = images if ref is None else ref
                rmse, de = errors_against(ref, images, lam, plan.white_percentile)
                rows.append(BenchRow("gauss", f"samples={m}", m, n_view, "gauss", "float64", t, p, rmse, de,
                                     role=role, cpu_s=c, _n_images=n_img))
            for name, settings, light in entries:
                label = ",".join(f"{k}={v}" for k, v in settings.items())
                stop, last, prep = "", None, math.nan
                try:
                    integ = make_integrator(name, **settings)
                    column_fn, prep = _prepare(integ, atm, device)
                    # First-use costs (CUDA kernels compiled on first call, caches) outside the timing.
                    _render_set(atm, integ, column_fn, warm_plan, plan.view_samples[0], plan.rule, device)
                except ValueError as e:
                    stop = f"refused: {str(e).splitlines()[0][:160]}"
                for n_view in plan.view_samples:
                    bar.set_postfix_str(f"{name} {label} N={n_view}")
                    nan_row = functools.partial(BenchRow, name, label, light, n_view, plan.rule, plan.dtype, math.nan,
                                                prep, math.nan, math.nan, _n_images=n_img)
                    if not stop and last and plan.row_budget_s:
                        predicted = last[1] * n_view / last[0]  # cost is linear in N
                        if predicted > plan.row_budget_s:
                            rows.append(nan_row(note=f"skipped: predicted {predicted:.0f} s > row budget {plan.row_budget_s:g} s"))
                            bar.update(n_img)
                            continue
                    if stop:
                        rows.append(nan_row(note=stop))
                        bar.update(n_img)
                        continue
                    done = bar.n
                    try:
                        images, t, c = _render_set(atm, integ, column_fn, plan, n_view, plan.rule, device, bar)
                        if t < 0.5:  # short rows: best of three, for stable timings
                            for _ in range(2):
                                t2, c2 = _render_set(atm, integ, column_fn, plan, n_view, plan.rule, device)[1:]
                                t, c = min(t, t2), min(c, c2)
                    except ValueError as e:  # the method refuses part of the sky
                        stop = f"refused: {str(e).splitlines()[0][:160]}"
                        rows.append(nan_row(note=stop))
                        bar.update(done + n_img - bar.n)
                        continue
                    last = (n_view, t)
                    rmse, de = errors_against(ref, images, lam, plan.white_percentile)
                    rows.append(BenchRow(name, label, light, n_view, plan.rule, plan.dtype, t, prep, rmse, de, cpu_s=c,
                                         note="" if math.isfinite(de) else "non-finite radiance", _n_images=n_img))
        methods = [r for r in rows if r.role == "method"]
        front = pareto_front(np.array([r.time_s for r in methods]), np.array([r.mean_delta_e for r in methods]))
        for r, f in zip(methods, front):
            r.pareto = bool(f)
        machine["load_average_1min_end"] = round(os.getloadavg()[0], 2) if hasattr(os, "getloadavg") else None
        summary = _summarise(rows, plan, notes, device, quick, machine)
        if torch.get_num_threads() != BENCH_THREADS:
            summary["command"] += f" (run with {torch.get_num_threads()} torch thread(s), not BENCH_THREADS = {BENCH_THREADS})"
        _write_outputs(out, rows, summary, plan)
    if as_json:
        print(json.dumps(summary))
    else:
        print((out / "bench.md").read_text())
    return summary


def _row_notes(rows: list[BenchRow], plan: BenchPlan) -> list[str]:
    """One line per method setting whose rows were skipped or refused."""
    out, seen = [], set()
    for r in rows:
        key = (r.method, r.settings)
        if not r.note or key in seen:
            continue
        seen.add(key)
        label = f"{r.method} {r.settings}".strip()
        if r.note.startswith("skipped: predicted"):
            out.append(f"{label}: rows from N = {r.view_samples} skipped, their time extrapolated linearly in N "
                       f"exceeds the {plan.row_budget_s:g} s row budget ({r.note.split(': ', 1)[1].split(' >')[0]} for this one)")
        else:
            out.append(f"{label}: {r.note} (from N = {r.view_samples})")
    return out


def _summarise(rows: list[BenchRow], plan: BenchPlan, notes: list[str], device: str, quick: bool, machine: dict) -> dict:
    paper_m = max(plan.light_samples.get("trapezoid", ()) or (None,), key=lambda v: v or 0)
    summary = {
        "command": "skyfit bench" + (" --quick" if quick else "") + (f" --device {device}" if device != "cpu" else ""),
        "machine": machine,
        "plan": {**dataclasses.asdict(plan), "wavelengths_nm": list(plan.wavelengths_nm)},
        "reference": {
            "optical_depth": f"gauss, {plan.reference_light_samples} samples",
            "view_integral": f"gauss, {plan.reference_view_samples} nodes",
            "dtype": "float64",
            "delta_e_white": f"{plan.white_percentile:g}th percentile of the reference image's luminance",
        },
        "notes": notes + _row_notes(rows, plan),
        "rows": [_row_dict(r) for r in rows],
    }
    for key, m, metric in (("ratio_paper_settings", paper_m, "mean_delta_e"), ("ratio_all_trapezoid", None, "mean_delta_e"),
                           ("ratio_all_trapezoid_rmse", None, "rmse_mw")):
        matches = speed_ratio_at_equal_error(rows, metric=metric, slow_light_samples=m)
        if matches:
            summary[key] = {"criterion": "mean ΔE" if metric == "mean_delta_e" else "RMSE",
                            "trapezoid_light_samples": m, "matches": matches, "median_ratio": _median_ratio(matches)}
    tay = {r.view_samples: r for r in rows if r.role == "method" and r.method == "taylor" and math.isfinite(r.time_s)}
    trap = {r.view_samples: r for r in rows if r.role == "method" and r.method == "trapezoid"
            and r.light_samples == paper_m and math.isfinite(r.time_s)}
    common = sorted(set(tay) & set(trap))
    if common:
        summary["ratio_same_view_samples"] = {"light_samples": paper_m,
                                              "ratios": {n: trap[n].time_s / tay[n].time_s for n in common}}
    return summary


def _write_outputs(out: Path, rows: list[BenchRow], summary: dict, plan: BenchPlan) -> None:
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=list(_COLUMNS), lineterminator="\n")
    w.writeheader()
    for r in rows:
        w.writerow({k: ("" if v is None else v) for k, v in _row_dict(r).items()})
    write_bytes_atomic(out / "bench.csv", buf.getvalue().encode())
    write_bytes_atomic(out / "bench.json", json.dumps(summary, indent=1, default=str).encode())
    mi = summary["machine"]
    title = (f"{plan.size}x{plan.size} fisheye, {len(plan.wavelengths_nm)} wavelengths, sun zeniths "
             f"{', '.join(f'{z:g}' for z in plan.sun_zeniths_deg)}°; {mi['cpu']}, {mi['torch_threads']} torch thread(s)")
    pareto_plot(rows, out / "bench_pareto.png", title)
    ref = summary["reference"]
    md = [
        "# skyfit bench: transmittance methods, speed against accuracy (Gałaj 2021 Table 3 layout)",
        "",
        f"Command: `{summary['command']}`  ",
        f"Machine: {mi['cpu']}, {mi['logical_cpus']} logical CPUs, torch {mi['torch']} with {mi['torch_threads']} thread{'s' if mi['torch_threads'] != 1 else ''}, "
        f"device {mi['device']}{' (' + mi['gpu'] + ')' if 'gpu' in mi else ''}, Python {mi['python']}; "
        f"1-min load average {mi['load_average_1min']} at the start, {mi['load_average_1min_end']} at the end  ",
        f"Sky: {plan.size}×{plan.size} equidistant fisheye, {len(plan.wavelengths_nm)} wavelengths "
        f"{plan.wavelengths_nm[0]:g}–{plan.wavelengths_nm[-1]:g} nm, sun zeniths "
        f"{', '.join(f'{z:g}' for z in plan.sun_zeniths_deg)}° (azimuth {plan.sun_azimuth_deg:g}°), observer at sea level, "
        f"`earth` atmosphere, single scattering, rows in {plan.dtype} with the {plan.rule} rule along the view ray.  ",
        f"Time: wall time of all {len(plan.sun_zeniths_deg)} images (the paper's cumulative time; best of 3 for rows under 0.5 s), "
        "after one small warm-up render per method; integrator precomputation excluded (bench.csv, `prepare_s`).  ",
        f"Reference: optical depth {ref['optical_depth']}, view integral {ref['view_integral']}, {ref['dtype']}. "
        "RMSE over valid pixels, wavelengths and images; ΔE = mean CIE 1976 colour difference over valid pixels and images, "
        f"XYZ scaled by the {ref['delta_e_white']}.",
        "",
        markdown_table(rows),
        _ratio_text(summary),
        "",
    ]
    if summary["notes"]:
        md += ["Notes:", ""] + [f"- {n}" for n in summary["notes"]] + [""]
    write_bytes_atomic(out / "bench.md", "\n".join(md).encode())
