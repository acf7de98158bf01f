"""The log-posterior that ``skyfit sample`` hands to emcee: priors plus the batched log-likelihood.

It is a density over the unconstrained vector x of :class:`~skyfit.fit.parameters.Parameterisation`
(every parameter's range is then the whole real line, which suits the stretch move), with the
density of the physical prior carried over by the Jacobian of the transform
(:meth:`~skyfit.fit.parameters.ParameterSpec.log_abs_dvdx`)::

    log p(x | data) = log L(x) + sum_k [ log pi_k(v_k(x)) + log |dv_k / dx_k| ]

log L = -sum over used elements of [rho(r / s) + log s] = -n_elements * objective(x):
the Gaussian log-likelihood up to a constant for the ``squared`` loss (known sigma, or
sigma times a fitted ``noise_scale`` s), and the same masks as the fit. Robust losses
give a pseudo-likelihood (recorded in the summary). Each call evaluates a whole array of
walkers in one batched torch forward pass (:class:`skyfit.fit.batched.BatchedLikelihood`),
in the problem's dtype (float64 by default) on its device (CPU or CUDA).
"""
from __future__ import annotations

import math
from typing import Mapping

import numpy as np
import torch
from torch import Tensor

from .batched import BatchedLikelihood, per_walker_loglike
from .model import FitProblem
from .parameters import PARAMETERS
from .priors import Prior, SampleError


class LogPosterior:
    """log p(x | data) for an array of walkers X (B, P) -> (B,), as emcee's ``vectorize=True`` expects.

    Args:
        problem: the fit problem.
        priors: name -> :class:`~skyfit.fit.priors.Prior` for every free parameter
            (:func:`~skyfit.fit.priors.make_priors`).
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
            out = out + (self.priors[n].log_density(v) + spec.log_abs_dvdx(xs, p._hi(n))).sum(-1)
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
