"""Fit Kider et al. 2014 captures and print the published score (RMSE, mW/(m^2 sr nm), 81 samples, 360-720 nm).

For each capture: the config's atmosphere as is (no fit), then a fit of the free
parameters. One JSON line per capture. Example (single scattering for now):

    .venv/bin/python scripts/fit_kider.py --captures 09.30,12.00 --loss log \
        --free rayleigh_scale,mie_beta_550,mie_scale_height,mie_g,sun_azimuth_offset

``--orders`` is passed to the model; orders > 1 works once multiple scattering
is wired into :meth:`skyfit.fit.SkyModel.renderer`.
"""
from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

import torch

from skyfit.atmosphere import atmosphere_from_config, load_yaml
from skyfit.transmittance import parse_integrator
from skyfit.fit import FitOptions, FitProblem, Parameterisation, SkyModel, fit, make_loss, observation_from_kider

DAY = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "kider2014" / "2013-05-27"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--day", default=str(DAY))
    ap.add_argument("--captures", default="09.30", help="comma list of HH.MM, or 'all'")
    ap.add_argument("--config", default=str(Path(__file__).resolve().parents[1] / "skyfit" / "configs" / "earth_clear_sky_eval.yaml"))
    ap.add_argument("--free", default="rayleigh_scale,mie_beta_550,mie_scale_height,mie_g,sun_azimuth_offset")
    ap.add_argument("--loss", default="log")
    ap.add_argument("--integrator", default="chapman")
    ap.add_argument("--view-samples", type=int, default=16)
    ap.add_argument("--rule", default="gauss")
    ap.add_argument("--orders", type=int, default=1)
    ap.add_argument("--starts", type=int, default=1)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--no-fit", action="store_true", help="only score the config's atmosphere")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    day = Path(args.day)
    folders = sorted(day.glob("2013-05-27___*")) if args.captures == "all" else [
        day / f"2013-05-27___{c}.00" for c in args.captures.split(",")]
    cfg = load_yaml(args.config)
    model = SkyModel(parse_integrator(args.integrator), orders=args.orders, view_samples=args.view_samples, rule=args.rule)
    for folder in folders:
        obs = observation_from_kider(folder)
        sun = dict(cfg.get("sun") or {})
        sun.setdefault("bandwidth_nm", 10.0)
        base = atmosphere_from_config({**cfg, "sun": sun}, obs.wavelengths.numpy())
        dist = float(sun.get("distance_au", 1.0))
        fixed = FitProblem(Parameterisation(base, []), model, [obs], make_loss(args.loss), base_sun_distance_au=dist)
        m0 = fixed.metrics(fixed.param.initial_vector())
        if args.no_fit:
            print(json.dumps({"capture": folder.name, "orders": args.orders, "config_rmse": round(m0["rmse"], 3),
                              "config_delta_e": round(m0["delta_e"], 3)}), flush=True)
            continue
        free = args.free.split(",")
        init = {"sun_azimuth_offset": obs.metadata["azimuth_offset_guess_rad"]} if "sun_azimuth_offset" in free else {}
        param = Parameterisation(base, free, values=init)
        problem = FitProblem(param, model, [obs], make_loss(args.loss), base_sun_distance_au=dist)
        t0 = time.process_time()
        res = fit(problem, FitOptions(starts=args.starts))
        m = problem.metrics(res.x)
        print(json.dumps({
            "capture": folder.name, "orders": args.orders, "loss": args.loss,
            "config_rmse": round(m0["rmse"], 3), "config_delta_e": round(m0["delta_e"], 3),
            "fit_rmse": round(m["rmse"], 3), "fit_delta_e": round(m["delta_e"], 3),
            "fit": {k: res.parameters[k] for k in free},
            "sun_azimuth_offset_deg": math.degrees(res.parameters["sun_azimuth_offset"]),
            "symmetry_guess_deg": math.degrees(obs.metadata["azimuth_offset_guess_rad"]),
            "reason": res.convergence["reason"], "cpu_seconds": round(time.process_time() - t0, 1),
        }), flush=True)


if __name__ == "__main__":
    main()
