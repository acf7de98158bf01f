"""Kider 2013-05-27 with exposure and heading as the only nuisances (issue 14): per-capture fits, one
joint fit of the day and fit-one-predict-the-others, for the plain aerosol and the new rungs (docs/aerosol.md).

    .venv/bin/python scripts/kider_aerosol.py --stage fits --variants hg,tthg_bl,mie
    .venv/bin/python scripts/kider_aerosol.py --stage joint --variants hg
    .venv/bin/python scripts/kider_aerosol.py --stage cross --variants hg --sources 12.00,09.30,13.30
    .venv/bin/python scripts/kider_aerosol.py --stage report --variants hg,tthg_bl,mie    # markdown + JSON

Config: configs/kider.yaml (its renderer and optimiser settings) with fit.free replaced by the
atmosphere's values of the variant + ``exposure`` + ``sun_azimuth_offset`` (no sun zenith offset, no
camera tilt). Variants:

- ``hg``: Henyey-Greenstein, exponential profile (the config's model);
- ``tthg``, ``bl``, ``tthg_bl``: + the two-term phase (g2, f), + the boundary layer (h_mix), both;
- ``mie``: the log-normal Mie phase (r_g, sigma_g in place of g and alpha; m = 1.45 + 0.005i);
- ``mie2``: + a coarse mode (its median radius and the fine-mode fraction of the 550 nm extinction free, its
  sigma_g 1.9); ``mie2_bl``: that + the boundary layer;
- any of them + ``_o``: + the orientation nuisances of docs/kider.md (a) (sun zenith offset, two tilts);
- any of them + ``_t``: one tilt of the scanner's axis for the whole day (issue 14 item 4): the joint fit frees
  ``camera_tilt_north`` and ``camera_tilt_east`` once for all captures (exposure and heading stay per capture),
  warm-started at the variant's fits without ``_t``; the per-capture fits and the cross predictions then hold the
  tilt at the joint fit's value (run ``--stage joint`` first);
- any of them + ``_b``: multiple scattering from Bruneton's 4 orders (``multiple: bruneton_lagged``) instead of
  the config's Hillaire LUT.

Results are cached per fit in --work (rerun to resume). Score: RMSE over the valid samples and the
36 bands of 10 nm in 360-720 nm, mW/(m^2 sr nm), as docs/kider.md.
"""
from __future__ import annotations

import argparse
import copy
import json
import statistics
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
DAY = ROOT.parent / "shared" / "data" / "kider2014" / "2013-05-27"
CONFIG = ROOT / "configs" / "kider.yaml"
ATMOSPHERE = ["rayleigh_scale", "mie_beta_550", "mie_angstrom_alpha", "mie_scale_height", "mie_g"]
NUISANCE = ["exposure", "sun_azimuth_offset"]
VARIANTS = {  # (added, dropped) atmosphere values
    "hg": ([], []),
    "tthg": (["mie_g2", "mie_hg_weight"], []),
    "bl": (["mie_mixing_height"], []),
    "tthg_bl": (["mie_g2", "mie_hg_weight", "mie_mixing_height"], []),
    "mie": (["mie_median_radius", "mie_geometric_sigma"], ["mie_g", "mie_angstrom_alpha"]),
    "mie2": (["mie_median_radius", "mie_geometric_sigma", "mie_coarse_radius", "mie_fine_fraction"],
             ["mie_g", "mie_angstrom_alpha"]),
    "mie2_fixr": (["mie_median_radius", "mie_geometric_sigma", "mie_coarse_radius", "mie_fine_fraction"],
                  ["mie_g", "mie_angstrom_alpha", "rayleigh_scale"]),
    "mie2_bl": (["mie_median_radius", "mie_geometric_sigma", "mie_coarse_radius", "mie_fine_fraction", "mie_mixing_height"],
                ["mie_g", "mie_angstrom_alpha"]),
}


def _captures() -> list[Path]:
    return sorted(p for p in DAY.iterdir() if p.is_dir() and "___" in p.name)


def _short(p: Path) -> str:
    return p.name.split("___")[-1][:5]


BRUNETON = {"multiple": "bruneton_lagged", "orders": 4, "table_sizes": [64, 32, 16, 8, 16, 64, 16, 8]}
"""Suffix ``_b`` of a variant: Bruneton's 4 orders as a factor on the live single scattering (frozen per fit,
refreshed; the photo fits' tables) instead of the config's Hillaire LUT (32 directions x 12 steps)."""


ORIENTATION = ["sun_zenith_offset", "camera_tilt_north", "camera_tilt_east"]
"""Suffix ``_o`` of a variant: the orientation nuisances of docs/kider.md (a) besides the heading (sun zenith
offset, two tilts of the scanner's axis), to show what each rung gains with and without them."""


TILT = ["camera_tilt_north", "camera_tilt_east"]
"""Suffix ``_t``: the scanner's tilt, one for the day (shared by the joint fit's captures)."""


def _parse(v: str) -> tuple[str, bool, bool, bool]:
    base, b, o, t = v, False, False, False
    while base.endswith(("_b", "_o", "_t")) and base not in VARIANTS:
        b, o, t = b or base.endswith("_b"), o or base.endswith("_o"), t or base.endswith("_t")
        base = base[:-2]
    if base not in VARIANTS:
        raise SystemExit(f"unknown variant {v!r}: one of {', '.join(VARIANTS)}, each optionally with _b (Bruneton), "
                         "_o (+ the orientation nuisances) and/or _t (one tilt for the day)")
    if o and t:
        raise SystemExit(f"variant {v!r}: _o (a tilt per capture) and _t (one for the day) exclude each other")
    return base, b, o, t


def _untilted(v: str) -> str:
    """The variant without its ``_t`` suffix (the joint fit's warm start)."""
    return "_".join(p for p in v.split("_") if p != "t") if v not in VARIANTS else v


def day_tilt(work: Path, v: str) -> dict:
    """The joint fit's tilt of a ``_t`` variant, for the per-capture fits and predictions to hold fixed."""
    jp = work / f"{v}_joint.json"
    if not jp.exists():
        raise SystemExit(f"{jp} missing: a _t variant's fits hold the day's tilt fixed; run --stage joint first")
    par = json.loads(jp.read_text())["parameters"]
    return {n: float(par[n]) for n in TILT}


def variant_config(v: str) -> dict:
    from skyfit.atmosphere import load_yaml

    base, bruneton, orientation, tilt = _parse(v)
    cfg = copy.deepcopy(load_yaml(str(CONFIG)))
    add, drop = VARIANTS[base]
    cfg["fit"]["free"] = [n for n in ATMOSPHERE if n not in drop] + add + NUISANCE + (ORIENTATION if orientation else [])
    if tilt:  # the tilt is shared: only exposure and heading take a value per capture
        cfg["fit"]["per_observation"] = list(NUISANCE)
    if bruneton:
        cfg["fit"].update(BRUNETON)
    return cfg


def stage_fits(work: Path, v: str, only: list[str] | None) -> None:
    from skyfit.fit.run import run_fit

    cfg = variant_config(v)
    if _parse(v)[3]:
        cfg["fit"]["initial"] = {**cfg["fit"].get("initial", {}), **day_tilt(work, v)}
    for cap in _captures():
        name = _short(cap)
        out = work / f"{v}_{name}.json"
        if (only and name not in only) or out.exists():
            continue
        t0 = time.process_time()
        res = run_fit([cap], cfg, out, config_source=str(CONFIG), plots=False)
        cpu = time.process_time() - t0
        out.write_text(json.dumps({**json.loads(out.read_text()), "cpu_seconds": cpu}, indent=1))
        print(json.dumps({"variant": v, "capture": name, "rmse": round(res["metrics"]["rmse"], 3), "cpu_s": round(cpu, 1),
                          "converged": (res.get("convergence") or {}).get("converged"),
                          "free": {k: res["parameters"][k] for k in res["free"]}}), flush=True)


def stage_joint(work: Path, v: str, max_iter: int = 300, only: list[str] | None = None) -> None:
    """One fit of the day: the atmosphere shared, exposure and heading per capture, warm-started at
    the per-capture fits (the atmosphere at their median). ``only``: these captures (HH.MM) alone, e.g. to take a
    ``_t`` variant's tilt from part of the day and predict the rest."""
    from skyfit.fit.parameters import PARAMETERS
    from skyfit.fit.run import run_fit

    out = work / f"{v}_joint.json"
    if out.exists():
        return
    cfg = variant_config(v)
    caps = [c for c in _captures() if not only or _short(c) in only]
    tilt = _parse(v)[3]
    if tilt:
        cfg["fit"]["free"] += TILT
    fits = [work / f"{_untilted(v) if tilt else v}_{_short(c)}.json" for c in caps]
    overrides: dict = {"max_iter": max_iter}
    if all(f.exists() for f in fits):
        per = [json.loads(f.read_text())["parameters"] for f in fits]
        overrides["initial"] = {n: ([p[n] for p in per] if PARAMETERS[n].nuisance else float(np.median([p[n] for p in per])))
                                for n in cfg["fit"]["free"] if n not in TILT or not tilt}
    t0 = time.process_time()
    res = run_fit(caps, cfg, out, config_source=str(CONFIG), plots=False, progress=True, overrides=overrides)
    cpu = time.process_time() - t0
    out.write_text(json.dumps({**json.loads(out.read_text()), "cpu_seconds": cpu}, indent=1))
    print(json.dumps({"variant": v, "joint_rmse": res["metrics"]["rmse"], "cpu_s": round(cpu, 1),
                      "per": [round(p["rmse"], 3) for p in res["metrics"]["per_observation"]]}), flush=True)


def axis_heading(cap: Path) -> float:
    """The scanner's heading in a capture from the data alone [rad]: the symmetry axis of rings 1 and 2 (mean)
    minus the computed sun azimuth (skyfit.io.kider.ring_symmetry_azimuths; docs/data.md), the convention of
    ``sun_azimuth_offset``."""
    import math

    from skyfit.io.kider import load_kider_capture, ring_symmetry_azimuths

    c = load_kider_capture(cap)
    axes = ring_symmetry_azimuths(c)
    mean = math.atan2(float(np.sin(axes).mean()), float(np.cos(axes).mean()))
    d = mean - float(c.sun_azimuth)
    return math.atan2(math.sin(d), math.cos(d))


def _hours(res: dict) -> float:
    """A result's capture time in hours of its local day."""
    import datetime

    t = datetime.datetime.fromisoformat(res["data"][0]["time"])
    return t.hour + t.minute / 60 + t.second / 3600


def drift_heading(work: Path, v: str, target: str) -> float:
    """The scanner's heading at the target's time from its drift over the day, without the target's data [rad]:
    a straight line in time through the headings fitted on every other capture (``{v}_HH.MM.json``). The
    heading of the Kider scanner drifts by about -3 deg/h (docs/kider.md (d); docs/data.md has the axis drift), which
    Bruneton's evaluation met too."""
    times, heads, t_target = [], [], None
    for cap in _captures():
        name = _short(cap)
        res = json.loads((work / f"{v}_{name}.json").read_text())
        if name == target:
            t_target = _hours(res)
            continue
        times.append(_hours(res))
        heads.append(float(res["parameters"]["sun_azimuth_offset"]))
    return float(np.polyval(np.polyfit(times, heads, 1), t_target))


def stage_cross(work: Path, v: str, sources: list[str]) -> None:
    """Each source's fit predicts every other capture as is; with the heading measured on the target's own
    symmetry axis (no fit: ``axis``); with the heading from the scanner's drift line through the other captures'
    fitted headings (``drift``: leave-one-out, nothing of the target's data); and with exposure and heading
    re-estimated (``refit``)."""
    import tempfile

    from skyfit.fit.run import run_evaluate

    caps = _captures()
    for src in sources:
        path = work / f"{v}_{src}.json"
        if not path.exists():
            raise SystemExit(f"{path} missing: run --stage fits first")
        # with a day tilt the symmetry axis is not the model's heading: no axis mode
        for mode in ("asis", "drift", "refit") if _parse(v)[3] else ("asis", "axis", "drift", "refit"):
            out = work / f"{v}_cross_{src}_{mode}.json"
            done = json.loads(out.read_text()) if out.exists() else {}
            for cap in caps:
                name = _short(cap)
                if name == src or name in done:
                    continue
                source = path
                if mode in ("axis", "drift"):  # the source's atmosphere and exposure, the target's heading measured
                    res = json.loads(path.read_text())
                    res["parameters"]["sun_azimuth_offset"] = axis_heading(cap) if mode == "axis" else drift_heading(work, v, name)
                    tmp = Path(tempfile.mkdtemp()) / path.name
                    tmp.write_text(json.dumps(res))
                    source = tmp
                ev = run_evaluate(source, [cap], refit_nuisance=mode == "refit", refit=NUISANCE if mode == "refit" else None)
                done[name] = {"rmse": ev["rmse"], "delta_e": ev["delta_e"]}
                out.write_text(json.dumps(done, indent=1))
            print(json.dumps({"variant": v, "source": src, "mode": mode,
                              "mean_rmse": round(statistics.mean(d["rmse"] for d in done.values()), 3)}), flush=True)


def _sun_share(res: dict, cap: Path) -> float:
    """Share of the squared error in the 5 samples nearest the sun, at the fitted values (the fit's own model)."""
    from kider_ms_residual import evaluate  # scripts/ is on the path of a script run from it

    return evaluate(res, cap, {}, None)["sun5_share"]


def stage_report(work: Path, variants: list[str], orientation_work: Path) -> None:
    """Markdown tables (stdout) and work/report.json: per capture RMSE per variant, the same with the
    orientation nuisances (docs/kider.md (a)), the 5-nearest-sun error share, joint and cross means."""
    caps = _captures()
    names = [_short(c) for c in caps]
    rep: dict = {"variants": {}}
    cols = []
    for v in variants:
        fits = {n: json.loads((work / f"{v}_{n}.json").read_text()) for n in names if (work / f"{v}_{n}.json").exists()}
        if not fits:
            continue
        cols.append(v)
        rm = {n: r["metrics"]["rmse"] for n, r in fits.items()}
        share = {n: _sun_share(fits[n], c) for c in caps if (n := _short(c)) in fits}
        entry = {"rmse": rm, "mean": statistics.mean(rm.values()), "worst": max(rm.items(), key=lambda t: t[1]),
                 "sun5_share": share, "sun5_share_mean": statistics.mean(share.values()),
                 "converged": sum(bool((r.get("convergence") or {}).get("converged")) for r in fits.values()),
                 "cpu_s_median": statistics.median(r.get("cpu_seconds", r.get("seconds", 0.0)) for r in fits.values()),
                 "fitted": {n: {k: r["parameters"][k] for k in r["free"]} for n, r in fits.items()}}
        jp = work / f"{v}_joint.json"
        if jp.exists():
            j = json.loads(jp.read_text())
            entry["joint"] = {"rmse": j["metrics"]["rmse"], "per": [p["rmse"] for p in j["metrics"]["per_observation"]]}
        for mode in ("asis", "axis", "drift", "refit"):
            per_src = {}
            for f in work.glob(f"{v}_cross_*_{mode}.json"):
                d = json.loads(f.read_text())
                per_src[f.stem.split("_")[-2]] = statistics.mean(x["rmse"] for x in d.values())
            if per_src:
                entry[f"cross_{mode}"] = {"per_source": per_src, "mean": statistics.mean(per_src.values())}
        rep["variants"][v] = entry
    orient = {n: json.loads((orientation_work / f"fit_{n}.json").read_text()) for n in names
              if (orientation_work / f"fit_{n}.json").exists()}
    if orient:
        rep["orientation"] = {"rmse": {n: r["metrics"]["rmse"] for n, r in orient.items()},
                              "sun5_share": {n: _sun_share(r, c) for c in caps if (n := _short(c)) in orient
                                             for r in [orient[n]]}}
    (work / "report.json").write_text(json.dumps(rep, indent=1))
    head = "| capture | " + " | ".join(cols) + (" | HG + 4 orientation nuisances (docs/kider.md (a)) |" if orient else " |")
    print(head)
    print("|" + "---|" * (head.count("|") - 1))
    for n in names:
        row = [f"{rep['variants'][v]['rmse'][n]:.2f} ({100 * rep['variants'][v]['sun5_share'][n]:.0f} %)"
               if n in rep["variants"][v]["rmse"] else "-" for v in cols]
        if orient:
            row.append(f"{rep['orientation']['rmse'][n]:.2f} ({100 * rep['orientation']['sun5_share'][n]:.0f} %)" if n in orient else "-")
        print(f"| {n} | " + " | ".join(row) + " |")
    for key, label in (("mean", "per-capture mean"), ("worst", "worst")):
        vals = [f"{rep['variants'][v][key]:.2f}" if key == "mean" else f"{rep['variants'][v][key][1]:.2f} ({rep['variants'][v][key][0]})"
                for v in cols]
        if orient:
            o = rep["orientation"]["rmse"]
            vals.append(f"{statistics.mean(o.values()):.2f}" if key == "mean" else
                        "{1:.2f} ({0})".format(*max(o.items(), key=lambda t: t[1])))
        print(f"| **{label}** | " + " | ".join(vals) + " |")
    for key, label in (("joint", "joint day fit"), ("cross_refit", "fit one, predict the others, exposure + heading re-estimated"),
                       ("cross_axis", "fit one, predict the others, heading from the target's symmetry axis (no fit)"),
                       ("cross_drift", "fit one, predict the others, heading from the day's drift line without the target (no fit)"),
                       ("cross_asis", "fit one, predict the others, as is")):
        vals = []
        for v in cols:
            e = rep["variants"][v].get(key)
            vals.append("-" if e is None else f"{e['rmse']:.2f}" if key == "joint" else f"{e['mean']:.2f} ({len(e['per_source'])} sources)")
        print(f"| {label} | " + " | ".join(vals) + (" | - |" if orient else " |"))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--stage", choices=("fits", "joint", "cross", "report"), default="fits")
    ap.add_argument("--variants", default="hg,tthg_bl")
    ap.add_argument("--captures", default="all", help="fits, joint: comma list of HH.MM")
    ap.add_argument("--sources", default="12.00", help="cross: comma list of HH.MM source captures")
    ap.add_argument("--work", default=str(ROOT / "docs" / "kider_instrument"))
    ap.add_argument("--orientation-work", default=str(ROOT / "docs" / "kider"), help="report: docs/kider.md (a)'s fits")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--joint-max-iter", type=int, default=300, help="joint: optimiser iterations")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    variants = args.variants.split(",")
    only = None if args.captures == "all" else args.captures.split(",")
    for v in variants:
        _parse(v)
    if args.stage == "report":
        stage_report(work, variants, Path(args.orientation_work))
        return
    for v in variants:
        if args.stage == "fits":
            stage_fits(work, v, only)
        elif args.stage == "joint":
            stage_joint(work, v, args.joint_max_iter, only)
        else:
            stage_cross(work, v, args.sources.split(","))


if __name__ == "__main__":
    main()
