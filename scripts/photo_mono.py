"""Turn a photo of the synthetic suite (scripts/photo_study.py's cases) into a monochrome camera's, to measure the
grey-image path of a photo fit (docs/photos.md, "Monochrome cameras").

    .venv/bin/python scripts/photo_mono.py /tmp/photo_cases/case_002 /tmp/mono/case_002
    skyfit fit /tmp/mono/case_002/photo.jpg --time T --location LAT,LON,ELEV --out r.json

    for c in $(seq -w 0 19); do .venv/bin/python scripts/photo_mono.py /tmp/photo_cases/case_0$c /tmp/mono/case_0$c; done
    OMP_NUM_THREADS=1 .venv/bin/python scripts/photo_study.py --cases /tmp/mono --n 20 --out docs/photos/mono --threads 1 --part 0/2

Each frame (``photo.jpg``, or every ``bracket/*.jpg``) is decoded from sRGB (colour-science's cctf), its linear
luminance taken with the sRGB (Rec. 709) weights, encoded to sRGB again and written as an 8-bit grey JPEG (quality
90, the EXIF kept). So the grey camera's curve is the luma-weighted sum of the case camera's output curves: the CIE
photopic luminance where the case's camera is colorimetric, a camera's own panchromatic mix otherwise, which is what
a monochrome sensor's is too (the fit's default curve is the CIE one). The saturated sun stays saturated: a channel at
the clip is 1 after decoding, and luminance of three clipped channels is 1.
"""
from __future__ import annotations

import argparse
import shutil
from pathlib import Path

import colour
import numpy as np
from PIL import Image

LUMA = np.array([0.2126, 0.7152, 0.0722])


def grey_jpeg(src: Path, dst: Path) -> None:
    im = Image.open(src)
    exif = im.info.get("exif")
    lin = colour.cctf_decoding(np.asarray(im).astype(np.float64) / 255, function="sRGB")
    enc = colour.cctf_encoding(np.clip(lin @ LUMA, 0, 1), function="sRGB")
    dst.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(np.round(enc * 255).astype(np.uint8), mode="L").save(dst, quality=90, **({"exif": exif} if exif else {}))


def reencode_case(case: Path, out: Path, write_frame) -> int:
    """Write every frame of a suite case (``photo.jpg`` or ``bracket/*.jpg``) through ``write_frame(src, dst)`` and copy
    its truth, mask and the suite's manifest; the number of frames."""
    frames = [case / "photo.jpg"] if (case / "photo.jpg").exists() else sorted((case / "bracket").glob("*.jpg"))
    for f in frames:
        write_frame(f, out / f.relative_to(case))
    for name in ("truth.json", "mask_truth.png"):
        if (case / name).exists():
            shutil.copy(case / name, out / name)
    if (case.parent / "suite.json").exists():  # scripts/photo_study.py then reads the new suite, not making its own
        shutil.copy(case.parent / "suite.json", out.parent / "suite.json")
    return len(frames)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("case", help="a case folder of the suite (photo.jpg or bracket/, truth.json, mask_truth.png)")
    ap.add_argument("out", help="folder to write the grey photo.jpg or bracket/, truth.json and mask_truth.png")
    a = ap.parse_args(argv)
    n = reencode_case(Path(a.case), Path(a.out), grey_jpeg)
    print(f"{a.out}: {n} grey frame(s)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
