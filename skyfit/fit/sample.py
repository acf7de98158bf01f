"""Posterior sampling with emcee (``skyfit sample``): priors, batched log-probability, checkpoints, diagnostics.

The sampler is emcee's affine-invariant ensemble sampler (Goodman & Weare 2010;
Foreman-Mackey et al. 2013) with ``vectorize=True``: each call evaluates half the
ensemble in one batched torch forward pass (:class:`skyfit.fit.batched.BatchedLikelihood`),
in the problem's dtype (float64 by default) on its device (CPU or CUDA).

It samples the unconstrained vector x of :class:`~skyfit.fit.parameters.Parameterisation`
(every parameter's range is then the whole real line, which suits the stretch move),
with the density of the physical prior carried over by the Jacobian of the transform::

    log p(x | data) = log L(x) + sum_k [ log pi_k(v_k(x)) + log |dv_k / dx_k| ]

log L = -sum over used elements of [rho(r / s) + log s] = -n_elements * objective(x):
the Gaussian log-likelihood up to a constant for the ``squared`` loss (known sigma, or
sigma times a fitted ``noise_scale`` s), and the same masks as the fit. Robust losses
give a pseudo-likelihood (recorded in the summary).

Priors (:data:`DEFAULT_PRIORS`, docs/uncertainty.md): log-uniform for the positive scale
parameters, uniform over the physical range for the bounded ones; the config's
``sample: priors:`` section overrides any (``{name: {kind: uniform|loguniform|normal|lognormal, ...}}``).
Outside a prior's support log p = -inf (STYLE.md, sampler boundaries); NaN is an error.

Checkpoints: the chain lives in memory and is written to ``DIR/chain.h5`` every
``checkpoint_seconds`` and at the end, each time as a complete file written to a
temporary name and renamed (an HDF5 file written in place is left unreadable by a
SIGKILL in mid-write). The file has emcee's HDFBackend layout (group ``mcmc``, so
``emcee.backends.HDFBackend(path, read_only=True)`` reads it) plus the random state and
the model signature; ``--resume`` restores both and continues the same chain: the result
equals an uninterrupted run's (tests/test_sample.py).

Diagnostics (Foreman-Mackey et al. 2013 Sec. 4; emcee's "Autocorrelation analysis"
tutorial): integrated autocorrelation time tau per parameter (Sokal's window, c = 5),
burn-in = 2 max tau, thinning = max(1, min tau / 2), effective sample size
n_walkers (steps - burn) / tau, acceptance fraction; the chain is long enough when
steps >= 50 max tau, else a warning.
"""
from __future__ import annotations

import dataclasses
import json
import math
import sys
import time
import warnings
from pathlib import Path
from typing import Mapping

import numpy as np
import torch
from torch import Tensor

from .batched import BatchedLikelihood, per_walker_loglike
from .model import FitProblem
from .laplace import laplace_summary
from .parameters import NUISANCE, PARAMETERS, FitError
from .problem import fit_settings, prepare
from .results import read_result
from .report import dumps, write_text_atomic
from ..io.atomic import atomic_path

SAMPLE_VERSION = 1
CHAIN_FILE = "chain.h5"
SUMMARY_FILE = "summary.json"
MIN_STEPS_PER_TAU = 50
"""emcee's guidance: the chain should be longer than 50 tau for a reliable tau estimate."""


class SampleError(FitError):
    """A sampling run that cannot start or resume as asked (one-line message, exit status 2)."""


# -- priors --------------------------------------------------------------------------------------
PRIOR_KINDS = ("uniform", "loguniform", "normal", "lognormal")


@dataclasses.dataclass(frozen=True)
class Prior:
    """Prior density of one physical parameter.

    Attributes:
        kind: ``uniform`` (lo, hi), ``loguniform`` (lo, hi > lo > 0; density ~ 1/v),
            ``normal`` (mean, sd) or ``lognormal`` (mean and sd of log v).
        lo, hi: support of the uniform kinds. [parameter unit]
        mean, sd: of the normal kinds. [unit, or log unit]
    """

    kind: str
    lo: float = -math.inf
    hi: float = math.inf
    mean: float = 0.0
    sd: float = 1.0

    def __post_init__(self):
        if self.kind not in PRIOR_KINDS:
            raise SampleError(f"unknown prior kind {self.kind!r}; valid: {', '.join(PRIOR_KINDS)}")
        if self.kind in ("uniform", "loguniform") and not (self.lo < self.hi and math.isfinite(self.lo) and math.isfinite(self.hi)):
            raise SampleError(f"{self.kind} prior needs finite lo < hi, got lo={self.lo}, hi={self.hi}")
        if self.kind == "loguniform" and not self.lo > 0:
            raise SampleError(f"loguniform prior needs lo > 0, got {self.lo}")
        if self.kind in ("normal", "lognormal") and not self.sd > 0:
            raise SampleError(f"{self.kind} prior needs sd > 0, got {self.sd}")

    def log_density(self, v: Tensor) -> Tensor:
        """log pi(v) (normalised), -inf outside the support, same shape as v."""
        ninf = torch.full_like(v, -math.inf)
        if self.kind == "uniform":
            inside = (v > self.lo) & (v < self.hi)
            return torch.where(inside, torch.full_like(v, -math.log(self.hi - self.lo)), ninf)
        if self.kind == "loguniform":
            inside = (v > self.lo) & (v < self.hi)
            safe = torch.where(inside, v, torch.ones_like(v))
            return torch.where(inside, -torch.log(safe) - math.log(math.log(self.hi / self.lo)), ninf)
        if self.kind == "normal":
            return -0.5 * ((v - self.mean) / self.sd) ** 2 - math.log(self.sd * math.sqrt(2 * math.pi))
        pos = v > 0
        lv = torch.log(torch.where(pos, v, torch.ones_like(v)))
        val = -0.5 * ((lv - self.mean) / self.sd) ** 2 - math.log(self.sd * math.sqrt(2 * math.pi)) - lv
        return torch.where(pos, val, ninf)

    def settings(self) -> dict:
        if self.kind in ("uniform", "loguniform"):
            return {"kind": self.kind, "lo": self.lo, "hi": self.hi}
        return {"kind": self.kind, "mean": self.mean, "sd": self.sd}


_DEG = math.pi / 180.0
DEFAULT_PRIORS: dict[str, Prior] = {
    "rayleigh_scale": Prior("loguniform", 0.2, 5.0),
    "rayleigh_scale_height": Prior("loguniform", 500.0, 50_000.0),
    "mie_beta_550": Prior("loguniform", 1e-7, 1e-3),
    "mie_aod_550": Prior("loguniform", 1e-4, 5.0),
    "mie_angstrom_alpha": Prior("uniform", -1.0, 4.0),
    "mie_ssa": Prior("uniform", 0.0, 1.0),
    "mie_scale_height": Prior("loguniform", 10.0, 20_000.0),
    "mie_g": Prior("uniform", -1.0, 1.0),
    "ground_albedo": Prior("uniform", 0.0, 1.0),
    "ground_albedo_scale": Prior("uniform", 0.0, 1.0),  # hi replaced by 1 / max(config albedo)
    "exposure": Prior("loguniform", 1e-6, 1e6),
    "noise_scale": Prior("loguniform", 1e-2, 1e2),
    "sun_azimuth_offset": Prior("uniform", -45 * _DEG, 45 * _DEG),
    "sun_zenith_offset": Prior("uniform", -10 * _DEG, 10 * _DEG),
    "camera_tilt_north": Prior("uniform", -10 * _DEG, 10 * _DEG),
    "camera_tilt_east": Prior("uniform", -10 * _DEG, 10 * _DEG),
}
"""Default prior of each parameter (physical units, docs/uncertainty.md): the transform's range
(log-uniform for positive scale parameters) where that range is physical, else a wide one."""


def make_priors(problem: FitProblem, overrides: Mapping | None = None) -> dict[str, Prior]:
    """Priors of the free parameters: :data:`DEFAULT_PRIORS` with the config's ``sample.priors`` overrides."""
    p = problem.param
    out = {}
    overrides = dict(overrides or {})
    unknown = [n for n in overrides if n not in PARAMETERS]
    if unknown:
        raise SampleError(f"unknown parameter(s) {unknown} in sample.priors; valid: {', '.join(PARAMETERS)}")
    for n in p.free:
        pr = DEFAULT_PRIORS[n]
        if n == "ground_albedo_scale":
            pr = dataclasses.replace(pr, hi=p._albedo_scale_hi)
        if n in overrides:
            spec = overrides[n]
            if not isinstance(spec, Mapping) or "kind" not in spec:
                raise SampleError(f"sample.priors.{n} must be a mapping with a 'kind' ({', '.join(PRIOR_KINDS)})")
            extra = set(spec) - {"kind", "lo", "hi", "mean", "sd"}
            if extra:
                raise SampleError(f"sample.priors.{n}: unknown key(s) {sorted(extra)}; valid: kind, lo, hi, mean, sd")
            try:
                pr = Prior(str(spec["kind"]), **{k: float(v) for k, v in spec.items() if k != "kind"})
            except (TypeError, ValueError) as e:
                raise SampleError(f"sample.priors.{n}: {e}") from None
        out[n] = pr
    return out


def _log_abs_dvdx(spec, x: Tensor, hi: float | None) -> Tensor:
    """log |dv/dx| of a parameter's transform (skyfit.fit.parameters), elementwise."""
    import torch.nn.functional as F

    if spec.transform == "log":
        return math.log(spec.ref) + x
    if spec.transform == "interval":
        top = spec.hi if hi is None else hi
        return math.log(top - spec.lo) + F.logsigmoid(x) + F.logsigmoid(-x)
    if spec.transform == "loginterval":
        return spec.forward(x).log() + math.log(math.log(spec.hi / spec.lo)) + F.logsigmoid(x) + F.logsigmoid(-x)
    return torch.full_like(x, math.log(abs(spec.ref)))


class LogPosterior:
    """log p(x | data) for an array of walkers X (B, P) -> (B,), as emcee's ``vectorize=True`` expects.

    Args:
        problem: the fit problem.
        priors: name -> :class:`Prior` for every free parameter (:func:`make_priors`).
        batched: ``True`` one batched forward pass per call (error when unsupported), ``False`` a
            loop over walkers, ``"auto"`` batched when supported.
        batch_hint: walkers per call expected (half the ensemble), sizes the batched chunks.
    """

    def __init__(self, problem: FitProblem, priors: Mapping[str, Prior], batched: bool | str = "auto", batch_hint: int = 16):
        self.problem = problem
        self.priors = dict(priors)
        p = problem.param
        missing = [n for n in p.free if n not in self.priors]
        if missing:
            raise SampleError(f"no prior for {missing}")
        reason = BatchedLikelihood.unsupported_reason(problem)
        if batched is True and reason:
            raise SampleError(f"batched sampling unsupported: {reason}")
        self.batched = bool(batched) and not reason
        self.unbatched_reason = reason if batched else "one walker at a time (asked)"
        self.likelihood = BatchedLikelihood(problem, batch_hint) if self.batched else None
        self.dtype, self.device = p.base.dtype, p.base.device
        self.n_calls = 0
        self.n_evaluations = 0

    def log_prior(self, X: Tensor) -> Tensor:
        """Sum over free slots of log pi(v) + log |dv/dx|, shape (B,)."""
        p = self.problem.param
        out = X.new_zeros(X.shape[0])
        for n in p.free:
            spec = PARAMETERS[n]
            xs = X[:, p._slots[n]]
            v = spec.forward(xs, p._hi(n))
            out = out + (self.priors[n].log_density(v) + _log_abs_dvdx(spec, xs, p._hi(n))).sum(-1)
        return out

    def log_likelihood(self, X: Tensor) -> Tensor:
        if self.batched:
            with torch.no_grad():
                return self.likelihood(X)
        return per_walker_loglike(self.problem, X)

    def torch_call(self, X: Tensor) -> Tensor:
        lp = self.log_prior(X)
        out = torch.full_like(lp, -math.inf)
        ok = torch.isfinite(lp)
        if bool(ok.any()):
            idx = torch.nonzero(ok).reshape(-1)
            ll = self.log_likelihood(X[idx])
            if bool(torch.isnan(ll).any()):
                bad = X[idx][torch.isnan(ll)][0]
                raise SampleError(f"log-likelihood is NaN at x = {bad.tolist()} ({self.problem.param.names})")
            out[idx] = lp[idx] + ll
            self.n_evaluations += int(idx.numel())
        self.n_calls += 1
        return out

    def __call__(self, X: np.ndarray) -> np.ndarray:
        X = np.atleast_2d(X)
        t = torch.as_tensor(X, dtype=self.dtype, device=self.device)
        return self.torch_call(t).detach().cpu().double().numpy()


# -- physical values of samples -------------------------------------------------------------------
def physical_samples(problem: FitProblem, X: np.ndarray | Tensor) -> dict[str, np.ndarray]:
    """Physical value of each slot of X (S, P) by name (``param.names``), plus the derived
    ``mie_aod_550`` / ``mie_beta_550`` when one of them is free. [SI]"""
    p = problem.param
    from .laplace import display_names

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


# -- diagnostics ----------------------------------------------------------------------------------
def chain_diagnostics(chain: np.ndarray, names: list[str], accepted: np.ndarray) -> dict:
    """tau, ESS, burn-in, thinning, acceptance of a chain (steps, walkers, P) (module docstring)."""
    import emcee

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


# -- checkpoints ----------------------------------------------------------------------------------
def write_checkpoint(path: Path, backend, meta: dict) -> None:
    """The chain so far as a complete HDF5 file (emcee's layout + skyfit attrs), written atomically."""
    import emcee
    import h5py

    with atomic_path(path) as tmp:
        it = int(backend.iteration)
        with h5py.File(tmp, "w") as f:
            g = f.create_group("mcmc")
            g.attrs["version"] = emcee.__version__
            g.attrs["nwalkers"] = backend.nwalkers
            g.attrs["ndim"] = backend.ndim
            g.attrs["has_blobs"] = False
            g.attrs["iteration"] = it
            g.create_dataset("accepted", data=np.asarray(backend.accepted, dtype=np.float64))
            g.create_dataset("chain", data=backend.chain[:it], maxshape=(None, backend.nwalkers, backend.ndim))
            g.create_dataset("log_prob", data=backend.log_prob[:it], maxshape=(None, backend.nwalkers))
            if backend.random_state is not None:
                for i, v in enumerate(backend.random_state):
                    g.attrs[f"random_state_{i}"] = v
            s = f.create_group("skyfit")
            s.attrs["meta"] = json.dumps(meta)


def read_checkpoint(path: Path):
    """(an in-memory emcee Backend holding the chain and random state, the skyfit meta dict)."""
    import emcee
    import h5py

    path = Path(path)
    try:
        with h5py.File(path, "r") as f:
            g = f["mcmc"]
            nw, ndim, it = int(g.attrs["nwalkers"]), int(g.attrs["ndim"]), int(g.attrs["iteration"])
            chain = g["chain"][:it]
            log_prob = g["log_prob"][:it]
            accepted = g["accepted"][...]
            rs = [v for k, v in sorted(g.attrs.items()) if k.startswith("random_state_")]
            meta = json.loads(f["skyfit"].attrs["meta"]) if "skyfit" in f else None
    except (OSError, KeyError, ValueError) as e:
        raise SampleError(f"{path}: not a readable skyfit chain file ({type(e).__name__}: {e})".splitlines()[0]) from None
    if meta is None:
        raise SampleError(f"{path}: not a skyfit chain file (no model record)")
    b = emcee.backends.Backend()
    b.reset(nw, ndim)
    b.grow(it, None)
    b.chain[:it] = chain
    b.log_prob[:it] = log_prob
    b.accepted = accepted.astype(np.float64)
    b.iteration = it
    b.random_state = tuple(rs) if rs else None
    if b.random_state is not None:
        b.random_state = (str(rs[0].decode() if isinstance(rs[0], bytes) else rs[0]), np.asarray(rs[1]), int(rs[2]), int(rs[3]), float(rs[4]))
    return b, meta


def model_signature(problem: FitProblem) -> dict:
    """What must match for a chain to be continued: parameter names, ndim, renderer, loss, data."""
    m = problem.model
    return {
        "names": list(problem.param.names), "ndim": problem.param.size,
        "integrator": {**m.integrator.settings(), **m.settings()},
        "loss": problem.loss.settings(),
        "data": [o.source for o in problem.observations],
        "n_elements": problem.n_elements,
    }


def check_resumable(meta: dict, problem: FitProblem, walkers: int, path: Path) -> None:
    sig = model_signature(problem)
    old = meta.get("signature", {})
    if old.get("names") != sig["names"] or old.get("ndim") != sig["ndim"]:
        raise SampleError(f"{path}: chain file is from another model (parameters {old.get('names')} vs {sig['names']})")
    for key in ("integrator", "loss", "n_elements"):
        if old.get(key) != json.loads(json.dumps(sig[key])):
            raise SampleError(f"{path}: chain file is from another model ({key} {old.get(key)} vs {sig[key]})")
    if int(meta.get("walkers", -1)) != walkers:
        raise SampleError(f"{path}: chain has {meta.get('walkers')} walkers, --walkers asks for {walkers}")


# -- the run --------------------------------------------------------------------------------------
def initial_ball(problem: FitProblem, x0: Tensor, walkers: int, rng: np.random.Generator, log_post: LogPosterior,
                 scale: float = 0.1, laplace: dict | None = None) -> np.ndarray:
    """Walkers in a small ball around the fit: x0 + scale * L z with L L^T the Laplace covariance in x
    (when positive definite), else x0 + 1e-3 z. Points with log p = -inf are redrawn (closer)."""
    P = x0.numel()
    x0n = x0.detach().cpu().double().numpy()
    L = None
    if laplace is not None and laplace.get("positive_definite"):
        try:
            L = np.linalg.cholesky(np.asarray(laplace["covariance_unconstrained"]))
        except np.linalg.LinAlgError:
            L = None
    if L is None:
        L = 1e-2 * np.eye(P)
    X = x0n + scale * rng.standard_normal((walkers, P)) @ L.T
    for shrink in range(20):
        lp = log_post(X)
        bad = ~np.isfinite(lp)
        if not bad.any():
            return X
        X[bad] = x0n + scale * 0.5 ** (shrink + 1) * rng.standard_normal((int(bad.sum()), P)) @ L.T
    raise SampleError("cannot place the walkers: log p is -inf around the fitted point (check the priors)")


def run_chain(log_post: LogPosterior, x_init: np.ndarray | None, walkers: int, steps: int, chain_path: Path, meta: dict, *,
              seed: int = 0, backend=None, progress: bool = False, checkpoint_seconds: float = 10.0,
              stop_after: int | None = None):
    """Run (or continue) the emcee chain to ``steps`` steps in all, checkpointing to ``chain_path``.

    Args:
        backend: an in-memory Backend from :func:`read_checkpoint` to continue (x_init unused).
        stop_after: stop (without the final checkpoint) after this many new steps: a stand-in for
            a killed run in tests.

    Returns:
        (emcee.EnsembleSampler, seconds spent in this call).
    """
    import emcee

    P = log_post.problem.param.size
    resumed = backend is not None
    if backend is None:
        backend = emcee.backends.Backend()
    sampler = emcee.EnsembleSampler(walkers, P, log_post, vectorize=True, backend=backend)
    if not resumed:
        sampler.random_state = np.random.RandomState(seed).get_state()
        start = x_init
    else:
        start = None
    done = int(backend.iteration) if resumed else 0
    todo = steps - done
    t0 = time.perf_counter()
    last_ck = time.perf_counter()
    if todo <= 0:
        return sampler, 0.0
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=steps, initial=done, desc="sample", unit="step", file=sys.stderr, dynamic_ncols=True)
    every = max(20, steps // 40)
    n_new = 0
    try:
        kw = {"initial_state": start, "iterations": todo} if start is not None else {"initial_state": sampler.get_last_sample(), "iterations": todo}
        for _ in sampler.sample(**kw, progress=False):
            n_new += 1
            if bar is not None:
                bar.update(1)
                it = int(backend.iteration)
                if it % every == 0 and it >= 2 * every:
                    import emcee.autocorr as ac

                    with warnings.catch_warnings():
                        warnings.simplefilter("ignore")
                        tau = ac.integrated_time(backend.chain[:it], c=5, tol=0, quiet=True)
                    tm = float(np.nanmax(tau))
                    bar.set_postfix(tau=f"{tm:.1f}", steps_per_tau=f"{it / tm:.0f}", acc=f"{np.mean(backend.accepted) / it:.2f}")
            if stop_after is not None and n_new >= stop_after:
                return sampler, time.perf_counter() - t0
            if time.perf_counter() - last_ck >= checkpoint_seconds:
                write_checkpoint(chain_path, backend, meta)
                last_ck = time.perf_counter()
    finally:
        if bar is not None:
            bar.close()
    write_checkpoint(chain_path, backend, meta)
    return sampler, time.perf_counter() - t0


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


def sample_posterior(problem: FitProblem, x0: Tensor, out_dir: str | Path, *, walkers: int = 32, steps: int = 2000,
                     priors: Mapping[str, Prior] | None = None, seed: int = 0, resume: bool = False,
                     progress: bool = False, batched: bool | str = "auto", laplace: dict | None = None,
                     final_problem: FitProblem | None = None, checkpoint_seconds: float = 10.0,
                     plots: bool = True, predictive_draws: int = 64, init_scale: float = 0.1,
                     stop_after: int | None = None, extra: dict | None = None) -> dict:
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

    Returns:
        the summary dict (also DIR/summary.json).
    """
    from .laplace import display_names

    out_dir = Path(out_dir)
    P = problem.param.size
    names = display_names(problem)
    if walkers < 2 * P:
        raise SampleError(f"--walkers {walkers} is fewer than 2 x {P} parameters ({', '.join(names)}); use at least {2 * P}")
    if walkers % 2:
        raise SampleError(f"--walkers must be even (the stretch move updates two halves), got {walkers}")
    if steps < 1:
        raise SampleError(f"--steps must be >= 1, got {steps}")
    chain_path = out_dir / CHAIN_FILE
    priors = dict(priors) if priors is not None else make_priors(problem)
    log_post = LogPosterior(problem, priors, batched=batched, batch_hint=walkers // 2)
    meta = {"signature": model_signature(problem), "walkers": walkers, "seed": seed, "steps_requested": steps,
            "x0": x0.detach().cpu().double().tolist(), "priors": {n: pr.settings() for n, pr in priors.items()}}
    backend = None
    if resume:
        if not chain_path.is_file():
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
        if chain_path.exists():
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
        "chain": str(chain_path),
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
    if plots:
        summary["plots"] = write_plots(out_dir, chain, diag, phys, names, problem, pstd)
    write_text_atomic(out_dir / SUMMARY_FILE, dumps(summary))
    return summary


# -- plots ----------------------------------------------------------------------------------------
def write_plots(out_dir: Path, chain: np.ndarray, diag: dict, phys: dict, names: list[str], problem: FitProblem,
                pstd: list[np.ndarray]) -> list[str]:
    """corner.png, trace.png and predictive_std_<obs>.png (atomic writes); returns the paths."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from .report import _sanitize, _save_fig

    out = []
    P = len(names)
    # trace (unconstrained x, every walker), burn-in marked
    fig, axes = plt.subplots(P, 1, figsize=(8, 1.6 * P + 0.6), sharex=True, squeeze=False)
    for k, ax in enumerate(axes[:, 0]):
        ax.plot(chain[:, :, k], color="k", alpha=0.15, lw=0.5)
        ax.axvline(diag["burn_in"], color="r", lw=1)
        ax.set_ylabel(f"x: {names[k]}", fontsize=7)
    axes[-1, 0].set_xlabel(f"step (red: burn-in {diag['burn_in']}; tau max {diag['tau_max']:.1f})")
    fig.tight_layout()
    out.append(str(_save_fig(fig, out_dir / "trace.png")))
    # corner (physical units)
    S = np.stack([phys[n] for n in names], 1)
    fig, axes = plt.subplots(P, P, figsize=(2.0 * P + 1, 2.0 * P + 1), squeeze=False)
    for i in range(P):
        for j in range(P):
            ax = axes[i, j]
            if j > i:
                ax.axis("off")
                continue
            if i == j:
                ax.hist(S[:, i], bins=40, color="k", histtype="step")
                q = np.percentile(S[:, i], [16, 50, 84])
                for v in q:
                    ax.axvline(v, color="b", lw=0.8, ls="--")
                ax.set_title(f"{names[i]}\n{q[1]:.4g} +{q[2] - q[1]:.2g} -{q[1] - q[0]:.2g}", fontsize=7)
            else:
                ax.hist2d(S[:, j], S[:, i], bins=40, cmap="Greys")
            if i == P - 1:
                ax.set_xlabel(names[j], fontsize=7)
            if j == 0 and i > 0:
                ax.set_ylabel(names[i], fontsize=7)
            ax.tick_params(labelsize=6)
    fig.tight_layout()
    out.append(str(_save_fig(fig, out_dir / "corner.png")))
    # posterior-predictive spread
    for o, s in zip(problem.observations, pstd):
        meas = o.values[o.mask].detach().cpu().double()
        rel = s / np.maximum(meas.numpy(), 1e-300)
        fig, ax = plt.subplots(figsize=(5.5, 4.8))
        if "image_shape" in o.metadata and "pixel_index" in o.metadata:
            h, w = o.metadata["image_shape"]
            idx = torch.as_tensor(o.metadata["pixel_index"])[o.mask].numpy()
            a = np.full(h * w, np.nan)
            a[idx] = rel.mean(-1)
            im = ax.imshow(a.reshape(h, w), cmap="viridis")
            fig.colorbar(im, ax=ax, fraction=0.046, label="std / measured (mean over channels)")
            ax.set_title(f"{o.name}: posterior-predictive std\n(fisheye: North up, East left)", fontsize=9)
        else:
            ax.plot(rel.mean(-1), ".")
            ax.set_xlabel("sample")
            ax.set_ylabel("std / measured (mean over channels)")
            ax.set_title(f"{o.name}: posterior-predictive std", fontsize=9)
        fig.tight_layout()
        out.append(str(_save_fig(fig, out_dir / f"predictive_std_{_sanitize(o.name)}.png")))
    return out


# -- the command ----------------------------------------------------------------------------------
@dataclasses.dataclass
class SampleSettings:
    """``skyfit sample`` settings: the config's ``sample:`` section, overridden by flags.

    Attributes:
        walkers: ensemble size (>= 2 x free parameters, even).
        steps: chain length in steps (per walker).
        seed: sampler and initial-ball seed.
        priors: name -> {kind, lo, hi | mean, sd} overriding :data:`DEFAULT_PRIORS`.
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


def sample_settings(section: dict | None, overrides: dict | None = None) -> SampleSettings:
    section = dict(section or {})
    known = {f.name for f in dataclasses.fields(SampleSettings)}
    unknown = set(section) - known
    if unknown:
        raise SampleError(f"unknown key(s) {sorted(unknown)} in config section 'sample'; known: {sorted(known)}")
    merged = {**section, **{k: v for k, v in (overrides or {}).items() if v is not None}}
    s = SampleSettings(**merged)
    if not isinstance(s.priors, dict):
        raise SampleError(f"sample.priors must map parameter names to prior specs, got {s.priors!r}")
    return s


def build_problem(data, config: dict, init: dict, init_path, kider_site: dict | None, integrator: str | None = None,
                  view_samples: int | None = None, rule: str | None = None, accuracy: str | None = None,
                  max_samples: int | None = None):
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
    prep = prepare(data, config, s, kider_site=kider_site)
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
        x0 = torch.tensor([float(fv[n]) for n in param.names], dtype=dtype)
    else:
        x0 = param.initial_vector(dtype)
    return problem, x0


def run_sample(data, config: dict, init_path, out_dir, *, overrides: dict | None = None, kider_site: dict | None = None,
               resume: bool = False, progress: bool = False, plots: bool = True, laplace: bool = True) -> dict:
    """``skyfit sample``: rebuild the fit's problem, sample it, write DIR/chain.h5, summary.json and plots."""
    init = read_result(init_path)
    if not init.get("free"):
        raise SampleError(f"{init_path}: the fit has no free parameter to sample")
    if not isinstance(config, dict):
        raise SampleError("config must be a mapping")
    ss = sample_settings(config.get("sample"), overrides)
    t0 = time.perf_counter()
    cheap = ss.integrator is not None or ss.view_samples is not None or ss.rule is not None or ss.accuracy is not None
    problem, x0 = build_problem(data, config, init, init_path, kider_site, ss.integrator, ss.view_samples, ss.rule,
                                accuracy=ss.accuracy, max_samples=ss.max_samples)
    final_problem = None
    if cheap:
        final_problem, _ = build_problem(data, config, init, init_path, kider_site, max_samples=ss.max_samples)
    P = problem.param.size
    if ss.walkers < 2 * P:
        raise SampleError(f"--walkers {ss.walkers} is fewer than 2 x {P} free parameters; use at least {2 * P}")
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
        init_scale=ss.init_scale, extra=extra)
    summary["seconds_total"] = time.perf_counter() - t0
    write_text_atomic(Path(out_dir) / SUMMARY_FILE, dumps(summary))
    return summary
