"""What a chain says: physical values of samples, posterior summary, convergence diagnostics, the bias of a
cheaper sampling renderer and the posterior-predictive spread.

Diagnostics (Foreman-Mackey et al. 2013 Sec. 4; emcee's "Autocorrelation analysis"
tutorial): integrated autocorrelation time tau per parameter (Sokal's window, c = 5),
burn-in = 2 max tau, thinning = max(1, min tau / 2), effective sample size
n_walkers (steps - burn) / tau, acceptance fraction; the chain is long enough when
steps >= 50 max tau, else a warning.
"""
from __future__ import annotations

import math
import warnings
from typing import Mapping

import emcee
import numpy as np
import torch
from torch import Tensor

from .laplace import display_names
from .model import FitProblem
from .parameters import PARAMETERS
from .posterior import LogPosterior

MIN_STEPS_PER_TAU = 50
"""emcee's guidance: the chain should be longer than 50 tau for a reliable tau estimate."""


def physical_samples(problem: FitProblem, X: np.ndarray | Tensor) -> dict[str, np.ndarray]:
    """Physical value of each slot of X (S, P) by name (``param.names``), plus the derived
    ``mie_aod_550`` / ``mie_beta_550`` when one of them is free. [SI]"""
    p = problem.param
    X = torch.as_tensor(np.asarray(X), dtype=torch.float64)
    names = display_names(problem)
    out = {}
    for n in p.free:
        spec = PARAMETERS[n]
        for k in p._slots[n]:
            out[names[k]] = spec.forward(X[:, k], p._hi(n)).numpy()
    free = set(p.free)
    h_m = out.get("mie_scale_height", np.full(X.shape[0], float(p.values["mie_scale_height"])))
    if "mie_beta_550" in free:
        out["mie_aod_550"] = out["mie_beta_550"] * h_m
    elif "mie_aod_550" in free:
        out["mie_beta_550"] = out["mie_aod_550"] / h_m
    return out


def posterior_summary(samples: Mapping[str, np.ndarray], names: list[str]) -> dict:
    """Median, 16/84 and 2.5/97.5 percentiles, mean, std per name; correlation matrix of ``names``."""
    out = {}
    for n, s in samples.items():
        q = np.percentile(s, [2.5, 16, 50, 84, 97.5])
        out[n] = {"median": q[2], "p16": q[1], "p84": q[3], "p2_5": q[0], "p97_5": q[4],
                  "mean": float(np.mean(s)), "std": float(np.std(s, ddof=1)) if len(s) > 1 else 0.0}
        out[n] = {k: float(v) for k, v in out[n].items()}
    M = np.stack([samples[n] for n in names], 1)
    corr = np.corrcoef(M, rowvar=False) if M.shape[0] > 1 else np.eye(len(names))
    return {"parameters": out, "names": list(names), "correlation": np.atleast_2d(corr).tolist()}


def chain_diagnostics(chain: np.ndarray, names: list[str], accepted: np.ndarray) -> dict:
    """tau, ESS, burn-in, thinning, acceptance of a chain (steps, walkers, P) (module docstring)."""
    steps, nw, ndim = chain.shape
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        tau = emcee.autocorr.integrated_time(chain, c=5, tol=0, quiet=True) if steps >= 2 else np.full(ndim, np.nan)
    tau = np.where(np.isfinite(tau) & (tau > 0), tau, np.nan)
    tmax = float(np.nanmax(tau)) if np.isfinite(tau).any() else float("nan")
    tmin = float(np.nanmin(tau)) if np.isfinite(tau).any() else float("nan")
    burn = int(math.ceil(2 * tmax)) if math.isfinite(tmax) else steps // 2
    burn = min(burn, max(steps - 1, 0))
    thin = max(1, int(0.5 * tmin)) if math.isfinite(tmin) else 1
    kept = steps - burn
    ess = nw * kept / tau
    long_enough = bool(math.isfinite(tmax) and steps >= MIN_STEPS_PER_TAU * tmax)
    acc = accepted / max(steps, 1)
    diag = {
        "steps": int(steps), "walkers": int(nw),
        "tau": {n: float(t) for n, t in zip(names, tau)}, "tau_max": tmax,
        "burn_in": burn, "thin": thin,
        "ess": {n: float(e) for n, e in zip(names, ess)},
        "acceptance_fraction": {"mean": float(np.mean(acc)), "min": float(np.min(acc)), "max": float(np.max(acc))},
        "steps_per_tau": steps / tmax if math.isfinite(tmax) else None,
        "long_enough": long_enough,
        "warning": None,
    }
    if not long_enough:
        diag["warning"] = (f"chain too short for its autocorrelation time: {steps} steps = "
                           f"{steps / tmax if math.isfinite(tmax) else 0:.1f} tau (max tau {tmax:.1f}); emcee's guidance is "
                           f">= {MIN_STEPS_PER_TAU} tau: run about {int(MIN_STEPS_PER_TAU * tmax) if math.isfinite(tmax) else '?'} "
                           "steps (--steps) and treat these intervals as rough")
    if diag["acceptance_fraction"]["mean"] < 0.1 or diag["acceptance_fraction"]["mean"] > 0.8:
        extra = f"mean acceptance fraction {diag['acceptance_fraction']['mean']:.2f} is outside 0.1-0.8"
        diag["warning"] = extra if diag["warning"] is None else diag["warning"] + "; " + extra
    return diag



def importance_bias(cheap: LogPosterior, final: LogPosterior, flat: np.ndarray, names: list[str], n: int = 256,
                    rng: np.random.Generator | None = None) -> dict:
    """Bias of the posterior from sampling with ``cheap``'s renderer instead of ``final``'s, measured by
    importance reweighting: w = p_final / p_cheap on ``n`` posterior draws; per parameter
    (weighted mean - mean) / std, in units of the posterior width; and the weights' ESS."""
    rng = rng or np.random.default_rng(0)
    idx = rng.choice(flat.shape[0], size=min(n, flat.shape[0]), replace=False)
    X = flat[idx]
    lc, lf = cheap(X), final(X)
    d = lf - lc
    ok = np.isfinite(d)
    d = d[ok] - np.max(d[ok])
    w = np.exp(d)
    w /= w.sum()
    ess = 1.0 / np.sum(w**2)
    phys = physical_samples(final.problem, X[ok])
    out = {}
    for k in names + [k for k in phys if k not in names]:
        s = phys[k]
        sd = np.std(s, ddof=1)
        out[k] = float((np.sum(w * s) - np.mean(s)) / sd) if sd > 0 else 0.0
    return {"draws": int(ok.sum()), "weights_ess": float(ess), "shift_in_sigma": out,
            "max_abs_shift_in_sigma": float(max(abs(v) for v in out.values())),
            "log_like_difference": {"mean": float(np.mean(lf[ok] - lc[ok])), "std": float(np.std(lf[ok] - lc[ok]))}}


def predictive_std(log_post: LogPosterior, flat: np.ndarray, n: int = 64, rng: np.random.Generator | None = None,
                   chunk: int = 16) -> list[np.ndarray]:
    """Posterior-predictive spread: per used sample and channel, the std over ``n`` posterior draws of the
    model prediction (exposure applied), one (N_i, C_i) array per observation. [data units]"""
    rng = rng or np.random.default_rng(1)
    problem = log_post.problem
    idx = rng.choice(flat.shape[0], size=min(n, flat.shape[0]), replace=False)
    X = torch.as_tensor(flat[idx], dtype=log_post.dtype, device=log_post.device)
    preds: list[list[Tensor]] = [[] for _ in problem.observations]
    with torch.no_grad():
        for i in range(0, X.shape[0], chunk):
            Xc = X[i:i + chunk]
            if log_post.batched:
                ps = log_post.likelihood.predict(Xc)
            else:
                per = [problem.predict(x) for x in Xc]
                ps = [torch.stack([q[j] for q in per]) for j in range(len(problem.observations))]
            for j, p in enumerate(ps):
                preds[j].append(p)
    return [torch.cat(p, 0).std(0).cpu().double().numpy() for p in preds]
