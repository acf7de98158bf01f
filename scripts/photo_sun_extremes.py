"""Synthetic photos with the sun near the zenith and near the horizon, beyond the suite's 20-80 deg (docs/photos.md,
"The sun at the zenith and at the horizon"):

    OMP_NUM_THREADS=2 .venv/bin/python scripts/photo_sun_extremes.py /tmp/sz

writes case_201 (sun zenith 8 deg, AOD 0.15), case_202 (86 deg, AOD 0.1; the seed draws the Sigma SD Merrill) and
case_203 (case 202's seed with the Canon 5D Mark II's sensitivities) with ``skyfit.tools.photo_synth.make_case``
at 600 x 600; each is then fitted as a user would, ``skyfit fit FOLDER/photo.jpg --time T --location L`` with T and
L from its truth.json.
"""
from __future__ import annotations

import sys
from pathlib import Path

import torch

from skyfit.tools.photo_synth import make_case

CASES = ((201, 8.0, 0.15, None), (202, 86.0, 0.1, None), (203, 86.0, 0.1, "Canon EOS 5D Mark II (rawtoaces)"))
"""(name, sun zenith [deg], AOD 550, camera or None: the seed's draw); case 203 uses seed 202."""


def main(argv=None) -> int:
    out = Path((argv or sys.argv[1:])[0])
    torch.set_num_threads(2)
    for name, zenith, aod, camera in CASES:
        seed = 202 if name == 203 else name
        t = make_case(seed, out / f"case_{name}", size=600, sun_zenith_deg=zenith, aod_550=aod, camera=camera)
        print(name, t["camera"]["projection"], t["sensor"]["name"], round(t["sun"]["zenith_deg"], 2), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
