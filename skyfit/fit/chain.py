"""The emcee chain of ``skyfit sample``: initial ball, the run, checkpoints and resuming.

The sampler is emcee's affine-invariant ensemble sampler (Goodman & Weare 2010;
Foreman-Mackey et al. 2013) with ``vectorize=True``: each call evaluates half the
ensemble (:class:`skyfit.fit.posterior.LogPosterior`).

Checkpoints: the chain lives in memory and is written to ``DIR/chain.h5`` every
``checkpoint_seconds`` and at the end, each time as a complete file written to a
temporary name and renamed (an HDF5 file written in place is left unreadable by a
SIGKILL in mid-write). The file has emcee's HDFBackend layout (group ``mcmc``, so
``emcee.backends.HDFBackend(path, read_only=True)`` reads it) plus the random state and
the model signature; ``--resume`` restores both and continues the same chain: the result
equals an uninterrupted run's (tests/test_sample.py).
"""
from __future__ import annotations

import json
import sys
import time
import warnings
from pathlib import Path

import emcee
import h5py
import numpy as np
from torch import Tensor
from tqdm import tqdm

from .model import FitProblem
from .posterior import LogPosterior
from .priors import SampleError
from ..io.atomic import atomic_path

CHAIN_FILE = "chain.h5"


def write_checkpoint(path: Path, backend, meta: dict) -> None:
    """The chain so far as a complete HDF5 file (emcee's layout + skyfit attrs), written atomically."""
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


def run_chain(log_post: LogPosterior, x_init: np.ndarray | None, walkers: int, steps: int, chain_path: Path | None, meta: dict, *,
              seed: int = 0, backend=None, progress: bool = False, checkpoint_seconds: float = 10.0,
              stop_after: int | None = None):
    """Run (or continue) the emcee chain to ``steps`` steps in all, checkpointing to ``chain_path`` (None: in memory).

    Args:
        backend: an in-memory Backend from :func:`read_checkpoint` to continue (x_init unused).
        stop_after: stop (without the final checkpoint) after this many new steps: a stand-in for
            a killed run in tests.

    Returns:
        (emcee.EnsembleSampler, seconds spent in this call).
    """
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
                    with warnings.catch_warnings():
                        warnings.simplefilter("ignore")
                        tau = emcee.autocorr.integrated_time(backend.chain[:it], c=5, tol=0, quiet=True)
                    tm = float(np.nanmax(tau))
                    bar.set_postfix(tau=f"{tm:.1f}", steps_per_tau=f"{it / tm:.0f}", acc=f"{np.mean(backend.accepted) / it:.2f}")
            if stop_after is not None and n_new >= stop_after:
                return sampler, time.perf_counter() - t0
            if chain_path is not None and time.perf_counter() - last_ck >= checkpoint_seconds:
                write_checkpoint(chain_path, backend, meta)
                last_ck = time.perf_counter()
    finally:
        if bar is not None:
            bar.close()
    if chain_path is not None:
        write_checkpoint(chain_path, backend, meta)
    return sampler, time.perf_counter() - t0
