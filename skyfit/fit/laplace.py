"""Laplace approximation: a Gaussian posterior from the Hessian of the negative log-likelihood at the fit.

At the optimum x* of the unconstrained vector (skyfit.fit.parameters) the negative
log-likelihood -log L(x) = n_elements * objective(x) (+ const; exact for the squared
loss with Gaussian noise, a pseudo-likelihood for the robust losses) is approximated
by its second-order Taylor expansion (e.g. MacKay 2003, "Information Theory, Inference,
and Learning Algorithms", Ch. 27; Gelman et al. 2013, BDA3 Sec. 4.1)::

    cov_x = H^-1,   H = d^2 (-log L) / dx dx   at x*

(flat priors in x: the default log-uniform priors of the positive scale parameters are
flat in x; :mod:`skyfit.fit.posterior` adds the others). H comes from torch autograd
(:func:`torch.autograd.functional.hessian`, float64). Physical units by the delta
method: v = f(x) elementwise, so cov_v = J cov_x J with J = diag(f'(x*)).
Intervals are Gaussian in x, mapped through f: [f(x* - z s), f(x* + z s)] (they respect
each parameter's range, e.g. g in (-1, 1)).
"""
from __future__ import annotations

import math
import time
from collections.abc import Sequence

import torch
from torch import Tensor

from .model import FitProblem
from .parameters import PARAMETERS, FitError

Z68 = 0.9944578832097535
"""Half-width of the central 68 % interval in units of sigma (Phi^-1(0.84)); 0.99446."""
Z95 = 1.959963984540054
"""Half-width of the central 95 % interval (Phi^-1(0.975))."""


def display_names(problem: FitProblem) -> list[str]:
    """``param.names`` with a single observation's ``[0]`` dropped (``exposure`` rather than ``exposure[0]``)."""
    p = problem.param
    return [n[:-3] if p.n_observations == 1 and n.endswith("[0]") else n for n in p.names]


def hessian_nll(problem: FitProblem, x: Tensor) -> Tensor:
    """Hessian of n_elements * objective at x, shape (P, P), float64. [1 / x^2]"""
    x = x.detach().to(torch.float64) if problem.param.base.dtype == torch.float64 else x.detach()
    n = problem.n_elements

    def f(v: Tensor) -> Tensor:
        return problem.objective(v) * n

    H = torch.autograd.functional.hessian(f, x)
    return 0.5 * (H + H.T)


def transform_jacobian(problem: FitProblem, x: Tensor) -> Tensor:
    """dv_k / dx_k of every slot of x (the transforms are elementwise), shape (P,)."""
    p = problem.param
    xr = x.detach().clone().requires_grad_(True)
    vals = torch.empty_like(xr)
    out = []
    for n in p.free:
        spec = PARAMETERS[n]
        for k in p._slots[n]:
            v = spec.forward(xr[k], p._hi(n))
            (g,) = torch.autograd.grad(v, xr)
            out.append(g[k])
    del vals
    return torch.stack(out).detach()


def physical_slot_values(problem: FitProblem, x: Tensor) -> Tensor:
    """Physical value of each slot of x (P,) in the order of ``param.names``. [SI]"""
    p = problem.param
    out = torch.empty_like(x)
    for n in p.free:
        spec = PARAMETERS[n]
        for k in p._slots[n]:
            out[k] = spec.forward(x[k], p._hi(n))
    return out


HELD_NEAR_BOUND = 1e-3
"""Where the Hessian is not positive definite, a bounded parameter whose position u in its range lies within this of 0
or 1 is held there for the others' covariance (:func:`laplace_summary`): pressed against its bound, its sigmoid all but
saturated, it is a flat direction of x (held-out synthetic photo 6, session 15: a camera's red saturation at 0.10007 of
its 0.1, u 1.7e-4, the Hessian's one negative eigenvalue -0.06 along it alone, took every sigma with it). [1]"""

AT_BOUND = 1e-6
"""A bounded parameter (``interval``, ``loginterval``) whose position u = sigmoid(x) in its range lies within this of 0
or 1 sits on its bound. [1]"""


def bound_slots(problem: FitProblem, x: Tensor, within: float = AT_BOUND) -> list[bool]:
    """Whether each slot of x (P,) sits on a bound of its range (``within`` of it in u; :data:`AT_BOUND`). There the
    transform's slope is 0 (the sigmoid saturates, and is clamped beyond :data:`skyfit.fit.parameters.SIGMOID_EDGE`),
    so the delta method's physical sigma is about 0 whatever the data allow: the likelihood is not Gaussian there, and
    only the interval (x +- z sigma_x mapped, which reaches from inside the range to the bound) describes it."""
    p = problem.param
    out = [False] * x.numel()
    for n in p.free:
        if PARAMETERS[n].transform not in ("interval", "loginterval"):
            continue
        for k in p._slots[n]:
            u = float(torch.sigmoid(x[k].detach().to(torch.float64)))
            out[k] = min(u, 1.0 - u) < within
    return out


def derived_functions(problem: FitProblem):
    """Derived quantities worth a sigma: name -> function of x (a tensor ()), for the free set."""
    p = problem.param
    free = set(p.free)
    out = {}
    if "mie_beta_550" in free or ("mie_aod_550" in free):
        other = "mie_aod_550" if "mie_beta_550" in free else "mie_beta_550"
        if other == "mie_aod_550":  # beta_550 x the column height (H_M, or h_mix + H_M for the boundary layer)
            out[other] = lambda x: (lambda ph: p._beta_550(ph) * p._column_height(ph))(p.to_physical(x))
        else:
            out[other] = lambda x: p._beta_550(p.to_physical(x))
    from .parameters import COARSE_MODE, LOGNORMAL_MIE

    if free & {*LOGNORMAL_MIE, *COARSE_MODE}:  # what the size distribution implies: alpha, g, ssa (delta method)
        for name in ("mie_angstrom_alpha", "mie_g", "mie_ssa"):
            out[name] = (lambda n: lambda x: p.lognormal_optics_derived(p.to_physical(x))[n])(name)
    return out



def covariance_from_hessian(H: Tensor, held: Sequence[bool] | None = None) -> tuple[Tensor, bool, float]:
    """(H^-1, positive definite, min eigenvalue) of a Hessian (P, P); the pseudo-inverse when not PD.

    ``held``: slots held where they are (a parameter on its bound, :func:`bound_slots`): the covariance of the others
    with those fixed (the inverse of H without their rows and columns, as for an active constraint), zero in their
    rows and columns; positive definite and the min eigenvalue are of that block."""
    H = H.to(torch.float64)
    if not bool(torch.isfinite(H).all()):
        raise FitError("Laplace: the Hessian at the fit is not finite")
    if held is not None and any(held):
        keep = torch.tensor([not h for h in held], device=H.device)
        idx = torch.nonzero(keep).reshape(-1)
        block, pd, min_eig = covariance_from_hessian(H.index_select(0, idx).index_select(1, idx))
        cov_x = torch.zeros_like(H)
        cov_x[idx.unsqueeze(1), idx.unsqueeze(0)] = block
        return cov_x, pd, min_eig
    evals = torch.linalg.eigvalsh(H)
    L, info = torch.linalg.cholesky_ex(H)
    pd = bool(evals.min() > 0) and int(info) == 0  # an eigenvalue at rounding level can fail the factorisation
    cov_x = torch.cholesky_inverse(L) if pd else torch.linalg.pinv(H, hermitian=True)
    return 0.5 * (cov_x + cov_x.T), pd, float(evals.min())


def covariance_summary(problem: FitProblem, x: Tensor, cov_x: Tensor, pd: bool = True) -> dict:
    """sigma, intervals, correlation and derived sigmas of a covariance ``cov_x`` (P, P) of the unconstrained x.

    The part of :func:`laplace_summary` after the Hessian, shared with the error budget
    (:mod:`skyfit.fit.budget`), which passes its total covariance. Keys: ``names``, ``values``,
    ``sigma`` (None where not ``pd``, zero, or on a bound), ``at_bound`` (:func:`bound_slots`' names), ``sigma_unconstrained``, ``correlation``,
    ``covariance`` (physical), ``covariance_unconstrained``, ``interval68``, ``interval95``, ``derived``.
    """
    x64 = x.detach().to(torch.float64)
    cov_x = cov_x.to(dtype=torch.float64, device=x.device)
    J = transform_jacobian(problem, x64)
    cov_v = J[:, None] * cov_x * J[None, :]
    s_x = torch.sqrt(torch.clamp_min(torch.diagonal(cov_x), 0.0))
    s_v = torch.sqrt(torch.clamp_min(torch.diagonal(cov_v), 0.0))
    d = torch.where(s_x > 0, s_x, torch.ones_like(s_x))
    corr = cov_x / d[:, None] / d[None, :]
    vals = physical_slot_values(problem, x64)
    names = display_names(problem)
    edge = bound_slots(problem, x64)
    out = {
        "names": names,
        "values": {n: float(v) for n, v in zip(names, vals)},
        # a variance the Hessian does not make positive is unknown, not zero; at a bound not Gaussian (bound_slots)
        "sigma": {n: (float(s) if pd and float(s) > 0 and not e else None) for n, s, e in zip(names, s_v, edge)},
        "at_bound": [n for n, e in zip(names, edge) if e],
        "sigma_unconstrained": {n: float(s) for n, s in zip(names, s_x)},
        "correlation": corr.tolist(),
        "covariance": cov_v.tolist(),
        "covariance_unconstrained": cov_x.tolist(),
    }
    for key, z in (("interval68", Z68), ("interval95", Z95)):
        lo = physical_slot_values(problem, x64 - z * s_x)
        hi = physical_slot_values(problem, x64 + z * s_x)
        out[key] = {n: [float(a), float(b)] for n, a, b in zip(names, lo, hi)}
    derived = {}
    for name, fn in derived_functions(problem).items():
        xr = x64.clone().requires_grad_(True)
        val = fn(xr)
        (g,) = torch.autograd.grad(val, xr)
        var = float(g @ cov_x @ g)
        derived[name] = {"value": float(val.detach()), "sigma": math.sqrt(max(var, 0.0))}
    out["derived"] = derived
    return out

def laplace_summary(problem: FitProblem, x: Tensor, hessian: Tensor | None = None) -> dict:
    """The Laplace approximation at the fitted x: sigma and correlation per free parameter.

    Args:
        problem: the fit problem (its objective is the mean loss per element).
        x: the fitted unconstrained vector, shape (P,).
        hessian: the Hessian of n_elements x objective at x, (P, P) (default :func:`hessian_nll`).

    Returns:
        dict with ``names`` (param.names), ``values`` and ``sigma`` (name -> physical value and
        its delta-method sigma [SI]), ``sigma_unconstrained``, ``interval68`` / ``interval95``
        (name -> [lo, hi], Gaussian in x mapped to physical units), ``correlation`` (P x P),
        ``covariance`` (physical, P x P), ``derived`` (e.g. mie_aod_550 value and sigma),
        ``positive_definite``, ``min_eigenvalue``, ``seconds``. When the Hessian is not positive
        definite (a flat direction: a parameter the data do not constrain) sigma is from the
        pseudo-inverse and ``positive_definite`` is False.
    """
    t0 = time.perf_counter()
    x = x.detach()
    H = hessian_nll(problem, x) if hessian is None else hessian
    cov_x, pd, min_eig = covariance_from_hessian(H)
    edge = bound_slots(problem, x, HELD_NEAR_BOUND)
    held = None
    if not pd and any(edge) and not all(edge):
        # a parameter pressed against its bound is a flat direction of x (the sigmoid saturates): it took every sigma
        # with it (HELD_NEAR_BOUND). The others' covariance with it held there, as an active constraint; its own
        # sigma None (a zero variance, covariance_summary)
        cov_x, pd, min_eig = covariance_from_hessian(H, held=edge)
        held = [n for n, e in zip(display_names(problem), edge) if e]
    out = covariance_summary(problem, x, cov_x, pd)
    out["positive_definite"] = pd
    out["min_eigenvalue"] = min_eig
    if held:
        out["held_at_bound"] = held
    out["seconds"] = time.perf_counter() - t0
    return out
