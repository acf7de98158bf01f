"""Turn a photo of the synthetic suite (scripts/photo_study.py's cases) into one in another RGB space with its ICC
profile embedded, as a phone (Display P3) or a camera set to Adobe RGB writes it, to measure the profile path of a
photo fit (docs/photos.md, "Photos in other colour spaces").

    .venv/bin/python scripts/photo_icc.py /tmp/photo_cases/case_002 /tmp/p3/case_002 --space "Display P3"
    for c in $(seq -w 0 19); do .venv/bin/python scripts/photo_icc.py /tmp/photo_cases/case_0$c /tmp/p3/case_0$c; done
    OMP_NUM_THREADS=1 .venv/bin/python scripts/photo_study.py --cases /tmp/p3 --n 20 --out docs/photos/p3 --threads 1 --part 0/2

Each frame is decoded from sRGB (colour-science's cctf), taken from linear sRGB to the space's linear RGB by
colour-science's RGB_to_RGB (both D65: no adaptation), encoded with the space's own transfer function (a pixel with a
channel clipped in sRGB written clipped in all three: the matrix would hide the clip), and written as
an 8-bit JPEG (quality 90, EXIF kept) carrying the profile of :func:`skyfit.camera.icc.profile_for`. ``--strip``
writes the same pixels without the profile: what a reader that ignores profiles sees. ``--exif-only`` (Adobe RGB)
writes them without the profile but with EXIF ColorSpace "uncalibrated" and the interoperability index "R03", as a
Canon DSLR in Adobe RGB mode does.
"""
from __future__ import annotations

import argparse
from pathlib import Path

import colour
import numpy as np
from PIL import ExifTags, Image

from photo_mono import reencode_case
from skyfit.camera.icc import profile_for


def space_jpeg(src: Path, dst: Path, space: str, strip: bool, exif_only: bool = False) -> None:
    im = Image.open(src)
    exif = im.info.get("exif")
    if exif_only:
        exif = im.getexif()
        sub = exif.get_ifd(ExifTags.IFD.Exif)
        sub[40961] = 0xFFFF  # ColorSpace: uncalibrated
        sub[ExifTags.IFD.Interop] = {1: "R03", 2: b"0100"}  # DCF option colour space (Adobe RGB)
    codes = np.asarray(im)
    lin = colour.cctf_decoding(codes.astype(np.float64) / 255, function="sRGB")
    cs = colour.RGB_COLOURSPACES[space]
    rgb = colour.RGB_to_RGB(lin, colour.RGB_COLOURSPACES["sRGB"], cs, chromatic_adaptation_transform=None)
    enc = cs.cctf_encoding(np.clip(rgb, 0, 1))
    # a channel clipped in sRGB leaves the pixel unknown: the matrix would mix the clip into unclipped-looking values
    # in every channel, so such a pixel is written clipped in all three (a camera clips in its own space)
    enc[(codes >= 254).any(-1)] = 1.0
    dst.parent.mkdir(parents=True, exist_ok=True)
    extra = {"exif": exif} if exif else {}
    if not (strip or exif_only):
        extra["icc_profile"] = profile_for(space)
    Image.fromarray(np.round(enc * 255).astype(np.uint8)).save(dst, quality=90, **extra)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("case", help="a case folder of the suite (photo.jpg or bracket/, truth.json, mask_truth.png)")
    ap.add_argument("out", help="folder to write the re-encoded photo.jpg or bracket/, truth.json and mask_truth.png")
    ap.add_argument("--space", default="Display P3", help="a colour-science RGB space: 'Display P3', 'Adobe RGB (1998)'")
    ap.add_argument("--strip", action="store_true", help="write no ICC profile (the same pixels)")
    ap.add_argument("--exif-only", action="store_true",
                    help="no ICC profile; EXIF ColorSpace uncalibrated + interoperability R03 (Adobe RGB only)")
    a = ap.parse_args(argv)
    if a.exif_only and not a.space.startswith("Adobe RGB"):
        ap.error("--exif-only declares Adobe RGB: use it with --space 'Adobe RGB (1998)'")
    n = reencode_case(Path(a.case), Path(a.out), lambda s, d: space_jpeg(s, d, a.space, a.strip, a.exif_only))
    how = " (profile stripped)" if a.strip else " (declared by EXIF alone)" if a.exif_only else ""
    print(f"{a.out}: {n} frame(s) in {a.space}{how}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
