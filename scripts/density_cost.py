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
from typing import Callable

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from skyfit.atmosphere.config import atmosphere_from_config, load_yaml  # noqa: E402
from skyfit.fit.photo import PHOTO_TABLES  # noqa: E402
from skyfit.scattering.bruneton_tables import TableSizes  # noqa: E402
from skyfit.scattering.multiple import Quadrature, precompute  # noqa: E402

RULES = {"16 x 32": (16, 32, 0), "16 x 32, 2 split": (16, 32, 2), "32 x 32": (32, 32, 0)}


def photo_build_args(description: str) -> argparse.Namespace:
    """--threads and --rounds of a side-by-side timing of photo-fit builds, torch's threads set."""
    ap = argparse.ArgumentParser(description=description)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--rounds", type=int, default=5)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    return args


def photo_atmosphere():
    """The hazy config on 6 wavelengths in float32, as a photo fit's tables are built."""
    return atmosphere_from_config(load_yaml(ROOT / "skyfit" / "configs" / "earth_hazy.yaml"), np.linspace(440, 660, 6),
                                  dtype=torch.float32)


def photo_build(atm, quadrature: Quadrature) -> None:
    """One Bruneton build of ``atm`` as a photo fit makes it: PHOTO_TABLES, 4 orders, no gradient."""
    with torch.no_grad():
        precompute(atm, orders=4, sizes=TableSizes(*PHOTO_TABLES), quadrature=quadrature, progress=False)


def alternate(builds: dict[str, Callable[[], None]], rounds: int) -> dict[str, list[float]]:
    """Seconds of each of ``builds`` over ``rounds`` rounds, one of each per round in turn, after a first round dropped."""
    seconds: dict[str, list[float]] = {k: [] for k in builds}
    for k in range(rounds + 1):
        for name, build in builds.items():
            t = time.perf_counter()
            build()
            if k:
                seconds[name].append(time.perf_counter() - t)
    return seconds


def main() -> None:
    args = photo_build_args(__doc__.splitlines()[0])
    atm = photo_atmosphere()
    seconds = alternate({name: (lambda q=Quadrature(ray_rule="gauss", density_theta=t, density_phi=p, density_zenith=z):
                                photo_build(atm, q)) for name, (t, p, z) in RULES.items()}, args.rounds)
    base = float(np.median(seconds["16 x 32"]))
    for name, v in seconds.items():
        print(f"{name:18s} median {np.median(v):.2f} s ({np.median(v) / base:.2f}x)  runs " + ", ".join(f"{x:.2f}" for x in v))


if __name__ == "__main__":
    main()
