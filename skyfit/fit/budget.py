"""The error budget of a fit: noise, numerical model error and model discrepancy in one sigma.

The Laplace sigma (:mod:`skyfit.fit.laplace`) counts only the data's noise. A fit's renderer
is coarser than the sky it is fitted to, and the parameters absorb the difference; on the
demo sky that bias was 5-34 noise sigmas. This module adds two terms to the covariance of
the unconstrained vector x at the optimum x*, so that the reported sigma is the error bar:

1. **Numerical** (what skyfit can compute itself). The model of the fit's setting m_fit and
   of a converged setting m_ref (:class:`ReferenceModel`, the trade study's reference:
   Gauss-Legendre optical depth with 32 nodes, a 128-node Gauss view integral and, for
   orders >= 2, Bruneton & Neyret 2008 tables with 6 orders) differ at x* by
   delta = m_ref(x*) - m_fit(x*). Refitting with m_fit + delta moves x by one Newton step

       dx = -H^-1 g,   g = d/dx [ -log L(m_fit(x) + delta) ] at x*

   (H the Laplace Hessian; for the Gaussian likelihood g = -J^T W delta and this is the
   Gauss-Newton shift (J^T W J)^-1 J^T W delta). Where the model is not linear along dx
   (:func:`nonlinearity` > :data:`NONLINEAR`) up to ``refits`` lagged refits replace the step
   (:func:`refit_shift`), and what an unconverged iteration has left adds to the error. The
   fitted value is left as it is; dx is reported (``numerical_shift``) and treated as an
   error: cov += dx dx^T.
2. **Discrepancy** (what no setting of this model family resolves, e.g. a two-term phase
   function fitted with one term). A relative error floor f is added in quadrature to each
   element's sigma, sigma'^2 = sigma^2 + (f m)^2, with f chosen so that the chi^2 of the
   residuals left after the numerical correction (o - m_fit(x* + dx) - delta) equals its
   degrees of freedom, n_elements - P (Birge 1932's ratio, spread as a relative floor). f = 0
   when chi^2 <= dof. Its covariance is the Gauss-Newton (J^T W' J)^-1 with sigma' minus that
   with sigma (positive semi-definite; the full Hessian with sigma' need not be, x* not being
   the optimum of the inflated problem), added to the noise's H^-1.

Total: cov_x = H^-1 + [(J^T W' J)^-1 - (J^T W J)^-1] + dx dx^T. ``sigma`` of the result is this total; ``budget`` holds the
parts (``sigma_noise``, ``sigma_numerical``, ``sigma_discrepancy``), the floor, chi^2/dof and
the shift. The floor is a white-noise model: model errors correlated over the sky are what
the numerical term is for; what is left after it is small where the fit's family contains
the truth (docs/uncertainty.md, "Honest sigma under model error", measures the coverage).
"""
from __future__ import annotations

import copy
import dataclasses
import math
import time

import torch
from torch import Tensor

from ..render.sky import render_vectors
from ..scattering.bruneton_tables import TableSizes
from ..scattering.multiple import precompute, sky_radiance
from ..scattering.single import ray_parameters
from ..transmittance import make_integrator
from .laplace import covariance_summary, derived_functions, display_names, laplace_summary, physical_slot_values, transform_jacobian
from .model import FitProblem, SkyModel
from .optimise import FitOptions, fit
from .parameters import FitError

SIGMA_MODES = ("total", "noise")
"""``fit.sigma``: ``total`` (noise + numerical + discrepancy, the default) or ``noise`` (the Laplace sigma of the noise alone)."""

REFERENCE_LIGHT_SAMPLES = 32
"""Gauss-Legendre nodes of the reference's optical depth (skyfit.tools.trade's reference_light)."""
REFERENCE_VIEW_SAMPLES = 128
"""Gauss-Legendre nodes of the reference's view integral (the trade study's reference_view)."""
REFERENCE_TABLES = (16, 64, 16, 8)
"""Bruneton scattering-table sizes (R, MU, MU_S, NU) of the reference's orders >= 2 (the trade study's)."""
REFERENCE_ORDERS = 6
"""Scattering orders of the reference's Bruneton tables (the trade study's reference_orders)."""


@dataclasses.dataclass
class ReferenceModel(SkyModel):
    """A converged renderer: single scattering by a fine Gauss-Legendre quadrature, plus orders >= 2 from
    Bruneton tables (Bruneton & Neyret 2008) as the trade study's reference (``skyfit bench --study trade``):

        L = L_1(gauss light_samples, gauss view_samples) + [L_tables(all orders) - L_tables(order 1)]

    (the bracket: orders >= 2 and the ground's indirect light). ``orders`` 1 keeps single scattering.

    Attributes (besides :class:`SkyModel`'s, of which ``integrator``, ``view_samples`` and ``rule`` are set here):
        reference_tables: scattering-table sizes (R, MU, MU_S, NU) of the orders >= 2.
        reference_orders: orders in those tables.
    """

    reference_tables: tuple[int, int, int, int] = REFERENCE_TABLES
    reference_orders: int = REFERENCE_ORDERS

    @classmethod
    def of(cls, model: SkyModel, light_samples: int = REFERENCE_LIGHT_SAMPLES, view_samples: int = REFERENCE_VIEW_SAMPLES,
           tables: tuple[int, int, int, int] = REFERENCE_TABLES, orders: int = REFERENCE_ORDERS) -> "ReferenceModel":
        """The reference of a fit's model: same orders (1 or more) and ground, converged settings."""
        return cls(make_integrator("gauss", samples=light_samples), orders=model.orders, view_samples=view_samples,
                   rule="gauss", ground=model.ground, reference_tables=tuple(tables), reference_orders=orders)

    def tables(self, atm):
        if self.orders == 1:
            return None
        t = self.reference_tables
        return precompute(atm, orders=self.reference_orders, progress=False,
                          sizes=TableSizes(scattering_r=t[0], scattering_mu=t[1], scattering_mu_s=t[2], scattering_nu=t[3]))

    def renderer(self, atm, altitude_m: float = 0.0, tables=None):
        if self.orders > 1 and tables is None:
            tables = self.tables(atm)

        def render(directions: Tensor, sun: Tensor) -> Tensor:
            single = render_vectors(atm, directions, sun, self.integrator, altitude_m, 1, view_samples=self.view_samples,
                                    rule=self.rule, ground=self.ground)
            if tables is None:
                return single
            r, mu, mu_s, nu = ray_parameters(atm, directions, sun, altitude_m)
            kw = dict(ground=self.ground, below_mu_s_min="clamp")
            return single + sky_radiance(tables, atm, r, mu, mu_s, nu, **kw) - sky_radiance(tables, atm, r, mu, mu_s, nu,
                                                                                             orders=1, **kw)

        return render

    def settings(self) -> dict:
        out = {"single": f"gauss optical depth {self.integrator.settings().get('samples')} nodes, gauss view integral "
                         f"{self.view_samples} nodes", "orders": self.orders, "ground": self.ground}
        if self.orders > 1:
            out.update(multiple="bruneton", table_sizes=list(self.reference_tables), table_orders=self.reference_orders)
        return out


def reference_problem(problem: FitProblem, reference: SkyModel | None = None) -> FitProblem:
    """``problem`` with its renderer replaced by ``reference`` (default :meth:`ReferenceModel.of` its model)."""
    ref = copy.copy(problem)
    ref.model = ReferenceModel.of(problem.model) if reference is None else reference
    ref.frozen_tables = None  # the reference builds its own tables
    if ref.model.orders > 1:  # a frozen factor (a photo's lagged Bruneton orders on live single scattering) stays
        ref.frozen_factor = None
    return ref


def _uncensored(problem: FitProblem, i: int, like: Tensor) -> Tensor:
    o = problem.observations[i]
    return torch.ones_like(like, dtype=torch.bool) if o.censored is None else (o.censored[o.mask] == 0)


def numerical_shift(problem: FitProblem, x: Tensor, cov_x: Tensor, reference: FitProblem) -> dict:
    """One Newton step of refitting with the reference model (module docstring, term 1).

    Args:
        problem: the fit's problem; x: its optimum (P,); cov_x: the inverse Hessian at x (P, P).
        reference: the same problem with the converged renderer (:func:`reference_problem`).

    Returns:
        ``dx`` (P,) [x units], ``delta`` (list of (N_i, C_i) tensors, m_ref - m_fit) [data units],
        ``relative_rms`` of delta / m_fit and ``rms_over_sigma`` of delta / sigma. [1]
    """
    x = x.detach()
    with torch.no_grad():
        m_fit = problem.predict(x)
        m_ref = reference.predict(x)
    delta = [(r - f).detach() for r, f in zip(m_ref, m_fit)]
    xr = x.clone().requires_grad_(True)
    preds = [p + d for p, d in zip(problem.predict(xr), delta)]
    nll = problem.loss_from_predictions(preds, problem.param.to_physical(xr)) * problem.n_elements
    (g,) = torch.autograd.grad(nll, xr)
    dx = -(cov_x.to(g.dtype) @ g)
    num = sum(float((d**2).sum()) for d in delta)
    rel = sum(float(((d / torch.where(f != 0, f, torch.ones_like(f))) ** 2).sum()) for d, f in zip(delta, m_fit))
    over = sum(float(((d / o.sigma[o.mask]) ** 2).sum()) for d, o in zip(delta, problem.observations))
    n = max(sum(d.numel() for d in delta), 1)
    return {"dx": dx.detach(), "delta": delta, "relative_rms": math.sqrt(rel / n), "rms_over_sigma": math.sqrt(over / n),
            "rms": math.sqrt(num / n)}


def reference_factor(problem: FitProblem, reference: FitProblem, x: Tensor) -> list[Tensor]:
    """Per observation, the spectra of the reference over the fit's at x, (N_i, W) [1] (times the fit's own
    frozen factor, when it has one): the fit's renderer times it is the reference at x."""
    with torch.no_grad():
        phys = problem.param.to_physical(x)
        saved = problem.frozen_factor
        problem.frozen_factor = None
        try:
            s_fit = problem.spectra(phys)
        finally:
            problem.frozen_factor = saved
        s_ref = reference.spectra(phys)
    return [torch.where(f != 0, r / torch.where(f != 0, f, torch.ones_like(f)), torch.ones_like(f)) for r, f in zip(s_ref, s_fit)]


def refit_shift(problem: FitProblem, x: Tensor, reference: FitProblem, x_start: Tensor, sigma_x: Tensor,
                iterations: int = 2, options: FitOptions | None = None, tol: float = 0.1) -> dict:
    """The fit with the reference model, by lagged refits of the fit's renderer (brute force, no linearisation).

    Iteration k holds the factor c_k = m_ref(x_k) / m_fit(x_k) (spectra, per sample and wavelength)
    fixed and refits m_fit(x) c_k from x_k (``FitProblem.frozen_factor``; as skyfit.fit.photo's lagged
    fit); at the fixed point the gradient of the reference's likelihood is zero up to the change of
    c with x. Stops after ``iterations`` or when a step moves every parameter by less than ``tol``
    noise sigmas ``sigma_x`` (P,).

    Returns:
        ``x`` (the last iterate (P,)), ``factor`` (the last c_k), ``steps`` (max |step| / sigma_x of each),
        ``tail`` (P,): what the iteration has still to go when it stopped unconverged, the last step
        times r / (1 - r) with r the ratio of the last two steps (at most 0.9; a geometric series),
        zero when it converged, None after a single unconverged refit.
    """
    opt = options or FitOptions(starts=1, adam_steps=0, max_iter=100)
    xk, steps, factor = x_start.detach().to(x.dtype), [], None
    last = prev = None
    for _ in range(iterations):
        factor = reference_factor(problem, reference, xk)
        lagged = copy.copy(problem)
        lagged.frozen_factor = factor
        xn = fit(lagged, opt, x0=xk).x.detach()
        step = float(((xn - xk).abs().to(torch.float64) / sigma_x.clamp_min(1e-300)).max())
        steps.append(step)
        prev, last = last, (xn - xk).to(torch.float64)
        xk = xn
        if step < tol:
            break
    tail = None  # unknown after a single unconverged step: the caller compares with the Newton step
    if steps and steps[-1] < tol:
        tail = torch.zeros_like(x, dtype=torch.float64)
    elif prev is not None:
        r = min(float(last.norm() / prev.norm().clamp_min(1e-300)), 0.9)
        tail = last * (r / (1.0 - r))
    return {"x": xk, "factor": factor, "steps": steps, "tail": tail}


NONLINEAR = 0.02
"""The Newton step is replaced by lagged refits when the model's change along it departs from the
linear prediction by more than this fraction (:func:`nonlinearity`). [1]"""


def nonlinearity(problem: FitProblem, x: Tensor, dx: Tensor, eps: float = 1e-3) -> float:
    """||m(x + dx) - m(x) - J dx|| / ||J dx|| in the noise-weighted norm, J dx by a forward difference
    at eps dx: 0 for a model linear along dx; > 0.1 and the Newton step is not to be trusted. [1]"""
    with torch.no_grad():
        m0 = problem.predict(x)
        m1 = problem.predict(x + dx.to(x.dtype))
        me = problem.predict(x + eps * dx.to(x.dtype))
    num = den = 0.0
    for a, b, c, o in zip(m0, m1, me, problem.observations):
        s = o.sigma[o.mask]
        lin = (c - a) / eps
        num += float((((b - a - lin) / s) ** 2).sum())
        den += float(((lin / s) ** 2).sum())
    return math.sqrt(num / den) if den > 0 else 0.0


def chi2_with_floor(problem: FitProblem, preds, floor: float, phys: dict) -> tuple[float, int]:
    """(sum of squared residuals, n) over the uncensored used elements of the model ``preds`` (list of (N_i, C_i))
    with sigma'^2 = sigma^2 + (floor m)^2; sigma is the data's times the ``noise_scale`` of ``phys``
    (:meth:`Parameterisation.to_physical` at the fit)."""
    total, n = 0.0, 0
    for i, (m, o) in enumerate(zip(preds, problem.observations)):
        s = o.sigma[o.mask] * phys_noise_scale(problem, phys, i)
        keep = _uncensored(problem, i, m)
        sp = torch.sqrt(s**2 + (floor * m) ** 2)
        r = problem.loss.residuals(m, o.values[o.mask], sp)
        total += float((r[keep] ** 2).sum())
        n += int(keep.sum())
    return total, n


def phys_noise_scale(problem: FitProblem, phys: dict, i: int) -> float:
    """Observation i's noise scale (1 unless ``noise_scale`` is fitted). [1]"""
    return float(problem.param.nuisance(phys, i)["noise_scale"])


def fit_floor(problem: FitProblem, preds, dof: int, phys: dict, target: float | None = None) -> float:
    """The relative floor f >= 0 with chi^2(f) = ``target`` (default ``dof``): 0 when chi^2(0) <= target. [1]

    chi^2(f) decreases with f; bisection in log f over [1e-9, 10]."""
    target = float(dof) if target is None else target
    c0, _ = chi2_with_floor(problem, preds, 0.0, phys)
    if c0 <= target:
        return 0.0
    lo, hi = math.log(1e-9), math.log(10.0)
    if chi2_with_floor(problem, preds, 10.0, phys)[0] > target:
        return 10.0
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        if chi2_with_floor(problem, preds, math.exp(mid), phys)[0] > target:
            lo = mid
        else:
            hi = mid
    return math.exp(0.5 * (lo + hi))


def inflated_problem(problem: FitProblem, preds, floor: float, phys: dict) -> FitProblem:
    """``problem`` whose observations' sigma has the relative floor added in quadrature (used elements),
    sigma'^2 = sigma^2 + (floor m / noise_scale)^2 with m the model ``preds`` [data units]."""
    out = copy.copy(problem)
    obs = []
    for i, (m, o) in enumerate(zip(preds, problem.observations)):
        ns = phys_noise_scale(problem, phys, i)
        sigma = o.sigma.clone()
        sigma[o.mask] = torch.sqrt(sigma[o.mask] ** 2 + (floor * m.to(sigma.dtype) / ns) ** 2)
        obs.append(dataclasses.replace(o, sigma=sigma))
    out.observations = obs
    return out


def prediction_jacobian(problem: FitProblem, x: Tensor) -> list[Tensor]:
    """d m_i / dx of every observation's predictions, a list of (N_i, C_i, P) tensors, by P Jacobian-vector
    products (torch.autograd.functional.jvp, the double-backward trick). [data units / x units]"""
    x = x.detach()
    cols = []
    for k in range(x.numel()):
        v = torch.zeros_like(x)
        v[k] = 1.0
        _, jv = torch.autograd.functional.jvp(lambda z: torch.cat([p.reshape(-1) for p in problem.predict(z)]), (x,), (v,))
        cols.append(jv.detach())
    J = torch.stack(cols, -1)
    out, i = [], 0
    with torch.no_grad():
        for p in problem.predict(x):
            n = p.numel()
            out.append(J[i:i + n].reshape(*p.shape, -1))
            i += n
    return out


def gauss_newton_covariance(problem: FitProblem, jac: list[Tensor], preds, floor: float, phys: dict) -> Tensor:
    """(J_r^T J_r)^-1 of the whitened residuals r with sigma'^2 = sigma^2 + (floor m)^2 (uncensored used
    elements; a linear or log residual), shape (P, P). [x units^2]"""
    rows = []
    for i, (Jm, m, o) in enumerate(zip(jac, preds, problem.observations)):
        s = o.sigma[o.mask] * phys_noise_scale(problem, phys, i)
        sp = torch.sqrt(s**2 + (floor * m) ** 2)
        w = 1.0 / sp if problem.loss.residual == "linear" else o.values[o.mask] / (m.clamp_min(1e-300) * sp)
        keep = _uncensored(problem, i, m)
        rows.append((Jm * w.unsqueeze(-1))[keep])
    Jr = torch.cat(rows).to(torch.float64)
    G = Jr.T @ Jr
    return torch.linalg.pinv(0.5 * (G + G.T), hermitian=True)


def error_budget(problem: FitProblem, x: Tensor, lap: dict | None = None, *, reference: SkyModel | None = None,
                 numerical: bool = True, floor: bool = True, refits: int = 0, options: FitOptions | None = None) -> dict:
    """The Laplace summary with the total sigma (noise + numerical + discrepancy) and its breakdown.

    Args:
        problem: the fit problem; x: the fitted unconstrained vector, shape (P,).
        lap: :func:`skyfit.fit.laplace.laplace_summary` at x (computed when None).
        reference: the converged renderer (default :meth:`ReferenceModel.of` the fit's).
        numerical, floor: include the numerical term / the discrepancy floor.
        refits: 0: the numerical shift is one Newton step; N > 0: up to N lagged refits with the
            reference's factor (:func:`refit_shift`; for shifts too large for the linearisation).
        options: the refits' optimiser options (default 1 start, 100 L-BFGS iterations).

    Returns:
        ``lap``'s keys with ``sigma``, ``interval68``, ``interval95``, ``covariance``, ``correlation``,
        ``derived`` of the total covariance, ``sigma_mode`` "total", ``sigma_noise`` (the Laplace sigma)
        and ``budget``: ``sigma_noise``, ``sigma_numerical``, ``sigma_discrepancy`` (name -> [SI]),
        ``numerical_shift`` (name -> physical value after the Newton step minus the fitted one [SI]),
        ``derived`` (the same for derived quantities), ``floor_relative`` f [1] and its range
        ``floor_relative_68`` (chi^2 at dof -+ sqrt(2 dof)), ``chi2_per_dof`` (at the fit),
        ``chi2_per_dof_corrected`` (after the numerical correction), ``dof``, ``reference`` (the
        converged renderer's settings), ``model_difference`` (rms of delta / m and delta / sigma), ``seconds``.
    """
    t0 = time.perf_counter()
    x = x.detach()
    lap = laplace_summary(problem, x) if lap is None else lap
    names = display_names(problem)
    cov_noise = torch.as_tensor(lap["covariance_unconstrained"], dtype=torch.float64)
    pd = bool(lap.get("positive_definite", True))
    P = x.numel()
    phys = {k: v.detach() for k, v in problem.param.to_physical(x).items()}
    budget: dict = {"reference": None, "model_difference": None}
    dx = torch.zeros(P, dtype=torch.float64)
    tail = torch.zeros(P, dtype=torch.float64)
    delta, lagged = None, None
    if numerical:
        ref = reference_problem(problem, reference)
        ns = numerical_shift(problem, x, cov_noise, ref)
        dx, delta = ns["dx"].to(torch.float64), ns["delta"]
        budget["reference"] = ref.model.settings()
        budget["model_difference"] = {k: ns[k] for k in ("relative_rms", "rms_over_sigma", "rms")}
        budget["method"] = "newton"
        v_newton = physical_slot_values(problem, x.to(torch.float64) + dx)
        budget["nonlinearity"] = rho = nonlinearity(problem, x, dx)
        if refits > 0 and rho > NONLINEAR:
            s_x = torch.as_tensor([lap["sigma_unconstrained"][n] for n in names], dtype=torch.float64)
            rs = refit_shift(problem, x, ref, x, s_x, refits, options)
            budget["method"] = f"refit ({len(rs['steps'])} lagged refits)"
            budget["refit_steps_in_sigma"] = rs["steps"]
            budget["numerical_shift_newton"] = {n: float(b - a) for n, a, b in zip(
                names, physical_slot_values(problem, x.to(torch.float64)), v_newton)}
            dx_newton = dx
            dx = (rs["x"] - x).to(torch.float64)
            # one unconverged refit: the two estimates of the shift disagree by about what is left
            tail = rs["tail"] if rs["tail"] is not None else dx - dx_newton
            budget["numerical_tail"] = {n: float(t) for n, t in zip(names, transform_jacobian(problem, x.to(torch.float64)) * tail)}
            lagged = copy.copy(problem)
            lagged.frozen_factor = rs["factor"]
    with torch.no_grad():
        m_fit = problem.predict(x)
        if lagged is not None:  # the refit's own model: m_fit c_k
            m_cor = lagged.predict(x + dx.to(x.dtype))
        else:
            m_cor = problem.predict(x + dx.to(x.dtype)) if numerical else m_fit
    if delta is not None and lagged is None:
        m_cor = [m + d for m, d in zip(m_cor, delta)]
    m_cor = [problem.censor(m, i) for i, m in enumerate(m_cor)]
    m_fit_c = [problem.censor(m, i) for i, m in enumerate(m_fit)]
    c_fit, n_used = chi2_with_floor(problem, m_fit_c, 0.0, phys)
    c_cor, _ = chi2_with_floor(problem, m_cor, 0.0, phys)
    dof = max(n_used - P, 1)
    budget.update(chi2_per_dof=c_fit / dof, chi2_per_dof_corrected=c_cor / dof, dof=dof)
    f, f_range, cov_infl = 0.0, [0.0, 0.0], cov_noise
    applicable = problem.loss.rho == "squared" and problem.loss.residual in ("linear", "log")
    if floor and applicable:
        f = fit_floor(problem, m_cor, dof, phys)
        spread = math.sqrt(2.0 * dof)
        f_range = [fit_floor(problem, m_cor, dof, phys, dof + spread), fit_floor(problem, m_cor, dof, phys, dof - spread)]
        if f > 0:  # the discrepancy's share: Gauss-Newton covariance with sigma' minus that with sigma (PSD,
            # where the full Hessian with sigma' need not be: x* is not the optimum of the inflated problem)
            jac = prediction_jacobian(problem, x)
            extra = gauss_newton_covariance(problem, jac, m_fit, f, phys) - gauss_newton_covariance(problem, jac, m_fit, 0.0, phys)
            ev, U = torch.linalg.eigh(0.5 * (extra + extra.T))
            cov_infl = cov_noise + (U * ev.clamp_min(0.0)) @ U.T
    budget["floor_relative"] = f if applicable else None
    budget["floor_relative_68"] = f_range if applicable else None
    if floor and not applicable:
        budget["floor_note"] = f"no floor for the {problem.loss.name} loss (it needs rho squared on a linear or log residual)"
    cov_total = cov_infl + torch.outer(dx, dx) + torch.outer(tail, tail)
    out = {**lap, **covariance_summary(problem, x, cov_total, pd)}
    out["positive_definite"] = pd
    out["sigma_mode"] = "total"
    out["sigma_noise"] = lap["sigma"]
    out["covariance_noise"] = lap["covariance"]
    J = transform_jacobian(problem, x.to(torch.float64))
    s_num = J.abs() * torch.sqrt(dx**2 + tail**2)
    s_dis = torch.sqrt(torch.clamp_min(torch.diagonal(cov_infl) - torch.diagonal(cov_noise), 0.0)) * J.abs()
    v0 = physical_slot_values(problem, x.to(torch.float64))
    v1 = physical_slot_values(problem, x.to(torch.float64) + dx)
    budget["sigma_noise"] = lap["sigma"]
    budget["sigma_numerical"] = {n: float(s) for n, s in zip(names, s_num)}
    budget["sigma_discrepancy"] = {n: float(s) for n, s in zip(names, s_dis)}
    budget["numerical_shift"] = {n: float(b - a) for n, a, b in zip(names, v0, v1)}
    derived = {}
    for name, fn in derived_functions(problem).items():
        xr = x.to(torch.float64).clone().requires_grad_(True)
        val = fn(xr)
        (g,) = torch.autograd.grad(val, xr)
        with torch.no_grad():
            shifted = float(fn(x.to(torch.float64) + dx))
        derived[name] = {"sigma_noise": lap["derived"][name]["sigma"], "sigma_numerical": abs(float(g @ dx)),
                         "sigma_discrepancy": math.sqrt(max(float(g @ (cov_infl - cov_noise) @ g), 0.0)),
                         "numerical_shift": shifted - float(val.detach())}
    budget["derived"] = derived
    budget["seconds"] = time.perf_counter() - t0
    out["budget"] = budget
    out["seconds"] = lap.get("seconds", 0.0) + budget["seconds"]
    return out


def uncertainty(problem: FitProblem, x: Tensor, sigma: str = "total", reference: SkyModel | None = None,
                refits: int = 0, options: FitOptions | None = None) -> dict:
    """RESULT.json's ``laplace``: :func:`error_budget` for ``sigma="total"``, the noise-only Laplace summary
    (``sigma_mode`` "noise") for ``"noise"``."""
    if sigma not in SIGMA_MODES:
        raise FitError(f"sigma must be one of {', '.join(SIGMA_MODES)}, got {sigma!r}")
    lap = laplace_summary(problem, x)
    if sigma == "noise" or not lap.get("positive_definite", True):
        return {**lap, "sigma_mode": "noise"}
    return error_budget(problem, x, lap, reference=reference, refits=refits, options=options)
