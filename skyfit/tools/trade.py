"""The speed/accuracy trade study of the whole renderer (``skyfit bench --study trade``).

Every transmittance method x light samples x view samples x outer rule x dtype, single
scattering, and multiple scattering by Hillaire 2020's LUT (two LUT sizes) or Bruneton &
Neyret 2008's tables (two sizes, 2-4 orders), on fixed scenes: sun zenith 20° (noon), 60°
(morning), 85° (sunset), 96° (civil twilight) for observers at sea level and at 10 km.
For each setting and scene it records

* the process CPU time and wall time of one render (best of 3 when under
  ``TradePlan.repeat_below_s``), and apart the precomputation it needs per atmosphere
  (integrator tables, Hillaire LUT, Bruneton tables; for Bruneton the stages up to its
  order), also as process CPU time,
* the peak memory: resident set size gained during the render (Linux ``VmHWM`` after
  resetting it through ``/proc/self/clear_refs``; torch's CPU allocator is invisible to
  tracemalloc) or ``torch.cuda.max_memory_allocated`` on CUDA,
* the error against a converged reference: RMSE [mW/(m^2 sr nm)], relative RMS error
  ||L - L_ref|| / ||L_ref|| and mean CIE 1976 ΔE (white: the 99th percentile of the
  reference's luminance, as :mod:`skyfit.tools.bench`).

References (float64): single scattering with Gauss-Legendre optical depth (32 nodes) and a
128-node Gauss-Legendre view integral; multiple scattering adds to that the orders >= 2 of
Bruneton tables larger than any row's, with more orders (``TradePlan.reference_tables``).
A reference check at half the samples and smaller tables bounds the references' own error.
Single-scattering rows are compared with the single-scattering reference (and, in an extra
column, with the multiple one: the error of neglecting orders >= 2); multiple-scattering
rows with the multiple one. The atmosphere is ``earth`` without ozone, so that every method
and both references integrate the same two exponential layers.

Outputs (atomic writes): ``trade.md`` (Gałaj 2021 Table 3 layout, one row per setting with
errors averaged over the scenes), ``trade.csv`` (one line per setting and scene),
``trade.json``, ``trade_pareto.png`` (CPU time per image against mean ΔE, frontiers of the
single- and multiple-scattering families marked) and ``frontier.json`` (the measurements
that :mod:`skyfit.render.auto` chooses from; shipped as ``skyfit/data/auto_settings.json``).
"""
from __future__ import annotations

import csv
import ctypes
import dataclasses
import io
import json
import math
import os
import re
import sys
import time
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from ..io.atomic import write_bytes_atomic
from ..atmosphere import load_atmosphere
from ..camera import FisheyeCamera, render_fisheye
from ..geometry import zenith_azimuth_to_enu
from ..render import delta_e_1976, spectral_to_xyz_matrix
from ..render.auto import choose, describe, parse_accuracy
from ..scattering.bruneton_tables import TableSizes
from ..scattering.hillaire import hillaire_lut
from ..scattering.multiple import precompute, sky_radiance
from ..transmittance import make_integrator, parse_integrator
from .bench import machine_info, pareto_front, torch_threads


@dataclasses.dataclass(frozen=True)
class Scene:
    """A fixed scene: sun position and observer altitude."""

    name: str
    sun_zenith_deg: float
    altitude_m: float
    sun_azimuth_deg: float = 180.0


def _scenes(zeniths: dict[str, float], altitudes: dict[str, float]) -> tuple[Scene, ...]:
    return tuple(Scene(f"{zn}{'' if not an else '-' + an}", z, h) for an, h in altitudes.items() for zn, z in zeniths.items())


TRADE_SCENES = _scenes({"noon": 20.0, "morning": 60.0, "sunset": 85.0, "twilight": 96.0}, {"": 0.0, "10km": 10000.0})
"""The fixed scenes: four sun zeniths [deg] x observers at 0 and 10 km [m]."""


@dataclasses.dataclass(frozen=True)
class TradePlan:
    """What one trade study renders.

    Attributes:
        size: fisheye width and height (equidistant, zenith up, 90° field). [px]
        wavelengths_nm: spectral samples. [nm]
        scenes: the fixed scenes.
        single_methods: integrator texts (``NAME[:key=value]``) of the single-scattering rows.
        view_samples: N of the single-scattering rows.
        rules: outer quadrature rules.
        dtypes: dtypes of the single-scattering rows.
        float64_methods: the methods also run in float64 (None: all of ``single_methods``).
        hillaire_luts: (n_h, n_mu_s, directions, samples) of the Hillaire rows.
        hillaire_methods, hillaire_view_samples, hillaire_rules: the Hillaire rows' single-scattering part.
        bruneton_sizes: (R, MU, MU_S, NU) scattering-table sizes of the Bruneton rows.
        bruneton_orders: orders of the Bruneton rows (one precomputation per size, all orders).
        multiple_dtype: dtype of the multiple-scattering rows.
        reference_light, reference_view: Gauss-Legendre nodes of the single-scattering reference.
        reference_tables, reference_orders: Bruneton tables of the reference's orders >= 2.
        check_tables, check_orders: the same for the reference check.
        repeat_below_s: renders faster than this are repeated (best of 3). [s]
    """

    size: int
    wavelengths_nm: tuple[float, ...]
    scenes: tuple[Scene, ...]
    single_methods: tuple[str, ...]
    view_samples: tuple[int, ...]
    rules: tuple[str, ...]
    dtypes: tuple[str, ...]
    hillaire_luts: tuple[tuple[int, int, int, int], ...]
    hillaire_methods: tuple[str, ...]
    hillaire_view_samples: tuple[int, ...]
    hillaire_rules: tuple[str, ...]
    bruneton_sizes: tuple[tuple[int, int, int, int], ...]
    bruneton_orders: tuple[int, ...]
    float64_methods: tuple[str, ...] | None = None
    multiple_dtype: str = "float32"
    reference_light: int = 32
    reference_view: int = 128
    reference_tables: tuple[int, int, int, int] = (16, 64, 16, 8)
    reference_orders: int = 6
    check_tables: tuple[int, int, int, int] = (8, 32, 16, 8)
    check_orders: int = 4
    repeat_below_s: float = 0.2


_WL8 = tuple(float(v) for v in np.linspace(400.0, 700.0, 8))

FULL_TRADE_PLAN = TradePlan(
    size=40,
    wavelengths_nm=_WL8,
    scenes=TRADE_SCENES,
    single_methods=("trapezoid:samples=16", "trapezoid:samples=64", "midpoint:samples=16", "simpson:samples=16",
                    "gauss:samples=4", "gauss:samples=8", "gauss:samples=16", "taylor", "spline", "bruneton_lut", "chapman"),
    view_samples=(4, 8, 16, 32, 64, 128),
    rules=("trapezoid", "gauss"),
    dtypes=("float32", "float64"),
    hillaire_luts=((16, 16, 32, 10), (32, 32, 64, 20)),
    hillaire_methods=("chapman", "gauss:samples=8", "taylor"),
    hillaire_view_samples=(8, 16, 32, 64),
    hillaire_rules=("trapezoid", "gauss"),
    bruneton_sizes=((8, 32, 8, 4), (8, 32, 16, 8)),
    bruneton_orders=(2, 3, 4),
    float64_methods=("trapezoid:samples=16", "gauss:samples=4", "gauss:samples=8", "gauss:samples=16", "taylor", "chapman"),
)
"""``skyfit bench --study trade``: 40 x 40 fisheye (1 264 directions), 8 wavelengths, 8 scenes."""

QUICK_TRADE_PLAN = TradePlan(
    size=12,
    wavelengths_nm=tuple(float(v) for v in np.linspace(400.0, 700.0, 5)),
    scenes=_scenes({"noon": 20.0, "sunset": 85.0}, {"": 0.0}),
    single_methods=("trapezoid:samples=16", "gauss:samples=8", "taylor", "chapman"),
    view_samples=(4, 16),
    rules=("trapezoid", "gauss"),
    dtypes=("float32",),
    hillaire_luts=((8, 8, 16, 5),),
    hillaire_methods=("chapman",),
    hillaire_view_samples=(8,),
    hillaire_rules=("gauss",),
    bruneton_sizes=((4, 8, 4, 4),),
    bruneton_orders=(2, 3),
    reference_light=16,
    reference_view=64,
    reference_tables=(8, 16, 4, 4),
    reference_orders=3,
    check_tables=(4, 8, 4, 4),
    check_orders=3,
    repeat_below_s=0.0,
)
"""``skyfit bench --study trade --quick``: a 12 x 12 sky, two scenes, a few settings (CI)."""


def _sizes(t):
    return TableSizes(scattering_r=t[0], scattering_mu=t[1], scattering_mu_s=t[2], scattering_nu=t[3])


def trade_settings(plan: TradePlan) -> list[dict]:
    """Every setting of the plan as a dict (the keys :mod:`skyfit.render.auto` returns)."""
    out = []
    for dtype in plan.dtypes:
        for rule in plan.rules:
            for integ in plan.single_methods:
                if dtype == "float64" and plan.float64_methods is not None and integ not in plan.float64_methods:
                    continue
                for n in plan.view_samples:
                    out.append({"family": "single", "multiple": None, "orders": 1, "integrator": integ, "view_samples": n,
                                "rule": rule, "dtype": dtype, "hillaire_lut": None, "table_sizes": None})
    for lut in plan.hillaire_luts:
        for rule in plan.hillaire_rules:
            for integ in plan.hillaire_methods:
                for n in plan.hillaire_view_samples:
                    out.append({"family": "multiple", "multiple": "hillaire", "orders": 2, "integrator": integ,
                                "view_samples": n, "rule": rule, "dtype": plan.multiple_dtype,
                                "hillaire_lut": ",".join(map(str, lut)), "table_sizes": None})
    for sz in plan.bruneton_sizes:
        for k in plan.bruneton_orders:
            out.append({"family": "multiple", "multiple": "bruneton", "orders": k, "integrator": "-", "view_samples": None,
                        "rule": None, "dtype": plan.multiple_dtype, "hillaire_lut": None,
                        "table_sizes": ",".join(map(str, sz))})
    for i, s in enumerate(out):
        s["id"] = f"s{i:03d}"
    return out


# -- measurement helpers ------------------------------------------------------------------
def _status_mib(key: str) -> float:
    try:
        m = re.search(key + r":\s+(\d+) kB", Path("/proc/self/status").read_text())
        return int(m.group(1)) / 1024.0 if m else math.nan
    except OSError:
        return math.nan


def _malloc_trim() -> None:
    """Give glibc's free heap pages back to the OS, so that a render's new pages show in the RSS."""
    try:
        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):
        pass


def _reset_peak(device: str) -> float:
    """Reset the peak-memory counter; -> the current usage it is measured from. [MiB]"""
    if device.startswith("cuda"):
        torch.cuda.synchronize(torch.device(device))
        torch.cuda.reset_peak_memory_stats(torch.device(device))
        return torch.cuda.memory_allocated(torch.device(device)) / 2**20
    _malloc_trim()  # without it, a render reusing freed heap pages showed no gain at all
    try:
        Path("/proc/self/clear_refs").write_text("5")  # Linux: VmHWM := VmRSS
    except OSError:
        return math.nan
    return _status_mib("VmRSS")


def _peak_since(device: str, base: float) -> float:
    if device.startswith("cuda"):
        return torch.cuda.max_memory_allocated(torch.device(device)) / 2**20 - base
    return _status_mib("VmHWM") - base


def _sync(device: str) -> None:
    if device.startswith("cuda"):
        torch.cuda.synchronize(torch.device(device))


def _timed(fn, device: str, repeat_below_s: float):
    """fn() -> (result, best wall s, best process CPU s, peak memory gained MiB)."""
    best_w = best_c = math.inf
    base = _reset_peak(device)
    out = None
    for k in range(3):
        _sync(device)
        w0, c0 = time.perf_counter(), time.process_time()
        out = fn()
        _sync(device)
        best_w, best_c = min(best_w, time.perf_counter() - w0), min(best_c, time.process_time() - c0)
        if k == 0:
            peak = _peak_since(device, base)
        if best_w >= repeat_below_s:
            break
    return out, best_w, best_c, max(peak, 0.0) if math.isfinite(peak) else math.nan


def image_errors(ref: np.ndarray, img: np.ndarray, xyz_matrix: np.ndarray, white_percentile: float = 99.0) -> dict:
    """RMSE [mW/(m^2 sr nm)], relative RMS error [1] and mean CIE 1976 ΔE of one image.

    Args:
        ref, img: spectral radiance of the valid pixels, shape (P, W). [W/(m^2 sr nm)]
        xyz_matrix: spectral -> XYZ matrix, shape (W, 3) (:func:`skyfit.render.spectral_to_xyz_matrix`).
        white_percentile: both images' XYZ are divided by this percentile of the reference luminance. [%]
    """
    if not np.all(np.isfinite(img)):
        return {"rmse_mw": math.nan, "rel_rmse": math.nan, "mean_delta_e": math.nan}
    diff = img - ref
    white = float(np.percentile(ref @ xyz_matrix[:, 1], white_percentile))
    de = np.asarray(delta_e_1976(img @ xyz_matrix, ref @ xyz_matrix, white))
    return {"rmse_mw": 1e3 * float(np.sqrt(np.mean(diff**2))),
            "rel_rmse": float(np.linalg.norm(diff) / max(np.linalg.norm(ref), 1e-300)),
            "mean_delta_e": float(de.mean())}


def bruneton_directions(atm, tables, camera, scene: Scene, orders: int) -> np.ndarray:
    """Radiance of the camera's valid pixels from Bruneton tables with ``orders`` orders, (P, W) float64 numpy."""
    T = lambda v: torch.tensor(math.radians(v), dtype=atm.dtype, device=atm.device)  # noqa: E731
    view, valid = camera.pixel_vectors(atm.dtype, atm.device)
    view = view[valid]
    sun = zenith_azimuth_to_enu(T(scene.sun_zenith_deg), T(scene.sun_azimuth_deg))
    r = atm.bottom_radius + scene.altitude_m
    with torch.no_grad():
        out = sky_radiance(tables, atm, torch.full_like(view[:, 2], r), view[:, 2], sun[2].expand_as(view[:, 2]),
                           (view * sun).sum(-1), orders=None if orders == tables.orders else orders)
    return out.to("cpu", torch.float64).numpy()


# -- the study ---------------------------------------------------------------------------------
def run_trade_study(out: Path, quick: bool = False, device: str = "cpu", as_json: bool = False,
                    plan: TradePlan | None = None, threads: int | None = None,
                    frontier_out: Path | None = None, command: str | None = None) -> dict:
    """Run the trade study; write trade.md/csv/json, trade_pareto.png and frontier.json into ``out``.

    Args:
        out: output folder (created).
        quick: QUICK_TRADE_PLAN instead of FULL_TRADE_PLAN (ignored when ``plan`` is given).
        device: torch device of every render.
        as_json: print the summary as JSON instead of the Markdown table.
        plan: an explicit plan.
        threads: torch intra-op threads during the run (default 1: CPU times are per core).
        frontier_out: also write frontier.json there (e.g. ``skyfit/data/auto_settings.json``).
        command: the command line to record (default: reconstructed from the arguments).

    Returns:
        The summary written to ``trade.json``.
    """
    plan = plan or (QUICK_TRADE_PLAN if quick else FULL_TRADE_PLAN)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    with torch_threads(1 if threads is None else threads):
        t_start = time.perf_counter()
        lam = np.asarray(plan.wavelengths_nm, float)
        dt = {"float32": torch.float32, "float64": torch.float64}
        atms = {k: load_atmosphere("earth", lam, dtype=v, device=device).replace(ozone_absorption=None) for k, v in dt.items()}
        xyz_m = spectral_to_xyz_matrix(torch.as_tensor(lam, dtype=torch.float64)).numpy()
        cam = FisheyeCamera(plan.size)
        settings = trade_settings(plan)
        machine = machine_info(device)
        scenes = plan.scenes
        n_sc = len(scenes)

        def render(atm, integ, scene, **kw):
            with torch.no_grad():
                img = render_fisheye(atm, cam, scene.sun_zenith_deg, scene.sun_azimuth_deg, integ,
                                     altitude=scene.altitude_m, **kw)
            return img.spectral[img.valid].detach().to("cpu", torch.float64).numpy()

        bar = tqdm(total=len(settings) * n_sc + 4 * n_sc, desc="skyfit bench trade", unit="render", file=sys.stderr,
                   mininterval=0.5, dynamic_ncols=True)
        # Warm-up outside any timing (lazy imports, allocator, colour tables).
        render(atms["float32"], make_integrator("taylor"), scenes[0], view_samples=4)

        # References: converged single scattering; plus Bruneton orders >= 2 from large tables.
        bar.set_postfix_str("references")
        refs: dict[str, dict[str, np.ndarray]] = {"single": {}, "multiple": {}, "single_check": {}, "multiple_check": {}}
        ref_info = {}
        a64 = atms["float64"]
        c0 = time.process_time()
        ref_tab = precompute(a64, orders=plan.reference_orders, sizes=_sizes(plan.reference_tables))
        chk_tab = precompute(a64, orders=plan.check_orders, sizes=_sizes(plan.check_tables))
        ref_info["tables_cpu_s"] = time.process_time() - c0
        for sc in scenes:
            for tag, m, n, tab in (("", plan.reference_light, plan.reference_view, ref_tab),
                                   ("_check", max(1, plan.reference_light // 2), max(1, plan.reference_view // 2), chk_tab)):
                single = render(a64, make_integrator("gauss", samples=m), sc, view_samples=n, rule="gauss")
                bar.update(1)
                ms = bruneton_directions(a64, tab, cam, sc, tab.orders) - bruneton_directions(a64, tab, cam, sc, 1)
                bar.update(1)
                refs["single" + tag][sc.name] = single
                refs["multiple" + tag][sc.name] = single + ms
        ref_rows = []
        for fam in ("single", "multiple"):
            for sc in scenes:
                e = image_errors(refs[fam][sc.name], refs[fam + "_check"][sc.name], xyz_m)
                ref_rows.append({"family": fam, "scene": sc.name, **e})
        ms_share = {sc.name: float(1 - np.linalg.norm(refs["single"][sc.name]) / np.linalg.norm(refs["multiple"][sc.name]))
                    for sc in scenes}

        results: dict[str, dict[str, dict]] = {}
        prepared: dict = {}
        for s in settings:
            label = _label(s)
            bar.set_postfix_str(label[:60])
            atm = atms[s["dtype"]]
            res: dict[str, dict] = {}
            results[s["id"]] = res
            try:
                if s["multiple"] == "bruneton":
                    key = ("bruneton", s["table_sizes"], s["dtype"])
                    if key not in prepared:
                        base, cc = _reset_peak(device), time.process_time()
                        with torch.no_grad():
                            tab = precompute(atm, orders=max(plan.bruneton_orders), keep_orders=True,
                                             sizes=_sizes(tuple(map(int, s["table_sizes"].split(",")))))
                        prepared[key] = (tab, time.process_time() - cc, _peak_since(device, base))
                    tab, cpu_all, prep_peak = prepared[key]
                    tm = tab.timings
                    upto = sum(v for k, v in tm.items() if k != "total" and not (k.startswith("order_") and int(k.split("_")[1]) > s["orders"]))
                    prep_cpu = cpu_all * upto / tm["total"]
                    kw = {"orders": s["orders"], "tables": tab}
                    integ = None
                else:
                    integ = parse_integrator(s["integrator"])
                    kw = {"view_samples": s["view_samples"], "rule": s["rule"]}
                    if s["multiple"] == "hillaire":
                        key = ("hillaire", s["hillaire_lut"], s["dtype"])
                        if key not in prepared:
                            nh, nm, nd, ns = map(int, s["hillaire_lut"].split(","))
                            base, cc = _reset_peak(device), time.process_time()
                            with torch.no_grad():
                                lut = hillaire_lut(atm, size=(nh, nm), directions=nd, samples=ns)
                            prepared[key] = (lut, time.process_time() - cc, _peak_since(device, base))
                        lut, prep_cpu, prep_peak = prepared[key]
                        kw.update(orders=2, multiple="hillaire", tables=lut)
                    else:
                        base, cc = _reset_peak(device), time.process_time()
                        column_fn = integ.prepare(atm.scale_heights, atm.bottom_radius, atm.top_radius)
                        prep_cpu, prep_peak = time.process_time() - cc, _peak_since(device, base)
                        kw["column_fn"] = column_fn
                refs_f = refs[s["family"]]
                for sc in scenes:
                    img, wall, cpu, peak = _timed(lambda: render(atm, integ, sc, **kw), device, plan.repeat_below_s)
                    e = image_errors(refs_f[sc.name], img, xyz_m)
                    row = {"wall_s": wall, "cpu_s": cpu, "prepare_cpu_s": prep_cpu, "peak_mib": peak,
                           "prepare_peak_mib": max(prep_peak, 0.0), **e}
                    if s["family"] == "single":
                        row["delta_e_vs_multiple"] = image_errors(refs["multiple"][sc.name], img, xyz_m)["mean_delta_e"]
                    res[sc.name] = row
                    bar.update(1)
            except ValueError as err:  # a method that refuses part of the sky
                for sc in scenes:
                    res.setdefault(sc.name, {"note": f"refused: {str(err).splitlines()[0][:120]}"})
                bar.update(n_sc - sum(1 for v in res.values() if "cpu_s" in v))
        bar.close()
        machine["load_average_1min_end"] = round(os.getloadavg()[0], 2) if hasattr(os, "getloadavg") else None
        if command is None:
            command = ("skyfit bench --study trade" + (" --quick" if quick else "") + f" --out {out}"
                       + (f" --device {device}" if device != "cpu" else "") + (f" --threads {threads}" if threads else ""))
        summary = _summarise(plan, settings, results, ref_rows, ref_info, ms_share, machine, device, command,
                             time.perf_counter() - t_start)
        _write_trade_outputs(out, plan, summary, frontier_out)
    if as_json:
        print(json.dumps({k: v for k, v in summary.items() if k not in ("results",)}, default=str))
    else:
        print((out / "trade.md").read_text())
    return summary


def _label(s: dict) -> str:
    return describe(s)


def _mean(vals):
    v = [x for x in vals if x is not None and math.isfinite(x)]
    return float(np.mean(v)) if len(v) == len(vals) and v else math.nan


def _summarise(plan, settings, results, ref_rows, ref_info, ms_share, machine, device, command, seconds) -> dict:
    """Per-setting means over scenes, Pareto flags per family, the speed ratio and the auto-setting table."""
    scenes = [sc.name for sc in plan.scenes]
    table = []
    for s in settings:
        res = results[s["id"]]
        ok = all("cpu_s" in res.get(n, {}) for n in scenes)
        g = lambda k: _mean([res[n].get(k) for n in scenes]) if ok else math.nan  # noqa: E731
        table.append({**s, "cpu_s": g("cpu_s"), "wall_s": g("wall_s"), "prepare_cpu_s": g("prepare_cpu_s"),
                      "peak_mib": max((res[n]["peak_mib"] for n in scenes), default=math.nan) if ok else math.nan,
                      "prepare_peak_mib": max((res[n].get("prepare_peak_mib", math.nan) for n in scenes), default=math.nan)
                      if ok else math.nan,
                      "rmse_mw": g("rmse_mw"), "rel_rmse": g("rel_rmse"), "mean_delta_e": g("mean_delta_e"),
                      "max_delta_e": max(res[n]["mean_delta_e"] for n in scenes) if ok else math.nan,
                      "delta_e_vs_multiple": g("delta_e_vs_multiple") if s["family"] == "single" else None,
                      "note": "" if ok else next((v.get("note", "") for v in res.values() if "note" in v), "")})
    for fam in ("single", "multiple"):
        rows = [r for r in table if r["family"] == fam]
        cost = np.array([r["cpu_s"] + r["prepare_cpu_s"] for r in rows])
        front = pareto_front(cost, np.array([r["mean_delta_e"] for r in rows]))
        for r, f in zip(rows, front):
            r["pareto"] = bool(f)
    summary = {
        "command": command,
        "machine": machine,
        "seconds": round(seconds, 1),
        "plan": dataclasses.asdict(plan),
        "scenes": [dataclasses.asdict(sc) for sc in plan.scenes],
        "reference": {
            "single": f"gauss optical depth {plan.reference_light} nodes, gauss view integral {plan.reference_view} nodes, float64",
            "multiple": (f"single reference + Bruneton orders 2-{plan.reference_orders} from tables {plan.reference_tables} "
                         f"(total({plan.reference_orders}) - total(1)), float64"),
            "check": (f"half the nodes ({plan.reference_light // 2}, {plan.reference_view // 2}); tables {plan.check_tables} "
                      f"with {plan.check_orders} orders"),
            "check_errors": ref_rows,
            "tables_cpu_s": ref_info.get("tables_cpu_s"),
            "multiple_share": ms_share,
        },
        "table": table,
        "results": results,
    }
    summary["speed_ratio"] = speed_ratio_de1(table)
    summary["speed_ratio_all_trapezoid"] = speed_ratio_de1(table, outer_rule="trapezoid")
    summary["auto"] = auto_table(summary)
    return summary


def speed_ratio_de1(table: list[dict], target: float = 1.0, family: str = "single", outer_rule: str | None = None) -> dict | None:
    """The frontier's cheapest setting with mean ΔE < target vs the trapezoid setting of equal error.

    "Equal error": the cheapest setting whose optical depth is the trapezoid rule (any light
    samples, view samples, dtype; outer rule ``outer_rule``, any if None) with mean ΔE <= the
    chosen setting's ΔE. If none reaches it, the most accurate trapezoid setting is reported.
    """
    rows = [r for r in table if r["family"] == family and math.isfinite(r["mean_delta_e"])]
    cost = lambda r: r["cpu_s"] + r["prepare_cpu_s"]  # noqa: E731
    ok = [r for r in rows if r["mean_delta_e"] < target]
    if not ok:
        return None
    fast = min(ok, key=cost)
    trap = [r for r in rows if r["integrator"].startswith("trapezoid") and (outer_rule is None or r["rule"] == outer_rule)]
    eq = [r for r in trap if r["mean_delta_e"] <= fast["mean_delta_e"]]
    out = {"target_delta_e": target, "outer_rule": outer_rule or "any", "fast": _short(fast), "fast_cpu_s": cost(fast), "fast_delta_e": fast["mean_delta_e"]}
    if eq:
        slow = min(eq, key=cost)
        out.update(slow=_short(slow), slow_cpu_s=cost(slow), slow_delta_e=slow["mean_delta_e"], ratio=cost(slow) / cost(fast),
                   equal_error=True)
    elif trap:
        slow = min(trap, key=lambda r: r["mean_delta_e"])
        out.update(slow=_short(slow), slow_cpu_s=cost(slow), slow_delta_e=slow["mean_delta_e"], ratio=cost(slow) / cost(fast),
                   equal_error=False)
    # Also: the cheapest trapezoid setting meeting the same target (ΔE < target).
    trap_ok = [r for r in trap if r["mean_delta_e"] < target]
    if trap_ok:
        t = min(trap_ok, key=cost)
        out.update(trapezoid_meeting_target=_short(t), trapezoid_meeting_target_cpu_s=cost(t),
                   ratio_at_target=cost(t) / cost(fast))
    return out


def _short(r: dict) -> str:
    return describe(r)


AUTO_TOLERANCES = {1: ("de=1", "de=0.3", "rel=0.01", "rel=0.003"), 2: ("de=3", "de=1.5", "rel=0.05", "rel=0.03")}
"""Tolerances of the auto table, single scattering (1) and multiple (2: looser, the multiple-scattering
reference itself is uncertain to about ΔE 1 and 2 %, see its reference check)."""


def auto_table(summary: dict) -> list[dict]:
    """Per scene and tolerance: the automatic choice, its measured error and cost, and the most expensive setting's cost."""
    fr = frontier_dict(summary)
    rows = []
    for sc in summary["scenes"]:
        for fam_orders in (1, 2):
            for tol_text in AUTO_TOLERANCES[fam_orders]:
                tol = parse_accuracy(tol_text)
                entry = {"scene": sc["name"], "orders": fam_orders, "tolerance": tol_text}
                try:
                    c = choose(tol, sc["sun_zenith_deg"], sc["altitude_m"], orders=fam_orders,
                               dtype="float32", frontier=fr)
                except ValueError as e:
                    entry["note"] = str(e)
                    rows.append(entry)
                    continue
                entry.update(setting=_short(c.setting), measured_error=c.predicted_error, cpu_s=c.predicted_cpu_s,
                             max_cpu_s=c.max_cpu_s, speedup=c.max_cpu_s / c.predicted_cpu_s)
                rows.append(entry)
    return rows


def frontier_dict(summary: dict) -> dict:
    """The subset of the summary :mod:`skyfit.render.auto` reads."""
    keep = ("cpu_s", "prepare_cpu_s", "wall_s", "mean_delta_e", "rel_rmse", "rmse_mw")
    return {
        "command": summary["command"],
        "machine": summary["machine"],
        "size": summary["plan"]["size"],
        "wavelengths_nm": list(summary["plan"]["wavelengths_nm"]),
        "reference": {k: summary["reference"][k] for k in ("single", "multiple", "check")},
        "scenes": summary["scenes"],
        "settings": [{k: r[k] for k in ("id", "family", "multiple", "orders", "integrator", "view_samples", "rule", "dtype",
                                        "hillaire_lut", "table_sizes")} for r in summary["table"]],
        "results": {sid: {n: {k: _round(v[k]) for k in keep if k in v} for n, v in res.items() if "cpu_s" in v}
                    for sid, res in summary["results"].items()},
    }


def _round(v):
    return float(f"{v:.4g}") if isinstance(v, float) and math.isfinite(v) else v


# -- outputs ---------------------------------------------------------------------------------
_CSV_COLUMNS = ("id", "family", "multiple", "orders", "integrator", "view_samples", "rule", "dtype", "hillaire_lut",
                "table_sizes", "scene", "sun_zenith_deg", "altitude_m", "cpu_s", "wall_s", "prepare_cpu_s", "peak_mib",
                "rmse_mw", "rel_rmse", "mean_delta_e", "delta_e_vs_multiple", "pareto", "note")


def _fmt(v, spec=".3g"):
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "—"
    return format(v, spec)


def _write_trade_outputs(out: Path, plan: TradePlan, summary: dict, frontier_out: Path | None) -> None:
    scenes = {sc["name"]: sc for sc in summary["scenes"]}
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=list(_CSV_COLUMNS), lineterminator="\n", extrasaction="ignore")
    w.writeheader()
    for r in summary["table"]:
        for name, res in summary["results"][r["id"]].items():
            row = {**{k: r.get(k) for k in _CSV_COLUMNS}, "scene": name, **scenes[name], **res}
            row["pareto"] = r["pareto"]
            w.writerow({k: ("" if row.get(k) is None else row.get(k)) for k in _CSV_COLUMNS})
    write_bytes_atomic(out / "trade.csv", buf.getvalue().encode())
    write_bytes_atomic(out / "trade.json", json.dumps(summary, indent=1, default=str).encode())
    fr = json.dumps(frontier_dict(summary), indent=0, default=str).encode()
    write_bytes_atomic(out / "frontier.json", fr)
    if frontier_out is not None:
        Path(frontier_out).parent.mkdir(parents=True, exist_ok=True)
        write_bytes_atomic(Path(frontier_out), fr)
    _trade_plot(summary, out / "trade_pareto.png")
    write_bytes_atomic(out / "trade.md", trade_markdown(summary, plan).encode())


def trade_markdown(summary: dict, plan: TradePlan) -> str:
    mi = summary["machine"]
    ref = summary["reference"]
    sc_text = ", ".join(f"{s['name']} ({s['sun_zenith_deg']:g}°, {s['altitude_m']:g} m)" for s in summary["scenes"])
    md = [
        "# skyfit bench --study trade: speed against accuracy of every renderer setting",
        "",
        f"Command: `{summary['command']}` ({summary['seconds']:.0f} s)  ",
        f"Machine: {mi['cpu']}, {mi['logical_cpus']} logical CPUs, torch {mi['torch']} with {mi['torch_threads']} "
        f"thread(s), device {mi['device']}{' (' + mi['gpu'] + ')' if 'gpu' in mi else ''}, Python {mi['python']}; "
        f"1-min load average {mi['load_average_1min']} at the start, {mi.get('load_average_1min_end')} at the end  ",
        f"Sky: {plan.size}×{plan.size} equidistant fisheye, {len(plan.wavelengths_nm)} wavelengths "
        f"{plan.wavelengths_nm[0]:g}–{plan.wavelengths_nm[-1]:g} nm, `earth` without ozone; scenes (sun zenith, "
        f"observer altitude; sun azimuth 180°): {sc_text}.  ",
        "Cost: process CPU time of one render (mean over the scenes; best of 3 under "
        f"{plan.repeat_below_s:g} s) + precomputation per atmosphere (`prep`: integrator tables, Hillaire LUT, "
        "Bruneton tables up to the row's order). Peak: resident memory gained during one render "
        "(Linux VmHWM after glibc malloc_trim and a reset through /proc/self/clear_refs; CUDA: max_memory_allocated), "
        "largest over the scenes; `prep peak`: the same for the precomputation (Bruneton: all orders at once).  ",
        f"References: single scattering: {ref['single']}; multiple: {ref['multiple']}. Reference check ({ref['check']}): "
        + "; ".join(f"{fam} max ΔE {max(r['mean_delta_e'] for r in ref['check_errors'] if r['family'] == fam):.2g}, "
                    f"max rel {max(r['rel_rmse'] for r in ref['check_errors'] if r['family'] == fam):.2g}"
                    for fam in ("single", "multiple"))
        + ". Orders ≥ 2 carry " + ", ".join(f"{k} {100 * v:.0f} %" for k, v in ref["multiple_share"].items())
        + " of the radiance norm (the single-scattering rows' `ΔE vs ms` column is the error of neglecting them).  ",
        "Errors: mean over the scenes of RMSE [mW/(m² sr nm)], relative RMS error ‖L−L_ref‖/‖L_ref‖ and mean CIE 1976 ΔE "
        "(white: 99th percentile of the reference luminance); `max ΔE` is the worst scene. ★ = on the Pareto frontier "
        "(cost vs mean ΔE) of its family.",
        "",
    ]
    for key, what in (("speed_ratio", "trapezoid optical depth, any outer rule"),
                      ("speed_ratio_all_trapezoid", "trapezoid optical depth and trapezoid outer rule, Gałaj 2021's setting")):
        sr = summary.get(key)
        if not sr or "slow" not in sr:
            continue
        md.append(f"**Speed ratio** ({what}; single scattering): the frontier's cheapest setting with mean ΔE < "
                  f"{sr['target_delta_e']:g} is {sr['fast']} ({sr['fast_cpu_s'] * 1e3:.3g} ms, ΔE {sr['fast_delta_e']:.3g}); "
                  "the cheapest trapezoid setting of "
                  + ("equal or smaller error" if sr.get("equal_error") else "the smallest error reached")
                  + f" is {sr['slow']} ({sr['slow_cpu_s'] * 1e3:.3g} ms, ΔE {sr['slow_delta_e']:.3g}): **{sr['ratio']:.1f}×**."
                  + (f" The cheapest trapezoid setting with ΔE < {sr['target_delta_e']:g}: {sr['trapezoid_meeting_target']} "
                     f"({sr['trapezoid_meeting_target_cpu_s'] * 1e3:.3g} ms), {sr['ratio_at_target']:.1f}×." if "ratio_at_target" in sr else ""))
        md.append("")
    for fam, title in (("single", "Single scattering"), ("multiple", "Multiple scattering")):
        md += [f"## {title}", "",
               "| Method | Light samples | No. view samples | Rule | dtype | Cost [ms] | prep [ms] | Wall [ms] | Peak [MiB] "
               "| prep peak [MiB] | RMSE | rel | ΔE | max ΔE |" + (" ΔE vs ms |" if fam == "single" else ""),
               "|---|---|---:|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|" + ("---:|" if fam == "single" else "")]
        rows = sorted((r for r in summary["table"] if r["family"] == fam),
                      key=lambda r: (r["dtype"], r["multiple"] or "", r["hillaire_lut"] or "", r["table_sizes"] or "",
                                     r["rule"] or "", r["integrator"], r["view_samples"] or 0, r["orders"]))
        for r in rows:
            name, _, opt = r["integrator"].partition(":")
            light = opt.split("=")[1] if "samples=" in opt else "—"
            if r["multiple"] == "hillaire":
                name = f"hillaire {r['hillaire_lut']} + {name}"
            elif r["multiple"] == "bruneton":
                name, light = f"bruneton {r['table_sizes']}, {r['orders']} orders", "—"
            md.append(f"| {'★ ' if r.get('pareto') else ''}{name} | {light} | {r['view_samples'] or '—'} | {r['rule'] or '—'} "
                      f"| {r['dtype']} | {_fmt(1e3 * r['cpu_s'])} | {_fmt(1e3 * r['prepare_cpu_s'])} | {_fmt(1e3 * r['wall_s'])} "
                      f"| {_fmt(r['peak_mib'], '.1f')} | {_fmt(r.get('prepare_peak_mib'), '.1f')} | {_fmt(r['rmse_mw'])} | {_fmt(r['rel_rmse'])} | {_fmt(r['mean_delta_e'])} "
                      f"| {_fmt(r['max_delta_e'])} |" + (f" {_fmt(r['delta_e_vs_multiple'])} |" if fam == "single" else "")
                      + (f" {r['note']}" if r.get("note") else ""))
        md.append("")
    md += ["## Automatic settings on the fixed scenes (float32)", "",
           "`skyfit.render.auto.choose` on this run's measurements: the chosen setting, its measured error (the tolerance's "
           "metric, worst of the bracketing scenes) and cost, and the cost of the most expensive measured setting of the "
           "family (each precomputation was timed once, so a load spike there inflates this column; "
           "scripts/auto_settings_check.py re-times the choice and the most expensive setting side by side).", "",
           "| Scene | Orders | Tolerance | Chosen | Measured error | Cost [ms] | Most expensive [ms] | Speed-up |",
           "|---|---:|---|---|---:|---:|---:|---:|"]
    for a in summary["auto"]:
        if "note" in a:
            md.append(f"| {a['scene']} | {a['orders']} | {a['tolerance']} | none: {a['note'][:90]} | | | | |")
        else:
            md.append(f"| {a['scene']} | {a['orders']} | {a['tolerance']} | {a['setting']} | {a['measured_error']:.3g} "
                      f"| {1e3 * a['cpu_s']:.3g} | {1e3 * a['max_cpu_s']:.4g} | {a['speedup']:.0f}× |")
    md.append("")
    return "\n".join(md)


def _trade_plot(summary: dict, path: Path) -> None:
    # matplotlib stays a local import: heavy, and needed only to draw this plot.
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker

    fig, axes = plt.subplots(1, 2, figsize=(13, 5.5))
    for ax, fam in zip(axes, ("single", "multiple")):
        rows = [r for r in summary["table"] if r["family"] == fam and math.isfinite(r["mean_delta_e"])]
        groups: dict[str, list] = {}
        for r in rows:
            key = (r["integrator"].split(":")[0] if r["multiple"] is None else
                   f"hillaire {r['hillaire_lut']}" if r["multiple"] == "hillaire" else f"bruneton {r['table_sizes']}")
            groups.setdefault(f"{key} {r['dtype'][-2:]}", []).append(r)
        methods = sorted({k.rsplit(" ", 1)[0] for k in groups})
        cmap = plt.get_cmap("tab20" if len(methods) > 10 else "tab10")
        for k, g in sorted(groups.items()):
            ax.scatter([1e3 * (r["cpu_s"] + r["prepare_cpu_s"]) for r in g], [r["mean_delta_e"] for r in g], s=12,
                       alpha=0.75, label=k, marker="o" if k.endswith("32") else "^",
                       color=cmap(methods.index(k.rsplit(" ", 1)[0]) % cmap.N))
        front = sorted((r for r in rows if r.get("pareto")), key=lambda r: r["cpu_s"] + r["prepare_cpu_s"])
        if front:
            ax.step([1e3 * (r["cpu_s"] + r["prepare_cpu_s"]) for r in front], [r["mean_delta_e"] for r in front],
                    where="post", color="k", lw=1.5, label="Pareto frontier")
            ax.scatter([1e3 * (r["cpu_s"] + r["prepare_cpu_s"]) for r in front], [r["mean_delta_e"] for r in front], s=60,
                       facecolors="none", edgecolors="k")
        ax.axhline(1.0, color="r", lw=0.8, ls="--", label="ΔE = 1")
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
        ax.set_xlabel("process CPU time per image incl. precomputation [ms]")
        ax.set_ylabel("mean ΔE (CIE 1976) vs converged reference")
        ax.set_title(f"{fam} scattering", fontsize=10)
        ax.grid(True, which="both", alpha=0.25)
        ax.legend(fontsize=6, ncol=2)
    mi = summary["machine"]
    fig.suptitle(f"{summary['command']} — {mi['cpu']}, {mi['torch_threads']} thread(s)", fontsize=8)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110)
    plt.close(fig)
    write_bytes_atomic(path, buf.getvalue())
