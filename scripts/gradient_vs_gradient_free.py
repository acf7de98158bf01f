"""Gradient fit vs gradient-free search on one synthetic sky, side by side in one run.

The sky: 32 x 32 equidistant fisheye, 6 wavelengths 420-680 nm, 1 % noise, single
scattering (Gauss-16 optical depth, 16 trapezoid view samples, as rendered), sun zenith 50 deg. Free: Ångström alpha, aerosol optical
depth at 550 nm, and g (the three axes of Bruneton 2017's libRadtran grid). Methods:

* ``gradient``: skyfit's fit (Adam warm start, L-BFGS strong Wolfe), one start;
* ``nelder-mead``: scipy.optimize.minimize(method="Nelder-Mead") on the same unconstrained
  vector from the same start, no gradients;
* ``grid``: Bruneton's grid, alpha 0-2 (step 0.2), Ångström beta 0.02-0.2 (step 0.02),
  g 0.5-0.9 (step 0.05): 11 x 10 x 9 = 990 forward evaluations.

"Reach the same loss": the first evaluation whose loss is within 0.5 / n_elements of the
gradient fit's optimum (Δχ² = 1 over the whole image). Times are process CPU seconds (one
torch thread); a gradient evaluation (forward + backward) counts once.

    .venv/bin/python scripts/gradient_vs_gradient_free.py [--out docs/gradient_vs_free.json]
"""
from __future__ import annotations

import argparse
import itertools
import json
import math
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=str(Path(__file__).resolve().parents[1] / "docs" / "gradient_vs_free.json"))
    ap.add_argument("--size", type=int, default=32)
    a = ap.parse_args()
    torch.set_num_threads(1)
    from scipy.optimize import minimize
    from test_fit_recovery import LAM, _config, synthetic, _truth_config

    from skyfit.atmosphere import atmosphere_from_config
    from skyfit.fit import FitOptions, FitProblem, Parameterisation, SkyModel, fit, make_loss
    from skyfit.transmittance import make_integrator

    alpha, beta_ang, g = 1.1, 0.08, 0.72
    h_m = 1200.0
    beta_550 = beta_ang * 0.55 ** -alpha / h_m  # Ångström: AOD(λ) = beta (λ / 1 µm)^-alpha
    truth_cfg = _truth_config("earth", 1.0, beta_550, alpha, h_m, g)
    obs = synthetic(truth_cfg, 1.0, (50.0, 140.0), size=a.size, seed=7)
    free = ["mie_angstrom_alpha", "mie_aod_550", "mie_g"]
    base = atmosphere_from_config(_config("earth"), LAM)
    param = Parameterisation(base, free, values={"mie_angstrom_alpha": 0.5, "mie_aod_550": 0.05, "mie_g": 0.6})
    model = SkyModel(make_integrator("gauss", samples=16), view_samples=16)  # as synthetic() renders: no model error
    n_el = obs.values.numel()
    rows = {}

    # -- gradient -------------------------------------------------------------------------------------
    problem = FitProblem(param, model, [obs], make_loss("squared"))
    trace = []
    orig = problem.objective

    def logged(x):
        v = orig(x)
        trace.append((time.process_time(), float(v.detach())))
        return v

    problem.objective = logged
    t0 = time.process_time()
    res = fit(problem, FitOptions(starts=1))
    best = res.loss
    target = best + 0.5 / n_el
    first = next(i for i, (_, v) in enumerate(trace) if v <= target)
    rows["gradient"] = {"evaluations_to_target": first + 1, "cpu_s_to_target": trace[first][0] - t0,
                        "evaluations_total": len(trace), "cpu_s_total": time.process_time() - t0, "best_loss": best,
                        "parameters": {k: res.parameters[k] for k in free}}

    # -- Nelder-Mead ----------------------------------------------------------------------------------
    problem_nm = FitProblem(param, model, [obs], make_loss("squared"))
    trace = []

    def f(xn):
        with torch.no_grad():
            v = float(problem_nm.objective(torch.as_tensor(xn, dtype=torch.float64)))
        trace.append((time.process_time(), v))
        return v

    t0 = time.process_time()
    r = minimize(f, param.initial_vector().numpy(), method="Nelder-Mead",
                 options={"maxfev": 2000, "xatol": 1e-8, "fatol": 1e-12})
    hit = next((i for i, (_, v) in enumerate(trace) if v <= target), None)
    rows["nelder-mead"] = {"evaluations_to_target": None if hit is None else hit + 1,
                           "cpu_s_to_target": None if hit is None else trace[hit][0] - t0,
                           "evaluations_total": len(trace), "cpu_s_total": time.process_time() - t0,
                           "best_loss": float(r.fun),
                           "parameters": param.free_dict(torch.as_tensor(r.x, dtype=torch.float64))}

    # -- Bruneton's grid --------------------------------------------------------------------------------
    problem_g = FitProblem(Parameterisation(base, free), model, [obs], make_loss("squared"))
    grid = list(itertools.product(np.arange(0, 2.0001, 0.2), np.arange(0.02, 0.2001, 0.02), np.arange(0.5, 0.9001, 0.05)))
    t0 = time.process_time()
    best_g, arg = math.inf, None
    for al, be, gg in grid:
        vals = {"mie_angstrom_alpha": al, "mie_aod_550": be * 0.55 ** -al, "mie_g": gg}
        x = problem_g.param.to_unconstrained(vals)
        with torch.no_grad():
            v = float(problem_g.objective(x))
        if v < best_g:
            best_g, arg = v, vals
    rows["grid"] = {"evaluations_to_target": None if best_g > target else len(grid), "cpu_s_to_target": None,
                    "evaluations_total": len(grid), "cpu_s_total": time.process_time() - t0, "best_loss": best_g,
                    "parameters": arg}
    out = {"command": "python scripts/gradient_vs_gradient_free.py", "n_elements": n_el, "target_loss": target,
           "truth": {"mie_angstrom_alpha": alpha, "mie_aod_550": beta_550 * h_m, "mie_g": g}, "rows": rows}
    Path(a.out).write_text(json.dumps(out, indent=1))
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
