"""The photo fit on realistic synthetic photos with known truth (docs/photos.md).

Makes (or reuses) a suite of photos with :func:`skyfit.tools.photo_synth.make_suite` — Bruneton multiple
scattering on fine tables, published camera sensitivities, Bayer demosaicing, vignetting, a skyline,
a saturated sun with flare, JPEG, brackets with unknown exposure ratios — fits each with
:func:`skyfit.fit_photo` from its time and place alone, and compares with the truth: AOD 550, Ångström
alpha, g, the heading (up azimuth), the lens centre, the sun's placement; writes a JSON of every case
and a Markdown table.

    .venv/bin/python scripts/photo_study.py --cases /tmp/photo_cases --n 20 --out docs/photos
"""
from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from pathlib import Path

import numpy as np
import torch


def circular_diff_deg(a: float, b: float) -> float:
    return (a - b + 180.0) % 360.0 - 180.0


def ray_errors(true_cam: dict, fit_cam: dict, step: int = 4, max_zenith_deg: float = 85.0) -> dict:
    """Angles between the rays the true and the fitted camera give the same pixels (every ``step``-th pixel
    both see, up to ``max_zenith_deg`` from the true camera's axis): the whole camera's error in one number,
    projection, lens, centre, heading and tilt together. [deg]"""
    from skyfit.camera import FisheyeCamera

    t, f = FisheyeCamera.from_metadata(true_cam), FisheyeCamera.from_metadata(fit_cam)
    vt, okt = t.pixel_vectors(torch.float64)
    vf, okf = f.pixel_vectors(torch.float64)
    axis = t.rotation(torch.float64)[:, 2]
    sel = torch.zeros_like(okt)
    sel[::step, ::step] = True
    m = okt & okf & sel & ((vt @ axis) >= math.cos(math.radians(max_zenith_deg)))
    ang = torch.rad2deg(torch.acos((vt[m] * vf[m]).sum(-1).clamp(-1.0, 1.0))).numpy()
    return {"median": float(np.median(ang)), "p95": float(np.percentile(ang, 95)), "max": float(ang.max())}


def sun_errors(truth: dict, sun: dict) -> dict:
    """Angles from the true sun, through the true camera, of the fitted camera's sun (``model``), the reported
    detection (``detected``: registered or centroid) and the detector's centroid (``centroid``). [deg]"""
    from skyfit.camera import FisheyeCamera

    cam = FisheyeCamera.from_metadata(truth["camera"])

    def ray(px):
        with torch.no_grad():
            return cam.pixel_to_direction(torch.tensor(float(px[0]), dtype=torch.float64),
                                          torch.tensor(float(px[1]), dtype=torch.float64)).numpy()

    t = ray(truth["sun"]["model_px"])
    ang = lambda px: None if px is None else math.degrees(math.atan2(float(np.linalg.norm(np.cross(ray(px), t))),  # noqa: E731
                                                                     float(np.dot(ray(px), t))))
    return {"model": ang(sun["model_px"]), "detected": ang(sun["detected_px"]), "centroid": ang(sun.get("centroid_px"))}


AEROSOL_NAMES = (("aod_550", "mie_aod_550"), ("angstrom_alpha", "mie_angstrom_alpha"), ("g", "mie_g"))
"""RESULT.json aerosol keys and the fit's parameter names of the three scored values."""


def _gains_true(truth: dict) -> list[float] | None:
    """The camera's red and blue gains over green against CIE linear sRGB, from the first frame whose unclipped sky
    gave them (the darkest frame of a bracket may have no sky above the noise: its factors are None)."""
    k = next((f["linear_over_cie_rgb"] for f in truth["frames"] if f.get("linear_over_cie_rgb")), None)
    return None if k is None else [v / k[1] for v in k[::2]]


def score(truth: dict, result: dict) -> dict:
    """Fit vs truth of one case."""
    tp = truth["atmosphere"]["parameters"]
    aer, cam, sun = result["aerosol"], result["camera"], result["sun"]
    budget = (result.get("laplace") or {}).get("budget") or {}
    tc = truth["camera"]
    return {
        "seed": truth["seed"], "bracket": truth["bracket"] is not None, "projection_true": tc["projection"],
        "projection_fit": cam.get("nominal_projection", cam["projection"]), "lens_radial": cam.get("lens_radial"),
        "kb_k1_true": (tc.get("kb_coeffs") or [None])[0], "ray_err_deg": ray_errors(tc, cam),
        "sun_zenith_deg": truth["sun"]["zenith_deg"],
        "aod_true": tp["aod_550"] if "aod_550" in tp else tp.get("mie_aod_550"), "aod_fit": aer["aod_550"],
        "aod_sigma": aer["sigma"].get("aod_550"),
        "sigma": {k: aer["sigma"].get(k) for k in ("aod_550", "angstrom_alpha", "g")},
        "sigma_statistical": aer.get("sigma_statistical"),
        "budget": {part: {k: (budget.get(part) or {}).get(n) for k, n in AEROSOL_NAMES}
                   for part in ("sigma_noise", "sigma_numerical", "sigma_discrepancy", "sigma_discrepancy_sandwich_cr1")},
        "sigma_noise": {k: ((result.get("laplace") or {}).get("sigma_noise") or {}).get(n) for k, n in AEROSOL_NAMES},
        "alpha_true": tp.get("angstrom_alpha", tp.get("mie_angstrom_alpha")), "alpha_fit": aer["angstrom_alpha"],
        "g_true": tp.get("mie_g"), "g_fit": aer["g"],
        "heading_err_deg": circular_diff_deg(cam["up_azimuth_deg"], tc["up_azimuth_deg"]),
        "centre_err_px": math.hypot(cam["cx"] - tc["cx"], cam["cy"] - tc["cy"]),
        "radius_err_px": cam["radius_px"] - tc["radius_px"],
        "sun_separation_deg": sun["separation_deg"], "sun_detected": sun["detected_px"] is not None,
        "sun_detected_by": sun.get("detected_by"), "sun_centroid_separation_deg": sun.get("centroid_separation_deg"),
        "sun_registration_iou": (sun.get("registration") or {}).get("iou"), "sun_err_deg": sun_errors(truth, sun),
        "rmse_rel": result["metrics"]["rmse_rel"], "seconds": result["seconds"], "split": result["seconds_split"],
        "horizon_fraction": truth["obstacles"]["horizon_fraction"], "camera": truth["sensor"]["name"],
        "vignetting_rim": truth["vignetting"]["rim_value"], "vignetting_fit": cam.get("vignetting"),
        "gains_true": _gains_true(truth),
        "gains_fit": [cam.get("gain_red"), cam.get("gain_blue")], "saturation_fit": [cam.get("saturation_red"), cam.get("saturation_blue")],
        "ms": {k: result.get("convergence", {}).get(k) for k in ("ms_refreshes", "ms_table_builds", "ms_factor_change")},
        "notes": result["notes"],
        "pixels_used": result["pixels"]["used"], "pixels_outliers": result["pixels"]["masked_by"].get("outliers", 0),
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", default="/tmp/photo_cases", help="folder of the suite (made when missing)")
    ap.add_argument("--n", type=int, default=20, help="number of cases (default 20)")
    ap.add_argument("--seed", type=int, default=0, help="suite seed (default 0)")
    ap.add_argument("--size", type=int, default=600, help="single photos' side [px] (default 600)")
    ap.add_argument("--bracket-size", type=int, default=300, help="bracket frames' side [px] (default 300)")
    ap.add_argument("--out", default="docs/photos", help="where study.json and study.md go (default docs/photos)")
    ap.add_argument("--threads", type=int, default=2, help="torch threads (default 2)")
    ap.add_argument("--only", help="comma list of case indices to fit")
    ap.add_argument("--part", help="K/N: fit every N-th case from the K-th (0-based) and write OUT/study_partK.json only "
                                   "(several processes on a shared machine); --merge joins them")
    ap.add_argument("--orders", type=int, help="scattering orders of the fits (default: the photo fit's, 4)")
    ap.add_argument("--merge", action="store_true", help="join OUT/study_part*.json into study.json and study.md")
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    import skyfit
    from skyfit.tools.photo_synth import make_suite

    cases = Path(args.cases)
    if not (cases / "suite.json").exists():
        t0 = time.perf_counter()
        make_suite(cases, n=args.n, seed=args.seed, size=args.size, bracket_size=args.bracket_size,
                   progress=lambda msg: print(msg, file=sys.stderr, flush=True))
        print(f"suite made in {time.perf_counter() - t0:.0f} s", file=sys.stderr)
    out = Path(args.out)
    if args.merge:
        rows = []
        for f in sorted(out.glob("study_part*.json")):
            rows += json.loads(f.read_text())["cases"]
        rows.sort(key=lambda r: r["case"])
        return write_study(rows, out, argv)
    folders = sorted(p for p in cases.iterdir() if (p / "truth.json").exists())
    if args.only:
        keep = {int(v) for v in args.only.split(",")}
        folders = [f for i, f in enumerate(folders) if i in keep]
    if args.part:
        k, n = (int(v) for v in args.part.split("/"))
        folders = folders[k::n]
    out.mkdir(parents=True, exist_ok=True)
    rows = []
    for f in folders:
        truth = json.loads((f / "truth.json").read_text())
        photo = f / truth["photo"].rstrip("/")
        t0, c0 = time.perf_counter(), time.process_time()
        try:
            extra = {"orders": args.orders} if args.orders else {}
            r = skyfit.fit_photo(photo, time=truth["time"], location=truth["location"], **extra)
            row = score(truth, r.result)
            r.save_report(f / "report.png")
        except ValueError as e:
            row = {"seed": truth["seed"], "error": str(e)}
        row["case"] = f.name
        row["wall_s"] = time.perf_counter() - t0
        row["cpu_s"] = time.process_time() - c0  # all threads of this process: the machine is shared
        row["load_avg"] = os.getloadavg()[0]
        rows.append(row)
        print(json.dumps({k: row.get(k) for k in ("case", "aod_true", "aod_fit", "heading_err_deg", "centre_err_px",
                                                  "sun_separation_deg", "rmse_rel", "wall_s", "cpu_s", "load_avg", "error")}),
              flush=True)
        if args.part:  # after every case: a killed part keeps what it has
            (out / f"study_part{args.part.split('/')[0]}.json").write_text(json.dumps({"cases": rows}, indent=1, default=str))
    if args.part:
        return 0
    return write_study(rows, out, argv)


def coverage(rows: list) -> dict:
    """How often the truth lies within 1 and 2 reported sigma (the total, the budget's without the validation term, and
    the noise's alone) of the fitted AOD,
    Angstrom exponent and g, over the cases that report both."""
    out = {}
    for key, fit, true in (("aod_550", "aod_fit", "aod_true"), ("angstrom_alpha", "alpha_fit", "alpha_true"), ("g", "g_fit", "g_true")):
        for kind in ("sigma", "sigma_statistical", "sigma_noise"):
            z = [abs(r[fit] - r[true]) / r[kind][key] for r in rows
                 if (r.get(kind) or {}).get(key) and r.get(true) is not None]
            out[f"{key}_{kind}"] = {"n": len(z), "within_1": int(sum(v <= 1 for v in z)), "within_2": int(sum(v <= 2 for v in z)),
                                    "median_abs_z": float(np.median(z)) if z else None}
    return out


def write_study(rows: list, out: Path, argv) -> int:
    """study.json (summary and every case) and study.md (the table) of the fitted cases."""
    ok = [r for r in rows if "error" not in r]
    aod_rel = np.array([r["aod_fit"] / r["aod_true"] - 1 for r in ok])
    summary = {
        "cases": len(rows), "fitted": len(ok),
        "aod_rel_err": {"median_abs": float(np.median(np.abs(aod_rel))) if ok else None,
                        "p90_abs": float(np.percentile(np.abs(aod_rel), 90)) if ok else None,
                        "within_15pct": int((np.abs(aod_rel) <= 0.15).sum()), "values": aod_rel.tolist()},
        "heading_within_2deg": sum(abs(r["heading_err_deg"]) <= 2 for r in ok),
        "centre_within_3px": sum(r["centre_err_px"] <= 3 for r in ok),
        "sun_within_1deg": sum(r["sun_separation_deg"] is not None and r["sun_separation_deg"] <= 1 for r in ok),
        "sun_centroid_within_1deg": sum(r.get("sun_centroid_separation_deg") is not None
                                        and r["sun_centroid_separation_deg"] <= 1 for r in ok),
        "sun_model_within_1deg_of_truth": sum((r.get("sun_err_deg") or {}).get("model") is not None
                                              and r["sun_err_deg"]["model"] <= 1 for r in ok),
        "sun_err_deg_median": {k: float(np.median([r["sun_err_deg"][k] for r in ok if (r.get("sun_err_deg") or {}).get(k) is not None]))
                               for k in ("model", "detected", "centroid") if any((r.get("sun_err_deg") or {}).get(k) is not None for r in ok)},
        "sun_detected": sum(r["sun_detected"] for r in ok),
        "projection_right": sum(r["projection_fit"] == r["projection_true"] for r in ok),
        "rays_p95_within_0.5deg": sum(r.get("ray_err_deg", {}).get("p95", math.inf) <= 0.5 for r in ok),
        "rays_p95_median_deg": float(np.median([r["ray_err_deg"]["p95"] for r in ok if "ray_err_deg" in r])) if ok else None,
        "coverage": coverage(ok),
        "median_wall_s": float(np.median([r["wall_s"] for r in ok])) if ok else None,
        "median_cpu_s": float(np.median([r["cpu_s"] for r in ok])) if ok else None,
        "median_load_avg": float(np.median([r["load_avg"] for r in rows])) if rows else None,
        "command": "scripts/photo_study.py " + " ".join(argv if argv is not None else sys.argv[1:]),
    }
    (out / "study.json").write_text(json.dumps({"summary": summary, "cases": rows}, indent=1, default=str))
    lines = ["| case | bracket | projection (true → fit) | sun zenith | AOD true | AOD fit ± σ | α true / fit | g true / fit "
             "| heading err [°] | centre err [px] | rays p95 [°] | lens k (KB k1 true) | sun sep [°] (centroid's) "
             "| sun from truth [°]: model / detected / centroid | rel. rms | wall s | CPU s | load |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        if "error" in r:
            lines.append(f"| {r['case']} | | | | | failed: {r['error']} | | | | | | | | | | | | |")
            continue
        sig = f" ± {r['aod_sigma']:.3f}" if r.get("aod_sigma") else ""
        sep = "—" if r["sun_separation_deg"] is None else f"{r['sun_separation_deg']:.2f}"
        if r.get("sun_centroid_separation_deg") is not None and r.get("sun_detected_by") == "registration":
            sep += f" ({r['sun_centroid_separation_deg']:.2f})"
        err = r.get("sun_err_deg") or {}
        truth_err = " / ".join("—" if err.get(k) is None else f"{err[k]:.2f}" for k in ("model", "detected", "centroid"))
        lines.append(f"| {r['case']} | {'yes' if r['bracket'] else 'no'} | {r['projection_true']} → {r['projection_fit']} "
                     f"| {r['sun_zenith_deg']:.1f} | {r['aod_true']:.3f} | {r['aod_fit']:.3f}{sig} "
                     f"| {r['alpha_true']:.2f} / {r['alpha_fit']:.2f} | {r['g_true']:.2f} / {r['g_fit']:.2f} "
                     f"| {r['heading_err_deg']:+.2f} | {r['centre_err_px']:.2f} | {r['ray_err_deg']['p95']:.2f} "
                     f"| {'—' if r.get('lens_radial') is None else format(r['lens_radial'], '+.3f')}"
                     f"{'' if r.get('kb_k1_true') is None else ' (' + format(r['kb_k1_true'], '+.3f') + ')'} "
                     f"| {sep} | {truth_err} | {r['rmse_rel']:.3f} | {r['wall_s']:.0f} "
                     f"| {r.get('cpu_s', float('nan')):.0f} | {r.get('load_avg', float('nan')):.1f} |")
    (out / "study.md").write_text("\n".join(lines) + "\n\n```json\n" + json.dumps(summary, indent=1) + "\n```\n")
    print(json.dumps(summary, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
