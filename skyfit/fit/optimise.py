"""Gradient fit: Adam warm start, then L-BFGS with a strong Wolfe line search, from several starts.

Each start (the given values, then points spread over each parameter's typical
span, :meth:`~skyfit.fit.parameters.Parameterisation.spread_starts`) has its free
exposure set in closed form (:meth:`~skyfit.fit.model.FitProblem.profile_exposure`),
takes ``adam_steps`` Adam steps (robust far from the optimum, where L-BFGS's
curvature pairs mislead), then L-BFGS (``torch.optim.LBFGS``, strong Wolfe line
search; Nocedal & Wright 2006, Alg. 7.5 and 3.5) until

* the gradient's largest component is below ``grad_tol``  ("gradient norm"),
* the loss changes by less than ``rel_tol`` x |loss| between iterations, or the
  step is that small ("relative loss change"),
* or ``max_iter`` iterations pass ("max iterations").

The start with the lowest final loss wins; every start's outcome is reported.
Work is in the problem's dtype (float64 by default, so that the line search and
the convergence tests see differences of 1e-10).
"""
from __future__ import annotations

import dataclasses
import math
import time

import torch
from torch import Tensor

from .model import FitProblem
from .parameters import FitError


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

    def __post_init__(self):
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


def _run_start(problem: FitProblem, x0: Tensor, opt: FitOptions, bar, label: str) -> dict:
    t0 = time.perf_counter()
    history: list[float] = []
    x = x0.detach().clone()
    if opt.profile_exposure:
        x = problem.profile_exposure(x)
    x_start = x.clone()

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
            "converged": ok, "reason": reason, "iterations": n_iter, "adam_steps": opt.adam_steps,
            "evaluations": len(history), "grad_norm": gmax, "rel_change": rel, "seconds": time.perf_counter() - t0,
            "warnings": bad[:3],
        },
    }


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
    bar = None
    if opt.progress:
        from tqdm import tqdm

        bar = tqdm(total=len(starts) * (opt.adam_steps + opt.max_iter), desc="fit", unit="eval", leave=False)
    t0 = time.perf_counter()
    runs = []
    try:
        for k, xs in enumerate(starts):
            try:
                runs.append(_run_start(problem, xs, opt, bar, f"start {k + 1}/{len(starts)}"))
            except FitError:
                raise
            except (ValueError, RuntimeError) as e:  # a start that leaves the model's domain
                runs.append({"x": xs, "x_start": xs, "loss": math.inf, "history": [],
                             "convergence": {"converged": False, "reason": f"failed: {e}", "iterations": 0,
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
