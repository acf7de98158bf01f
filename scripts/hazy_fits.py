"""Hazy synthetic skies fitted with Hillaire's multiple scattering and with Bruneton's lagged orders
(docs/hillaire.md, "Hazy skies").

The truths are scripts/coverage_model_error.py's (its defaults: an equidistant 10 x 10 fisheye, 3 wavelengths
420-680 nm, 1 % + 0.5 % noise, truths rendered by the error budget's reference model with 8 orders), drawn with
Mie beta_550 in 1e-4 - 3e-4 1/m (AOD 0.15-0.55) from seed 5, the draw of docs/uncertainty.md's hazy coverage
skies; odd skies have a two-term HG aerosol. Each sky is fitted from the same start with the coverage study's fit
model (Hillaire 16 x 16, Chapman, 16 Gauss view nodes; free Rayleigh scale, beta_550, Angstrom exponent, H_M, g,
ground albedo) and with ``multiple: bruneton_lagged`` at 4 orders on a photo fit's tables and rules
(skyfit.fit.photo.PHOTO_TABLES, Gauss view rays, PHOTO_DENSITY) through ``skyfit fit``'s own solver
(skyfit.fit.run.solve: skyfit.fit.photo.lagged_fit, LAGGED_REFRESHES). One JSON line per fit; all of them in OUT.

    OMP_NUM_THREADS=1 .venv/bin/python scripts/hazy_fits.py --skies 0,1,2,3 --out docs/hillaire/hazy_fits.json
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
import coverage_model_error as C  # noqa: E402

from skyfit.fit.photo import PHOTO_DENSITY, PHOTO_TABLES  # noqa: E402
from skyfit.fit.problem import fit_settings, prepare  # noqa: E402
from skyfit.fit.run import solve  # noqa: E402

SETTINGS = {"hillaire": {},
            "lagged4photo": {"multiple": "bruneton_lagged", "orders": 4, "table_sizes": list(PHOTO_TABLES),
                             "ray_rule": "gauss", "density_directions": list(PHOTO_DENSITY)}}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--skies", default="0,1,2,3")
    ap.add_argument("--settings", default=",".join(SETTINGS))
    ap.add_argument("--out", required=True)
    a = ap.parse_args()
    torch.set_num_threads(1)
    args = C.truth_args(seed=5, beta_range="1e-4,3e-4")
    rows = []
    for k in [int(v) for v in a.skies.split(",")]:
        rng = np.random.default_rng([args.seed, k])
        t = C.draw_truth(rng, k % 2 == 1, (1e-4, 3e-4))
        obs, _ = C.observe(t, args, rng)
        aod_t = t["mie_beta_550"] * t["mie_scale_height"]
        for name in a.settings.split(","):
            cfg = C.fit_config()
            cfg["fit"].update(SETTINGS[name])
            prep = prepare([obs], cfg, fit_settings(cfg["fit"]))
            problem = prep.fit_problem()
            c0 = time.process_time()
            res = solve(problem, prep.settings.options(False))
            v = problem.param.physical_dict(res.x)
            aod = v["mie_beta_550"] * v["mie_scale_height"]
            row = {"sky": k, "two_term": k % 2 == 1, "setting": name, "aod_true": aod_t, "aod_fit": aod,
                   "aod_err": aod / aod_t - 1, "H_true": t["mie_scale_height"], "H_fit": v["mie_scale_height"],
                   "g_true": t["g1"], "g_fit": v["mie_g"], "alpha_true": t["mie_angstrom_alpha"],
                   "alpha_fit": v["mie_angstrom_alpha"], "albedo_true": t["ground_albedo"], "albedo_fit": v["ground_albedo"],
                   "loss": res.loss, "cpu_s": time.process_time() - c0, "sun_zenith": t["sun_zenith_deg"],
                   "convergence": res.convergence.get("reason")}
            print(json.dumps(row), flush=True)
            rows.append(row)
    Path(a.out).write_text(json.dumps({"command": " ".join(sys.argv), "fits": rows}, indent=1))


if __name__ == "__main__":
    main()
