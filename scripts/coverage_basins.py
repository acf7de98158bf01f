"""Are the coverage study's high aerosol layers a local minimum? (docs/uncertainty.md, "Where the misses are")

For skies of scripts/coverage_model_error.py (same draw: ``--seed``, the sky's index), the fit of the study (one start) is
repeated from ``--starts`` spread starts (skyfit's Latin-hypercube over each parameter's typical span) and from
the truth's aerosol scale height H_M, and with ``--reference`` the budget's reference renderer (Bruneton tables
16 x 64 x 16 x 8, 6 orders, a 32/128-node single scattering; skyfit.fit.budget) is fitted from the fit's optimum:
where the fit's own likelihood puts H_M, and where a converged renderer's does. Always: the fit's and the
reference's loss at the truth. With ``--lagged`` the budget's three lagged refits (skyfit.fit.budget.refit_shift, as
``numerical_term`` runs them) from the fit's optimum and from H_M = 1.2 km, and the reference's loss where they end.
With ``--polish N`` (after ``--lagged``), N Levenberg-Marquardt steps on the reference renderer itself from the
lagged iterate (skyfit.fit.budget.reference_polish, what ``fit.sigma_polish`` does). One JSON line per sky.

    OMP_NUM_THREADS=1 .venv/bin/python scripts/coverage_basins.py --seed 0 --skies 3,7,17
    OMP_NUM_THREADS=1 .venv/bin/python scripts/coverage_basins.py --seed 1 --skies 4,6 --lagged
    OMP_NUM_THREADS=1 .venv/bin/python scripts/coverage_basins.py --seed 0 --skies 3 --reference
    OMP_NUM_THREADS=1 .venv/bin/python scripts/coverage_basins.py --seed 1 --skies 6 --lagged --polish 5
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
import coverage_model_error as C  # noqa: E402

from skyfit.fit import FitOptions, fit  # noqa: E402
from skyfit.fit.budget import ReferenceModel, display_names, reference_polish, reference_problem, refit_shift  # noqa: E402
from skyfit.fit.laplace import laplace_summary  # noqa: E402
from skyfit.fit.problem import fit_settings, prepare  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--skies", required=True, help="comma list of sky indices")
    ap.add_argument("--starts", type=int, default=4)
    ap.add_argument("--reference", action="store_true", help="also fit the budget's reference renderer (minutes a sky)")
    ap.add_argument("--polish", type=int, default=0, help="with --lagged: Levenberg-Marquardt steps on the reference "
                    "from the lagged iterate (about a minute of CPU each)")
    ap.add_argument("--lagged", action="store_true", help="also the budget's three lagged refits from the optimum and "
                    "from H_M = 1.2 km (a minute or two a sky)")
    ap.add_argument("--reference-axis", choices=("window", "whole"), default="window",
                    help="the truth's and the budget reference's Bruneton tables (coverage_model_error.py's flag; the "
                         "studies of docs/uncertainty.md before session 18: whole)")
    a = ap.parse_args(argv)
    torch.set_num_threads(1)
    truth_args = C.truth_args(reference_axis=a.reference_axis)
    for k in (int(v) for v in a.skies.split(",")):
        rng = np.random.default_rng([a.seed, k])
        t = C.draw_truth(rng, k % 2 == 1)
        obs, _ = C.observe(t, truth_args, rng)
        cfg = C.fit_config()
        prep = prepare([obs], cfg, fit_settings(cfg["fit"]))
        problem = prep.fit_problem()
        param, base = problem.param, prep.settings.options(False)
        row = {"seed": a.seed, "sky": k, "two_term": k % 2 == 1, "truth": {n: t[n] for n in C.FREE}}
        c0 = time.process_time()
        res = fit(problem, base)  # the study's own fit (one start): the lagged refits and the reference start here
        spread = fit(problem, dataclasses.replace(base, starts=a.starts))
        row["starts"] = [{"H_M_start": s["initial"]["mie_scale_height"], "H_M": s["final"]["mie_scale_height"],
                          "loss": s["loss"]} for s in spread.starts]
        start = {**param.free_dict(param.initial_vector(torch.float64)), "mie_scale_height": t["mie_scale_height"]}
        r_t = fit(problem, dataclasses.replace(base, starts=1), x0=param.to_unconstrained(start, torch.float64))
        row["from_true_H_M"] = {"H_M": param.free_dict(r_t.x)["mie_scale_height"], "loss": r_t.loss}
        row["fit"] = {"values": param.free_dict(res.x), "loss": res.loss, "cpu_s": time.process_time() - c0}
        ref = reference_problem(problem, ReferenceModel.of(problem.model, sun_window=a.reference_axis == "window"))

        def ref_loss(x):
            with torch.no_grad():
                return float(ref.loss_from_predictions(ref.predict(x), ref.param.to_physical(x)))

        x_true = param.to_unconstrained({n: t[n] for n in C.FREE}, torch.float64)
        with torch.no_grad():
            row["loss_at_truth"] = {"fit": float(problem.loss_from_predictions(problem.predict(x_true), param.to_physical(x_true))),
                                    "reference": ref_loss(x_true), "n": problem.n_elements}
        row["fit"]["reference_loss"] = ref_loss(res.x)
        if a.lagged:
            lap = laplace_summary(problem, res.x)
            s_x = torch.as_tensor([lap["sigma_unconstrained"][n] for n in display_names(problem)], dtype=torch.float64)
            row["lagged"] = {}
            for label, hm in (("from_fit", None), ("from_1200_m", 1200.0)):
                xs = res.x if hm is None else param.to_unconstrained({**param.free_dict(res.x), "mie_scale_height": hm},
                                                                     torch.float64)
                rs = refit_shift(problem, res.x, ref, xs, s_x, 3, FitOptions(starts=1, adam_steps=0, max_iter=200))
                row["lagged"][label] = {"values": param.free_dict(rs["x"]), "reference_loss": ref_loss(rs["x"]),
                                        "steps_in_sigma": rs["steps"]}
                if label == "from_fit" and a.polish:
                    pol = reference_polish(problem, ref, rs["x"], a.polish)
                    row["polish"] = {"values": param.free_dict(pol["x"]), **{k: pol[k] for k in ("loss", "loss_start",
                                                                                               "steps", "converged")}}
        if a.reference:
            c0 = time.process_time()
            r = fit(ref, FitOptions(starts=1, adam_steps=0, max_iter=60), x0=res.x)
            row["reference"] = {"values": ref.param.free_dict(r.x), "loss": r.loss, "convergence": r.convergence["reason"],
                                "cpu_s": time.process_time() - c0}
        print(json.dumps(row, default=float), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
