"""How three published cameras render sky colours against CIE colorimetry (docs/photos.md, "A camera is not a
colorimeter"): :func:`skyfit.tools.photo_synth.colour_rendering` for each, with its colour matrix (sRGB output) and
without (white-balanced camera RGB, docs/photos.md "Fewer builds"), as a Markdown table.

    .venv/bin/python scripts/camera_colour.py
"""
from __future__ import annotations

import warnings

import numpy as np

from skyfit.tools.photo_synth import colour_rendering

CAMERAS = ("Canon EOS 5D Mark II (rawtoaces)", "Nikon 5100 (NPL)", "Sigma SDMerill (NPL)")


def main() -> int:
    warnings.filterwarnings("ignore")
    print("| camera | output | R/G over CIE at a = 4, 2, 0.5 | B/G over CIE at a = 4, 2, 0.5 | rms log chromaticity: gains | "
          "+ one saturation (s) | + red, blue saturations (s_R, s_B) |")
    print("|---|---|---|---|---|---|---|")
    for output, name in ((o, n) for o in ("srgb", "camera_rgb") for n in CAMERAS):
        r = colour_rendering(name, output=output)
        pick = [int(np.argmin(abs(r["slopes"] - a))) for a in (4.0, 2.0, 0.5)]
        rel = r["relative"]
        print(f"| {name} | {output} | " + ", ".join(f"{rel[k, 0]:.3f}" for k in pick) + " | " + ", ".join(f"{rel[k, 2]:.3f}" for k in pick)
              + f" | {r['rms_gains']:.4f} | {r['rms_one']:.4f} (s {r['s']:.2f}) | {r['rms_two']:.4f} "
              f"(s_R {r['s_red']:.2f}, s_B {r['s_blue']:.2f}) |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
