"""The error budget's reference (skyfit.fit.budget.ReferenceModel) under three precomputation rules of its Bruneton
tables, on scripts/coverage_model_error.py's truths (docs/uncertainty.md, "The reference's view-ray rule"): 2017's
(equal steps along the view ray, 16 x 32 density directions), REFERENCE_QUADRATURE (Gauss-Legendre view rays, the two
density bands nearest the zenith split) and Gauss-Legendre with 32 x 64 density directions. Per sky, the quantiles of
each one's noisy radiance over the last's (the same noise draw: the ratio is of the clean radiances to the noise).

    OMP_NUM_THREADS=2 .venv/bin/python scripts/reference_ray_rule.py
"""
from __future__ import annotations

import dataclasses
import functools
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
import coverage_model_error as C  # noqa: E402

from skyfit.fit import budget  # noqa: E402
from skyfit.scattering.multiple import Quadrature  # noqa: E402

RULES = {"2017": Quadrature(), "reference": budget.REFERENCE_QUADRATURE,
         "gauss 32x64": dataclasses.replace(budget.REFERENCE_QUADRATURE, density_theta=32, density_phi=64, density_zenith=0)}
SKIES = [(5, (1e-4, 3e-4), 0), (5, (1e-4, 3e-4), 3), (0, (1e-5, 8e-5), 0), (0, (1e-5, 8e-5), 1), (0, (1e-5, 8e-5), 2)]
"""(seed, beta_550 range, sky): two of the hazy coverage draw's skies, three of the first clear draw's."""


def main() -> None:
    torch.set_num_threads(2)
    args = C.truth_args()
    for seed, beta, k in SKIES:
        t = C.draw_truth(np.random.default_rng([seed, k]), k % 2 == 1, beta)
        values = {}
        for name, q in RULES.items():  # the truth's ReferenceModel with the rule's view rays and density directions
            C.ReferenceModel = functools.partial(budget.ReferenceModel, ray_rule=q.ray_rule,
                                                 density_directions=(q.density_theta, q.density_phi, q.density_zenith))
            values[name] = C.observe(t, args, np.random.default_rng(0))[0].values
        C.ReferenceModel = budget.ReferenceModel
        last = values["gauss 32x64"]

        def q(r: torch.Tensor) -> str:
            return "median %.3f p10 %.3f p90 %.3f max %.3f" % (float(r.median()), float(torch.quantile(r.flatten(), 0.1)),
                                                           float(torch.quantile(r.flatten(), 0.9)), float(r.max()))

        aod = t["mie_beta_550"] * t["mie_scale_height"]
        print(f"seed {seed} sky {k}: AOD {aod:.3f}, sun at {t['sun_zenith_deg']:.1f} deg; over gauss 32x64: "
              f"2017 {q(values['2017'] / last)}; reference {q(values['reference'] / last)}", flush=True)


if __name__ == "__main__":
    main()
