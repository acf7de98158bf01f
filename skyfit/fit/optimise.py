"""Gradient fits from several starts: Levenberg-Marquardt for least squares, else Adam then L-BFGS.

Each start (the given values, then points spread over each parameter's typical
span, :meth:`~skyfit.fit.parameters.Parameterisation.spread_starts`) has its free
exposure set in closed form (:meth:`~skyfit.fit.model.FitProblem.profile_exposure`),
then runs one of :data:`METHODS`:

``lm``
    Levenberg-Marquardt on the residual vector r (loss = |r|^2 / 2 per element;
    rho ``squared`` with any residual, ``noise_scale`` not free): Marquardt's scaled
    damping ``(J^T J + S + lambda diag(J^T J)) d = -J^T r`` with Nielsen's update of lambda
    (Madsen, Nielsen & Tingleff 2004, "Methods for non-linear least squares problems",
    Sec. 3.2, eq. 3.16) and, for residuals that stay large at the optimum (model error),
    the structured secant term S ~ sum r_i Hess(r_i) of NL2SOL (Dennis, Gay & Welsch 1981,
    ACM TOMS 7(3), eqs. 4-5 with their sizing), which turns Gauss-Newton's linear tail into
    a superlinear one (the Kider fits: 8 iterations instead of 20; docs/benchmarks.md).
    J comes from forward differences, one column per free parameter; a column of an
    instrument (nuisance) parameter reuses the multiple-scattering tables of x, which do
    not depend on it. Stops when an accepted step's actual and predicted loss reductions
    are both below ``rel_tol`` x loss ("relative loss change"), when max |d loss / d x| is
    below ``grad_tol`` ("gradient norm"), or after ``max_iter`` iterations.
``lbfgs``
    ``adam_steps`` Adam steps (robust far from the optimum, where L-BFGS's curvature
    pairs mislead), then L-BFGS (``torch.optim.LBFGS``, strong Wolfe line search;
    Nocedal & Wright 2006, Alg. 7.5 and 3.5) until max |d loss / d x| < ``grad_tol``
    ("gradient norm"), the loss changes by less than ``rel_tol`` x |loss at the start| between
    iterations, or the step is that small ("relative loss change"), or ``max_iter`` iterations.
``auto`` (default)
    ``lm`` where it applies (:func:`least_squares_applies`), else ``lbfgs``.

The start with the lowest final loss wins; every start's outcome is reported
(``convergence``: converged, reason, iterations, evaluations, method, ...). Work is in
the problem's dtype (float64 by default, so that the line search and the convergence
tests see differences of 1e-10).
"""
from __future__ import annotations

import dataclasses
import math
import time

import torch
from torch import Tensor

from .model import FitProblem
from .parameters import PARAMETERS, FitError

METHODS = ("auto", "lm", "lbfgs")
"""Optimisers of :class:`FitOptions` (module docstring)."""


@dataclasses.dataclass
class FitOptions:
    """Optimiser settings.

    Attributes:
        starts: number of starting points (1 = only the given values).
        seed: seed of the generator that spreads the starts.
        adam_steps: Adam warm-start steps per start.
        adam_lr: Adam step size in unconstrained units (one unit = a factor e for log parameters).
        max_iter: L-BFGS iterations per start.
        grad_tol: stop when max |d loss / d x| is below this.
        rel_tol: stop when the loss changes by less than rel_tol x |loss|.
        history_size: L-BFGS memory.
        profile_exposure: set a free exposure in closed form at each start.
        progress: show a tqdm bar with the loss (stderr).
        method: one of :data:`METHODS`; ``lm`` ignores ``adam_steps`` and ``history_size``.
    """

    starts: int = 3
    seed: int = 0
    adam_steps: int = 10
    adam_lr: float = 0.05
    max_iter: int = 100
    grad_tol: float = 1e-7
    rel_tol: float = 1e-10
    history_size: int = 20
    profile_exposure: bool = True
    progress: bool = False
    method: str = "auto"

    def __post_init__(self):
        if self.method not in METHODS:
            raise FitError(f"unknown optimiser {self.method!r}; valid: {', '.join(METHODS)}")
        for name in ("starts", "max_iter"):
            if getattr(self, name) < 1:
                raise FitError(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.adam_steps < 0:
            raise FitError(f"adam_steps must be >= 0, got {self.adam_steps}")
        for name in ("adam_lr", "grad_tol", "rel_tol"):
            if not getattr(self, name) > 0:
                raise FitError(f"{name} must be > 0, got {getattr(self, name)}")


@dataclasses.dataclass
class OptimiseResult:
    """Outcome of :func:`fit`.

    Attributes:
        x: best unconstrained vector, shape (P,).
        loss: its loss (mean per used element).
        parameters: every parameter's physical value (SI; lists for per-observation ones).
        free: the fitted names.
        convergence: converged, reason, iterations, evaluations, grad_norm (max |g|),
            rel_change, seconds.
        starts: each start's initial and final free values, loss and convergence.
        history: loss after each evaluation of the winning start.
    """

    x: Tensor
    loss: float
    parameters: dict
    free: list[str]
    convergence: dict
    starts: list[dict]
    history: list[float]


def _value_and_grad(problem: FitProblem, x: Tensor) -> tuple[float, Tensor]:
    xg = x.detach().clone().requires_grad_(True)
    loss = problem.objective(xg)
    (g,) = torch.autograd.grad(loss, xg)
    return float(loss.detach()), g


def _nonfinite_names(problem: FitProblem, *vectors: Tensor) -> list[str]:
    """Names of the parameters at which any of ``vectors`` (each shape (P,), in x's order) is NaN or Inf."""
    finite = torch.stack([torch.isfinite(v) for v in vectors]).all(0).tolist()
    return [n for n, ok in zip(problem.param.names, finite) if not ok]


# -- Levenberg-Marquardt ---------------------------------------------------------------------
def least_squares_applies(problem: FitProblem) -> str | None:
    """None when ``problem``'s loss is a sum of squared residuals that ``lm`` can minimise, else why not."""
    if problem.loss.rho != "squared":
        return f"the loss rho is {problem.loss.rho!r}, not 'squared'"
    if "noise_scale" in problem.param.free:
        return "noise_scale is free (its log term is not a squared residual)"
    return None


def resolved_method(problem: FitProblem, opt: FitOptions) -> str:
    """The optimiser :func:`fit` runs for ``opt.method``: ``lbfgs``, or ``lm`` where it is asked for or, under
    ``auto``, where it applies (:func:`least_squares_applies`); a FitError where ``lm`` is asked for and cannot
    minimise the loss."""
    if opt.method == "lbfgs":
        return "lbfgs"
    why = least_squares_applies(problem)
    if why is not None and opt.method == "lm":
        raise FitError(f"the lm optimiser minimises squared residuals, but {why}; use lbfgs or auto")
    return "lbfgs" if why is not None else "lm"


def residual_vector(problem: FitProblem, x: Tensor, tables=None) -> Tensor:
    """The residuals r of every element, so that ``problem.objective(x) = (|r|^2 / 2 + sum log s) / n_elements``
    for a squared rho (0 for elements the loss leaves out), shape (M,).

    Mirrors :meth:`skyfit.fit.losses.Loss.elementwise` (masks, censoring, ``noise_scale`` s).
    ``tables``: multiple-scattering tables to use (None: the problem's own, frozen or rebuilt).
    """
    frozen = problem.frozen_tables
    if tables is not None and frozen is None:
        problem.frozen_tables = tables
    try:
        problem.n_evaluations += 1
        preds = problem.predict(x)
    finally:
        problem.frozen_tables = frozen
    phys = problem.param.to_physical(x)
    loss, out = problem.loss, []
    for i, (p, o) in enumerate(zip(preds, problem.observations)):
        model, observed = torch.broadcast_tensors(problem.censor(p, i), o.values[o.mask].to(p.dtype))
        sigma = torch.broadcast_to(o.sigma[o.mask].to(p.dtype), model.shape)
        use = (sigma > 0) & torch.isfinite(sigma) & torch.isfinite(observed)
        if loss.residual in ("log", "relative"):
            use = use & (observed > 0)
        one = torch.ones_like(model)
        m, ob, sg = torch.where(use, model, one), torch.where(use, observed, one), torch.where(use, sigma, one)
        if loss.residual == "log":
            m = torch.where(m > 0, m, one)
        r = loss.residuals(m, ob, sg) / problem.param.nuisance(phys, i)["noise_scale"]
        out.append(torch.where(use, r, torch.zeros_like(r)).reshape(-1))
    return torch.cat(out)


def _atmosphere_columns(problem: FitProblem) -> list[bool]:
    """Per entry of x: True when it changes the atmosphere (and so the multiple-scattering tables)."""
    return [not PARAMETERS[n.split("[")[0]].nuisance for n in problem.param.names]


def _tables_at(problem: FitProblem, x: Tensor):
    """The multiple-scattering tables at x (None: single scattering, or the caller froze them)."""
    if problem.frozen_tables is not None or problem.model.orders == 1:
        return None
    return problem.model.tables(problem.param.atmosphere(problem.param.to_physical(x)))


def _evaluate(problem: FitProblem, x: Tensor, trial: bool = False):
    """(residuals, tables) at x, or (None, None) where the model refuses x or returns non-finite values.

    ``trial``: x is a trial step from a point that evaluated; a FitError there (a sigmoid rounded onto a
    parameter's bound, e.g. mie_g2 = -1 exactly, which the atmosphere refuses) rejects the step instead of
    ending the fit."""
    try:
        tables = _tables_at(problem, x)
        r = residual_vector(problem, x, tables)
    except FitError:
        if trial:
            return None, None
        raise
    except ValueError:
        return None, None
    return (r, tables) if bool(torch.isfinite(r).all()) else (None, None)


def _jacobian(problem: FitProblem, x: Tensor, r: Tensor, tables, atmospheric: list[bool]) -> Tensor:
    """Forward-difference dr/dx, shape (M, P); steps sqrt(eps) max(1, |x_j|) (one backward step where
    the forward point is refused). Instrument columns reuse ``tables``, the tables at x."""
    h0 = torch.finfo(x.dtype).eps ** 0.5
    cols = []
    for j in range(x.numel()):
        h = h0 * max(1.0, abs(float(x[j])))
        col = None
        for sgn in (1.0, -1.0):
            xj = x.clone()
            xj[j] = xj[j] + sgn * h
            step = float(xj[j] - x[j])  # the step actually taken (rounding of x + h)
            try:
                rj = residual_vector(problem, xj, tables if not atmospheric[j] else _tables_at(problem, xj))
            except FitError:
                raise
            except ValueError:
                continue
            if bool(torch.isfinite(rj).all()):
                col = (rj - r) / step
                break
        if col is None:
            raise ValueError(f"the model refuses both sides of {problem.param.names[j]} = {float(x[j]):.6g} (+-{h:.2g})")
        cols.append(col)
    return torch.stack(cols, 1)


def _secant_update(S: Tensor, s: Tensor, y: Tensor, y_sharp: Tensor) -> Tensor:
    """NL2SOL's update of S ~ sum r_i Hess(r_i) (Dennis, Gay & Welsch 1981, eqs. 4-5): S+ s = y# with
    y# = (J+ - J)^T r+, y = J+^T r+ - J^T r, after sizing S by min(1, |s^T y#| / |s^T S s|)."""
    ys = float(y @ s)
    if not ys > 0:
        return S
    sss = float(s @ (S @ s))
    if sss != 0.0:
        S = S * min(1.0, abs(float(s @ y_sharp)) / abs(sss))
    w = y_sharp - S @ s
    return S + (torch.outer(w, y) + torch.outer(y, w)) / ys - float(w @ s) * torch.outer(y, y) / (ys * ys)


LM_MAX_DAMPING = 1e16
"""Largest Marquardt lambda tried before a start gives up ("no decrease")."""
LM_MAX_STEP = 1.0
"""Largest change of any unconstrained value in one LM step (a factor e for log parameters, 10 deg for the
azimuth offset: :mod:`skyfit.fit.parameters` puts x on a scale of order one). Without it, a parameter whose
Jacobian column is small (a sigmoid near its end) takes a step that lands it on the plateau, where it stays:
a synthetic ground albedo went from 0.15 to 1.0 in one step (tests/test_fit_recovery_ms.py, sun 75 deg)."""


def _start_point(problem: FitProblem, x0: Tensor, opt: FitOptions) -> tuple[float, list[float], Tensor, Tensor]:
    """(clock, loss history, x, x at the start) of one start: x0 with the exposure profiled when asked."""
    t0 = time.perf_counter()
    x = x0.detach().clone()
    if opt.profile_exposure:
        x = problem.profile_exposure(x)
    return t0, [], x, x.clone()


def _run_start_lm(problem: FitProblem, x0: Tensor, opt: FitOptions, bar, label: str) -> dict:
    t0, history, x, x_start = _start_point(problem, x0, opt)
    n_el = max(problem.n_elements, 1)
    atmospheric = _atmosphere_columns(problem)
    evals = 0

    def show(v: float) -> None:
        history.append(v)
        if bar is not None:
            bar.update(1)
            bar.set_postfix_str(f"{label} loss {v:.6g}")

    with torch.no_grad():
        r, tables = _evaluate(problem, x)
        evals += 1
        if r is None:
            raise ValueError(f"the model refuses the start x = {x.tolist()}")
        f = 0.5 * float(r @ r)  # sum of squares / 2; the loss is f / n_el (+ a constant log s)
        show(f / n_el)
        lam, nu = 1e-3, 2.0
        S = None
        prev = None  # (step, J, g) of the last accepted step
        reason, ok, n_iter, rel_a, rel_p, gmax = "max iterations", False, 0, math.nan, math.nan, math.nan
        while n_iter < opt.max_iter:
            J = _jacobian(problem, x, r, tables, atmospheric)
            evals += J.shape[1]
            g = J.T @ r
            A = J.T @ J
            if prev is not None:
                s_prev, J_prev, g_prev = prev
                S = _secant_update(torch.zeros_like(A) if S is None else S, s_prev, g - g_prev, (J - J_prev).T @ r)
            gmax = float(g.abs().max()) / n_el
            if gmax <= opt.grad_tol:
                reason, ok = "gradient norm", True
                break
            n_iter += 1
            # Marquardt's scaling (Moré's monotone max(d_prev, diag) cost the Kider fits 3 more iterations)
            d = torch.diagonal(A).clone()
            d = torch.clamp_min(d, 1e-12 * float(d.max()) if float(d.max()) > 0 else 1.0)
            first_pred = None
            while True:
                H = A if S is None else A + S
                M = H + lam * torch.diag(d)
                if S is not None and int(torch.linalg.cholesky_ex(M).info) != 0:
                    H, M = A, A + lam * torch.diag(d)  # the augmented model is not convex here: Gauss-Newton
                step = -torch.linalg.solve(M, g)
                big = float(step.abs().max())
                if big > LM_MAX_STEP:  # a shorter step along the same direction (still a descent direction)
                    step = step * (LM_MAX_STEP / big)
                pred = -(float(g @ step) + 0.5 * float(step @ (H @ step)))
                first_pred = pred if first_pred is None else first_pred
                r_new, t_new = _evaluate(problem, x + step, trial=True)
                evals += 1
                f_new = 0.5 * float(r_new @ r_new) if r_new is not None else math.inf
                rho = (f - f_new) / pred if pred > 0 else -1.0
                if rho > 1e-4:
                    break
                lam, nu = lam * nu, nu * 2.0
                if lam > LM_MAX_DAMPING:
                    break
            if lam > LM_MAX_DAMPING:  # no step decreases the loss: converged if the model predicted none either
                ok = f > 0 and first_pred <= opt.rel_tol * f
                reason = "relative loss change" if ok else "no decrease"
                break
            prev = (step, J, g)
            rel_a, rel_p = (f - f_new) / f if f > 0 else 0.0, pred / f if f > 0 else 0.0
            x, r, tables, f = x + step, r_new, t_new, f_new
            lam, nu = lam * max(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3), 2.0
            show(f / n_el)
            if rel_a <= opt.rel_tol and rel_p <= opt.rel_tol:
                reason, ok = "relative loss change", True
                break
    x_end = x.detach().clone()
    f_end, g_end = _value_and_grad(problem, x_end)  # the problem's own loss and an exact gradient at the end
    evals += 1
    bad_names = _nonfinite_names(problem, x_end, g_end)
    if not math.isfinite(f_end) or bad_names:
        reason, ok, f_end = "diverged: non-finite " + (", ".join(bad_names) if bad_names else "loss"), False, math.nan
    return {
        "x": x_end, "x_start": x_start, "loss": f_end, "history": history,
        "convergence": {
            "converged": ok, "reason": reason, "iterations": n_iter, "adam_steps": 0, "method": "lm",
            "evaluations": evals, "grad_norm": float(g_end.abs().max()), "rel_change": rel_a,
            "predicted_change": rel_p, "damping": lam, "seconds": time.perf_counter() - t0, "warnings": [],
        },
    }


def _run_start(problem: FitProblem, x0: Tensor, opt: FitOptions, bar, label: str) -> dict:
    t0, history, x, x_start = _start_point(problem, x0, opt)

    def show(v: float) -> None:
        history.append(v)
        if bar is not None:
            bar.update(1)
            bar.set_postfix_str(f"{label} loss {v:.6g}")

    # Adam warm start
    if opt.adam_steps:
        p = x.clone().requires_grad_(True)
        adam = torch.optim.Adam([p], lr=opt.adam_lr)
        best = (math.inf, x.clone())
        for _ in range(opt.adam_steps):
            adam.zero_grad()
            try:
                loss = problem.objective(p)
            except ValueError:  # a step outside the renderer's domain: keep the best point so far
                break
            if not torch.isfinite(loss):
                break
            loss.backward()
            v = float(loss.detach())
            show(v)
            if v < best[0]:
                best = (v, p.detach().clone())
            adam.step()
        x = best[1]

    # L-BFGS
    p = x.clone().requires_grad_(True)
    f0, _ = _value_and_grad(problem, x)
    show(f0)
    lbfgs = torch.optim.LBFGS(
        [p], lr=1.0, max_iter=opt.max_iter, max_eval=int(opt.max_iter * 2.5), tolerance_grad=opt.grad_tol,
        tolerance_change=opt.rel_tol * max(abs(f0), 1e-300), history_size=opt.history_size, line_search_fn="strong_wolfe",
    )
    bad: list[str] = []

    def closure():
        lbfgs.zero_grad()
        try:
            loss = problem.objective(p)
        except FitError:
            raise
        except ValueError as e:  # the integrator refuses the point (e.g. outside its regime)
            bad.append(f"{e} at x = {p.detach().tolist()}")
            return torch.tensor(1e30, dtype=p.dtype, device=p.device)
        if not torch.isfinite(loss):
            bad.append(f"non-finite loss at evaluation {len(history) + 1}, x = {p.detach().tolist()}")
            # a large finite value makes the line search step back instead of failing
            return torch.full_like(loss, 1e30).requires_grad_(True) * 1.0
        loss.backward()
        names = _nonfinite_names(problem, p.grad)
        if names:
            bad.append(f"non-finite gradient w.r.t. {', '.join(names)} at evaluation {len(history) + 1}")
            p.grad.zero_()
            return torch.full_like(loss, 1e30)
        show(float(loss.detach()))
        return loss

    lbfgs.step(closure)
    state = lbfgs.state[lbfgs._params[0]]
    x_end = p.detach().clone()
    f_end, g_end = _value_and_grad(problem, x_end)
    gmax = float(g_end.abs().max())
    prev = state.get("prev_loss")
    rel = abs(f_end - float(prev)) / max(abs(f_end), 1e-300) if prev is not None else math.nan
    n_iter = int(state.get("n_iter", 0))
    bad_names = _nonfinite_names(problem, x_end, g_end)
    if not math.isfinite(f_end) or bad_names:
        reason = "diverged: non-finite " + (", ".join(bad_names) if bad_names else "loss")
        reason += f" after {len(history)} evaluations" + (f" ({bad[0]})" if bad else "")
        ok = False
        f_end = math.nan
    elif gmax <= opt.grad_tol:
        reason, ok = "gradient norm", True
    elif n_iter >= opt.max_iter:
        reason, ok = "max iterations", False
    elif int(state.get("func_evals", 0)) >= int(opt.max_iter * 2.5):
        reason, ok = "max evaluations", False
    else:
        reason, ok = "relative loss change", True
    return {
        "x": x_end, "x_start": x_start, "loss": f_end, "history": history,
        "convergence": {
            "converged": ok, "reason": reason, "iterations": n_iter, "adam_steps": opt.adam_steps, "method": "lbfgs",
            "evaluations": len(history), "grad_norm": gmax, "rel_change": rel, "seconds": time.perf_counter() - t0,
            "warnings": bad[:3],
        },
    }


# -- a known curvature -----------------------------------------------------------------------
CURVED_TOL = 0.005
""":func:`curved` has converged when the gradient, whitened by the given curvature, is under this (the Newton step's
length in the fit's noise sigmas, Mahalanobis): a twentieth of the lagged refits' own tolerance between refits
(skyfit.fit.budget.refit_shift, 0.1). [1]"""

CURVED_ITERATIONS = 30
"""BFGS iterations :func:`curved` may take before it gives up (the caller falls back to L-BFGS). [1]"""

CURVED_PRECISION_TOL = 0.05
"""A photo's lagged fits (:func:`skyfit.fit.photo.lagged_fit`) accept a :func:`curved` run that scipy stops for
precision loss (its line search finds no decrease the float64 objective can resolve) where the whitened gradient, the
Newton step still to go in noise sigmas, is under this: half the lagged refits' tolerance between refits (0.1). Seed-0
synthetic case 16's fit carried on from its race stopped so at 0.009 with the loss L-BFGS then reached from the same
start in 76 more evaluations (5 s), to the printed digit (docs/photos.md, "A line search at the loss's precision"). [1]"""


def curved(problem: FitProblem, x0: Tensor, cov_x: Tensor, tol: float = CURVED_TOL,
           iterations: int = CURVED_ITERATIONS, precision_tol: float | None = None) -> OptimiseResult | None:
    """Minimise ``problem``'s objective from x0 where its curvature is already known: a problem that changed little
    since its Hessian was taken (a lagged fit's next refresh; a refit with a factor near 1 held). scipy's BFGS
    (Nocedal & Wright 2006, Numerical Optimization, alg. 6.1, Wolfe line search) in the coordinates z that whiten the
    given inverse Hessian, x = x0 + L z with L L^T = cov_x, where the Hessian of n_elements x the objective starts as
    the identity: its first step is the Newton step, and BFGS corrects the curvature as the problem moved since. A step
    costs about one gradient, where L-BFGS from no curvature spends tens of them rebuilding what the matrix holds.

    Args:
        problem: the objective (mean loss per element); x0: the start (P,).
        cov_x: the inverse Hessian of n_elements x the objective near x0, (P, P), positive definite
            (:func:`skyfit.fit.laplace.hessian_nll`).
        precision_tol: where given, a run stopped for precision loss (the line search cannot lower the objective
            further in float64) stands when its whitened gradient is under this (:data:`CURVED_PRECISION_TOL`).

    Returns:
        :class:`OptimiseResult` (convergence ``method`` "bfgs (known curvature)") where the whitened gradient (the
        Newton step in noise sigmas) is under ``tol`` (or ``precision_tol`` at a precision-loss stop); None where BFGS
        does not get there in ``iterations``, its line search fails otherwise, or the objective leaves its domain.
    """
    import numpy as np
    import scipy.optimize

    t0 = time.perf_counter()
    n = max(problem.n_elements, 1)
    L, info = torch.linalg.cholesky_ex(cov_x.to(device=x0.device, dtype=torch.float64))
    if int(info) != 0:
        return None
    base = x0.detach().to(torch.float64)
    history: list[float] = []
    failed: list[str] = []

    def to_x(z) -> Tensor:
        return (base + L @ torch.as_tensor(z, dtype=torch.float64, device=base.device)).to(x0.dtype)

    def fun(z):
        try:
            f, g = _value_and_grad(problem, to_x(z))
        except ValueError as e:  # outside the renderer's domain
            failed.append(str(e))
            return math.inf, np.zeros_like(z)
        history.append(f)
        return f * n, (L.T @ g.to(torch.float64)).cpu().numpy() * n

    with np.errstate(all="ignore"):
        out = scipy.optimize.minimize(fun, np.zeros(x0.numel()), jac=True, method="BFGS",
                                      options={"gtol": tol, "norm": 2, "maxiter": iterations})
    # scipy flags a run that reaches gtol on its last allowed iteration as out of iterations (status 1): its
    # whitened gradient is under tol all the same, and it stands (held-out synthetic case 16: |g| 0.0042 after 30)
    gnorm = float(np.linalg.norm(out.jac))  # the whitened gradient where scipy stopped
    reached = out.success or (out.status == 1 and gnorm <= tol)
    # status 2: "desired error not necessarily achieved due to precision loss", at the loss's resolution
    at_precision = precision_tol is not None and out.status == 2 and gnorm <= precision_tol
    reached = reached or at_precision
    if not reached or failed or not math.isfinite(float(out.fun)):
        return None
    x = to_x(out.x).detach()
    f = float(out.fun) / n
    reason = (f"precision loss with the whitened gradient {gnorm:.2g} under {precision_tol:g}"
              if at_precision and not out.success else f"whitened gradient under {tol:g}")
    conv = {"converged": True, "reason": reason, "iterations": int(out.nit), "adam_steps": 0,
            "method": "bfgs (known curvature)", "evaluations": len(history), "grad_norm": math.nan, "rel_change": math.nan,
            "seconds": time.perf_counter() - t0, "warnings": []}
    conv.update({"start": 0, "n_starts": 1, "seconds_total": conv["seconds"], "evaluations_total": len(history)})
    p = problem.param
    return OptimiseResult(x=x, loss=f, parameters=p.physical_dict(x), free=list(p.free), convergence=conv,
                          starts=[{"initial": p.free_dict(x0), "final": p.free_dict(x), "loss": f, "convergence": conv}],
                          history=history)


def fit(problem: FitProblem, options: FitOptions | None = None, x0: Tensor | None = None) -> OptimiseResult:
    """Minimise ``problem.objective`` over the free parameters (module docstring).

    Args:
        problem: the objective.
        options: optimiser settings (defaults :class:`FitOptions`).
        x0: first start (default: the parameterisation's current values).

    Returns:
        :class:`OptimiseResult` of the best start.
    """
    opt = options or FitOptions()
    param = problem.param
    if param.size == 0:
        raise FitError("no free parameters: give at least one (e.g. --free mie_beta_550,mie_g)")
    dtype, device = param.base.dtype, param.base.device
    gen = torch.Generator().manual_seed(opt.seed)
    starts = param.spread_starts(opt.starts, gen, dtype, device)
    if x0 is not None:
        starts[0] = x0.to(dtype=dtype, device=device)
    method = resolved_method(problem, opt)
    run_start = _run_start_lm if method == "lm" else _run_start
    bar = None
    if opt.progress:
        from tqdm import tqdm

        bar = tqdm(total=len(starts) * (opt.adam_steps + opt.max_iter), desc="fit", unit="eval", leave=False)
    t0 = time.perf_counter()
    runs = []
    try:
        for k, xs in enumerate(starts):
            try:
                runs.append(run_start(problem, xs, opt, bar, f"start {k + 1}/{len(starts)}"))
            except FitError:
                raise
            except (ValueError, RuntimeError) as e:  # a start that leaves the model's domain
                runs.append({"x": xs, "x_start": xs, "loss": math.inf, "history": [],
                             "convergence": {"converged": False, "reason": f"failed: {e}", "iterations": 0, "method": method,
                                             "evaluations": 0, "grad_norm": math.nan, "rel_change": math.nan,
                                             "seconds": 0.0, "warnings": []}})
    finally:
        if bar is not None:
            bar.close()
    best = min(range(len(runs)), key=lambda k: runs[k]["loss"] if math.isfinite(runs[k]["loss"]) else math.inf)
    if not math.isfinite(runs[best]["loss"]):
        what = runs[0]["convergence"]["reason"]
        raise FitError(f"the fit {what}" if what.startswith("diverged") else f"every start failed; first: {what}")
    win = runs[best]
    conv = dict(win["convergence"])
    conv.update({"start": best, "n_starts": len(runs), "seconds_total": time.perf_counter() - t0,
                 "evaluations_total": sum(r["convergence"]["evaluations"] for r in runs)})
    return OptimiseResult(
        x=win["x"], loss=win["loss"], parameters=param.physical_dict(win["x"]), free=list(param.free), convergence=conv,
        starts=[{"initial": param.free_dict(r["x_start"]), "final": param.free_dict(r["x"]), "loss": r["loss"],
                 "convergence": r["convergence"]} for r in runs],
        history=win["history"],
    )
