#!/usr/bin/env python
"""A photo fit's Bruneton build with the Gauss-Legendre view-ray rule recomputed by numpy's leggauss per chunk
(before session 15) and taken from skyfit.quadrature's cache (now), side by side (docs/benchmarks.md, "Third pass: the
Gauss nodes cached"): the builds of scripts/density_cost.py (PHOTO_TABLES, 6 wavelengths, float32), alternating, a
first round dropped.

    .venv/bin/python scripts/gauss_nodes_speed.py [--threads 2] [--rounds 5]
"""
from __future__ import annotations

import numpy as np
import torch
from density_cost import alternate, photo_atmosphere, photo_build, photo_build_args

import skyfit.scattering.multiple as M


def uncached(n: int, rule: str, dtype, device):
    """``ray_nodes`` as it was: the Gauss-Legendre rule from numpy on every call (the same numbers)."""
    if rule == "trapezoid":
        return M._trapezoid(n, dtype, device)
    t, w = np.polynomial.legendre.leggauss(n + 1)
    return torch.as_tensor(0.5 * (t + 1.0), dtype=dtype, device=device), torch.as_tensor(0.5 * w, dtype=dtype, device=device)


def main() -> None:
    args = photo_build_args(__doc__.splitlines()[0])
    cached, atm = M.ray_nodes, photo_atmosphere()

    def with_nodes(fn):
        def build() -> None:
            M.ray_nodes = fn
            photo_build(atm, M.Quadrature(ray_rule="gauss"))
        return build

    seconds = alternate({"before": with_nodes(uncached), "after": with_nodes(cached)}, args.rounds)
    for name, v in seconds.items():
        print(name, "median %.2f s" % np.median(v), [round(x, 2) for x in v])
    print("ratio after/before of medians %.3f" % (np.median(seconds["after"]) / np.median(seconds["before"])))


if __name__ == "__main__":
    main()
