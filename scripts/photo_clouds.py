"""Paint clouds on a photo of the synthetic suite (scripts/photo_study.py's cases) to see what a cloudy sky does to
a photo fit (docs/photos.md, "Clouds").

    .venv/bin/python scripts/photo_clouds.py /tmp/photo_cases/case_002 0.15 1 /tmp/cl/case_002
    skyfit fit /tmp/cl/case_002/photo.jpg --time T --location LAT,LON,ELEV --out r.json

The clouds: a fractal field (Gaussian-filtered white noise at 4, 10, 25 and 50 px, weighted by the scale) over the
case's sky (``mask_truth.png`` 0) within 0.85 of the lens radius, thresholded at the share asked; their optical
depth rises from the edge inward over 0.6 of the field's sigma (thin edges show the sky through them); their
radiance is grey, 2.5 x the sky's median luminance times a texture of 0.7-1.3, where it replaces the sky. Done
on the photo's decoded linear values (sRGB, 8 bits), then encoded again (JPEG quality 90, the EXIF kept). Not a
cloud model: no shading by the sun's direction, no silver lining, no shadows on the sky; a test of the pipeline's
robustness to bright, colourless, textured patches over a share of the sky, the sun's aureole included.
"""
from __future__ import annotations

import argparse
import json
import shutil
from pathlib import Path

import colour
import numpy as np
import scipy.ndimage as ndi
from PIL import Image


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("case", help="a case folder of the suite (photo.jpg, truth.json, mask_truth.png)")
    ap.add_argument("share", type=float, help="share of the sky within 0.85 of the lens radius under cloud")
    ap.add_argument("seed", type=int)
    ap.add_argument("out", help="folder to write photo.jpg, truth.json (with a 'clouds' entry) and mask_truth.png")
    a = ap.parse_args(argv)
    case, out = Path(a.case), Path(a.out)
    truth = json.loads((case / "truth.json").read_text())
    im = Image.open(case / "photo.jpg")
    exif = im.info.get("exif")
    code = np.asarray(im).astype(np.float64) / 255
    lin = colour.cctf_decoding(code, function="sRGB")
    mask = np.asarray(Image.open(case / "mask_truth.png"))
    cam = truth["camera"]
    H, W = lin.shape[:2]
    yy, xx = np.mgrid[:H, :W]
    sky = (mask == 0) & (np.hypot(xx - cam["cx"], yy - cam["cy"]) / cam["radius_px"] < 0.85)
    rng = np.random.default_rng(a.seed)
    field = sum(ndi.gaussian_filter(rng.standard_normal((H, W)), s) * s for s in (4, 10, 25, 50))
    field = (field - field[sky].mean()) / field[sky].std()
    thr = np.quantile(field[sky], 1 - a.share)
    cloud = sky & (field > thr)
    depth = np.clip((field - thr) / 0.6, 0, 1)[..., None]
    base = float(np.median((lin @ np.array([0.2126, 0.7152, 0.0722]))[sky]))
    grey = (2.5 * base * (0.7 + 0.6 * ndi.gaussian_filter(rng.uniform(size=(H, W)), 2)))[..., None]
    out_lin = np.clip(np.where(cloud[..., None], (1 - depth) * lin + depth * grey, lin), 0, 1)
    enc = colour.cctf_encoding(out_lin, function="sRGB")
    out.mkdir(parents=True, exist_ok=True)
    Image.fromarray(np.round(enc * 255).astype(np.uint8)).save(out / "photo.jpg", quality=90, **({"exif": exif} if exif else {}))
    truth["clouds"] = {"share_of_sky_within_0.85_radius": a.share, "seed": a.seed, "pixels": int(cloud.sum()),
                       "how": "scripts/photo_clouds.py"}
    (out / "truth.json").write_text(json.dumps(truth))
    shutil.copy(case / "mask_truth.png", out / "mask_truth.png")
    print(f"{out}: {int(cloud.sum())} cloud px of {int(sky.sum())}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
