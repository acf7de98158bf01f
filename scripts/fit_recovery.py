"""Recovery and timing of a synthetic fisheye fit (docs/fitting.md, "Speed and recovery").

Renders a fisheye sky (single scattering) from a known atmosphere, adds Gaussian
noise of ``--noise`` relative sigma with a seeded generator, and fits
mie_beta_550, mie_scale_height, mie_g, rayleigh_scale and exposure from a
perturbed start. Prints one JSON line per case: wall time, evaluations,
convergence, truth, recovered values and relative errors.

    .venv/bin/python scripts/fit_recovery.py --size 128 --wavelengths 16 --threads 2
    .venv/bin/python scripts/fit_recovery.py --orders 2 --cases earth,hazy,hazy75 --threads 1   # + ground albedo

The truth may be rendered with a more accurate model than the fit uses
(``--truth-integrator gauss:samples=64 --truth-view-samples 64``) to see the
bias that the fit's integrator causes. Wall time and process CPU time are both
printed, with the load average: on a shared machine wall time overstates the cost.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import time

import numpy as np
import torch

from skyfit.atmosphere import load_atmosphere
from skyfit.camera import FisheyeCamera
from skyfit.transmittance import parse_integrator
from skyfit.fit import FitOptions, FitProblem, Observation, Parameterisation, SkyModel, fit, make_loss

CASES = {
    "earth": ("earth", {"mie_beta_550": 2.0e-5, "mie_scale_height": 1500.0, "mie_g": 0.75, "rayleigh_scale": 1.05,
                        "exposure": 1.3}, (40.0, 120.0)),
    "hazy": ("earth_hazy", {"mie_beta_550": 8.0e-5, "mie_scale_height": 900.0, "mie_g": 0.6, "rayleigh_scale": 0.95,
                            "exposure": 0.8}, (65.0, 250.0)),
    "hazy75": ("earth_hazy", {"mie_beta_550": 4.0e-5, "mie_scale_height": 800.0, "mie_g": 0.7, "rayleigh_scale": 1.02,
                              "exposure": 1.1}, (75.0, 30.0)),
}
ALBEDO = {"earth": 0.3, "hazy": 0.2, "hazy75": 0.5}
"""True ground albedo with --orders >= 2 (then ``ground_albedo`` is free too, starting at 0.1)."""
START = {"mie_beta_550": 1.0e-5, "mie_scale_height": 1200.0, "mie_g": 0.7, "rayleigh_scale": 1.0, "exposure": 1.0}
FREE = list(START)


def observation(values, sigma, view, sun_zenith_deg, sun_azimuth_deg, lam):
    n = view.shape[0]
    t = lambda d: torch.tensor(math.radians(d), dtype=torch.float64)  # noqa: E731
    return Observation("synthetic", "synthetic", "spectral", view, t(sun_zenith_deg), t(sun_azimuth_deg), values, sigma,
                       torch.ones(n, dtype=torch.bool), tuple(f"L{x:g}" for x in lam), torch.tensor(lam))


def run_case(name, args) -> dict:
    cfg, truth, (sz, sa) = CASES[name]
    truth, start, free = dict(truth), dict(START), list(FREE)
    if args.aod:  # fit the optical depth beta x H_M instead of the extinction coefficient
        truth["mie_aod_550"] = truth.pop("mie_beta_550") * truth["mie_scale_height"]
        start["mie_aod_550"] = start.pop("mie_beta_550") * start["mie_scale_height"]
        free = [("mie_aod_550" if n == "mie_beta_550" else n) for n in free]
    if args.orders > 1:
        truth["ground_albedo"], start["ground_albedo"] = ALBEDO[name], 0.1
        free.append("ground_albedo")
    lam = np.linspace(400.0, 700.0, args.wavelengths)
    base = load_atmosphere(cfg, lam)
    cam = FisheyeCamera(args.size)
    view, valid = cam.pixel_vectors(torch.float64)
    view = view[valid]
    if args.max_samples and view.shape[0] > args.max_samples:
        view = view[:: math.ceil(view.shape[0] / args.max_samples)]
    n = view.shape[0]
    ones = torch.ones(n, len(lam), dtype=torch.float64)
    truth_model = SkyModel(parse_integrator(args.truth_integrator or args.integrator),
                           view_samples=args.truth_view_samples or args.view_samples, rule=args.truth_rule or args.rule,
                           orders=args.orders)
    p_true = Parameterisation(base, free, values=truth)
    t0 = time.perf_counter()
    with torch.no_grad():
        clean = FitProblem(p_true, truth_model, [observation(ones, ones, view, sz, sa, lam)], make_loss("squared")).predict(
            p_true.initial_vector())[0]
    t_render = time.perf_counter() - t0
    gen = torch.Generator().manual_seed(args.seed)
    noisy = clean * (1 + args.noise * torch.randn(clean.shape, generator=gen, dtype=torch.float64))
    obs = observation(noisy, args.noise * clean, view, sz, sa, lam)
    model = SkyModel(parse_integrator(args.integrator), view_samples=args.view_samples, rule=args.rule, orders=args.orders)
    param = Parameterisation(base, free, values=start)
    problem = FitProblem(param, model, [obs], make_loss("squared"))
    t0, c0 = time.perf_counter(), time.process_time()
    res = fit(problem, FitOptions(starts=args.starts, adam_steps=args.adam_steps, max_iter=args.max_iter, progress=args.progress))
    seconds, cpu = time.perf_counter() - t0, time.process_time() - c0
    rel = {k: res.parameters[k] / truth[k] - 1 for k in free}
    return {
        "case": name, "orders": args.orders, "size": args.size, "wavelengths": args.wavelengths, "samples": n, "integrator": args.integrator,
        "view_samples": args.view_samples, "rule": args.rule, "truth_integrator": args.truth_integrator or args.integrator,
        "threads": torch.get_num_threads(), "render_seconds": round(t_render, 2), "fit_seconds": round(seconds, 2),
        "fit_cpu_seconds": round(cpu, 2), "load_average": [round(v, 2) for v in os.getloadavg()],
        "evaluations": res.convergence["evaluations_total"], "seconds_per_evaluation": round(seconds / max(res.convergence["evaluations_total"], 1), 3),
        "reason": res.convergence["reason"], "iterations": res.convergence["iterations"], "loss": res.loss,
        "truth": truth, "recovered": {k: res.parameters[k] for k in free}, "relative_error": rel,
        "mie_g_abs_error": res.parameters["mie_g"] - truth["mie_g"],
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=128)
    ap.add_argument("--wavelengths", type=int, default=16, help="number of wavelengths in 400-700 nm")
    ap.add_argument("--integrator", default="chapman")
    ap.add_argument("--view-samples", type=int, default=16)
    ap.add_argument("--rule", default="gauss", help="outer (view-ray) quadrature rule of the fit")
    ap.add_argument("--truth-rule", help="default: the fit's")
    ap.add_argument("--truth-integrator", help="default: the fit's")
    ap.add_argument("--truth-view-samples", type=int)
    ap.add_argument("--noise", type=float, default=0.01)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--starts", type=int, default=1)
    ap.add_argument("--adam-steps", type=int, default=10)
    ap.add_argument("--max-iter", type=int, default=100)
    ap.add_argument("--max-samples", type=int, help="use every k-th pixel so that at most this many remain")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--cases", default="earth,hazy")
    ap.add_argument("--orders", type=int, default=1, help=">= 2: Hillaire multiple scattering, ground_albedo free too")
    ap.add_argument("--progress", action="store_true")
    ap.add_argument("--aod", action="store_true", help="fit mie_aod_550 instead of mie_beta_550")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    for name in args.cases.split(","):
        print(json.dumps(run_case(name, args)), flush=True)


if __name__ == "__main__":
    main()
