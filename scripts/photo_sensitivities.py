"""A colour-only CAMERA.yaml for a synthetic photo: the curves of its channels, from its truth.json (docs/photos.md,
"The camera's colour given").

    .venv/bin/python scripts/photo_sensitivities.py /tmp/sz/case_202 /tmp/sz/sigma
    skyfit fit /tmp/sz/case_202/photo.jpg --time T --location L --camera /tmp/sz/sigma.yaml --out r.json

writes OUT.csv (wavelength_nm,R,G,B: the sensor's published sensitivities, colour-science's
``MSDS_CAMERA_SENSITIVITIES``, times the white balance's gains, through the colour matrix where the photo's output
space is sRGB; green's peak 1) and OUT.yaml (``spectral_sensitivities: OUT.csv``, no lens). What a camera
characterised in a laboratory (its output's response to monochromatic light) would give.
"""
from __future__ import annotations

import json
import sys
from pathlib import Path

import colour
import numpy as np


def main(argv=None) -> int:
    case, out = (Path(a) for a in (argv or sys.argv[1:]))
    sen = json.loads((case / "truth.json").read_text())["sensor"]
    curves = colour.MSDS_CAMERA_SENSITIVITIES[sen["name"]]
    eff = np.asarray(sen["white_balance"]["gains_rgb"])[:, None] * curves.values.T  # (3, K)
    if sen.get("output_space") == "srgb":
        eff = np.asarray(sen["colour_matrix"]) @ eff
    eff = (eff / eff[1].max()).T
    np.savetxt(out.with_suffix(".csv"), np.column_stack([curves.wavelengths, eff]), delimiter=",",
               header="wavelength_nm,R,G,B", comments="")
    out.with_suffix(".yaml").write_text(f"spectral_sensitivities: {out.with_suffix('.csv').name}\n")
    print(f"{out.with_suffix('.yaml')}: {sen['name']}, output {sen.get('output_space')}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
