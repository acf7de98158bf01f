#!/usr/bin/env python
"""A photo fit's Bruneton build with three rules of the scattering density's incident directions, side by side
(docs/multiple_scattering.md, "The density directions' pole"): 2017's 16 x 32, the photo fit's 16 x 32 with the two
theta bands nearest the zenith split (skyfit.fit.photo.PHOTO_DENSITY), and 32 x 32; PHOTO_TABLES, 6 wavelengths,
float32, the builds alternating, a first round dropped.

    .venv/bin/python scripts/density_cost.py [--threads 2] [--rounds 5]
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from skyfit.atmosphere.config import atmosphere_from_config, load_yaml  # noqa: E402
from skyfit.fit.photo import PHOTO_TABLES  # noqa: E402
from skyfit.scattering.bruneton_tables import TableSizes  # noqa: E402
from skyfit.scattering.multiple import Quadrature, precompute  # noqa: E402

RULES = {"16 x 32": (16, 32, 0), "16 x 32, 2 split": (16, 32, 2), "32 x 32": (32, 32, 0)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--rounds", type=int, default=5)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    root = Path(__file__).resolve().parents[1]
    atm = atmosphere_from_config(load_yaml(root / "skyfit" / "configs" / "earth_hazy.yaml"), np.linspace(440, 660, 6),
                                 dtype=torch.float32)
    seconds: dict[str, list[float]] = {k: [] for k in RULES}
    for k in range(args.rounds + 1):
        for name, (theta, phi, zenith) in RULES.items():
            t = time.perf_counter()
            with torch.no_grad():
                precompute(atm, orders=4, sizes=TableSizes(*PHOTO_TABLES), progress=False,
                           quadrature=Quadrature(ray_rule="gauss", density_theta=theta, density_phi=phi, density_zenith=zenith))
            if k:
                seconds[name].append(time.perf_counter() - t)
    base = float(np.median(seconds["16 x 32"]))
    for name, v in seconds.items():
        print(f"{name:18s} median {np.median(v):.2f} s ({np.median(v) / base:.2f}x)  runs " + ", ".join(f"{x:.2f}" for x in v))


if __name__ == "__main__":
    main()
