"""Posterior sampling with emcee (``skyfit sample``): settings, the sampling run and its summary.

The sampler is emcee's affine-invariant ensemble sampler (Goodman & Weare 2010;
Foreman-Mackey et al. 2013) with ``vectorize=True``: each call evaluates half the
ensemble in one batched torch forward pass (:class:`skyfit.fit.batched.BatchedLikelihood`),
in the problem's dtype (float64 by default) on its device (CPU or CUDA). The parts:

=========================  ====================================================================
:mod:`.priors`             prior densities; defaults from the parameter table
:mod:`.posterior`          log p(x | data) over the unconstrained vector (priors, Jacobian, likelihood)
:mod:`.chain`              initial ball, the emcee run, ``chain.h5`` checkpoints and ``--resume``
:mod:`.diagnostics`        physical samples, posterior summary, tau / ESS / burn-in, integrator
                           bias, posterior-predictive spread
:mod:`.sample_plots`       trace, corner and predictive-spread plots
this module                :class:`SampleSettings`, :func:`sample_posterior` (chain -> summary.json),
                           :func:`run_sample` (the command)
=========================  ====================================================================
"""
from __future__ import annotations

import dataclasses
import math
import sys
import time
from pathlib import Path
from typing import Mapping

import numpy as np
import torch
from torch import Tensor

from .chain import CHAIN_FILE, check_resumable, initial_ball, model_signature, read_checkpoint, run_chain
from .diagnostics import chain_diagnostics, importance_bias, physical_samples, posterior_summary, predictive_std
from .budget import inflated_problem
from .laplace import display_names, laplace_summary
from .model import FitProblem
from .parameters import NUISANCE, PARAMETERS
from .posterior import LogPosterior
from .priors import Prior, SampleError, make_priors
from .problem import check_setting, coerce_setting, fit_settings, prepare, run_estimate
from .report import dumps, write_text_atomic
from .results import read_result
from .sample_plots import write_plots
from ..resources import BASE_MEMORY_BYTES, MAX_RUN_SECONDS, Estimate, chain_estimate, check

__all__ = ["SAMPLE_VERSION", "SUMMARY_FILE", "SampleError", "SampleSettings", "build_problem", "run_sample",
           "sample_posterior", "sample_settings"]

SAMPLE_VERSION = 1
SUMMARY_FILE = "summary.json"


def sample_posterior(problem: FitProblem, x0: Tensor, out_dir: str | Path | None, *, walkers: int = 32, steps: int = 2000,
                     priors: Mapping[str, Prior] | None = None, seed: int = 0, resume: bool = False,
                     progress: bool = False, batched: bool | str = "auto", laplace: dict | None = None,
                     final_problem: FitProblem | None = None, checkpoint_seconds: float = 10.0,
                     plots: bool = True, predictive_draws: int = 64, init_scale: float = 0.1,
                     stop_after: int | None = None, extra: dict | None = None,
                     truths: Mapping[str, float] | None = None) -> dict:
    """Sample the posterior of ``problem`` around the fitted ``x0``; write DIR/chain.h5, summary.json, plots.

    Args:
        problem: the problem to sample (its renderer may be cheaper than the fit's: see ``final_problem``).
        x0: the fitted unconstrained vector, shape (P,).
        out_dir: output folder.
        walkers: ensemble size (>= 2 P; even).
        steps: total steps of the chain (a resumed run continues to this total).
        priors: name -> Prior (default :func:`make_priors`).
        seed: seeds the sampler's random generator and the initial ball.
        resume: continue DIR/chain.h5 (error when it is missing or from another model).
        batched: see :class:`LogPosterior`.
        laplace: :func:`skyfit.fit.laplace.laplace_summary` at x0: shapes the initial ball, and its sigmas
            are compared with the chain's (``laplace_vs_emcee``).
        final_problem: the fit's problem when ``problem`` uses a cheaper renderer: the summary then
            measures the bias this causes by importance reweighting (:func:`importance_bias`).
        checkpoint_seconds: wall time between checkpoints. [s]
        plots: write corner.png, trace.png, predictive_std_<obs>.png.
        predictive_draws: posterior draws for the predictive spread.
        stop_after: stop after this many new steps, leaving only the last checkpoint (tests).
        extra: merged into summary.json (e.g. the command's settings).
        truths: name -> true value, drawn as lines on the corner plot where known (``skyfit demo``).

    Returns:
        the summary dict (also DIR/summary.json).
    """
    out_dir = None if out_dir is None else Path(out_dir)
    P = problem.param.size
    names = display_names(problem)
    if walkers < 2 * P:
        raise SampleError(f"--walkers {walkers} is fewer than 2 x {P} parameters ({', '.join(names)}); use at least {2 * P}")
    if walkers % 2:
        raise SampleError(f"--walkers must be even (the stretch move updates two halves), got {walkers}")
    if steps < 1:
        raise SampleError(f"--steps must be >= 1, got {steps}")
    chain_path = None if out_dir is None else out_dir / CHAIN_FILE
    priors = dict(priors) if priors is not None else make_priors(problem)
    log_post = LogPosterior(problem, priors, batched=batched, batch_hint=walkers // 2)
    meta = {"signature": model_signature(problem), "walkers": walkers, "seed": seed, "steps_requested": steps,
            "x0": x0.detach().cpu().double().tolist(), "priors": {n: pr.settings() for n, pr in priors.items()}}
    backend = None
    if resume and chain_path is not None and not chain_path.exists():
        # resume = continue what exists, start what does not (a job killed before its first checkpoint)
        print(f"skyfit sample: --resume: no chain {chain_path} yet; starting a new chain", file=sys.stderr)
        resume = False
    if resume:
        if chain_path is None or not chain_path.is_file():
            raise SampleError(f"--resume: no chain file {chain_path} to continue")
        backend, old_meta = read_checkpoint(chain_path)
        check_resumable(old_meta, problem, walkers, chain_path)
        seed = int(old_meta.get("seed", seed))
        meta["seed"] = seed
        meta["x0"] = old_meta.get("x0", meta["x0"])
        x_init = None
        if backend.iteration >= steps:
            steps = int(backend.iteration)
    else:
        if chain_path is not None and chain_path.exists():
            raise SampleError(f"{chain_path} exists; continue it with --resume or choose another --out")
        rng = np.random.default_rng(seed)
        x_init = initial_ball(problem, x0, walkers, rng, log_post, init_scale, laplace)
    done_before = int(backend.iteration) if backend is not None else 0
    sampler, secs = run_chain(log_post, x_init, walkers, steps, chain_path, meta, seed=seed, backend=backend,
                              progress=progress, checkpoint_seconds=checkpoint_seconds, stop_after=stop_after)
    if stop_after is not None:
        return {"stopped_after": stop_after, "iteration": int(sampler.backend.iteration)}
    be = sampler.backend
    chain = be.chain[: be.iteration]
    diag = chain_diagnostics(chain, names, be.accepted)
    if diag["warning"]:
        print(f"skyfit sample: warning: {diag['warning']}", file=sys.stderr)
    flat = chain[diag["burn_in"]:: diag["thin"]].reshape(-1, P)
    phys = physical_samples(problem, flat)
    summ = posterior_summary(phys, names)
    # ESS per second of sampling (None for a resumed run: its ESS includes earlier runs' steps)
    ess_per_s = {n: (e / secs if secs > 0 and done_before == 0 else None) for n, e in diag["ess"].items()}
    fit_values = physical_samples(problem, x0.detach().cpu().double().numpy()[None])
    for n, d in summ["parameters"].items():
        d["fit"] = float(fit_values[n][0]) if n in fit_values else None
        base = n.split("[")[0]
        d["unit"] = PARAMETERS[base].unit if base in PARAMETERS else ""
    summary = {
        "skyfit_sample": SAMPLE_VERSION,
        **summ,
        "diagnostics": diag,
        "throughput": {"seconds_this_run": secs, "steps_this_run": int(chain.shape[0] - done_before),
                       "log_prob_evaluations": log_post.n_evaluations, "log_prob_calls": log_post.n_calls,
                       "evaluations_per_second": log_post.n_evaluations / secs if secs > 0 else None,
                       "ess_per_second": ess_per_s, "batched": log_post.batched,
                       "unbatched_reason": None if log_post.batched else log_post.unbatched_reason,
                       "device": str(log_post.device), "dtype": str(log_post.dtype).replace("torch.", "")},
        "priors": meta["priors"],
        "likelihood": {"loss": problem.loss.settings(), "n_elements": problem.n_elements,
                       "noise": "sigma x fitted noise_scale" if "noise_scale" in problem.param.free else "data sigma (known)",
                       "exact_gaussian": problem.loss.rho == "squared" and problem.loss.residual == "linear"},
        "sampler": {"walkers": walkers, "steps": int(chain.shape[0]), "seed": seed, "moves": "emcee StretchMove (a=2)",
                    "vectorize": True, "resumed": resume},
        "integrator": {**problem.model.integrator.settings(), **problem.model.settings()},
        "chain": None if chain_path is None else str(chain_path),
    }
    if laplace is not None:
        ratios = {}
        for n in names + [k for k in laplace.get("derived", {}) if k in summ["parameters"]]:
            s_l = laplace["sigma"].get(n) if n in laplace["sigma"] else laplace.get("derived", {}).get(n, {}).get("sigma")
            s_e = summ["parameters"][n]["std"]
            ratios[n] = {"laplace_sigma": s_l, "emcee_sigma": s_e, "ratio": (s_l / s_e) if s_l is not None and s_e > 0 else None}
        summary["laplace_vs_emcee"] = ratios
    if final_problem is not None:
        final_post = LogPosterior(final_problem, priors, batched=batched, batch_hint=walkers // 2)
        summary["sampler_integrator"] = {**problem.model.integrator.settings(), **problem.model.settings()}
        summary["final_integrator"] = {**final_problem.model.integrator.settings(), **final_problem.model.settings()}
        summary["integrator_bias"] = importance_bias(log_post, final_post, flat, names)
    else:
        summary["integrator_bias"] = {"note": "sampled with the fit's own renderer: no integrator bias", "max_abs_shift_in_sigma": 0.0}
    pstd = predictive_std(log_post, flat, predictive_draws)
    summary["predictive"] = [{"name": o.name, "draws": min(predictive_draws, flat.shape[0]),
                              "median_relative_std": float(np.median(s / np.maximum(o.values[o.mask].cpu().double().numpy(), 1e-300))),
                              "max_relative_std": float(np.max(s / np.maximum(o.values[o.mask].cpu().double().numpy(), 1e-300)))}
                             for s, o in zip(pstd, problem.observations)]
    if extra:
        summary.update(extra)
    if out_dir is None:  # in memory (skyfit.sample): the chain goes back to the caller, nothing is written
        summary["chain_array"] = chain
        return summary
    if plots:
        summary["plots"] = write_plots(out_dir, chain, diag, phys, names, problem, pstd, truths=truths)
    write_text_atomic(out_dir / SUMMARY_FILE, dumps(summary))
    return summary



# -- the command ----------------------------------------------------------------------------------
@dataclasses.dataclass
class SampleSettings:
    """``skyfit sample`` settings: the config's ``sample:`` section, overridden by flags.

    Attributes:
        walkers: ensemble size (>= 2 x free parameters, even).
        steps: chain length in steps (per walker).
        seed: sampler and initial-ball seed.
        priors: name -> {kind, lo, hi | mean, sd} overriding :data:`~skyfit.fit.priors.DEFAULT_PRIORS`.
        integrator: optical-depth integrator while sampling (None: the fit's); a cheaper one
            is allowed, and its bias is measured (summary ``integrator_bias``).
        view_samples, rule: the view-ray integral while sampling (None: the fit's).
        accuracy: ``auto``, ``de=X`` or ``rel=X``: the renderer while sampling is the cheapest measured
            setting meeting it (:mod:`skyfit.render.auto`; None: the fit's); its bias is measured too.
        checkpoint_seconds: wall time between chain checkpoints. [s]
        predictive_draws: posterior draws for the predictive spread image.
        init_scale: initial ball radius in units of the Laplace sigma.
        batched: true / false / "auto" (see :class:`LogPosterior`).
        max_samples: images: sample the posterior of every k-th pixel so that at most this many
            remain (None: the fit's pixels); cheaper, and wider than the full data's posterior.
    """

    walkers: int = 32
    steps: int = 2000
    seed: int = 0
    priors: dict = dataclasses.field(default_factory=dict)
    integrator: str | None = None
    view_samples: int | None = None
    rule: str | None = None
    accuracy: str | None = None
    checkpoint_seconds: float = 10.0
    predictive_draws: int = 64
    init_scale: float = 0.1
    batched: bool | str = "auto"
    max_samples: int | None = None


SAMPLE_RANGES: dict[str, tuple[str, float, float, str]] = {
    "walkers": ("int", 2, math.inf, "[)"), "steps": ("int", 1, math.inf, "[)"), "seed": ("int", 0, math.inf, "[)"),
    "view_samples": ("int", 1, math.inf, "[)"), "checkpoint_seconds": ("float", 0, math.inf, "()"),
    "predictive_draws": ("int", 1, math.inf, "[)"), "init_scale": ("float", 0, math.inf, "()"),
    "max_samples": ("int", 1, math.inf, "[)"),
}
"""Type and range of the numeric sample settings (:func:`skyfit.fit.problem.check_setting`)."""


def sample_settings(section: dict | None, overrides: dict | None = None, where: str = "") -> SampleSettings:
    """Merge the config's ``sample:`` section and overrides (None values are ignored); SampleError when invalid.

    ``where`` names the config in messages about its ``sample:`` section.
    """
    if section is not None and not isinstance(section, dict):
        raise SampleError(f"{where + ': ' if where else ''}config section 'sample' must be a mapping, got {section!r}")
    section = dict(section or {})
    known = {f.name for f in dataclasses.fields(SampleSettings)}
    unknown = set(section) - known
    if unknown:
        raise SampleError(f"unknown key(s) {sorted(unknown)} in config section 'sample'; known: {sorted(known)}")
    flags = {k: coerce_setting(k, v, SAMPLE_RANGES) for k, v in (overrides or {}).items() if v is not None}
    section = {k: coerce_setting(k, v, SAMPLE_RANGES) for k, v in section.items()}
    for k, v in section.items():
        check_setting(k, v, f"{where + ': ' if where else ''}sample.{k}", SAMPLE_RANGES)
    for k, v in flags.items():
        check_setting(k, v, k, SAMPLE_RANGES)
    merged = {**section, **flags}
    s = SampleSettings(**merged)
    if not isinstance(s.priors, dict):
        raise SampleError(f"sample.priors must map parameter names to prior specs, got {s.priors!r}")
    return s


def build_problem(data, config: dict, init: dict, init_path, kider_site: dict | None, integrator: str | None = None,
                  view_samples: int | None = None, rule: str | None = None, accuracy: str | None = None,
                  max_samples: int | None = None, device="cpu"):
    """(problem, x0) for DATA with the fit settings, free set and fitted values of the RESULT.json ``init``.

    The masks, loss, noise model and renderer are the fit's (``init['settings']``); ``integrator``,
    ``view_samples``, ``rule`` replace the renderer's (a cheaper sampler); ``max_samples`` keeps every
    k-th image pixel (the posterior is then that subsample's: wider than the full data's).
    """
    try:
        s = fit_settings(init.get("settings"), {"integrator": integrator, "view_samples": view_samples, "rule": rule,
                                                "max_samples": max_samples, "accuracy": accuracy})
    except TypeError as e:
        raise SampleError(f"{init_path}: malformed fit settings ({e})") from None
    if not accuracy:  # the fit's own accuracy was resolved into its renderer fields when it ran
        s = dataclasses.replace(s, accuracy=None)
    prep = prepare(data, config, s, kider_site=kider_site, device=device)
    s, observations = prep.settings, prep.observations
    free = list(init["free"])
    pars = init["parameters"]
    keep = set(free) | set((s.initial or {}).keys()) | set(NUISANCE)
    values = {}
    for n in keep:
        if n in pars:
            v = pars[n]
            if isinstance(v, list) and len(v) != len(observations):
                raise SampleError(f"{init_path}: {n} has {len(v)} values for {len(observations)} observation(s) of DATA")
            values[n] = v
    problem = prep.problem(free, init.get("per_observation"), values)
    param, dtype = problem.param, s.torch_dtype
    fv = init.get("fitted_vector") or {}
    if all(n in fv for n in param.names):
        x0 = torch.tensor([float(fv[n]) for n in param.names], dtype=dtype, device=prep.base.device)
    else:
        x0 = param.initial_vector(dtype, prep.base.device)
    return problem, x0


def run_sample(data, config: dict, init_path, out_dir, *, overrides: dict | None = None, kider_site: dict | None = None,
               resume: bool = False, progress: bool = False, plots: bool = True, laplace: bool = True,
               device="cpu", force: bool = False, config_source: str = "",
               truths: Mapping[str, float] | None = None) -> dict:
    """``skyfit sample``: rebuild the fit's problem, sample it, write DIR/chain.h5, summary.json and plots.

    ``force`` runs even when the memory or time estimate says no (skyfit.resources); ``config_source``
    names the config in messages about its ``sample:`` section; ``truths`` (name -> true value, where known)
    are drawn on the corner plot.
    """
    init = read_result(init_path)
    if not init.get("free"):
        raise SampleError(f"{init_path}: the fit has no free parameter to sample")
    if not isinstance(config, dict):
        raise SampleError("config must be a mapping")
    ss = sample_settings(config.get("sample"), overrides, where=f"config {config_source}" if config_source else "")
    hint = "reduce --walkers, --steps, --view-samples or the --integrator's samples, or add --force"
    check(chain_estimate(ss.walkers, ss.steps, len(init["free"])), force=force, hint=hint)
    t0 = time.perf_counter()
    cheap = ss.integrator is not None or ss.view_samples is not None or ss.rule is not None or ss.accuracy is not None
    problem, x0 = build_problem(data, config, init, init_path, kider_site, ss.integrator, ss.view_samples, ss.rule,
                                device=device,
                                accuracy=ss.accuracy, max_samples=ss.max_samples)
    final_problem = None
    if cheap:
        final_problem, _ = build_problem(data, config, init, init_path, kider_site, max_samples=ss.max_samples,
                                         device=device)
    budget = (init.get("laplace") or {}).get("budget") or {}
    floor = float(budget.get("floor_relative") or 0.0)
    if floor > 0:  # the fit's discrepancy floor, fixed (not sampled): sigma'^2 = sigma^2 + (f m(x0))^2
        problem = with_floor(problem, x0, floor)
        final_problem = None if final_problem is None else with_floor(final_problem, x0, floor)
    P = problem.param.size
    if ss.walkers < 2 * P:
        raise SampleError(f"--walkers {ss.walkers} is fewer than 2 x {P} free parameters; use at least {2 * P}")
    base = problem.param.base
    run = run_estimate(problem.model, problem.observations, base, evaluations=2 * ss.steps, batch=max(ss.walkers // 2, 1),
                       autograd=False, what="sample")
    chain = chain_estimate(ss.walkers, ss.steps, P)
    both = Estimate("sample", run.memory_bytes + chain.memory_bytes - BASE_MEMORY_BYTES, run.seconds,
                    f"{chain.detail}; {run.detail}")
    check(both, force=force, max_seconds=MAX_RUN_SECONDS, device=str(base.device), hint=hint)
    if not resume and (Path(out_dir) / CHAIN_FILE).exists():
        raise SampleError(f"{Path(out_dir) / CHAIN_FILE} exists; continue it with --resume or choose another --out")
    priors = make_priors(problem, ss.priors)
    lap = None
    if laplace:
        try:
            lap = laplace_summary(final_problem or problem, x0)
        except (ValueError, RuntimeError) as e:  # a flat or non-finite Hessian: sample anyway
            lap = None
            print(f"skyfit sample: warning: no Laplace approximation ({e})".splitlines()[0], file=sys.stderr)
    extra = {"init": str(init_path), "data": [str(d) for d in data], "settings": dataclasses.asdict(ss)}
    summary = sample_posterior(
        problem, x0, out_dir, walkers=ss.walkers, steps=ss.steps, priors=priors, seed=ss.seed, resume=resume,
        progress=progress, batched=ss.batched, laplace=lap, final_problem=final_problem,
        checkpoint_seconds=ss.checkpoint_seconds, plots=plots, predictive_draws=ss.predictive_draws,
        init_scale=ss.init_scale, extra=extra, truths=truths)
    if budget:
        summary["error_budget"] = sampled_budget(summary, budget, floor)
    summary["seconds_total"] = time.perf_counter() - t0
    write_text_atomic(Path(out_dir) / SUMMARY_FILE, dumps(summary))
    return summary


def with_floor(problem: FitProblem, x0: Tensor, floor: float) -> FitProblem:
    """``problem`` with the relative error floor ``floor`` added in quadrature to its sigma, at the model of x0
    (:func:`skyfit.fit.budget.inflated_problem`)."""
    with torch.no_grad():
        preds = problem.predict(x0)
        phys = problem.param.to_physical(x0)
    return inflated_problem(problem, preds, floor, phys)


def sampled_budget(summary: dict, budget: dict, floor: float) -> dict:
    """summary.json's ``error_budget``: the chain's std with the fit's numerical term added in quadrature.

    The chain samples the likelihood with the fit's discrepancy floor held fixed (``floor_relative``); the
    numerical model error is a bias, not a width, so it is added to the posterior std as the fit's result
    adds it to the Laplace sigma (docs/uncertainty.md, "Honest sigma under model error")."""
    num = budget.get("sigma_numerical") or {}
    num.update({k: v.get("sigma_numerical") for k, v in (budget.get("derived") or {}).items()})
    total = {}
    for n, d in summary.get("parameters", {}).items():
        s = d.get("std")
        total[n] = None if s is None else math.sqrt(s**2 + float(num.get(n) or 0.0) ** 2)
    return {"floor_relative": floor, "floor": "fixed at the fit's value (RESULT.json laplace.budget), not sampled",
            "sigma_numerical": num, "sigma_total": total}
