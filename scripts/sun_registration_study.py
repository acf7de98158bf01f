"""The sun's registration against its centroid on the single photos of the synthetic suites (docs/photos.md, "A flat
aureole registers nothing"): for every photo that is not a bracket, the photo fit (no Laplace sigma), then the
distance in pixels from the true sun (truth.json) of the fitted camera's sun, of the saturated region's centroid and
of the registered sun (skyfit.fit.photo.register_sun), with the registration's overlap, size and contrast. One JSON
line per photo on stdout, all of them in OUT.

    OMP_NUM_THREADS=1 .venv/bin/python scripts/sun_registration_study.py OUT.json /tmp/photo_cases/case_0*
"""
from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import torch


def main(out_path: str, cases: list[str]) -> None:
    import skyfit

    torch.set_num_threads(1)
    out = []
    for d in cases:
        f = Path(d)
        t = json.loads((f / "truth.json").read_text())
        if len(t["frames"]) > 1:
            continue
        r = skyfit.fit_photo(f / t["photo"].rstrip("/"), time=t["time"], location=t["location"], laplace=False)
        s, truth = r.result["sun"], t["sun"]["model_px"]
        reg = s["registration"] or {}

        def err(p):
            return None if p is None else math.hypot(p[0] - truth[0], p[1] - truth[1])

        registered = None if not reg else [s["model_px"][0] + reg["shift_px"][0], s["model_px"][1] + reg["shift_px"][1]]
        rec = {"case": d, "by": s["detected_by"], "kind": s["detected_kind"], "radius_px": s["detected_radius_px"],
               "err_px": {"model": err(s["model_px"]), "centroid": err(s["centroid_px"]), "registered": err(registered)},
               "sep_deg": s["separation_deg"], "centroid_sep_deg": s["centroid_separation_deg"], "reg": reg,
               "aod": r.result["aerosol"]["aod_550"]}
        print(json.dumps(rec), flush=True)
        out.append(rec)
    Path(out_path).write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    if len(sys.argv) < 3:
        sys.exit("usage: sun_registration_study.py OUT.json CASE_DIR...")
    main(sys.argv[1], sys.argv[2:])
