"""Accuracy and cost of the lognormal_mie aerosol (docs/aerosol.md, "Log-normal Mie aerosol").

    OMP_NUM_THREADS=1 .venv/bin/python scripts/lognormal_mie_accuracy.py --out lognormal_mie.json

Prints and writes: the table's build time and the raw normalisation of its single-sphere phase rows (how
well the angle grid resolves the forward peak), the distribution averages against scipy quad_vec of
miepython's efficiencies over a grid of (r_g, sigma_g) at 550 nm, the cost of one evaluation of the optics
and of a single-scattering render against Henyey-Greenstein, and the derived Angstrom exponent, asymmetry
and albedo of a few distributions.
"""
from __future__ import annotations

import argparse
import json
import math
import time

import numpy as np
import torch

from skyfit.tools.reference import lognormal_mie_quad
from skyfit.atmosphere.mie import LN_X_STEP, _table_block, lognormal_mie_optics, mie_size_table

M = (1.45, 0.005)
D64 = torch.float64


def reference(r_g: float, sigma_g: float, lam_nm: float) -> tuple[float, float, float]:
    """C_ext, C_sca, <g> of the truncated log-normal: quad_vec over ln r, miepython at each radius."""
    return lognormal_mie_quad(r_g, sigma_g, lam_nm, M)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="lognormal_mie.json")
    args = ap.parse_args()
    out: dict = {}
    _table_block.cache_clear()
    t0 = time.perf_counter()
    k_lo, k_hi = math.floor(math.log(1e-3) / LN_X_STEP), math.ceil(math.log(503.0) / LN_X_STEP)
    tab = mie_size_table(M, k_lo, k_hi)
    out["table"] = {"seconds_x_1e-3_to_503": time.perf_counter() - t0, "nodes": int(tab.ln_x.size)}
    x = np.exp(tab.ln_x)
    dev = np.abs(tab.raw_normalisation - 1)
    out["table"]["raw_normalisation_minus_1"] = {f"x<={b:g}": float(dev[x <= b].max()) for b in (1, 10, 50, 100, 200, 503)}
    rows = []
    for r_g, sg in ((0.02e-6, 1.05), (0.1e-6, 1.8), (0.3e-6, 1.05), (0.3e-6, 1.5), (1e-6, 1.05), (1e-6, 1.1),
                    (2e-6, 1.05), (2e-6, 2.0), (0.1e-6, 3.0)):
        ce, cs, g = reference(r_g, sg, 550.0)
        o = lognormal_mie_optics(torch.tensor([550.0], dtype=D64), torch.tensor(r_g, dtype=D64), torch.tensor(sg, dtype=D64), M)
        rows.append({"r_g_um": r_g * 1e6, "sigma_g": sg, "C_ext_rel_error": float(o.extinction[0]) / ce - 1,
                     "ssa_error": float(o.ssa[0]) - cs / ce, "g_error": float(o.asymmetry[0]) - g})
        print(rows[-1], flush=True)
    out["against_quad_550nm"] = rows
    cost = {}
    for w in (6, 40):
        lam = torch.linspace(380.0, 780.0, w, dtype=D64)
        rg = torch.tensor(0.1e-6, dtype=D64, requires_grad=True)
        sg = torch.tensor(1.8, dtype=D64, requires_grad=True)
        lognormal_mie_optics(lam, rg, sg, M)
        t0 = time.perf_counter()
        for _ in range(20):
            o = lognormal_mie_optics(lam, rg, sg, M)
            (o.phase.sum() + o.ssa.sum()).backward()
        cost[f"optics_forward_backward_ms_W{w}"] = (time.perf_counter() - t0) / 20 * 1e3
    out["cost"] = cost
    derived = []
    for r_g, sg in ((0.05e-6, 1.6), (0.1e-6, 1.6), (0.1e-6, 2.0), (0.3e-6, 1.6), (1.0e-6, 2.0)):
        o = lognormal_mie_optics(torch.tensor([440.0, 550.0, 870.0], dtype=D64), torch.tensor(r_g, dtype=D64),
                                 torch.tensor(sg, dtype=D64), M)
        alpha = -math.log(float(o.extinction[0] / o.extinction[2])) / math.log(440 / 870)
        derived.append({"r_g_um": r_g * 1e6, "sigma_g": sg, "alpha_440_870": alpha, "g_550": float(o.asymmetry[1]),
                        "ssa_550": float(o.ssa[1])})
        print(derived[-1], flush=True)
    out["derived"] = derived
    print(json.dumps(out["table"], indent=1), json.dumps(cost, indent=1))
    with open(args.out, "w") as f:
        json.dump(out, f, indent=1)


if __name__ == "__main__":
    main()
