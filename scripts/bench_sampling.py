"""Sampling throughput: batched (one torch pass per half-ensemble) vs one walker at a time, side by side.

A synthetic fisheye sky (earth config, 1 % noise) with the fit's renderer (Chapman optical
depth, 16-node Gauss view integral, single scattering, float64) and the five default free
parameters. Part 1 times the log-posterior of the same half-ensemble X (B = walkers / 2 rows)
both ways, interleaved, ``--repeats`` times (process CPU time and wall time; median ratio).
Part 2 runs an emcee chain with the batched log-posterior and reports tau, ESS and ESS per
second per parameter; the one-walker-at-a-time mode is timed on the first ``--loop-steps``
steps of the same chain (same seed) and its ESS/s is the chain's ESS over its projected time.

    .venv/bin/python scripts/bench_sampling.py --out docs/bench/sampling_cpu.json
    .venv/bin/python scripts/bench_sampling.py --device cuda --threads 1 --out docs/bench_cuda/sampling_cuda.json

Numbers: docs/benchmarks.md, "Sampling throughput".
"""
from __future__ import annotations

import argparse
import copy
import math
import os
import platform
import shutil
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch

import skyfit
from skyfit.atmosphere import atmosphere_from_config, load_yaml
from skyfit.camera import FisheyeCamera
from skyfit.fit import FitProblem, Observation, Parameterisation, SkyModel, make_loss
from skyfit.fit.report import dumps, write_text_atomic
from skyfit.fit.chain import initial_ball, run_chain
from skyfit.fit.diagnostics import chain_diagnostics
from skyfit.fit.posterior import LogPosterior
from skyfit.fit.priors import make_priors
from skyfit.transmittance import make_integrator

FREE = ["mie_beta_550", "mie_scale_height", "mie_g", "rayleigh_scale", "exposure"]
TRUTH = {"mie_beta_550": 2.5e-5, "mie_scale_height": 1400.0, "mie_g": 0.74, "rayleigh_scale": 1.03, "exposure": 1.2}


def problem(size, n_lam, view_samples, device, noise=0.01, seed=0):
    cfg = copy.deepcopy(load_yaml(Path(skyfit.__file__).parent / "configs" / "earth.yaml"))
    lam = np.linspace(400.0, 700.0, n_lam)
    base = atmosphere_from_config(cfg, lam).to(device=device)
    view, valid = FisheyeCamera(size).pixel_vectors(torch.float64, device)
    view = view[valid]
    n = view.shape[0]
    t = lambda d: torch.tensor(math.radians(d), dtype=torch.float64, device=device)  # noqa: E731
    ones = torch.ones(n, n_lam, dtype=torch.float64, device=device)
    chans, lamt = tuple(f"L{x:g}" for x in lam), torch.tensor(lam, device=device)
    mask = torch.ones(n, dtype=torch.bool, device=device)
    model = SkyModel(make_integrator("chapman"), view_samples=view_samples, rule="gauss")
    tp = Parameterisation(base, FREE, values=TRUTH)
    dummy = Observation("t", "t", "spectral", view, t(45.0), t(130.0), ones, ones, mask, chans, lamt)
    with torch.no_grad():
        clean = FitProblem(tp, model, [dummy], make_loss("squared")).predict(tp.initial_vector(device=device))[0]
    g = torch.Generator(device=device).manual_seed(seed)
    noisy = clean * (1 + noise * torch.randn(clean.shape, generator=g, dtype=clean.dtype, device=device))
    obs = Observation("bench", "bench", "spectral", view, t(45.0), t(130.0), noisy, noise * clean, mask, chans, lamt)
    prob = FitProblem(Parameterisation(base, FREE, values=TRUTH), model, [obs], make_loss("squared"))
    return prob, prob.param.initial_vector(device=device)


def _sync(device):
    if torch.device(device).type == "cuda":
        torch.cuda.synchronize()


def timed(f, X, device):
    _sync(device)
    c, w = time.process_time(), time.perf_counter()
    f(X)
    _sync(device)
    return time.process_time() - c, time.perf_counter() - w


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=40, help="fisheye size [px]")
    ap.add_argument("--wavelengths", type=int, default=16)
    ap.add_argument("--view-samples", type=int, default=16)
    ap.add_argument("--walkers", default="32,64,128", help="ensemble sizes (each call sees half)")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--chain-walkers", type=int, default=32)
    ap.add_argument("--chain-steps", type=int, default=1000)
    ap.add_argument("--loop-steps", type=int, default=20, help="steps of the one-walker-at-a-time chain to time")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--out", default="docs/bench/sampling_cpu.json")
    a = ap.parse_args(argv)
    torch.set_num_threads(a.threads)
    prob, x0 = problem(a.size, a.wavelengths, a.view_samples, a.device)
    priors = make_priors(prob)
    info = {"device": a.device if a.device == "cpu" else torch.cuda.get_device_name(), "threads": a.threads,
            "cpu": platform.processor() or platform.machine(), "load_average": os.getloadavg(),
            "pixels": prob.observations[0].n_samples, "wavelengths": a.wavelengths, "view_samples": a.view_samples,
            "free": FREE, "torch": torch.__version__}
    print(f"sky: {info['pixels']} px x {a.wavelengths} wavelengths, {a.view_samples} view samples, chapman; "
          f"device {info['device']}, {a.threads} thread(s), load {info['load_average'][0]:.1f}", file=sys.stderr)
    rows = []
    rng = np.random.default_rng(0)
    for W in [int(w) for w in a.walkers.split(",")]:
        B = W // 2
        X = (x0.cpu().numpy() + 0.02 * rng.standard_normal((B, x0.numel())))
        Xt = torch.as_tensor(X, dtype=torch.float64, device=a.device)
        loop = LogPosterior(prob, priors, batched=False)
        bat = LogPosterior(prob, priors, batched=True, batch_hint=B)
        diff = float(np.max(np.abs(bat(X) - loop(X)) / np.abs(loop(X))))
        tl, tb = [], []
        for _ in range(a.repeats):
            tl.append(timed(loop.torch_call, Xt, a.device))
            tb.append(timed(bat.torch_call, Xt, a.device))
        cl, wl = statistics.median(t[0] for t in tl), statistics.median(t[1] for t in tl)
        cb, wb = statistics.median(t[0] for t in tb), statistics.median(t[1] for t in tb)
        row = {"walkers": W, "batch": B, "loop_cpu_s": cl, "loop_wall_s": wl, "batched_cpu_s": cb, "batched_wall_s": wb,
               "loop_evals_per_cpu_s": B / cl, "batched_evals_per_cpu_s": B / cb, "ratio_cpu": cl / cb, "ratio_wall": wl / wb,
               "max_rel_diff": diff}
        rows.append(row)
        print(f"walkers {W:4d} (batch {B:3d}): one at a time {B / cl:8.1f} eval/s CPU ({B / wl:8.1f} wall), batched "
              f"{B / cb:8.1f} eval/s CPU ({B / wb:8.1f} wall): x{cl / cb:.2f} CPU, x{wl / wb:.2f} wall; max rel diff {diff:.1e}",
              file=sys.stderr, flush=True)
    # Part 2: a chain, ESS/s
    work = Path("/tmp/skyfit_bench_sampling")
    shutil.rmtree(work, ignore_errors=True)
    Wc = a.chain_walkers
    bat = LogPosterior(prob, priors, batched=True, batch_hint=Wc // 2)
    x_init = initial_ball(prob, x0, Wc, np.random.default_rng(1), bat, scale=0.1)
    meta = {"signature": {}, "walkers": Wc}
    c0 = time.process_time()
    sampler, secs_b = run_chain(bat, x_init, Wc, a.chain_steps, work / "b.h5", meta, seed=3, checkpoint_seconds=60)
    cpu_b = time.process_time() - c0
    chain = sampler.backend.chain[: sampler.backend.iteration]
    diag = chain_diagnostics(chain, FREE, sampler.backend.accepted)
    loop = LogPosterior(prob, priors, batched=False)
    c0 = time.process_time()
    _, secs_l = run_chain(loop, x_init, Wc, a.loop_steps, work / "l.h5", meta, seed=3, checkpoint_seconds=60)
    cpu_l = time.process_time() - c0
    per_step_b, per_step_l = secs_b / a.chain_steps, secs_l / a.loop_steps
    ess_s_b = {n: diag["ess"][n] / secs_b for n in FREE}
    ess_s_l = {n: diag["ess"][n] / (per_step_l * a.chain_steps) for n in FREE}
    ess_cpu_b = {n: diag["ess"][n] / cpu_b for n in FREE}
    ess_cpu_l = {n: diag["ess"][n] / (cpu_l / a.loop_steps * a.chain_steps) for n in FREE}
    chain_row = {"walkers": Wc, "steps": a.chain_steps, "batched_wall_s": secs_b, "loop_wall_s_per_step": per_step_l,
                 "batched_wall_s_per_step": per_step_b, "ratio_wall": per_step_l / per_step_b, "tau": diag["tau"],
                 "ess": diag["ess"], "ess_per_s_batched": ess_s_b, "ess_per_s_loop": ess_s_l, "batched_cpu_s": cpu_b,
                 "loop_cpu_s_per_step": cpu_l / a.loop_steps, "ess_per_cpu_s_batched": ess_cpu_b, "ess_per_cpu_s_loop": ess_cpu_l,
                 "acceptance": diag["acceptance_fraction"]["mean"], "steps_per_tau": diag["steps_per_tau"]}
    info["load_average_end"] = os.getloadavg()
    write_text_atomic(Path(a.out), dumps({"info": info, "logprob": rows, "chain": chain_row}))
    print("| walkers | batch | one at a time [eval/s CPU] | batched [eval/s CPU] | ratio CPU | ratio wall |")
    print("|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['walkers']} | {r['batch']} | {r['loop_evals_per_cpu_s']:.1f} | {r['batched_evals_per_cpu_s']:.1f} | "
              f"{r['ratio_cpu']:.2f} | {r['ratio_wall']:.2f} |")
    print(f"\nchain: {Wc} walkers x {a.chain_steps} steps, {secs_b:.1f} s wall batched ({per_step_b * 1e3:.1f} ms/step), "
          f"one at a time {per_step_l * 1e3:.1f} ms/step (x{per_step_l / per_step_b:.2f}); CPU {cpu_b / a.chain_steps * 1e3:.1f} vs "
          f"{cpu_l / a.loop_steps * 1e3:.1f} ms/step (x{cpu_l / a.loop_steps / (cpu_b / a.chain_steps):.2f}); acceptance {chain_row['acceptance']:.2f}, "
          f"{chain_row['steps_per_tau']:.0f} steps/tau")
    print("| parameter | tau [steps] | ESS | ESS/s wall batched | ESS/s wall one at a time | ESS/s CPU batched | ESS/s CPU one at a time |")
    print("|---|---|---|---|---|---|---|")
    for n in FREE:
        print(f"| {n} | {diag['tau'][n]:.1f} | {diag['ess'][n]:.0f} | {ess_s_b[n]:.2f} | {ess_s_l[n]:.3f} | "
              f"{ess_cpu_b[n]:.2f} | {ess_cpu_l[n]:.3f} |")


if __name__ == "__main__":
    main()
