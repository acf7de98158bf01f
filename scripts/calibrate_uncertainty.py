"""Coverage of skyfit's credible intervals on synthetic skies with known parameters and noise.

For each of ``--skies`` skies: random truth (beta_550, H_M, g, Rayleigh scale, exposure) and sun,
a small fisheye rendered with the fit's own renderer (Chapman optical depth, Gauss view integral)
so that only the noise separates data and model, Gaussian noise of ``--noise`` (relative), then
the gradient fit from the config's values, the Laplace approximation, and emcee. A parameter's
68 % (95 %) interval covers the truth when p16 <= truth <= p84 (p2.5 ... p97.5); for Laplace the
Gaussian interval in the unconstrained x mapped to physical units. Calibrated intervals cover at
68 % and 95 % within binomial error sqrt(p (1 - p) / n).

    .venv/bin/python scripts/calibrate_uncertainty.py --skies 20 --out docs/uncertainty_calibration.json

Measured numbers: docs/uncertainty.md.
"""
from __future__ import annotations

import argparse
import copy
import json
import math
import sys
import time
from pathlib import Path

import numpy as np
import torch

import skyfit
from skyfit.atmosphere import atmosphere_from_config, load_yaml
from skyfit.camera import FisheyeCamera
from skyfit.fit import FitOptions, FitProblem, Observation, Parameterisation, SkyModel, fit, make_loss
from skyfit.fit.laplace import laplace_summary
from skyfit.fit.report import dumps, write_text_atomic
from skyfit.fit.sample import sample_posterior
from skyfit.transmittance import make_integrator

FREE = ["mie_beta_550", "mie_scale_height", "mie_g", "rayleigh_scale", "exposure"]


def sky(rng, size, lam, noise, view_samples, device):
    cfg = copy.deepcopy(load_yaml(Path(skyfit.__file__).parent / "configs" / "earth.yaml"))
    base = atmosphere_from_config(cfg, lam).to(device=device)
    truth = {"mie_beta_550": float(np.exp(rng.uniform(np.log(1e-5), np.log(8e-5)))),
             "mie_scale_height": float(rng.uniform(800, 2500)), "mie_g": float(rng.uniform(0.6, 0.85)),
             "rayleigh_scale": float(rng.uniform(0.9, 1.1)), "exposure": float(rng.uniform(0.7, 1.4))}
    sun = (float(rng.uniform(25, 65)), float(rng.uniform(0, 360)))
    view, valid = FisheyeCamera(size).pixel_vectors(torch.float64, device)
    view = view[valid]
    n, c = view.shape[0], len(lam)
    t = lambda d: torch.tensor(math.radians(d), dtype=torch.float64, device=device)  # noqa: E731
    ones = torch.ones(n, c, dtype=torch.float64, device=device)
    chans = tuple(f"L{x:g}" for x in lam)
    lamt = torch.tensor(lam, device=device)
    model = SkyModel(make_integrator("chapman"), view_samples=view_samples, rule="gauss")
    dummy = Observation("t", "t", "spectral", view, t(sun[0]), t(sun[1]), ones, ones, torch.ones(n, dtype=torch.bool, device=device), chans, lamt)
    tp = Parameterisation(base, FREE, values=truth)
    with torch.no_grad():
        clean = FitProblem(tp, model, [dummy], make_loss("squared")).predict(tp.initial_vector(device=device))[0]
    g = torch.Generator(device=device).manual_seed(int(rng.integers(1 << 30)))
    noisy = clean * (1 + noise * torch.randn(clean.shape, generator=g, dtype=clean.dtype, device=device))
    obs = Observation("sky", "synthetic", "spectral", view, t(sun[0]), t(sun[1]), noisy, noise * clean,
                      torch.ones(n, dtype=torch.bool, device=device), chans, lamt)
    return FitProblem(Parameterisation(base, FREE), model, [obs], make_loss("squared")), truth, sun


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--skies", type=int, default=20)
    ap.add_argument("--size", type=int, default=14, help="fisheye size [px]")
    ap.add_argument("--wavelengths", type=int, default=5)
    ap.add_argument("--noise", type=float, default=0.01)
    ap.add_argument("--view-samples", type=int, default=8)
    ap.add_argument("--walkers", type=int, default=24)
    ap.add_argument("--steps", type=int, default=1500)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--work", default="/tmp/skyfit_calibration")
    ap.add_argument("--out", default="docs/uncertainty_calibration.json")
    ap.add_argument("--report", help="only print the table of a finished or .partial.json run")
    a = ap.parse_args(argv)
    if a.report:
        d = json.loads(Path(a.report).read_text())
        return report(d["rows"], argparse.Namespace(**{**d["settings"], "out": a.out}), float("nan"))
    torch.set_num_threads(a.threads)
    rng = np.random.default_rng(a.seed)
    lam = np.linspace(420.0, 680.0, a.wavelengths)
    rows = []
    t_all = time.process_time()
    for i in range(a.skies):
        t0 = time.process_time()
        prob, truth, sun = sky(rng, a.size, lam, a.noise, a.view_samples, a.device)
        res = fit(prob, FitOptions(starts=1, adam_steps=10, max_iter=200))
        lap = laplace_summary(prob, res.x)
        work = Path(a.work) / f"sky{i:02d}"
        if (work / "chain.h5").exists():
            (work / "chain.h5").unlink()
        s = sample_posterior(prob, res.x, work, walkers=a.walkers, steps=a.steps, laplace=lap, seed=i, plots=False,
                             predictive_draws=8)
        row = {"sky": i, "truth": truth, "sun_deg": sun, "n_elements": prob.n_elements, "tau_max": s["diagnostics"]["tau_max"],
               "steps_per_tau": s["diagnostics"]["steps_per_tau"], "acceptance": s["diagnostics"]["acceptance_fraction"]["mean"],
               "cpu_s": time.process_time() - t0, "emcee": {}, "laplace": {}}
        for n, v in truth.items():
            p = s["parameters"][n]
            row["emcee"][n] = {"in68": p["p16"] <= v <= p["p84"], "in95": p["p2_5"] <= v <= p["p97_5"],
                               "z": (v - p["median"]) / p["std"], "std": p["std"]}
            lo68, hi68 = lap["interval68"][n]
            lo95, hi95 = lap["interval95"][n]
            row["laplace"][n] = {"in68": lo68 <= v <= hi68, "in95": lo95 <= v <= hi95, "sigma": lap["sigma"][n],
                                 "ratio_to_emcee": lap["sigma"][n] / p["std"]}
        rows.append(row)
        write_text_atomic(Path(a.out).with_suffix(".partial.json"), dumps({"settings": vars(a), "rows": rows}))
        print(f"sky {i:2d}: tau {row['tau_max']:.0f} ({row['steps_per_tau']:.0f} steps/tau), acc {row['acceptance']:.2f}, "
              f"emcee 68/95 {sum(r['in68'] for r in row['emcee'].values())}/{sum(r['in95'] for r in row['emcee'].values())} of 5, "
              f"laplace {sum(r['in68'] for r in row['laplace'].values())}/{sum(r['in95'] for r in row['laplace'].values())}, "
              f"{row['cpu_s']:.0f} s CPU", file=sys.stderr, flush=True)
    report(rows, a, time.process_time() - t_all)


def report(rows, a, cpu_s):
    """Coverage table of finished skies (also usable on a .partial.json: ``--report FILE``)."""
    n = len(rows)
    table = {}
    for method in ("emcee", "laplace"):
        table[method] = {}
        for name in FREE:
            c68 = sum(r[method][name]["in68"] for r in rows) / n
            c95 = sum(r[method][name]["in95"] for r in rows) / n
            table[method][name] = {"cover68": c68, "cover95": c95}
        all68 = np.mean([r[method][nm]["in68"] for r in rows for nm in FREE])
        all95 = np.mean([r[method][nm]["in95"] for r in rows for nm in FREE])
        table[method]["all"] = {"cover68": float(all68), "cover95": float(all95)}
    out = {"skies": n, "binomial_error68": math.sqrt(0.68 * 0.32 / n), "binomial_error95": math.sqrt(0.95 * 0.05 / n),
           "binomial_error68_pooled": math.sqrt(0.68 * 0.32 / (n * len(FREE))),
           "binomial_error95_pooled": math.sqrt(0.95 * 0.05 / (n * len(FREE))),
           "settings": vars(a), "coverage": table, "rows": rows, "cpu_s_total": cpu_s,
           "laplace_over_emcee_sigma_median": {nm: float(np.median([r["laplace"][nm]["ratio_to_emcee"] for r in rows])) for nm in FREE}}
    write_text_atomic(Path(a.out), dumps(out))
    print(f"| parameter | emcee 68 % | emcee 95 % | Laplace 68 % | Laplace 95 % | Laplace/emcee sigma (median) |")
    print("|---|---|---|---|---|---|")
    for nm in FREE + ["all"]:
        e, l = table["emcee"][nm], table["laplace"][nm]
        r = out["laplace_over_emcee_sigma_median"].get(nm)
        print(f"| {nm} | {e['cover68']:.2f} | {e['cover95']:.2f} | {l['cover68']:.2f} | {l['cover95']:.2f} | "
              f"{'' if r is None else f'{r:.2f}'} |")
    print(f"n = {n} skies: binomial error {out['binomial_error68']:.3f} (68 %), {out['binomial_error95']:.3f} (95 %); "
          f"pooled over {len(FREE)} parameters {out['binomial_error68_pooled']:.3f} / {out['binomial_error95_pooled']:.3f}")


if __name__ == "__main__":
    main()
