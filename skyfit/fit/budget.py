"""The error budget of a fit: noise, numerical model error and model discrepancy in one sigma.

The Laplace sigma (:mod:`skyfit.fit.laplace`) counts only the data's noise. A fit's renderer
is coarser than the sky it is fitted to, and the parameters absorb the difference; on the
demo sky that bias was 5-34 noise sigmas. This module adds two terms to the covariance of
the unconstrained vector x at the optimum x*, so that the reported sigma is the error bar:

1. **Numerical** (what skyfit can compute itself). The model of the fit's setting m_fit and
   of a converged setting m_ref (:class:`ReferenceModel`, the trade study's reference:
   Gauss-Legendre optical depth with 32 nodes, a 128-node Gauss view integral and, for
   orders >= 2, Bruneton & Neyret 2008 tables with 6 orders, their sun axis spanning the fit's suns:
   :data:`REFERENCE_SUN_WINDOW`) differ at x* by
   delta = m_ref(x*) - m_fit(x*). Refitting with m_fit + delta moves x by one Newton step

       dx = -H^-1 g,   g = d/dx [ -log L(m_fit(x) + delta) ] at x*

   (H the Laplace Hessian; for the Gaussian likelihood g = -J^T W delta and this is the
   Gauss-Newton shift (J^T W J)^-1 J^T W delta). Where the model is not linear along dx
   (:func:`nonlinearity` > :data:`NONLINEAR`) up to ``refits`` lagged refits replace the step
   (:func:`refit_shift`), and what an unconverged iteration has left adds to the error. The
   fitted value is left as it is; dx is reported (``numerical_shift``) and treated as an
   error: cov += dx dx^T.
2. **Discrepancy** (what no setting of this model family resolves, e.g. a two-term phase
   function fitted with one term). Two models (``discrepancy``) and their bound, each a Gauss-Newton covariance
   of the residuals r left after the numerical correction (o - m_fit(x* + dx) - delta) minus the
   noise's (J^T W J)^-1, added to the noise's H^-1:

   * ``floor``: a white relative error floor f added in quadrature to each element's sigma,
     sigma'^2 = sigma^2 + (f m)^2, with f chosen so that chi^2 of r equals its degrees of freedom,
     n_elements - P (Birge 1932's ratio, spread as a relative floor); f = 0 when chi^2 <= dof.
     Its share: (J^T W' J)^-1 - (J^T W J)^-1 (positive semi-definite; the full Hessian with
     sigma' need not be, x* not being the optimum of the inflated problem).
   * ``sandwich``: the cluster-robust sandwich (Liang & Zeger 1986, Biometrika 73, 13; White 1980,
     Econometrica 48, 817 for the heteroscedastic form) over sky regions that share a systematic
     model error (:func:`sky_clusters`: equal-count bins in scattering angle x view zenith, all
     channels of a sample in one cluster),

         V = A^-1 (sum_c s_c s_c^T) A^-1 G / (G - 1),   A = J^T W J,   s_c = sum_{e in c} J_e^T W_e r_e

     with G clusters (CR1), by default in its jackknife form (CR3, :func:`sandwich_covariance`:
     the scores scaled by A (A - A_c)^-1, for the share of a cluster's error the fit absorbed);
     its share is the positive part of V - A^-1. A model error that is smooth over the sky (a
     phase function's, following the scattering angle) makes the scores of a cluster add up where
     the white floor's cancel. What the parameters absorb as a fixed offset (a one-term fit of a
     two-term phase) neither model sees: the residuals do not show it.
   * ``larger``: a minimal upper bound of the two totals A^-1 + D_floor and A^-1 + D_sandwich (at
     least each along every direction, equal to the larger where one contains the other;
     :func:`loewner_upper`), less A^-1.

3. **Phase** (optional, ``fit.sigma_phase``; :func:`phase_expansion`): a one-term Henyey-Greenstein fit refitted
   with the two-term phase from x + dx. What a one-term fit absorbs of a backward lobe shows in no residual; this
   term asks the data for the lobe instead. Its spread S (:func:`expansion_spread`: the two-term refit's covariance
   mapped onto the one-term parameters, g standing for the asymmetry parameter; where the refit found no lobe, the
   profile over the backward lobes the data cannot rule out) bounds the total from below (:func:`loewner_upper`),
   and the shift e of every parameter is treated as an error, cov += e e^T (docs/uncertainty.md, "The phase term").

Total: cov_x = H^-1 + D + dx dx^T (+ S' + e e^T), D the chosen model's share, S' what the spread adds.
``sigma`` of the result is this total; ``budget`` holds the parts (``sigma_noise``, ``sigma_numerical``,
``sigma_discrepancy`` of the chosen model, ``sigma_discrepancy_floor`` and ``sigma_discrepancy_sandwich`` of each where computed), the
floor, the clusters (``discrepancy``), chi^2/dof and the shift. docs/uncertainty.md, "Coverage under
model error", measures each model on skies rendered by a richer model: ``floor`` stays the default,
the sandwich having changed 3 of 280 interval outcomes there (the numerical term dominates).
"""
from __future__ import annotations

import copy
import dataclasses
import math
import time

import torch
from torch import Tensor

from ..render.sky import render_vectors
from ..scattering.bruneton_tables import TableSizes, sun_window
from ..scattering.multiple import ACCURATE_QUADRATURE, precompute, sky_radiance
from ..scattering.single import ray_parameters
from ..transmittance import make_integrator
from .laplace import (bound_slots, covariance_summary, derived_functions, display_names, laplace_summary,
                      physical_slot_values, transform_jacobian)
from .model import FitProblem, SkyModel, sun_zenith_span
from .optimise import FitOptions, curved, fit
from .parameters import (MIE_G2_DEFAULT, MIE_HG_WEIGHT_DEFAULT, NUISANCE, PARAMETERS, TWO_TERM_HG, FitError, Parameterisation,
                         inside_bounds)

SIGMA_MODES = ("total", "noise")
"""``fit.sigma``: ``total`` (noise + numerical + discrepancy, the default) or ``noise`` (the Laplace sigma of the noise alone)."""
DISCREPANCY_MODELS = ("floor", "sandwich", "larger")
"""``fit.sigma_discrepancy``: the discrepancy term's model (module docstring, term 2)."""
DISCREPANCY_DEFAULT = "floor"
"""The default discrepancy model (docs/uncertainty.md, "Coverage under model error", says why)."""
CLUSTERS = 12
"""Target number of sandwich clusters per observation, 6 scattering-angle x 2 view-zenith bins
(:func:`sky_clusters`). The cluster-robust covariance has rank <= G - 1 and a relative spread of its
variances of about sqrt(2 / (G - 1)) (0.43 at 12), so G must exceed the number of free parameters
(Cameron & Miller 2015, J. Human Resources 50, 317: unreliable with few clusters); fewer, larger
clusters hold more of a smooth error's correlation. Measured (docs/uncertainty.md, "Coverage under
model error", and tests/test_sigma_sandwich.py's scattering-angle error): 12 covers g better than 24
(RMS z on the two-term skies 4.6 against 6.5, fit failures left out) with 6 free parameters on ~60 sky samples (5 a
cluster). Raise it (``fit.sigma_clusters``) for fits with more free parameters; the budget notes when
G - 1 < P."""
MIN_PER_CLUSTER = 3
"""Fewest used samples per sandwich cluster: an observation with N samples gets min(G, N // 3) clusters,
one per sample when that is < 2 (spectra at a few directions). [1]"""

REFERENCE_LIGHT_SAMPLES = 32
"""Gauss-Legendre nodes of the reference's optical depth (skyfit.tools.trade's reference_light)."""
REFERENCE_VIEW_SAMPLES = 128
"""Gauss-Legendre nodes of the reference's view integral (the trade study's reference_view)."""
REFERENCE_TABLES = (16, 64, 16, 8)
"""Bruneton scattering-table sizes (R, MU, MU_S, NU) of the reference's orders >= 2 (the trade study's)."""
REFERENCE_ORDERS = 6
"""Scattering orders of the reference's Bruneton tables (the trade study's reference_orders)."""
REFERENCE_QUADRATURE = ACCURATE_QUADRATURE
"""The precomputation rules of the reference's Bruneton tables: Gauss-Legendre nodes along the view rays and the two
density bands nearest the zenith split (:class:`~skyfit.scattering.multiple.Quadrature`; a photo fit's, docs/photos.md,
"The view ray's rule", "The density directions' pole"). With 2017's equal steps the reference was no reference on a
hazy sky: against these rules with 32 x 64 density directions (equidistant 10 x 10 fisheye, 420-680 nm,
coverage_model_error.py's truths), its radiance was +21 % at the median pixel and up to 3.9x at AOD 0.31, +4 % (up
to 1.6x) at AOD 0.15, +0.3 to +0.9 % (up to 1.13x) at AOD 0.015-0.08; these rules are within 1 % of 32 x 64
everywhere there, at 1.1-1.3x 2017's build (docs/uncertainty.md, "The reference's view-ray rule"; docs/luts.md)."""
REFERENCE_SUN_WINDOW = True
"""The reference's Bruneton tables span the fit's suns (their zenith angles +- the window's margin, texels at most
:data:`~skyfit.scattering.bruneton_tables.SUN_SPACING_DEG` apart: :func:`~skyfit.scattering.bruneton_tables.sun_window`)
instead of 2017's whole mu_s axis of ``REFERENCE_TABLES[2]`` texels, which gives a high sun about one texel: on
``earth_hazy`` with the sun at 30 deg the whole axis put the total radiance 16 % high at the zenith and 28 % at 60 deg
elevation opposite the sun, where the window's 6 texels are within 0.3 % of tables of twice the texels in every
dimension, and build 4.5x faster (docs/uncertainty.md, "A reference for the fit's suns"). False (``fit.sigma_reference_axis:
whole``): the whole axis, as every budget before session 18 was measured. Not where a ``sun_zenith_offset`` is fitted
(the sun moves) or an observer is in space (:func:`skyfit.fit.model.sun_zenith_span`)."""


@dataclasses.dataclass
class ReferenceModel(SkyModel):
    """A converged renderer: single scattering by a fine Gauss-Legendre quadrature, plus orders >= 2 from
    Bruneton tables (Bruneton & Neyret 2008) as the trade study's reference (``skyfit bench --study trade``):

        L = L_1(gauss light_samples, gauss view_samples) + [L_tables(all orders) - L_tables(order 1)]

    (the bracket: orders >= 2 and the ground's indirect light). ``orders`` 1 keeps single scattering.

    Attributes (besides :class:`SkyModel`'s, of which ``integrator``, ``view_samples`` and ``rule`` are set here, and
    ``ray_rule`` and ``density_directions`` default to :data:`REFERENCE_QUADRATURE`'s):
        reference_tables: scattering-table sizes (R, MU, MU_S, NU) of the orders >= 2.
        reference_orders: orders in those tables.
    """

    ray_rule: str = REFERENCE_QUADRATURE.ray_rule
    density_directions: tuple[int, ...] = REFERENCE_QUADRATURE.density_directions
    reference_tables: tuple[int, int, int, int] = REFERENCE_TABLES
    reference_orders: int = REFERENCE_ORDERS
    sun_window: bool = REFERENCE_SUN_WINDOW
    sun_zenith_deg: tuple[float, float] | None = None  # the suns the tables span (set by reference_problem)

    @classmethod
    def of(cls, model: SkyModel, light_samples: int = REFERENCE_LIGHT_SAMPLES, view_samples: int = REFERENCE_VIEW_SAMPLES,
           tables: tuple[int, int, int, int] = REFERENCE_TABLES, orders: int = REFERENCE_ORDERS,
           sun_window: bool = REFERENCE_SUN_WINDOW) -> "ReferenceModel":
        """The reference of a fit's model: same orders (1 or more) and ground, converged settings."""
        return cls(make_integrator("gauss", samples=light_samples), orders=model.orders, view_samples=view_samples,
                   rule="gauss", ground=model.ground, reference_tables=tuple(tables), reference_orders=orders,
                   sun_window=sun_window)

    def window(self) -> tuple[tuple[float, float] | None, int]:
        """``(mu_s_range, texels)`` of the tables: :data:`REFERENCE_SUN_WINDOW`'s window around :attr:`sun_zenith_deg`,
        or ``(None, REFERENCE_TABLES[2])`` (2017's whole axis) without one."""
        if not self.sun_window or self.sun_zenith_deg is None:
            return None, self.reference_tables[2]
        return sun_window(*self.sun_zenith_deg, self.reference_tables[2])

    def tables(self, atm):
        if self.orders == 1:
            return None
        t = self.reference_tables
        mu_s_range, texels = self.window()
        return precompute(atm, orders=self.reference_orders, progress=False, mu_s_range=mu_s_range,
                          quadrature=self.quadrature(),
                          sizes=TableSizes(scattering_r=t[0], scattering_mu=t[1], scattering_mu_s=texels, scattering_nu=t[3]))

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
            mu_s_range, texels = self.window()
            out.update(multiple="bruneton", table_sizes=list(self.reference_tables[:2]) + [texels, self.reference_tables[3]],
                       table_orders=self.reference_orders, ray_rule=self.ray_rule,
                       density_directions=list(self.density_directions),
                       mu_s_range=None if mu_s_range is None else [float(v) for v in mu_s_range])
        return out


def reference_problem(problem: FitProblem, reference: SkyModel | None = None) -> FitProblem:
    """``problem`` with its renderer replaced by ``reference`` (default :meth:`ReferenceModel.of` its model); a
    :class:`ReferenceModel` of multiple scattering gets the fit's suns (:data:`REFERENCE_SUN_WINDOW`)."""
    ref = copy.copy(problem)
    ref.model = ReferenceModel.of(problem.model) if reference is None else reference
    if isinstance(ref.model, ReferenceModel) and ref.model.orders > 1 and ref.model.sun_window and ref.model.sun_zenith_deg is None:
        ref.model = dataclasses.replace(ref.model, sun_zenith_deg=sun_zenith_span(problem))
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
    dx = -(cov_x.to(g) @ g)
    num = sum(float((d**2).sum()) for d in delta)
    rel = sum(float(((d / torch.where(f != 0, f, torch.ones_like(f))) ** 2).sum()) for d, f in zip(delta, m_fit))
    over = sum(float(((d / o.sigma[o.mask]) ** 2).sum()) for d, o in zip(delta, problem.observations))
    n = max(sum(d.numel() for d in delta), 1)
    return {"dx": dx.detach(), "delta": delta, "relative_rms": math.sqrt(rel / n), "rms_over_sigma": math.sqrt(over / n),
            "rms": math.sqrt(num / n)}


def shares_factor(problem: FitProblem, reference: FitProblem) -> bool:
    """Whether the reference keeps the fit's own frozen multiple-scattering factor: a photo's Bruneton orders, lagged
    on live single scattering, under a single-scattering reference (:func:`reference_problem`)."""
    return problem.frozen_factor is not None and reference.frozen_factor is not None


def reference_factor(problem: FitProblem, reference: FitProblem, x: Tensor, on_factor: bool | None = None) -> list[Tensor]:
    """Per observation, the spectra of the reference over the fit's at x, (N_i, W) [1]: the fit's renderer times it
    is the reference at x. ``on_factor`` False: the fit's frozen factor is left out of the fit's spectra, and the ratio
    is to replace it; True: both spectra carry it (a reference that keeps the fit's factor), and the ratio goes on top
    of it. Default: :func:`shares_factor`, as :func:`held_reference` holds it."""
    if on_factor is None:
        on_factor = shares_factor(problem, reference)
    with torch.no_grad():
        phys = problem.param.to_physical(x)
        saved = problem.frozen_factor
        if not on_factor:
            problem.frozen_factor = None
        try:
            s_fit = problem.spectra(phys)
        finally:
            problem.frozen_factor = saved
        s_ref = reference.spectra(phys)
    return [torch.where(f != 0, r / torch.where(f != 0, f, torch.ones_like(f)), torch.ones_like(f)) for r, f in zip(s_ref, s_fit)]


def held_reference(problem: FitProblem, reference: FitProblem, factor: list[Tensor]) -> FitProblem:
    """A copy of the fit's problem that renders the reference at the iterate ``factor`` was taken at
    (:func:`reference_factor`), ``factor`` held fixed: in place of the fit's frozen factor, or, where the reference
    keeps that factor (:func:`shares_factor`), on top of it, the factor still followed in the aerosol's optical depth,
    its g and the camera's geometry as the fit followed it. Held in their place, a hazy photo's factor (1.3-2) hid how
    the multiple scattering's share grows with the aerosol and the refits ran away from a model 0.2 % from the
    reference (synthetic held-out case 4: steps of 11, 14 and 17 noise sigma, an AOD tail of 0.12;
    docs/photos.md, "The race side by side")."""
    lagged = copy.copy(problem)
    if shares_factor(problem, reference):
        lagged.held_ratio = factor
    else:
        lagged.frozen_factor = factor
        lagged.frozen_slope = lagged.frozen_slope_g = None  # c_k held as it is (the fit's following is for its own factor)
    return lagged


def refit_shift(problem: FitProblem, x: Tensor, reference: FitProblem, x_start: Tensor, sigma_x: Tensor,
                iterations: int = 2, options: FitOptions | None = None, tol: float = 0.1,
                cov_x: Tensor | None = None) -> dict:
    """The fit with the reference model, by lagged refits of the fit's renderer (brute force, no linearisation).

    Iteration k holds the factor c_k = m_ref(x_k) / m_fit(x_k) (spectra, per sample and wavelength)
    fixed and refits m_fit(x) c_k from x_k (:func:`held_reference`; as skyfit.fit.photo's lagged
    fit); at the fixed point the gradient of the reference's likelihood is zero up to the change of
    c with x. Stops after ``iterations`` or when a step moves every parameter by less than ``tol``
    noise sigmas ``sigma_x`` (P,). With ``cov_x`` (the fit's inverse Hessian) each refit starts from that curvature
    (:func:`skyfit.fit.optimise.curved`): its problem is the fit's own with a factor near 1 held, so its Hessian is
    about the fit's, and L-BFGS from no curvature took 40-60 gradients a refit (synthetic held-out case 4: 154
    evaluations, 8.8 s of an 11.3 s report; docs/photos.md, "Fits that start from a known curvature"); L-BFGS
    (``options``) where that does not converge.

    Returns:
        ``x`` (the last iterate (P,)), ``factor`` (the last c_k), ``steps`` (max |step| / sigma_x of each),
        ``tail`` (P,): what the iteration has still to go when it stopped unconverged, the last step
        times r / (1 - r) with r the ratio of the last two steps (at most 0.9; a geometric series),
        zero when it converged, None after a single unconverged refit; ``solvers`` ("curved" or "lbfgs" per refit).
    """
    opt = options or FitOptions(starts=1, adam_steps=0, max_iter=100)
    xk, steps, factor, solvers = x_start.detach().to(x.dtype), [], None, []
    last = prev = None
    for _ in range(iterations):
        factor = reference_factor(problem, reference, xk)
        held = held_reference(problem, reference, factor)
        res = curved(held, xk, cov_x) if cov_x is not None else None
        solvers.append("lbfgs" if res is None else "curved")
        xn = (res or fit(held, opt, x0=xk)).x.detach()
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
    return {"x": xk, "factor": factor, "steps": steps, "tail": tail, "solvers": solvers}


POLISH_EDGE = 1e-6
""":func:`reference_polish` keeps a bounded parameter this far inside its range (relative to it). [1]"""

POLISH_START_EDGE = 0.75
"""A bounded parameter on its bound starts :func:`reference_polish` at this position of its range's natural
coordinate (log for ``loginterval``, linear for ``interval``), counted from the other end: off the bound, where the
data can pull it (H_M on its 20 km bound starts at 3.0 km, 10 m x 2000^0.75). [1]"""


def _natural(spec, v: float) -> float:
    return math.log(v) if spec.transform in ("log", "loginterval") else v


def _from_natural(spec, z: float, hi: float | None) -> float:
    v = math.exp(z) if spec.transform in ("log", "loginterval") else z
    if spec.transform in ("interval", "loginterval"):
        lo, top = spec.lo, spec.hi if hi is None else hi
        pad = POLISH_EDGE * (top - lo)
        v = min(max(v, lo + pad), top - pad)
    return v


def reference_polish(problem: FitProblem, reference: FitProblem, x_start: Tensor, steps: int) -> dict | None:
    """Levenberg-Marquardt on the reference's whitened residuals from ``x_start`` (the lagged refits' iterate).

    The lagged refits hold the factor m_ref / m_fit fixed between refits; where it changes fast with a parameter
    (the aerosol scale height on a fit whose renderer pushed it to its bound) they stop far from the reference's
    optimum (docs/uncertainty.md, "Where the misses are": on two one-term skies the reference's loss 3.7 and 10.7
    where they ended, 1.35 and 0.96 at the truth). Gauss-Newton on the reference itself reaches it in a few
    steps. The steps are taken in natural coordinates (log of ``log`` and ``loginterval`` parameters, the value of
    the others), where a parameter on its bound still has a slope (the fit's sigmoid coordinates have none); a
    bounded one on its bound starts at :data:`POLISH_START_EDGE`. The Jacobian is a forward difference (P + 1
    renders of the reference a step; the reference's autograd through its tables costs more). Squared losses only.

    Returns None where it does not apply (another loss), else ``x`` (P,), ``loss`` (the reference's mean half
    squared whitened residual there, and at ``x_start``: ``loss_start``), ``steps`` (accepted step sizes, max over
    parameters in natural units) and ``converged`` (the last step under 1e-4, or no step lowers the loss).
    """
    if problem.loss.rho != "squared":
        return None
    p = problem.param
    slots = [(n, k) for n in p.free for k in p._slots[n]]
    order = sorted(range(len(slots)), key=lambda i: slots[i][1])
    slots = [slots[i] for i in order]
    specs = [PARAMETERS[n] for n, _ in slots]
    his = [p._hi(n) for n, _ in slots]
    x0 = x_start.detach().to(torch.float64)
    with torch.no_grad():
        v0 = physical_slot_values(problem, x0)
    edge = bound_slots(problem, x0)
    z = []
    for (n, k), spec, hi, v in zip(slots, specs, his, v0.tolist()):
        if edge[k]:  # on a bound: no slope there for the data to pull on
            lo, top = _natural(spec, spec.lo), _natural(spec, spec.hi if hi is None else hi)
            z.append(lo + POLISH_START_EDGE * (top - lo) if float(x0[k]) > 0 else top - POLISH_START_EDGE * (top - lo))
            continue
        z.append(_natural(spec, v))
    z = torch.tensor(z, dtype=torch.float64)

    def to_x(zz: Tensor) -> Tensor:
        x = x0.clone()
        for i, ((n, k), spec, hi) in enumerate(zip(slots, specs, his)):
            x[k] = spec.inverse(_from_natural(spec, float(zz[i]), hi), hi)
        return x.to(x_start.dtype)

    def resid(zz: Tensor) -> Tensor:
        x = to_x(zz)
        with torch.no_grad():
            preds = reference.predict(x)
            phys = reference.param.to_physical(x)
        # the few-parameter LM runs on the CPU whatever the problem's device
        return torch.cat(whitened_residuals(reference, preds, phys)).to(dtype=torch.float64, device="cpu")

    r = resid(z)
    loss_start = 0.5 * float((r**2).mean())
    lam, taken, converged = 1e-3, [], False
    for _ in range(steps):
        J = torch.empty(r.numel(), z.numel(), dtype=torch.float64)
        for i in range(z.numel()):
            h = 1e-4 * max(1.0, abs(float(z[i])))
            dz = torch.zeros_like(z)
            dz[i] = h
            J[:, i] = (resid(z + dz) - r) / h
        A, g = J.T @ J, J.T @ r
        eye = torch.eye(z.numel(), dtype=torch.float64)
        moved = False
        while lam < 1e6:
            step = -torch.linalg.solve(A + lam * (torch.diag(torch.diag(A)) + 1e-9 * torch.trace(A) * eye), g)
            rn = resid(z + step)
            if float((rn**2).sum()) < float((r**2).sum()):
                z, r, lam, moved = z + step, rn, lam / 3.0, True
                taken.append(float(step.abs().max()))
                break
            lam *= 4.0
        # converged: no step lowers the loss (a minimum to the difference Jacobian's resolution), or the last was tiny
        converged = not moved or taken[-1] < 1e-4
        if converged:
            break
    return {"x": to_x(z), "loss": 0.5 * float((r**2).mean()), "loss_start": loss_start, "steps": taken,
            "converged": converged}


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


def whitened_residuals(problem: FitProblem, preds, phys: dict, floor: float = 0.0) -> list[Tensor]:
    """The loss's residuals of the model ``preds`` (list of (N_i, C_i)) over each observation's uncensored used
    elements, flattened, with sigma'^2 = sigma^2 + (floor m)^2; sigma is the data's times the ``noise_scale`` of
    ``phys`` (:meth:`Parameterisation.to_physical` at the fit)."""
    out = []
    for i, (m, o) in enumerate(zip(preds, problem.observations)):
        s = o.sigma[o.mask] * phys_noise_scale(problem, phys, i)
        sp = torch.sqrt(s**2 + (floor * m) ** 2) if floor else s
        r = problem.loss.residuals(m, o.values[o.mask], sp)
        out.append(r[_uncensored(problem, i, m)].reshape(-1))
    return out


def chi2_with_floor(problem: FitProblem, preds, floor: float, phys: dict) -> tuple[float, int]:
    """(sum of squared residuals, n) over the uncensored used elements of the model ``preds`` with the relative
    floor (:func:`whitened_residuals`)."""
    rs = whitened_residuals(problem, preds, phys, floor)
    return sum(float((r**2).sum()) for r in rs), sum(int(r.numel()) for r in rs)


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


def whitened_jacobian(problem: FitProblem, jac: list[Tensor], preds, floor: float, phys: dict) -> list[Tensor]:
    """Per observation, d r / dx of the whitened residual r with sigma'^2 = sigma^2 + (floor m)^2 (a linear or log
    residual), zero at censored elements, shape (N_i, C_i, P), float64. [1 / x units]"""
    out = []
    for i, (Jm, m, o) in enumerate(zip(jac, preds, problem.observations)):
        s = o.sigma[o.mask] * phys_noise_scale(problem, phys, i)
        sp = torch.sqrt(s**2 + (floor * m) ** 2)
        w = 1.0 / sp if problem.loss.residual == "linear" else o.values[o.mask] / (m.clamp_min(1e-300) * sp)
        keep = _uncensored(problem, i, m)
        out.append((Jm * (w * keep).unsqueeze(-1)).to(torch.float64))
    return out


def _pinv_sym(G: Tensor) -> Tensor:
    return torch.linalg.pinv(0.5 * (G + G.T), hermitian=True)


def gauss_newton_covariance(problem: FitProblem, jac: list[Tensor], preds, floor: float, phys: dict) -> Tensor:
    """(J_r^T J_r)^-1 of the whitened residuals r with sigma'^2 = sigma^2 + (floor m)^2 (uncensored used
    elements; a linear or log residual), shape (P, P). [x units^2]"""
    Jr = torch.cat([j.reshape(-1, j.shape[-1]) for j in whitened_jacobian(problem, jac, preds, floor, phys)])
    return _pinv_sym(Jr.T @ Jr)


def sky_clusters(problem: FitProblem, phys: dict, clusters: int = CLUSTERS, min_count: int = MIN_PER_CLUSTER) -> list[Tensor]:
    """Sky regions that share a systematic model error: a cluster label for every used sample of each observation.

    Per observation with N used samples, G = min(``clusters``, N // ``min_count``) clusters: the samples sorted by
    scattering angle (view direction against the sun, with the fitted sun offsets and camera tilts) are cut into
    n_theta equal-count bins, and each bin, sorted by view zenith, into n_zeta equal-count bins, with
    n_zeta = max(1, round(sqrt(G / 3))) and n_theta = G // n_zeta (12: 6 x 2, 24: 8 x 3; a phase-function
    error follows the scattering angle, an air-mass or profile error the zenith). When G < 2 (spectra at a few directions)
    each sample is its own cluster. All channels of a sample share its label; labels run on over the
    observations (0 .. total - 1), so no cluster spans two observations.

    Args:
        problem: the fit problem; phys: :meth:`Parameterisation.to_physical` at the fit.
        clusters: target number of clusters per observation, >= 2.
        min_count: fewest samples per cluster, >= 1.

    Returns:
        One int64 tensor of labels per observation, shape (N_i,) over its used samples.
    """
    if int(clusters) < 2 or int(min_count) < 1:
        raise FitError(f"sandwich clusters must be >= 2 and min_count >= 1, got {clusters!r} and {min_count!r}")
    out, offset = [], 0
    with torch.no_grad():
        for i, o in enumerate(problem.observations):
            d = problem.view_directions(phys, i)
            sun = problem.sun_vectors(phys, i)
            if sun.ndim == 2:
                sun = sun[o.mask]
            n = d.shape[0]
            labels = torch.empty(n, dtype=torch.int64, device=d.device)
            g = min(int(clusters), n // int(min_count))
            if g < 2:  # a few directions: one cluster each
                labels[:] = torch.arange(n, device=d.device)
                out.append(labels + offset)
                offset += n
                continue
            cos_theta = (d * sun).sum(-1).clamp(-1.0, 1.0)
            n_zeta = max(1, int(round(math.sqrt(g / 3.0))))
            n_theta = g // n_zeta
            k = 0
            for theta_bin in torch.tensor_split(torch.argsort(-cos_theta, stable=True), n_theta):  # scattering angle up
                for zeta_bin in torch.tensor_split(theta_bin[torch.argsort(-d[theta_bin, 2], stable=True)], n_zeta):
                    labels[zeta_bin] = k
                    k += 1
            out.append(labels + offset)
            offset += k
    return out


SANDWICH_FORMS = ("jackknife", "cr1")
"""The sandwich's small-sample forms (:func:`sandwich_covariance`); ``jackknife`` is the default."""


def sandwich_covariance(problem: FitProblem, jac: list[Tensor], preds, residual_preds, labels: list[Tensor],
                        phys: dict, form: str = "jackknife") -> tuple[Tensor, Tensor]:
    """The cluster-robust sandwich covariance of x and the Gauss-Newton A^-1 it wraps (module docstring, term 2).

    ``cr1``: V = A^-1 (sum_c s_c s_c^T) A^-1 G / (G - 1) (Liang & Zeger 1986 with the usual G / (G - 1)).
    The fit absorbs the part of a cluster's error that its parameters can mimic, so the residuals
    under-state it, the more the larger the cluster's share of the information A_c = J_c^T W J_c.
    ``jackknife`` (CR3; MacKinnon & White 1985, J. Econometrics 29, 305; Bell & McCaffrey 2002, Survey
    Methodology 28, 169) restores it: each score becomes A (A - A_c)^-1 s_c (the residuals times
    (I - H_cc)^-1, H the hat matrix, by Woodbury), so that

        V = (G - 1) / G  sum_c d_c d_c^T,   d_c = (A - A_c)^-1 s_c,

    d_c being the Gauss-Newton change of x when cluster c is left out: the jackknife over sky regions.
    (A - A_c)^-1 is a pseudo-inverse where leaving c out leaves a parameter undetermined.

    Args:
        problem: the fit problem; jac: :func:`prediction_jacobian` at the fit, list of (N_i, C_i, P).
        preds: the model at the fit (its weights for a log residual), list of (N_i, C_i) [data units].
        residual_preds: the model whose residuals o - m enter the scores (the numerically corrected one).
        labels: :func:`sky_clusters`, list of (N_i,).
        phys: the physical values at the fit (the noise scale).
        form: ``jackknife`` or ``cr1`` (:data:`SANDWICH_FORMS`).

    Returns:
        (V, A^-1), each (P, P), with s_c the sum of J_e^T W_e r_e over the uncensored elements of cluster c and
        G the number of clusters with used elements. [x units^2]
    """
    if form not in SANDWICH_FORMS:
        raise FitError(f"sandwich form must be one of {', '.join(SANDWICH_FORMS)}, got {form!r}")
    Jr = whitened_jacobian(problem, jac, preds, 0.0, phys)
    P = Jr[0].shape[-1]
    G = int(max(int(lab.max()) + 1 for lab in labels if lab.numel()))
    scores = torch.zeros(G, P, dtype=torch.float64, device=Jr[0].device)
    info = torch.zeros(G, P, P, dtype=torch.float64, device=Jr[0].device)  # A_c
    for i, (j, m, o, lab) in enumerate(zip(Jr, residual_preds, problem.observations, labels)):
        s = o.sigma[o.mask] * phys_noise_scale(problem, phys, i)
        r = problem.loss.residuals(m, o.values[o.mask], s).to(torch.float64) * _uncensored(problem, i, m)
        lab = lab.to(scores.device)
        scores.index_add_(0, lab, (j * r.unsqueeze(-1)).sum(1))  # one score per sample, then per cluster
        info.index_add_(0, lab, torch.einsum("ncp,ncq->npq", j, j))
    A = info.sum(0)
    A_inv = _pinv_sym(A)
    V = _cluster_sandwich(A, A_inv, scores, info, form)
    return 0.5 * (V + V.T), A_inv


def _cluster_sandwich(A: Tensor, A_inv: Tensor, scores: Tensor, info: Tensor, form: str) -> Tensor:
    """V of the cluster scores s_c (G, P) and their information parts A_c (G, P, P) about the bread A (P, P):
    ``cr1`` A^-1 (sum_c s_c s_c^T) A^-1 G / (G - 1), else the jackknife (G - 1) / G sum_c d_c d_c^T with
    d_c = (A - A_c)^-1 s_c; G counts the clusters with used elements."""
    used = info.diagonal(dim1=-2, dim2=-1).sum(-1) > 0
    g = int(used.sum())
    if form == "cr1":
        return A_inv @ (scores.T @ scores) @ A_inv * (g / max(g - 1, 1))
    d = torch.stack([_pinv_sym(A - info[c]) @ scores[c] for c in range(info.shape[0]) if bool(used[c])])
    return d.T @ d * ((g - 1) / max(g, 1))


ROBUST_RHOS = ("huber", "cauchy")
"""Robust rhos (:mod:`skyfit.fit.losses`): the fit is an M-estimator, no chi^2 sets a floor, and the discrepancy term is
:func:`robust_sandwich_share`."""


def _robust_weights(problem: FitProblem, preds, phys: dict, i: int) -> tuple[Tensor, Tensor, Tensor]:
    """(psi, psi', psi / r) of observation i's whitened residuals r under the loss's rho (the last, the IRLS weight, is
    psi' where r = 0), (N_i, C_i) each, float64, zero at censored elements."""
    o = problem.observations[i]
    s = o.sigma[o.mask] * phys_noise_scale(problem, phys, i)
    r = problem.loss.residuals(preds[i], o.values[o.mask], s).to(torch.float64).detach().requires_grad_(True)
    (psi,) = torch.autograd.grad(problem.loss.rho_fn(r).sum(), r, create_graph=True)
    (dpsi,) = torch.autograd.grad(psi.sum(), r)  # psi' (rho acts elementwise)
    keep = _uncensored(problem, i, preds[i]).to(torch.float64)
    psi, dpsi, r = psi.detach() * keep, dpsi.detach() * keep, r.detach()
    small = r.abs() <= 1e-12
    return psi, dpsi, torch.where(small, dpsi, psi / torch.where(small, torch.ones_like(r), r))


def robust_hessian(problem: FitProblem, x: Tensor, jac: list[Tensor]) -> Tensor:
    """The Gauss-Newton Hessian of a robust fit in IRLS weights (Holland & Welsch 1977), (P, P): sum_e w_e g_e g_e^T
    with g_e = dr_e/dx and w = psi(r) / r, plus the exact Hessian of the objective's non-data part
    (:meth:`FitProblem.penalty`: a photo's priors and sun datum), on the scale of n_elements x objective.

    A redescending rho (Cauchy) has psi' < 0 beyond |r| = c, and a lagged fit is evaluated where its rebuilt tables
    leave it a little off its optimum, so the exact Hessian can be indefinite (min eigenvalue -1515 on synthetic
    photo 6, docs/photos.md) and the Laplace sigma undefined; w > 0, so this one is positive semi-definite wherever
    the penalty's is."""
    x = x.detach()
    with torch.no_grad():
        preds = problem.predict(x)
    phys = {k: v.detach() for k, v in problem.param.to_physical(x).items()}
    grads = whitened_jacobian(problem, jac, preds, 0.0, phys)
    n = problem.n_elements
    out = torch.autograd.functional.hessian(lambda v: problem.penalty(problem.param.to_physical(v)) * n,
                                            x.to(torch.float64)).to(torch.float64)
    for i, g in enumerate(grads):
        w = _robust_weights(problem, preds, phys, i)[2]
        out = out + torch.einsum("ncp,nc,ncq->pq", g, w, g)
    return 0.5 * (out + out.T)


def robust_sandwich_share(problem: FitProblem, jac: list[Tensor], preds, labels: list[Tensor], phys: dict,
                          cov_noise: Tensor, irls: bool = False, forms: tuple = ("jackknife",)) -> dict[str, Tensor]:
    """The discrepancy share of a robust fit (huber or cauchy rho on a linear or log residual): the cluster
    jackknife over sky regions of an M-estimator, less what independent elements would give, (P, P). [x units^2]

    An M-estimator's covariance is the sandwich H^-1 M H^-1 (Huber 1967, Proc. 5th Berkeley Symp. 1, 221), H the
    Hessian of the objective (the Laplace one: robust rho, priors and penalties included; ``cov_noise`` = H^-1)
    and M the covariance of its score sum_e psi(r_e) dr_e/dx over the data, psi = rho'. Elements with independent
    errors give M_white = sum_e psi_e^2 g_e g_e^T (g_e = dr_e/dx, White 1980); a model error shared by a sky
    region makes a cluster's scores add up. The jackknife form (as :func:`sandwich_covariance`) leaves each
    cluster c out by one Newton step, d_c = (H - H_c)^-1 s_c with s_c = sum_{e in c} psi_e g_e and H_c = sum_{e in c}
    psi'_e g_e g_e^T, the cluster's part of H in its Gauss-Newton form (IRLS weights psi / r instead over-state it by
    ~25 % under Gaussian noise for the Cauchy rho, and H - H_c then nearly loses a direction: the white-noise share
    came out 2-6 sigma; ``irls``: H is :func:`robust_hessian`'s, and H_c takes psi / r likewise), and
    V = (G - 1) / G sum_c d_c d_c^T ("cr1": H^-1 (sum_c s_c s_c^T) H^-1 G / (G - 1), no leaving out). The
    share is the positive part of V - H^-1 M_white H^-1: zero when the residuals are as independent as the noise
    model says, the excess when sky regions err together. Returns form -> share for each of ``forms`` (the scores
    are summed once)."""
    grads = whitened_jacobian(problem, jac, preds, 0.0, phys)
    P = grads[0].shape[-1]
    dev = grads[0].device
    G = int(max(int(lab.max()) + 1 for lab in labels if lab.numel()))
    scores = torch.zeros(G, P, dtype=torch.float64, device=dev)
    info = torch.zeros(G, P, P, dtype=torch.float64, device=dev)
    white = torch.zeros(P, P, dtype=torch.float64, device=dev)
    for i, (g, lab) in enumerate(zip(grads, labels)):
        psi, dpsi, w_irls = _robust_weights(problem, preds, phys, i)
        w = w_irls if irls else dpsi  # irls: H is robust_hessian's, the clusters' parts in the same form
        lab = lab.to(dev)
        scores.index_add_(0, lab, (g * psi.unsqueeze(-1)).sum(1))
        info.index_add_(0, lab, torch.einsum("ncp,nc,ncq->npq", g, w, g))
        white += torch.einsum("ncp,nc,ncq->pq", g, psi**2, g)
    H_inv = cov_noise.to(torch.float64)
    H = _pinv_sym(H_inv)
    noise = H_inv @ white @ H_inv
    return {form: psd_part(_cluster_sandwich(H, H_inv, scores, info, form) - noise) for form in forms}


def psd_part(M: Tensor) -> Tensor:
    """The positive semi-definite part of a symmetric matrix (negative eigenvalues set to zero), (P, P)."""
    ev, U = torch.linalg.eigh(0.5 * (M + M.T))
    return (U * ev.clamp_min(0.0)) @ U.T


def loewner_upper(C1: Tensor, C2: Tensor) -> Tensor:
    """A minimal upper bound of two covariances in the Loewner order, C1 positive definite, (P, P).

    With L L^T = C1 and L^-1 C2 L^-T = U diag(lam) U^T: L U diag(max(lam, 1)) U^T L^T. It is >= C1 and >= C2,
    equals the larger where one contains the other, and its ellipsoid is the smallest coaxial one (axes of
    the joint diagonalisation) holding both; the same when C1 and C2 swap. Each diagonal element is at
    least the larger of the two."""
    L = torch.linalg.cholesky(0.5 * (C1 + C1.T))
    M = torch.linalg.solve_triangular(L, torch.linalg.solve_triangular(L, C2, upper=False).T, upper=False)
    lam, U = torch.linalg.eigh(0.5 * (M + M.T))
    B = L @ U
    out = (B * lam.clamp_min(1.0)) @ B.T
    return 0.5 * (out + out.T)


@dataclasses.dataclass
class NumericalTerm:
    """Term 1 of one fit at its x (:func:`numerical_term`); several :func:`error_budget` calls can share it
    (e.g. to compare discrepancy models without re-rendering the reference).

    Attributes:
        dx: the shift of x by refitting with the reference, shape (P,), float64. [x units]
        tail: what an unconverged refit has still to go, shape (P,), float64. [x units]
        m_cor: the numerically corrected model at x + dx, censored, list of (N_i, C_i). [data units]
        budget: its entries of ``budget`` (reference, model_difference, method, nonlinearity, refit_steps_in_sigma,
            numerical_shift_newton, numerical_tail).
        jacobian: :func:`prediction_jacobian` at x, filled by the first :func:`error_budget` that needs it.
    """

    dx: Tensor
    tail: Tensor
    m_cor: list
    budget: dict
    jacobian: list | None = None


def numerical_term(problem: FitProblem, x: Tensor, lap: dict, *, reference: SkyModel | None = None, numerical: bool = True,
                   refits: int = 0, options: FitOptions | None = None, polish: int = 0) -> NumericalTerm:
    """The numerical shift of the fit at x (module docstring, term 1; arguments as :func:`error_budget`'s);
    ``numerical`` False: no shift, the corrected model is the fit's. ``polish`` > 0: after the lagged refits, up to
    that many Levenberg-Marquardt steps on the reference itself (:func:`reference_polish`), kept where they lower
    the reference's loss."""
    x = x.detach()
    names = display_names(problem)
    cov_noise = torch.as_tensor(lap["covariance_unconstrained"], dtype=torch.float64, device=x.device)
    P = x.numel()
    budget: dict = {"reference": None, "model_difference": None}
    dx = torch.zeros(P, dtype=torch.float64, device=x.device)
    tail = torch.zeros(P, dtype=torch.float64, device=x.device)
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
            s_x = torch.as_tensor([lap["sigma_unconstrained"][n] for n in names], dtype=torch.float64, device=x.device)
            rs = refit_shift(problem, x, ref, x, s_x, refits, options, cov_x=cov_noise)
            budget["method"] = f"refit ({len(rs['steps'])} lagged refits)"
            budget["refit_steps_in_sigma"] = rs["steps"]
            budget["refit_solvers"] = rs["solvers"]
            budget["numerical_shift_newton"] = {n: float(b - a) for n, a, b in zip(
                names, physical_slot_values(problem, x.to(torch.float64)), v_newton)}
            dx_newton = dx
            dx = (rs["x"] - x).to(torch.float64)
            # one unconverged refit: the two estimates of the shift disagree by about what is left
            tail = rs["tail"] if rs["tail"] is not None else dx - dx_newton
            budget["numerical_tail"] = {n: float(t) for n, t in zip(names, transform_jacobian(problem, x.to(torch.float64)) * tail)}
            lagged = held_reference(problem, ref, rs["factor"])
            pol = reference_polish(problem, ref, rs["x"], polish) if polish > 0 else None
            if pol is not None:
                budget["polish"] = {k: pol[k] for k in ("loss", "loss_start", "steps", "converged")}
                if pol["loss"] < pol["loss_start"]:
                    budget["method"] += f" + {len(pol['steps'])} reference LM steps"
                    dx_lagged = dx
                    dx = (pol["x"] - x).to(torch.float64)
                    tail = torch.zeros_like(dx) if pol["converged"] else dx - dx_lagged
                    budget["numerical_tail"] = {n: float(t) for n, t in zip(
                        names, transform_jacobian(problem, x.to(torch.float64)) * tail)}
                    lagged = ref  # the corrected model is the reference's own
    with torch.no_grad():
        if lagged is not None:  # the refit's own model: m_fit c_k (the reference after a polish)
            m_cor = lagged.predict(x + dx.to(x.dtype))
        else:
            m_cor = problem.predict(x + dx.to(x.dtype)) if numerical else problem.predict(x)
    if delta is not None and lagged is None:
        m_cor = [m + d for m, d in zip(m_cor, delta)]
    m_cor = [problem.censor(m, i) for i, m in enumerate(m_cor)]
    return NumericalTerm(dx, tail, m_cor, budget)


def expansion_applies(problem: FitProblem) -> bool:
    """Whether :func:`phase_expansion` can refit ``problem`` with the next phase rung: a one-term Henyey-Greenstein
    phase with its asymmetry free (the two-term parameters neither free nor set)."""
    p = problem.param
    return (p.base.mie_phase == "henyey_greenstein" and "mie_g" in p.free
            and not (set(p.free) | p._overridden) & set(TWO_TERM_HG))


def _refreed(p: Parameterisation, x: Tensor, free: list[str], **held) -> Parameterisation:
    """``p`` with the free set ``free``, every value as at x (free ones moved inside their bounds, overridden ones
    and the nuisances as set) and ``held`` set (starting points where free, fixed values where not)."""
    vals = {n: p.values[n] for n in p._overridden}
    vals.update({n: p.values[n] for n in NUISANCE})
    vals.update({n: inside_bounds(n, v) for n, v in p.free_dict(x).items()})
    vals.update(held)
    return Parameterisation(p.base, free, p.n_observations, p.per_observation, vals)


def phase_expansion(problem: FitProblem, x: Tensor, term: NumericalTerm, *, reference: SkyModel | None = None,
                    options: FitOptions | None = None) -> dict | None:
    """The shift of every parameter when the fit's one-term Henyey-Greenstein phase is widened to two terms.

    A one-term fit of a sky whose aerosol has a backward lobe estimates the forward lobe and lets the other
    parameters absorb the rest (docs/uncertainty.md, "Coverage under model error": g 0.04-0.16 above the asymmetry
    parameter, beta -13 %); the residuals do not show what the parameters absorbed, so neither discrepancy model
    of :func:`error_budget` can. This refits the same data with the next rung of the phase ladder
    (skyfit.fit.select's ``two_term_hg``: f HG(g1) + (1 - f) HG(g2)), from the numerically corrected optimum
    x + dx with g2 and f at their ladder starts (:data:`MIE_G2_DEFAULT`, :data:`MIE_HG_WEIGHT_DEFAULT`), the
    reference's factor at that start held (as :func:`refit_shift`, so that the new lobe does not soak up the
    numerical error). The two-term phase's asymmetry parameter f g1 + (1 - f) g2 stands for ``mie_g``.

    Returns None where :func:`expansion_applies` is False, else ``e`` (P,) [x units]: the refit's values mapped
    back into x minus x + dx, ``covariance`` (P, P) [x units^2] and ``spread`` (its summary) from
    :func:`expansion_spread`, ``values`` (the refit's physical g1, g2, f and asymmetry), ``loss`` (the refit's
    and the one-term fit's corrected loss) and ``seconds``.
    """
    if not expansion_applies(problem):
        return None
    t0 = time.perf_counter()
    p = problem.param
    xc = (x.detach().to(torch.float64) + term.dx).to(x.dtype)
    wide = _refreed(p, xc, list(p.free) + list(TWO_TERM_HG), mie_g2=MIE_G2_DEFAULT, mie_hg_weight=MIE_HG_WEIGHT_DEFAULT)
    ep = copy.copy(problem)
    ep.param = wide
    ep.frozen_tables = None
    ep.frozen_slope = ep.frozen_slope_g = None
    x0 = wide.initial_vector(x.dtype, x.device)
    # the ratio to the bare single scattering in the factor's place, held in the aerosol (not held_reference's
    # followed factor: its slopes in g are the one-term g's, which the two-term refit does not have)
    ep.frozen_factor = reference_factor(ep, reference_problem(ep, reference), x0, on_factor=False)
    opt = options or FitOptions(starts=1, adam_steps=0, max_iter=100)
    res = fit(ep, opt, x0=x0)
    w = wide.physical_dict(res.x)
    asym = w["mie_hg_weight"] * w["mie_g"] + (1.0 - w["mie_hg_weight"]) * w["mie_g2"]
    mapped = {n: w[n] for n in p.free}
    mapped["mie_g"] = asym
    mapped = {n: inside_bounds(n, v) for n, v in mapped.items()}
    try:
        x_new = p.to_unconstrained(mapped, torch.float64, x.device)
    except FitError:  # the asymmetry beyond mie_g's range cannot happen (|asym| < 1); name it if it does
        raise FitError(f"the two-term refit's values lie outside the one-term parameters' ranges: {mapped}") from None
    with torch.no_grad():
        base_loss = float(problem.loss_from_predictions(term.m_cor, p.to_physical(xc)))
    spread = expansion_spread(problem, x, ep, res.x, w)
    return {"e": (x_new - xc.to(torch.float64)).detach(), "values": {"g1": w["mie_g"], "g2": w["mie_g2"],
            "hg_weight": w["mie_hg_weight"], "asymmetry": asym}, "loss": {"two_term": float(res.loss), "one_term": base_loss},
            "covariance": spread["covariance"], "spread": {k: v for k, v in spread.items() if k != "covariance"},
            "converged": bool(res.convergence.get("converged", False)), "seconds": time.perf_counter() - t0}


PHASE_EDGE = 0.02
"""A two-term refit with weight f above 1 - this found no backward lobe: its g2 is then not measured. [1]"""

PHASE_G2_PROFILE = (-0.9, -0.6, -0.3, -0.05)
"""Backward lobes tried where the refit found none (:func:`expansion_spread`): the range two-term fits of aerosol
phase functions take, inside mie_g2's open range (-1, 0). [1]"""

PHASE_WEIGHT_PROBE = 1e-3
"""Where the refit found no lobe, its covariance is taken at f = 1 - this, where every g2 fits alike (the model is
linear in f; at f = 1 exactly the sigmoid's slope rounds to 0). [1]"""


def _natural_covariance(problem: FitProblem, x: Tensor) -> Tensor:
    """Gauss-Newton covariance of ``problem``'s free slots at x in physical units (P, P), with the relative floor
    that brings chi^2 of its own residuals to the degrees of freedom (module docstring, term 2). [SI^2]"""
    x = x.detach()
    phys = {k: v.detach() for k, v in problem.param.to_physical(x).items()}
    with torch.no_grad():
        m = problem.predict(x)
    m_c = [problem.censor(v, i) for i, v in enumerate(m)]
    floor = 0.0
    if problem.loss.rho == "squared" and problem.loss.residual in ("linear", "log"):
        _, n = chi2_with_floor(problem, m_c, 0.0, phys)
        floor = fit_floor(problem, m_c, max(n - x.numel(), 1), phys)
    C = gauss_newton_covariance(problem, prediction_jacobian(problem, x), m, floor, phys)
    T = transform_jacobian(problem, x.to(torch.float64))
    return T[:, None] * C * T[None, :]


def expansion_spread(problem: FitProblem, x: Tensor, wide: FitProblem, x_wide: Tensor, w: dict) -> dict:
    """What the two-term refit lets every parameter of the one-term fit be: its covariance mapped into x (P, P).

    The one-term fit's ``mie_g`` stands for the asymmetry parameter A = f g1 + (1 - f) g2, the other parameters
    for themselves, so the refit's Gauss-Newton covariance (with its own relative floor) maps through
    dA = f dg1 + (1 - f) dg2 + (g1 - g2) df. Where the refit found a lobe (1 - f >= :data:`PHASE_EDGE`) that is
    the Laplace spread at its optimum. Where it found none (f at 1) g2 costs nothing and is not measured: the
    profile likelihood of A is then the union over g2 of the spreads with g2 held (the data bound f, and
    A moves by (g1 - g2) df), here the largest over :data:`PHASE_G2_PROFILE`, f and g2 held fixed in turn:
    not the linearisation at g2 free, which at f -> 1 lets A move by (1 - f) dg2 beyond |g2| <= 1.

    Args:
        problem, x: the one-term fit and its optimum; wide, x_wide: the two-term refit's problem and optimum;
            w: its physical values.

    Returns:
        ``covariance`` (P, P) in the units of x, float64 (at x's transform), ``sigma_asymmetry`` [1], ``g2``
        (the refit's, or the profile's g2 that gave the largest spread), ``hg_weight`` f where the covariance was
        taken and ``sigma_weight`` (f's sigma there) [1], ``lobe`` (whether the refit found one).
    """
    wp = wide.param
    names1 = display_names(problem)
    lobe = 1.0 - float(w["mie_hg_weight"]) >= PHASE_EDGE
    candidates = []
    if lobe:
        candidates.append((wide, x_wide.detach(), dict(w)))
    else:
        for g2 in PHASE_G2_PROFILE:  # no lobe: f at 1, where g2 costs nothing
            held = _refreed(wp, x_wide, [n for n in wp.free if n != "mie_g2"], mie_g2=g2,
                            mie_hg_weight=1.0 - PHASE_WEIGHT_PROBE)
            q = copy.copy(wide)
            q.param = held
            x_held = held.initial_vector(x_wide.dtype, x.device)
            candidates.append((q, x_held, held.physical_dict(x_held)))
    T1 = transform_jacobian(problem, x.detach().to(torch.float64))
    best = None
    for q, xq, v in candidates:
        C2 = _natural_covariance(q, xq)
        names2 = display_names(q)
        f, g1, g2 = float(v["mie_hg_weight"]), float(v["mie_g"]), float(v["mie_g2"])
        M = torch.zeros(len(names1), len(names2), dtype=torch.float64, device=x.device)
        for i, n in enumerate(names1):
            if n == "mie_g":
                for m_, c in (("mie_g", f), ("mie_g2", 1.0 - f), ("mie_hg_weight", g1 - g2)):
                    if m_ in names2:
                        M[i, names2.index(m_)] = c
            else:
                M[i, names2.index(n)] = 1.0
        C1 = M @ C2.to(torch.float64) @ M.T
        s_a = math.sqrt(max(float(C1[names1.index("mie_g"), names1.index("mie_g")]), 0.0))
        if best is None or s_a > best["sigma_asymmetry"]:
            k = names2.index("mie_hg_weight")
            best = {"covariance": C1 / (T1[:, None] * T1[None, :]), "sigma_asymmetry": s_a, "g2": g2, "lobe": lobe,
                    "hg_weight": f, "sigma_weight": math.sqrt(max(float(C2[k, k]), 0.0))}
    return best


def _cluster_meta(labels: list[Tensor], P: int, min_count: int, **extra) -> dict:
    """``budget["discrepancy"]``'s facts of the sandwich's clusters, and a note when they are too few for P."""
    sizes = torch.bincount(torch.cat(labels))
    out = {**extra, "clusters": int(sizes.numel()), "min_per_cluster": int(min_count),
           "cluster_sizes": [int(sizes.min()), int(sizes.max())]}
    if sizes.numel() - 1 < P:
        out["note"] = (f"{sizes.numel()} clusters for {P} free parameters: the sandwich is singular along some "
                       "directions (raise fit.sigma_clusters)")
    return out


def error_budget(problem: FitProblem, x: Tensor, lap: dict | None = None, *, reference: SkyModel | None = None,
                 numerical: bool = True, floor: bool = True, refits: int = 0, options: FitOptions | None = None,
                 polish: int = 0,
                 discrepancy: str = DISCREPANCY_DEFAULT, clusters: int = CLUSTERS, min_count: int = MIN_PER_CLUSTER,
                 sandwich_form: str = "jackknife", term: NumericalTerm | None = None, expand: bool = False,
                 expansion: dict | None = None) -> dict:
    """The Laplace summary with the total sigma (noise + numerical + discrepancy) and its breakdown.

    Args:
        problem: the fit problem; x: the fitted unconstrained vector, shape (P,).
        lap: :func:`skyfit.fit.laplace.laplace_summary` at x (computed when None).
        reference: the converged renderer (default :meth:`ReferenceModel.of` the fit's).
        numerical: include the numerical term.
        floor: include the discrepancy term (of the model ``discrepancy``).
        refits: 0: the numerical shift is one Newton step; N > 0: up to N lagged refits with the
            reference's factor (:func:`refit_shift`; for shifts too large for the linearisation).
        options: the refits' optimiser options (default 1 start, 100 L-BFGS iterations).
        polish: after the refits, up to this many Levenberg-Marquardt steps on the reference (:func:`reference_polish`).
        discrepancy: ``floor``, ``sandwich`` or ``larger`` (:data:`DISCREPANCY_MODELS`, module docstring).
        clusters, min_count: the sandwich's clusters per observation and fewest samples per cluster (:func:`sky_clusters`).
        sandwich_form: ``jackknife`` or ``cr1`` (:func:`sandwich_covariance`).
        term: :func:`numerical_term` of this problem, x and lap computed before (``reference``, ``numerical``,
            ``refits`` and ``options`` are then not used).
        expand: add the phase term (:func:`phase_expansion`, where it applies): the total at least the two-term
            Henyey-Greenstein refit's spread (:func:`expansion_spread`), plus the shift to that refit as an error
            like the numerical shift (cov += e e^T); ``budget`` then has ``sigma_phase`` (the shift's part) and
            ``sigma_phase_spread`` (what the spread added).
        expansion: :func:`phase_expansion`'s result computed before (implies ``expand``).

    Returns:
        ``lap``'s keys with ``sigma``, ``interval68``, ``interval95``, ``covariance``, ``correlation``,
        ``derived`` of the total covariance, ``corrected`` (the numerically corrected estimate: ``values`` at
        x + dx with ``sigma``, ``interval68``, ``interval95`` and ``derived`` of the covariance without the
        shift's outer product, the tail, discrepancy, phase term and noise kept), ``sigma_mode`` "total",
        ``sigma_noise`` (the Laplace sigma)
        and ``budget``: ``sigma_noise``, ``sigma_numerical``, ``sigma_discrepancy`` (name -> [SI]; the chosen
        model's), ``sigma_discrepancy_floor`` and ``sigma_discrepancy_sandwich`` (each model's, where computed),
        ``discrepancy`` (``model``, and for the sandwich ``clusters`` G, ``min_per_cluster`` and the
        ``cluster_sizes`` range in samples), ``numerical_shift`` (name -> physical value after the Newton step
        minus the fitted one [SI]), ``derived`` (the same for derived quantities), ``floor_relative`` f [1]
        and its range ``floor_relative_68`` (chi^2 at dof -+ sqrt(2 dof)), ``chi2_per_dof`` (at the fit),
        ``chi2_per_dof_corrected`` (after the numerical correction), ``dof``, ``reference`` (the converged
        renderer's settings), ``model_difference`` (rms of delta / m and delta / sigma), ``seconds``.
    """
    if discrepancy not in DISCREPANCY_MODELS:
        raise FitError(f"discrepancy must be one of {', '.join(DISCREPANCY_MODELS)}, got {discrepancy!r}")
    t0 = time.perf_counter()
    x = x.detach()
    lap = laplace_summary(problem, x) if lap is None else lap
    names = display_names(problem)
    cov_noise = torch.as_tensor(lap["covariance_unconstrained"], dtype=torch.float64, device=x.device)
    pd = bool(lap.get("positive_definite", True))
    P = x.numel()
    phys = {k: v.detach() for k, v in problem.param.to_physical(x).items()}
    if term is None:
        term = numerical_term(problem, x, lap, reference=reference, numerical=numerical, refits=refits, options=options,
                              polish=polish)
    budget: dict = copy.deepcopy(term.budget)
    dx, tail, m_cor = term.dx, term.tail, term.m_cor
    with torch.no_grad():
        m_fit = problem.predict(x)
    m_fit_c = [problem.censor(m, i) for i, m in enumerate(m_fit)]
    c_fit, n_used = chi2_with_floor(problem, m_fit_c, 0.0, phys)
    c_cor, _ = chi2_with_floor(problem, m_cor, 0.0, phys)
    dof = max(n_used - P, 1)
    budget.update(chi2_per_dof=c_fit / dof, chi2_per_dof_corrected=c_cor / dof, dof=dof)
    f, f_range = 0.0, [0.0, 0.0]
    zero = torch.zeros(P, P, dtype=torch.float64, device=x.device)
    shares: dict[str, Tensor] = {}  # discrepancy model -> its covariance share D (P, P)
    applicable = problem.loss.rho == "squared" and problem.loss.residual in ("linear", "log")
    robust = problem.loss.rho in ROBUST_RHOS and problem.loss.residual in ("linear", "log") and pd
    budget["discrepancy"] = {"model": discrepancy if floor and applicable else "sandwich" if floor and robust else None}
    if floor and applicable:
        f = fit_floor(problem, m_cor, dof, phys)
        spread = math.sqrt(2.0 * dof)
        f_range = [fit_floor(problem, m_cor, dof, phys, dof + spread), fit_floor(problem, m_cor, dof, phys, dof - spread)]
        if f > 0 or discrepancy != "floor":
            if term.jacobian is None:
                term.jacobian = prediction_jacobian(problem, x)
            jac = term.jacobian
            labels = sky_clusters(problem, phys, clusters, min_count)
            V, A_inv = sandwich_covariance(problem, jac, m_fit, m_cor, labels, phys, sandwich_form)
            shares["sandwich"] = psd_part(V - A_inv)
            # the floor's share: Gauss-Newton covariance with sigma' minus that with sigma (PSD, where the full
            # Hessian with sigma' need not be: x* is not the optimum of the inflated problem)
            shares["floor"] = psd_part(gauss_newton_covariance(problem, jac, m_fit, f, phys) - A_inv) if f > 0 else zero
            budget["discrepancy"].update(_cluster_meta(labels, P, min_count, form=sandwich_form))
            if discrepancy == "larger":
                shares["larger"] = psd_part(loewner_upper(A_inv + shares["floor"], A_inv + shares["sandwich"]) - A_inv)
    elif floor and robust:
        # an M-estimator: no chi^2 to set a floor; the robust cluster jackknife is the discrepancy term
        if term.jacobian is None:
            term.jacobian = prediction_jacobian(problem, x)
        labels = sky_clusters(problem, phys, clusters, min_count)
        both = robust_sandwich_share(problem, term.jacobian, m_fit, labels, phys, cov_noise, irls="hessian" in lap,
                                     forms=("jackknife", "cr1"))
        shares["sandwich"], shares["sandwich_cr1"] = both["jackknife"], both["cr1"]
        budget["discrepancy"].update(_cluster_meta(labels, P, min_count, form="jackknife", robust=problem.loss.rho))
    budget["floor_relative"] = f if applicable else None
    budget["floor_relative_68"] = f_range if applicable else None
    if floor and not applicable:
        budget["floor_note"] = (f"no floor for the {problem.loss.name} loss (it needs rho squared on a linear or log residual)"
                                + ("; the discrepancy is the robust cluster sandwich" if robust else ""))
    share = shares.get("sandwich" if robust else discrepancy, zero)
    if expansion is None and expand:
        expansion = phase_expansion(problem, x, term, reference=reference, options=options)
    e = torch.zeros(P, dtype=torch.float64, device=x.device) if expansion is None else expansion["e"].to(dtype=torch.float64, device=x.device)
    cov_exp = (expansion["covariance"].to(dtype=torch.float64, device=x.device)
               if expansion is not None and expansion.get("covariance") is not None and pd else None)

    def phase_added(cov: Tensor) -> tuple[Tensor, Tensor | None]:
        """``cov`` with the phase term: at least what the two-term refit allows, along every direction
        (loewner_upper), then its shift; and the spread that added."""
        spread = None if cov_exp is None else psd_part(loewner_upper(cov, cov_exp) - cov)
        cov = cov if spread is None else cov + spread
        return cov + torch.outer(e, e), spread

    cov_total, spread = phase_added(cov_noise + share + torch.outer(dx, dx) + torch.outer(tail, tail))
    # the corrected estimate (GUM 3.2.4: correct for a recognised systematic effect): at x + dx, the shift not an
    # error, what is left of it (the tail) still one
    cov_corr, _ = phase_added(cov_noise + share + torch.outer(tail, tail))
    out = {**lap, **covariance_summary(problem, x, cov_total, pd)}
    corr = covariance_summary(problem, x + dx.to(x.dtype), cov_corr, pd)
    out["corrected"] = {k: corr[k] for k in ("values", "sigma", "interval68", "interval95", "derived")}
    out["positive_definite"] = pd
    out["sigma_mode"] = "total"
    out["sigma_noise"] = lap["sigma"]
    out["covariance_noise"] = lap["covariance"]
    J = transform_jacobian(problem, x.to(torch.float64))
    s_num = J.abs() * torch.sqrt(dx**2 + tail**2)
    v0 = physical_slot_values(problem, x.to(torch.float64))
    v1 = physical_slot_values(problem, x.to(torch.float64) + dx)
    budget["sigma_noise"] = lap["sigma"]
    budget["sigma_numerical"] = {n: float(s) for n, s in zip(names, s_num)}
    budget["sigma_discrepancy"] = {n: float(s) for n, s in zip(names, torch.sqrt(torch.diagonal(share).clamp_min(0.0)) * J.abs())}
    for model in ("floor", "sandwich", "sandwich_cr1"):
        if model in shares:
            budget[f"sigma_discrepancy_{model}"] = {n: float(s) for n, s in zip(
                names, torch.sqrt(torch.diagonal(shares[model]).clamp_min(0.0)) * J.abs())}
    budget["numerical_shift"] = {n: float(b - a) for n, a, b in zip(names, v0, v1)}
    if expand and expansion is None:
        p_ = problem.param
        why = [f"its phase is {p_.base.mie_phase}"] if p_.base.mie_phase != "henyey_greenstein" else []
        why += [] if "mie_g" in p_.free else ["g is not free"]
        why += ["its two-term parameters are set"] if (set(p_.free) | p_._overridden) & set(TWO_TERM_HG) else []
        budget["phase_note"] = ("no phase term (it widens a one-term Henyey-Greenstein phase with g free): "
                                + ", ".join(why or ["it does not apply"]))
    if expansion is not None:
        budget["sigma_phase"] = {n: float(s_) for n, s_ in zip(names, J.abs() * e.abs())}
        budget["phase_expansion"] = {k: expansion[k] for k in ("values", "loss", "converged", "seconds", "spread") if k in expansion}
        if spread is not None:
            budget["sigma_phase_spread"] = {n: float(s_) for n, s_ in zip(names, J.abs() * torch.sqrt(torch.diagonal(spread).clamp_min(0.0)))}
    derived = {}
    for name, fn in derived_functions(problem).items():
        xr = x.to(torch.float64).clone().requires_grad_(True)
        val = fn(xr)
        (g,) = torch.autograd.grad(val, xr)
        with torch.no_grad():
            shifted = float(fn(x.to(torch.float64) + dx))
        derived[name] = {"sigma_noise": lap["derived"][name]["sigma"], "sigma_numerical": abs(float(g @ dx)),
                         **({"sigma_phase": abs(float(g @ e))} if expansion is not None else {}),
                         **({"sigma_phase_spread": math.sqrt(max(float(g @ spread @ g), 0.0))} if spread is not None else {}),
                         "sigma_discrepancy": math.sqrt(max(float(g @ share @ g), 0.0)),
                         "numerical_shift": shifted - float(val.detach())}
        for model in ("floor", "sandwich"):
            if model in shares:
                derived[name][f"sigma_discrepancy_{model}"] = math.sqrt(max(float(g @ shares[model] @ g), 0.0))
    budget["derived"] = derived
    budget["seconds"] = time.perf_counter() - t0
    out["budget"] = budget
    out["seconds"] = lap.get("seconds", 0.0) + budget["seconds"]
    return out


def uncertainty(problem: FitProblem, x: Tensor, sigma: str = "total", reference: SkyModel | None = None,
                refits: int = 0, options: FitOptions | None = None, discrepancy: str = DISCREPANCY_DEFAULT,
                clusters: int = CLUSTERS, expand: bool = False, polish: int = 0) -> dict:
    """RESULT.json's ``laplace``: :func:`error_budget` (with the ``discrepancy`` model, ``clusters`` and the phase
    term when ``expand``) for
    ``sigma="total"``, the noise-only Laplace summary (``sigma_mode`` "noise") for ``"noise"``."""
    if sigma not in SIGMA_MODES:
        raise FitError(f"sigma must be one of {', '.join(SIGMA_MODES)}, got {sigma!r}")
    if discrepancy not in DISCREPANCY_MODELS:
        raise FitError(f"discrepancy must be one of {', '.join(DISCREPANCY_MODELS)}, got {discrepancy!r}")
    lap = laplace_summary(problem, x)
    term = None
    if sigma == "total" and not lap["positive_definite"] and problem.loss.rho in ROBUST_RHOS:
        # outliers' negative curvature under a redescending rho: the IRLS curvature instead (robust_hessian)
        jac = prediction_jacobian(problem, x)
        irls = laplace_summary(problem, x, hessian=robust_hessian(problem, x, jac))
        if irls["positive_definite"]:
            lap = {**irls, "hessian": f"Gauss-Newton in IRLS weights: the Hessian of the {problem.loss.rho} fit was not "
                                      f"positive definite (min eigenvalue {lap['min_eigenvalue']:.3g})"}
            term = numerical_term(problem, x, lap, reference=reference, refits=refits, options=options, polish=polish)
            term.jacobian = jac
    if sigma == "noise" or not lap.get("positive_definite", True):
        return {**lap, "sigma_mode": "noise"}
    return error_budget(problem, x, lap, reference=reference, refits=refits, options=options, polish=polish,
                        discrepancy=discrepancy, clusters=clusters, expand=expand, term=term)
