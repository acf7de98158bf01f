"""The camera from the image alone, on the synthetic photo suite: circle, sun, projection, heading vs the truth.

Runs only what :func:`skyfit.fit.photo.prepare_scene` does before the atmosphere fit when no camera is given
(read the photo, compute the sun (SPA), :func:`skyfit.fit.photo.cameras_from_image`: circle, symmetry axis,
sun, one camera per projection) on every case of a suite made by :func:`skyfit.tools.photo_synth.make_suite`
(``truth.json`` in each folder) and prints a Markdown table: the true projection, the sun's best and
runner-up (with their scores), which projections the sun cannot tell apart (:func:`skyfit.fit.photo.
projection_decision`; :func:`skyfit.fit.photo.fit_scene` fits those briefly and keeps the lowest loss, not run
here: "—" where the sun decides alone), the detected vs the true sun pixel [px] and the angle between them
[deg, under the true camera], the heading error of the untilted guess [deg; a tilt t adds up to about
t / sin(zenith)] and the centre error [px]. About 1 s per case.

    OMP_NUM_THREADS=1 .venv/bin/python scripts/photo_calibration_check.py --cases /tmp/photo_cases
"""
from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np
import torch


def circular_diff_deg(a: float, b: float) -> float:
    return (a - b + 180.0) % 360.0 - 180.0


def check_case(folder: Path, diag: Path | None = None) -> dict:
    """The camera-from-image step of one case against its ``truth.json``."""
    from skyfit.camera.fisheye import CLASSICAL_PROJECTIONS, FisheyeCamera, zenith_azimuth_to_enu
    from skyfit.camera.sun import parse_location, parse_time, sun_position
    from skyfit.fit.photo import cameras_from_image, projection_decision
    from skyfit.io.photo import read_photo

    truth = json.loads((folder / "truth.json").read_text())
    t0 = time.perf_counter()
    photo = read_photo(folder / truth["photo"].rstrip("/"))
    lat, lon, elev = parse_location(truth["location"])
    sp = sun_position(parse_time(truth["time"]), lat, lon, elev)
    sz, sa = float(sp.zenith), float(sp.azimuth)
    h, w = photo.rgb.shape[:2]
    circle, sun, cands = cameras_from_image(photo, sz, sa, CLASSICAL_PROJECTIONS)
    seconds = time.perf_counter() - t0
    tc = truth["camera"]
    true_cam = FisheyeCamera.from_metadata({k: v for k, v in tc.items() if k in (
        "projection", "size", "width", "height", "cx", "cy", "radius_px", "focal_px", "kb_coeffs", "up_azimuth_deg",
        "tilt_deg", "max_zenith_deg")} | {"size": [h, w] if h != w else h})
    tx, ty = truth["sun"]["model_px"]
    row = {"case": folder.name, "bracket": truth["bracket"] is not None, "projection_true": tc["projection"],
           "sun_zenith_deg": sz, "tilt_deg": tc.get("tilt_magnitude_deg"), "seconds": seconds,
           "centre_err_px": math.hypot(circle.cx - tc["cx"], circle.cy - tc["cy"]),
           "radius_err_px": circle.radius - tc["radius_px"], "true_sun_px": [tx, ty]}
    row["ranking"] = [(c.projection, c.score) for c in cands]
    row["projection_sun"] = cands[0].projection
    row["heading_err_deg"] = circular_diff_deg(float(cands[0].camera.up_azimuth_deg), tc["up_azimuth_deg"])
    fitted = projection_decision(cands, sun)
    row["short_fits"] = [c.projection for c in fitted] if len(fitted) > 1 else []
    if sun is None:
        row.update(sun_px=None, sun_err_px=None, sun_err_deg=None, sun_kind="none")
    else:
        with torch.no_grad():
            d = true_cam.pixel_to_direction(torch.tensor(sun.x, dtype=torch.float64),
                                            torch.tensor(sun.y, dtype=torch.float64)).numpy()
        s = zenith_azimuth_to_enu(torch.tensor(math.radians(sz), dtype=torch.float64),
                                  torch.tensor(math.radians(sa), dtype=torch.float64)).numpy()
        err = math.degrees(math.atan2(float(np.linalg.norm(np.cross(d, s))), float(np.dot(d, s))))
        row.update(sun_px=[sun.x, sun.y], sun_err_px=math.hypot(sun.x - tx, sun.y - ty), sun_err_deg=err,
                   sun_kind=getattr(sun, "kind", "extended" if sun.extended else "core" if sun.saturated else "peak"))
    if diag is not None:
        save_diag(diag / f"{folder.name}.png", photo, circle, sun, (tx, ty), truth)
    return row


class _StopBeforeMainFit(Exception):
    pass


def short_fit_choice(folder: Path) -> tuple[str | None, str]:
    """The projection :func:`skyfit.fit.photo.fit_scene` keeps after its short fits and its note, stopped before the
    main fit: ``block_image`` is wrapped to raise at the main fit's block count (the short fits use
    ``QUICK_SAMPLES``). 15-40 s of CPU per case."""
    import copy

    import skyfit.fit.photo as fp
    from skyfit.atmosphere import read_config

    truth = json.loads((folder / "truth.json").read_text())
    scene = fp.prepare_scene(folder / truth["photo"].rstrip("/"), time=truth["time"], location=truth["location"])
    block_image = fp.block_image

    def stop_at_main_fit(sc, step=None, exclude=None, target=fp.TARGET_SAMPLES, **kw):
        if target == fp.TARGET_SAMPLES:
            raise _StopBeforeMainFit
        return block_image(sc, step=step, exclude=exclude, target=target, **kw)

    fp.block_image = stop_at_main_fit
    try:
        fp.fit_scene(scene, copy.deepcopy(read_config("earth")[0]), laplace=False)
    except _StopBeforeMainFit:
        pass
    finally:
        fp.block_image = block_image
    note = next((n for n in scene.notes if n.startswith("projection chosen")), None)
    if note is None:
        return None, "the sun decided"
    losses = [item.rsplit(" ", 1) for item in note.split(" among ", 1)[1].split(", ")]
    return min(losses, key=lambda pv: float(pv[1]))[0], note


def save_diag(path: Path, photo, circle, sun, true_px, truth) -> None:
    """The darkest frame (log scale), its saturated pixels in red, the circle, true sun (green +), detected (cyan x)."""
    import skimage

    lum = photo.darkest @ np.array([0.2126, 0.7152, 0.0722])
    v = np.log10(np.maximum(lum, 1e-6))
    lo, hi = np.percentile(v[np.isfinite(v)], [5, 99.9])
    g = np.clip((v - lo) / max(hi - lo, 1e-9), 0, 1)
    img = np.stack([g, g, g], -1)
    img[photo.darkest_saturated] = 0.5 * img[photo.darkest_saturated] + [0.5, 0, 0]
    rr, cc = skimage.draw.circle_perimeter(int(round(circle.cy)), int(round(circle.cx)), int(round(circle.radius)),
                                           shape=img.shape[:2])
    img[rr, cc] = [1, 1, 0]

    def mark(x, y, colour, diagonal):
        for k in range(-6, 7):
            for dx, dy in (((k, k), (k, -k)) if diagonal else ((k, 0), (0, k))):
                i, j = int(round(y + dy)), int(round(x + dx))
                if 0 <= i < img.shape[0] and 0 <= j < img.shape[1]:
                    img[i, j] = colour

    mark(*true_px, [0, 1, 0], False)
    if sun is not None:
        mark(sun.x, sun.y, [0, 1, 1], True)
    path.parent.mkdir(parents=True, exist_ok=True)
    skimage.io.imsave(path, (img * 255).astype(np.uint8), check_contrast=False)


def table(rows: list[dict]) -> str:
    lines = ["| case | bracket | sun zen. [°] | projection true | by the sun (score °) | runner-up (score °) | short fits "
             "| sun kind | sun err [px] | sun err [°] | heading err [°] | centre err [px] |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        if "error" in r:
            lines.append(f"| {r['case']} | | | | failed: {r['error']} | | | | | | | |")
            continue
        (p1, s1), (p2, s2) = r["ranking"][0], r["ranking"][1]
        ok = "" if p1 == r["projection_true"] else " ✗"
        fits = ", ".join(r["short_fits"]) if r["short_fits"] else "—"
        if r.get("projection_fits"):
            fits += f" → {r['projection_fits']}" + ("" if r["projection_fits"] == r["projection_true"] else " ✗")
        se = "—" if r["sun_err_px"] is None else f"{r['sun_err_px']:.1f}"
        sd = "—" if r["sun_err_deg"] is None else f"{r['sun_err_deg']:.2f}"
        lines.append(f"| {r['case']} | {'yes' if r['bracket'] else 'no'} | {r['sun_zenith_deg']:.1f} | {r['projection_true']} "
                     f"| {p1} ({s1:.2f}){ok} | {p2} ({s2:.2f}) | {fits} | {r['sun_kind']} | {se} | {sd} "
                     f"| {r['heading_err_deg']:+.2f} | {r['centre_err_px']:.2f} |")
    return "\n".join(lines)


def summary(rows: list[dict]) -> dict:
    ok = [r for r in rows if "error" not in r]
    classical = [r for r in ok if r["projection_true"] != "kannala_brandt"]
    out = {
        "cases": len(rows),
        "heading_within_2deg": sum(abs(r["heading_err_deg"]) <= 2 for r in ok),
        "centre_within_3px": sum(r["centre_err_px"] <= 3 for r in ok),
        "sun_within_1deg": sum(r["sun_err_deg"] is not None and r["sun_err_deg"] <= 1 for r in ok),
        "classical_cases": len(classical),
        "projection_right_by_sun": sum(r["projection_sun"] == r["projection_true"] for r in classical),
        "projection_wrong_and_decided_by_sun": [r["case"] for r in classical if r["projection_sun"] != r["projection_true"]
                                                and not r["short_fits"]],
        "truth_among_short_fits": sum(r["projection_true"] in r["short_fits"] for r in classical if r["short_fits"]),
        "short_fit_cases": sum(bool(r["short_fits"]) for r in classical),
    }
    if any("projection_fits" in r for r in ok):
        out["projection_right_after_short_fits"] = sum(r.get("projection_fits", r["projection_sun"]) == r["projection_true"]
                                                       for r in classical)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", default="/tmp/photo_cases", help="folder of the suite (case_*/truth.json)")
    ap.add_argument("--only", help="comma list of case indices")
    ap.add_argument("--diag", help="folder for one diagnostic PNG per case (darkest frame, saturation, suns)")
    ap.add_argument("--json", help="write the rows and the summary to this JSON file")
    ap.add_argument("--short-fits", action="store_true", help="also run fit_scene's short projection fits where the "
                    "sun does not decide (15-40 s CPU per such case) and print the projection they keep")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    folders = sorted(p for p in Path(args.cases).iterdir() if (p / "truth.json").exists())
    if args.only:
        keep = {int(v) for v in args.only.split(",")}
        folders = [f for i, f in enumerate(folders) if i in keep]
    rows = []
    for f in folders:
        try:
            rows.append(check_case(f, Path(args.diag) if args.diag else None))
        except ValueError as e:
            rows.append({"case": f.name, "error": str(e)})
        print(f"{f.name} done", file=sys.stderr, flush=True)
    if args.short_fits:
        for r in rows:
            if r.get("short_fits"):
                r["projection_fits"], r["short_fit_note"] = short_fit_choice(Path(args.cases) / r["case"])
                print(f"{r['case']} ({r['projection_true']}): {r['short_fit_note']}", file=sys.stderr, flush=True)
    print(table(rows))
    for r in rows:
        if r.get("short_fit_note"):
            print(f"- {r['case']} ({r['projection_true']}): {r['short_fit_note']}")
    s = summary(rows)
    print("\n```json\n" + json.dumps(s, indent=1) + "\n```")
    if args.json:
        Path(args.json).write_text(json.dumps({"summary": s, "cases": rows}, indent=1, default=str))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
