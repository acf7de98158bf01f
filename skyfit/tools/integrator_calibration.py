"""Calibrate the optical-depth integrators' settings for one atmosphere (``skyfit calibrate-integrator``).

Three settings of Gałaj 2021 depend on the atmosphere they are used for:

1. Taylor's hyperparameters (a, b) (Sec. IV.F, eq. 17). The paper picked
   a = b = 0.45 for Earth by a 101 x 101 grid search over {0, 0.01, ..., 1}^2
   of the "cumulative error" on points d in [0, R], t in [t_min(d), t_max(d)]
   (Sec. VI.A.2). Here (a, b) are fitted by gradient -- Adam, then L-BFGS,
   through a = sigmoid(theta_a), b = sigmoid(theta_b) so they stay in (0, 1)
   without clamping -- on the same (d, t) domain and an explicit metric
   (:data:`CALIBRATION_METRICS`), shared by all layers or one pair per layer.
   :func:`grid_search_taylor` runs the paper's grid search on the same
   objective for comparison.
2. The spline grid (height x distance points, Table 1): the smallest one whose
   transmittance and single-scattering radiance errors meet a tolerance.
3. The number of view samples of the outer single-scattering integral: the
   smallest one whose radiance error meets the tolerance.

The error of every candidate is measured against float64 references:
Gauss-Legendre optical depth with many nodes (checked against
``scipy.integrate.quad`` in the tests and by ``scripts/calibrate_compare.py``)
and, for radiance, a Gauss-Legendre view integral with many nodes on top of it.

Error budget. The spline grid and the view-sample count are chosen with half
the radiance tolerance each, every other error source held at the reference
(spline: reference view integral; view samples: reference optical depth), so
that the two errors of a render with both settings add up to at most the
tolerance; :func:`calibrate_integrators` measures that combined error too.
"""
from __future__ import annotations

import dataclasses
import math
import time

import torch
from torch import Tensor

from ..atmosphere import Atmosphere
from ..scattering import single_scattering
from ..transmittance import ColumnFn
from ..transmittance.quadrature import GaussOpticalDepth
from ..transmittance.spline import SplineOpticalDepth
from ..transmittance.taylor import TAYLOR_A_DEFAULT, TAYLOR_B_DEFAULT, TaylorOpticalDepth, taylor_column
from .reference import COLUMN_ERROR_FLOOR_M

LAYER_NAMES: tuple[str, ...] = ("rayleigh", "mie")
"""Layers in the order of :attr:`Atmosphere.scale_heights` and the rows of its extinction matrix."""

CALIBRATION_METRICS: tuple[str, ...] = ("transmittance", "column", "radiance")
"""Error metrics of the Taylor fit: the first two on Gałaj's (d, t) domain (:func:`layer_errors`,
:class:`TaylorObjective`), the last on single-scattering radiance (:class:`RadianceObjective`)."""
DOMAIN_METRICS: tuple[str, ...] = ("transmittance", "column")

D_SPACINGS: tuple[str, ...] = ("view", "paper")
"""How the line distances d of the (d, t) domain are spaced (see :func:`galaj_domain`)."""

METRIC_DESCRIPTIONS: dict[str, str] = {
    "transmittance": (
        "RMS over layers k, wavelengths and (d, t) domain points of exp(-beta_k c~_k) - exp(-beta_k c_k): the "
        "per-layer transmittance error, with beta_k the atmosphere's sea-level extinction of layer k at each wavelength, "
        "c~ the Taylor column (Galaj 2021 eq. 17) and c the float64 Gauss-Legendre reference column of the segment "
        "from t_min(d) to t (eq. 12)"
    ),
    "column": (
        "RMS over layers and (d, t) domain points of (c~_k - c_k) / max(c_k, 1 mm): relative column error "
        "with a floor, independent of the extinction coefficients"
    ),
    "radiance": (
        "RMS over rays and wavelengths of (L~ - L) / L, the relative single-scattering radiance error of a render "
        "with Taylor optical depth against the same render with float64 Gauss-Legendre optical depth (same view "
        "integral), on the fit rays (FIT_RAYS, distinct from the evaluation rays)"
    ),
}

REFERENCE_COLUMN_SAMPLES: int = 256
"""Gauss-Legendre nodes of the reference columns: 256 and 512 agree to < 1e-12 relative on Earth's
and Mars's domains (measured by scripts/calibrate_compare.py, checked against scipy quad in the tests)."""
REFERENCE_LIGHT_SAMPLES: int = 128
"""Gauss-Legendre optical-depth nodes of the reference radiance. [1]"""
REFERENCE_VIEW_SAMPLES: int = 256
"""Gauss-Legendre view-integral nodes of the reference radiance. [1]"""

HEIGHT_CANDIDATES: tuple[int, ...] = (5, 6, 8, 10, 12, 16, 20, 24, 32, 40, 50, 64, 80, 100, 128)
"""Spline height points tried, ascending; "one step smaller" means the previous entry."""
DISTANCE_CANDIDATES: tuple[int, ...] = (3, 4, 5, 6, 8, 10, 12, 16, 20, 24, 32, 40, 50, 64)
"""Spline distance points tried, ascending (3 is the least catmull_rom distance interpolation takes)."""
VIEW_CANDIDATES: tuple[int, ...] = (2, 3, 4, 6, 8, 12, 16, 24, 32, 48, 64, 96, 128, 192, 256, 384, 512, 768, 1024)
"""View samples tried, ascending."""

TOLERANCE_DEFAULT: float = 1e-3
"""Relative single-scattering radiance tolerance (max over rays and wavelengths). [1]"""
TRANSMITTANCE_TOLERANCE_DEFAULT: float = 1e-3
"""Absolute per-layer transmittance tolerance of the spline (max over the domain and wavelengths). [1]"""

CALIBRATE_QUICK: dict = {
    "n_d": 21,
    "n_t": 20,
    "rays": {"sun_zeniths_deg": (30.0, 85.0), "view_zeniths_deg": (0.0, 60.0, 85.0, 90.0), "relative_azimuths_deg": (0.0, 180.0)},
    "height_candidates": (5, 8, 12, 16, 24, 32, 48, 64),
    "distance_candidates": (3, 4, 6, 8, 12, 16, 24),
    "view_candidates": (4, 8, 16, 32, 64, 128, 256, 512, 1024),
}
"""``skyfit calibrate-integrator --quick`` (for CI): a 21 x 20 (d, t) domain instead of 101 x 100,
16 rays instead of 63, coarser candidate lists."""


def _validate(name: str, value: str, valid: tuple[str, ...]) -> str:
    if value not in valid:
        raise ValueError(f"unknown {name} {value!r}; valid: {', '.join(valid)}")
    return value


# --------------------------------------------------------------------------
# Gałaj's (d, t) domain and its reference columns
# --------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class GalajDomain:
    """Points (d, t) of Gałaj 2021 Sec. IV.C as segments from t_min(d) to t (eq. 12).

    Attributes (P points):
        d: distance of the ray's line from the planet centre, shape (P,). [m]
        t: end of the segment, measured from the line's closest point P_o, shape (P,). [m]
        r, mu, length: the segment as an integrator sees it, start radius, view cosine
            at the start and length, shape (P,) each. [m], [1], [m]
        bottom_radius, top_radius: [m]
        spacing: one of :data:`D_SPACINGS`.
    """

    d: Tensor
    t: Tensor
    r: Tensor
    mu: Tensor
    length: Tensor
    bottom_radius: float
    top_radius: float
    spacing: str

    @property
    def size(self) -> int:
        return int(self.d.shape[0])

    def describe(self) -> dict:
        return {"points": self.size, "d_spacing": self.spacing}


def galaj_domain(
    bottom_radius: float,
    top_radius: float,
    n_d: int = 101,
    n_t: int = 100,
    spacing: str = "view",
    dtype: torch.dtype = torch.float64,
    device: torch.device | str = "cpu",
) -> GalajDomain:
    """``n_d`` line distances d in [0, R_top] times ``n_t`` ends t in (t_min(d), t_max(d)] (Gałaj 2021 Sec. VI.A.2).

    With Gałaj's notation (r = planet, R = top radius) t_min(d) = sqrt(r^2 - d^2)
    for d < r, else 0, and t_max(d) = sqrt(R^2 - d^2) (Sec. IV.C). The ends are
    t = t_min + k/n_t (t_max - t_min), k = 1..n_t (t = t_min is a zero segment).

    Spacing of d:
        ``"paper"``: uniform on [0, R_top], as a grid over the paper's domain;
            for Earth it puts one node in 100 above the ground (d > r), where
            the horizon rays and Taylor's largest errors are.
        ``"view"`` (default): the distances a ground observer's sky sees. Half
            the nodes uniform in the ground zenith cosine c = sqrt(1 - (d/r)^2)
            in (0, 1] (uniform in solid angle over the sky), the rest uniform in
            the tangent altitude d - r in [0, R - r) (rays that graze the
            atmosphere: horizon views and sun rays from altitude).

    Returns:
        A :class:`GalajDomain` of n_d * n_t points.
    """
    _validate("d spacing", spacing, D_SPACINGS)
    if int(n_d) < 2 or int(n_t) < 1:
        raise ValueError(f"the domain needs n_d >= 2 and n_t >= 1, got {n_d}, {n_t}")
    if not 0 < bottom_radius < top_radius:
        raise ValueError(f"need 0 < bottom_radius < top_radius, got {bottom_radius}, {top_radius}")
    T = dict(dtype=dtype, device=device)
    Rb, Rt = float(bottom_radius), float(top_radius)
    if spacing == "paper":
        d = torch.linspace(0.0, Rt, int(n_d), **T)
    else:
        n_in = int(n_d) // 2
        c = torch.arange(1, n_in + 1, **T) / n_in  # ground cosine in (0, 1]
        d_in = Rb * torch.sqrt((1.0 - c) * (1.0 + c))
        n_out = int(n_d) - n_in
        d_out = Rb + (Rt - Rb) * torch.arange(n_out, **T) / n_out
        d = torch.cat([d_in, d_out])
    t_min = torch.sqrt(torch.clamp_min((Rb - d) * (Rb + d), 0.0))
    t_max = torch.sqrt(torch.clamp_min((Rt - d) * (Rt + d), 0.0))
    k = torch.arange(1, int(n_t) + 1, **T) / int(n_t)
    t = t_min[:, None] + k * (t_max - t_min)[:, None]
    r0 = torch.sqrt(d * d + t_min * t_min)  # the ground (d < r) or the tangent point P_o (d >= r)
    mu0 = t_min / r0
    length = t - t_min[:, None]
    dd = d[:, None].expand_as(t)
    return GalajDomain(
        d=dd.reshape(-1), t=t.reshape(-1), r=r0[:, None].expand_as(t).reshape(-1), mu=mu0[:, None].expand_as(t).reshape(-1),
        length=length.reshape(-1), bottom_radius=Rb, top_radius=Rt, spacing=spacing,
    )


def reference_columns(domain: GalajDomain, scale_heights: Tensor, samples: int = REFERENCE_COLUMN_SAMPLES, chunk: int = 4096) -> Tensor:
    """Float64-grade columns of the domain's segments by ``samples``-node Gauss-Legendre, shape (P, K). [m]

    Computed in the domain's dtype: pass a float64 domain for a reference.
    """
    g = GaussOpticalDepth(samples)
    H = scale_heights.to(dtype=domain.r.dtype, device=domain.r.device)
    parts = [
        g.column(domain.r[i : i + chunk], domain.mu[i : i + chunk], domain.length[i : i + chunk], H, domain.bottom_radius, domain.top_radius)
        for i in range(0, domain.size, chunk)
    ]
    return torch.cat(parts, 0)


# --------------------------------------------------------------------------
# The error metric
# --------------------------------------------------------------------------
def layer_errors(columns: Tensor, reference: Tensor, extinction: Tensor, metric: str = "transmittance") -> Tensor:
    """Mean squared error of each layer over the domain (and wavelengths), shape (..., K).

    Args:
        columns: approximate columns, shape (..., P, K). [m]
        reference: reference columns, shape (P, K). [m]
        extinction: sea-level extinction per layer and wavelength, shape (K, W). [1/m]
        metric: ``"transmittance"``: mean over points and wavelengths of
            (exp(-beta c~) - exp(-beta c))^2. ``"column"``: mean over points of
            ((c~ - c) / max(c, 1 mm))^2.

    Why transmittance: the renderer only sees exp(-sum beta_k c_k), so a column
    error matters as much as it changes the transmittance for the atmosphere's
    extinction. Relative column error weighs a 7x error in a Mie column that
    is opaque anyway, or a 1 mm column at the top of the atmosphere, like an
    error in the zenith column; transmittance error weighs each by its effect.
    Per layer (not the total exp(-sum_k ...)) so that per-layer fits separate.
    Squared mean (not max) so that the objective is smooth for the gradient fit
    and close to the paper's "cumulative error".
    """
    _validate("metric", metric, DOMAIN_METRICS)
    if metric == "column":
        rel = (columns - reference) / torch.clamp_min(reference, COLUMN_ERROR_FLOOR_M)
        return (rel * rel).mean(dim=-2)
    beta = extinction.to(dtype=columns.dtype, device=columns.device)
    e = torch.exp(-columns.unsqueeze(-1) * beta) - torch.exp(-reference.unsqueeze(-1) * beta)  # (..., P, K, W)
    return (e * e).mean(dim=(-3, -1))


class TaylorObjective:
    """Per-layer mean squared error of Taylor columns on a domain, for given (a, b).

    Args:
        atm: the atmosphere (scale heights, radii and extinction are read from it).
        domain: points of :func:`galaj_domain`.
        metric: one of :data:`DOMAIN_METRICS`.
        reference: precomputed :func:`reference_columns` (computed here otherwise).
    """

    separable = True
    """Each layer's error depends on its own (a, b) only."""

    def __init__(self, atm: Atmosphere, domain: GalajDomain, metric: str = "transmittance", reference: Tensor | None = None):
        self.metric = _validate("metric", metric, DOMAIN_METRICS)
        self.domain = domain
        dt, dev = domain.r.dtype, domain.r.device
        self.scale_heights = atm.scale_heights.detach().to(dtype=dt, device=dev)
        self.extinction = atm.extinction_matrix.detach().to(dtype=dt, device=dev)
        self.reference = reference_columns(domain, self.scale_heights) if reference is None else reference.to(dtype=dt, device=dev)
        self.evaluations = 0

    def columns(self, a: Tensor, b: Tensor) -> Tensor:
        """Taylor columns, shape (..., P, K) for a, b broadcastable to (..., 1, K)."""
        d = self.domain
        return taylor_column(d.r, d.mu, d.length, self.scale_heights, d.bottom_radius, d.top_radius, a, b)

    def __call__(self, a: Tensor, b: Tensor) -> Tensor:
        """Mean squared error per layer, shape (..., K), for a, b of shape (), (K,) or (..., 1, K)."""
        self.evaluations += 1
        return layer_errors(self.columns(a, b), self.reference, self.extinction, self.metric)

    def rms(self, a, b) -> tuple[float, list[float]]:
        """(RMS over layers, RMS per layer) at fixed (a, b) (floats or (K,) sequences)."""
        T = dict(dtype=self.reference.dtype, device=self.reference.device)
        with torch.no_grad():
            e = self(torch.as_tensor(a, **T), torch.as_tensor(b, **T))
        return math.sqrt(float(e.mean())), [math.sqrt(float(v)) for v in e]


# --------------------------------------------------------------------------
# Gradient fit and the paper's grid search
# --------------------------------------------------------------------------
@dataclasses.dataclass
class TaylorFit:
    """Result of :func:`fit_taylor` or :func:`grid_search_taylor`.

    Attributes:
        a, b: fitted hyperparameters, one per layer (equal when shared). [1]
        error: RMS error over layers (sqrt of the objective). [1]
        layer_error: RMS error per layer. [1]
        seconds: wall time of the search. [s]
        evaluations: objective evaluations (a grid evaluation counts each grid point).
        method: "gradient" or "grid".
        per_layer: one (a, b) per layer or one shared pair.
    """

    a: list[float]
    b: list[float]
    error: float
    layer_error: list[float]
    seconds: float
    evaluations: int
    method: str
    per_layer: bool
    history: list[float] = dataclasses.field(default_factory=list, repr=False)


def _logit(p: float) -> float:
    return math.log(p / (1.0 - p))


def fit_taylor(
    objective: TaylorObjective | RadianceObjective,
    per_layer: bool = False,
    start: tuple[float, float] = (TAYLOR_A_DEFAULT, TAYLOR_B_DEFAULT),
    adam_steps: int = 30,
    adam_lr: float = 0.1,
    lbfgs_iterations: int = 100,
) -> TaylorFit:
    """Fit (a, b) by gradient: Adam, then L-BFGS, on a = sigmoid(theta_a), b = sigmoid(theta_b).

    The objective is the mean over layers of :class:`TaylorObjective`'s per-layer
    errors (or :class:`RadianceObjective`'s error), divided by its value at
    ``start`` (L-BFGS's tolerances are absolute). Per layer, a domain metric's
    terms are independent, so one joint fit equals K separate ones; the
    radiance metric fits the 2K parameters jointly. A short Adam warm-up from the paper's (0.45, 0.45) moves into
    the objective's narrow valley (a and b trade off against each other,
    docs/integrator_calibration.md) and L-BFGS (strong Wolfe line search)
    converges in it; on Earth and Mars L-BFGS alone reaches the same point to
    1e-12. The best point seen is returned.

    Returns:
        :class:`TaylorFit` with method "gradient".
    """
    t0 = time.perf_counter()
    k = objective.scale_heights.shape[0]
    T = dict(dtype=objective.reference.dtype, device=objective.reference.device)
    n = k if per_layer else 1
    if not (0.0 < start[0] < 1.0 and 0.0 < start[1] < 1.0):
        raise ValueError(f"start must lie in (0, 1)^2 (sigmoid parametrisation), got {start}")
    theta = torch.tensor([[_logit(start[0])] * n, [_logit(start[1])] * n], **T).requires_grad_(True)
    evals0 = objective.evaluations
    with torch.no_grad():
        scale = float(objective(torch.full((k,), start[0], **T), torch.full((k,), start[1], **T)).mean())
    scale = scale if scale > 0 else 1.0
    best = [math.inf, theta.detach().clone()]
    history: list[float] = []

    def loss_fn() -> Tensor:
        ab = torch.sigmoid(theta).expand(2, k)
        loss = objective(ab[0], ab[1]).mean() / scale
        v = float(loss.detach())
        history.append(v)
        if v < best[0]:
            best[0], best[1] = v, theta.detach().clone()
        return loss

    adam = torch.optim.Adam([theta], lr=adam_lr)
    for _ in range(int(adam_steps)):
        adam.zero_grad()
        loss = loss_fn()
        loss.backward()
        adam.step()
    if lbfgs_iterations > 0:
        with torch.no_grad():
            theta.copy_(best[1])
        lbfgs = torch.optim.LBFGS([theta], lr=1.0, max_iter=int(lbfgs_iterations), tolerance_grad=1e-12,
                                  tolerance_change=1e-15, history_size=20, line_search_fn="strong_wolfe")

        def closure():
            lbfgs.zero_grad()
            loss = loss_fn()
            loss.backward()
            return loss

        lbfgs.step(closure)
    ab = torch.sigmoid(best[1]).expand(2, k)
    a, b = ab[0].tolist(), ab[1].tolist()
    err, layer_err = objective.rms(a, b)
    return TaylorFit(a, b, err, layer_err, time.perf_counter() - t0, objective.evaluations - evals0, "gradient", per_layer, history)


def grid_search_taylor(objective: TaylorObjective | RadianceObjective, values: Tensor | None = None, chunk_elements: float = 4e6) -> tuple[TaylorFit, TaylorFit, Tensor]:
    """Gałaj 2021 Sec. VI.A.2's grid search: every (a, b) in values^2 (default {0, 0.01, ..., 1}).

    A :class:`TaylorObjective` separates by layer, so one pass gives the shared
    optimum (least mean over layers) and each layer's own; a
    :class:`RadianceObjective` does not (per-layer fit None: a 4-D grid).

    Returns:
        (shared fit, per-layer fit or None, mean squared errors of shape (G, G, K) indexed
        [a, b, layer], K = 1 for radiance). Fits carry the whole search's wall time and evaluation count.
    """
    t0 = time.perf_counter()
    T = dict(dtype=objective.reference.dtype, device=objective.reference.device)
    v = torch.linspace(0.0, 1.0, 101, **T) if values is None else torch.as_tensor(values, **T)
    g = v.shape[0]
    if not objective.separable:
        k = objective.scale_heights.shape[0]
        table = torch.empty(g, g, 1, **T)
        with torch.no_grad():
            for i in range(g):
                for j in range(g):
                    table[i, j, 0] = objective(v[i], v[j])
        seconds = time.perf_counter() - t0
        i, j = divmod(int(torch.argmin(table[..., 0])), g)
        fit_s = TaylorFit([float(v[i])] * k, [float(v[j])] * k, math.sqrt(float(table[i, j, 0])), [], seconds, g * g, "grid", False)
        return fit_s, None, table
    p, k = objective.reference.shape
    w = objective.extinction.shape[1] if objective.metric == "transmittance" else 1
    step = max(1, int(chunk_elements // (p * k * w)))
    table = torch.empty(g, g, k, **T)
    evals0 = objective.evaluations
    with torch.no_grad():
        for i in range(g):
            for j in range(0, g, step):
                bb = v[j : j + step].reshape(-1, 1, 1)
                table[i, j : j + step] = objective(v[i], bb)
    n_eval = g * g
    objective.evaluations = evals0 + n_eval
    seconds = time.perf_counter() - t0
    shared = table.mean(-1)
    i, j = divmod(int(torch.argmin(shared)), g)
    fit_s = TaylorFit([float(v[i])] * k, [float(v[j])] * k, math.sqrt(float(shared[i, j])),
                      [math.sqrt(float(e)) for e in table[i, j]], seconds, n_eval, "grid", False)
    a_l, b_l, e_l = [], [], []
    for kk in range(k):
        ii, jj = divmod(int(torch.argmin(table[..., kk])), g)
        a_l.append(float(v[ii]))
        b_l.append(float(v[jj]))
        e_l.append(float(table[ii, jj, kk]))
    fit_l = TaylorFit(a_l, b_l, math.sqrt(sum(e_l) / k), [math.sqrt(e) for e in e_l], seconds, n_eval, "grid", True)
    return fit_s, fit_l, table


# --------------------------------------------------------------------------
# Radiance: rays, reference, errors
# --------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class RadianceRays:
    """Rays of a ground observer, shape (R,) each: r [m], mu, mu_s, nu [1]."""

    r: Tensor
    mu: Tensor
    mu_s: Tensor
    nu: Tensor
    description: dict


def radiance_rays(
    atm: Atmosphere,
    sun_zeniths_deg=(30.0, 60.0, 85.0),
    view_zeniths_deg=(0.0, 30.0, 60.0, 75.0, 85.0, 88.0, 90.0),
    relative_azimuths_deg=(0.0, 90.0, 180.0),
    altitude_m: float = 0.0,
) -> RadianceRays:
    """Every combination of sun zenith, view zenith and view azimuth relative to the sun, for one observer."""
    T = dict(dtype=atm.dtype, device=atm.device)
    sz, vz, az = torch.meshgrid(
        torch.deg2rad(torch.tensor(sun_zeniths_deg, **T)),
        torch.deg2rad(torch.tensor(view_zeniths_deg, **T)),
        torch.deg2rad(torch.tensor(relative_azimuths_deg, **T)),
        indexing="ij",
    )
    mu, mu_s = torch.cos(vz).reshape(-1), torch.cos(sz).reshape(-1)
    nu = (torch.cos(vz) * torch.cos(sz) + torch.sin(vz) * torch.sin(sz) * torch.cos(az)).reshape(-1)
    r = torch.full_like(mu, atm.bottom_radius + float(altitude_m))
    desc = {"sun_zeniths_deg": list(sun_zeniths_deg), "view_zeniths_deg": list(view_zeniths_deg),
            "relative_azimuths_deg": list(relative_azimuths_deg), "altitude_m": float(altitude_m), "rays": int(mu.shape[0])}
    return RadianceRays(r, mu, mu_s, nu, desc)


def render_rays(atm: Atmosphere, rays: RadianceRays, integrator, view_samples: int, rule: str, column_fn: ColumnFn | None = None) -> Tensor:
    """Single-scattering radiance of the rays, shape (R, W), without gradients. [W/(m^2 sr nm)]"""
    with torch.no_grad():
        return single_scattering(atm, rays.r, rays.mu, rays.mu_s, rays.nu, integrator, view_samples=view_samples, rule=rule,
                                 column_fn=column_fn)


def radiance_reference(atm: Atmosphere, rays: RadianceRays, light_samples: int = REFERENCE_LIGHT_SAMPLES,
                       view_samples: int = REFERENCE_VIEW_SAMPLES) -> Tensor:
    """Converged radiance: Gauss-Legendre optical depth and view integral, shape (R, W). [W/(m^2 sr nm)]"""
    return render_rays(atm, rays, GaussOpticalDepth(light_samples), view_samples, "gauss")


FIT_RAYS: dict = {
    "sun_zeniths_deg": (20.0, 45.0, 70.0, 80.0, 88.0),
    "view_zeniths_deg": (0.0, 40.0, 70.0, 80.0, 86.0, 89.0, 90.0),
    "relative_azimuths_deg": (0.0, 60.0, 120.0, 180.0),
}
"""Rays of the "radiance" Taylor fit; the errors reported are measured on :func:`radiance_rays`'s
defaults, which share only the zenith and horizontal view zeniths with these."""


class RadianceObjective:
    """Mean squared relative single-scattering radiance error of Taylor (a, b) on rays ("radiance" metric).

    The reference renders the same rays with the same view integral (``view_samples``
    Gauss-Legendre nodes) and float64 Gauss-Legendre optical depth, so only the
    optical depth differs. The renderer is differentiable in (a, b).

    Args:
        atm: the atmosphere.
        rays: the fit rays.
        view_samples: Gauss-Legendre nodes of the view integral. [1]
    """

    separable = False
    metric = "radiance"

    def __init__(self, atm: Atmosphere, rays: RadianceRays, view_samples: int = 64):
        self.atm, self.rays, self.view_samples = atm, rays, int(view_samples)
        self.scale_heights = atm.scale_heights.detach()
        self.reference = radiance_reference(atm, rays, view_samples=self.view_samples)
        if bool((self.reference <= 0).any()):
            raise ValueError("the fit rays' reference radiance must be > 0 (no rays in full shadow)")
        self.evaluations = 0

    def __call__(self, a: Tensor, b: Tensor) -> Tensor:
        """Mean squared relative radiance error, shape (), for a, b of shape () or (K,)."""
        self.evaluations += 1
        r = self.rays
        rad = single_scattering(self.atm, r.r, r.mu, r.mu_s, r.nu, TaylorOpticalDepth(a, b), view_samples=self.view_samples, rule="gauss")
        rel = (rad - self.reference) / self.reference
        return (rel * rel).mean()

    def rms(self, a, b) -> tuple[float, list[float]]:
        """(RMS relative radiance error, []) at fixed (a, b): no per-layer split."""
        T = dict(dtype=self.reference.dtype, device=self.reference.device)
        with torch.no_grad():
            e = self(torch.as_tensor(a, **T), torch.as_tensor(b, **T))
        return math.sqrt(float(e)), []


def relative_radiance_error(radiance: Tensor, reference: Tensor) -> float:
    """max over rays and wavelengths of |L - L_ref| / L_ref. [1]"""
    if bool((reference <= 0).any()):
        raise ValueError("the reference radiance must be > 0 for a relative error (rays in full shadow?)")
    return float(((radiance - reference).abs() / reference).max())


def max_transmittance_error(columns: Tensor, reference: Tensor, extinction: Tensor) -> float:
    """max over points, layers and wavelengths of |exp(-beta c~) - exp(-beta c)|. [1]"""
    beta = extinction.to(dtype=columns.dtype, device=columns.device)
    return float((torch.exp(-columns.unsqueeze(-1) * beta) - torch.exp(-reference.unsqueeze(-1) * beta)).abs().max())


# --------------------------------------------------------------------------
# Spline grid and view samples
# --------------------------------------------------------------------------
def spline_errors(atm: Atmosphere, domain: GalajDomain, column_reference: Tensor, rays: RadianceRays, radiance_ref: Tensor,
                  height_points: int, distance_points: int, kind: str = "natural_cubic",
                  view_samples: int = REFERENCE_VIEW_SAMPLES, radiance: bool = True) -> tuple[float, float]:
    """(max transmittance error on the domain, max relative radiance error) of one spline grid.

    The radiance uses the reference's Gauss view integral with ``view_samples``
    nodes, so that only the spline's error is measured. ``radiance=False`` skips
    it (returns NaN).
    """
    spl = SplineOpticalDepth(height_points=height_points, distance_points=distance_points, kind=kind)
    H = atm.scale_heights.detach()
    with torch.no_grad():
        fn = spl.prepare(H, atm.bottom_radius, atm.top_radius)
        cols = torch.cat([fn(domain.r[i : i + 8192], domain.mu[i : i + 8192], domain.length[i : i + 8192]) for i in range(0, domain.size, 8192)])
    t_err = max_transmittance_error(cols, column_reference, atm.extinction_matrix.detach())
    if not radiance:
        return t_err, math.nan
    rad = render_rays(atm, rays, spl, view_samples, "gauss", column_fn=fn)
    return t_err, relative_radiance_error(rad, radiance_ref)


def select_spline_grid(atm: Atmosphere, domain: GalajDomain, column_reference: Tensor, rays: RadianceRays, radiance_ref: Tensor,
                       radiance_tolerance: float, transmittance_tolerance: float, kind: str = "natural_cubic",
                       height_candidates=HEIGHT_CANDIDATES, distance_candidates=DISTANCE_CANDIDATES,
                       view_samples: int = REFERENCE_VIEW_SAMPLES, assume_monotone: bool = True) -> dict:
    """The spline grid of least height x distance points meeting both tolerances (ties: fewer height points).

    Rows of distance points M are scanned in ascending order; in each, the
    height points N that could still beat the best grid so far ascend until the
    first grid that passes. With ``assume_monotone`` a row is first tried at its
    largest such N and skipped when that fails (errors fall with N in every row
    measured, docs/integrator_calibration.md). The result's two neighbours one
    step smaller (previous N, previous M) are then evaluated; should one pass,
    contradicting the assumption, the search is redone exhaustively, in which
    every grid with fewer points than the result is evaluated and fails.

    Returns:
        {"height_points", "distance_points", "kind", "transmittance_error", "radiance_error", "passed",
         "neighbours", "evaluated": [[N, M, transmittance error, radiance error or None, passed], ...]};
        None values and "passed": False where no candidate meets the tolerances.
    """
    hc, dc = sorted(int(x) for x in height_candidates), sorted(int(x) for x in distance_candidates)
    cache: dict[tuple[int, int], list] = {}

    def evaluate(n: int, m: int) -> list:
        if (n, m) not in cache:
            te, _ = spline_errors(atm, domain, column_reference, rays, radiance_ref, n, m, kind, view_samples, radiance=False)
            re = None
            ok = te <= transmittance_tolerance
            if ok:
                _, re = spline_errors(atm, domain, column_reference, rays, radiance_ref, n, m, kind, view_samples)
                ok = re <= radiance_tolerance
            cache[(n, m)] = [n, m, te, re, bool(ok)]
        return cache[(n, m)]

    def search(monotone: bool):
        best = None
        for m in dc:
            row = [n for n in hc if best is None or (n * m, n) < (best[0] * best[1], best[0])]
            if not row:
                break  # later rows have more distance points: none can beat the best
            if monotone and not evaluate(row[-1], m)[4]:
                continue
            for n in row:
                if evaluate(n, m)[4]:
                    best = cache[(n, m)]
                    break
        return best

    best = search(assume_monotone)
    neighbours = []
    if best is not None:
        i, j = hc.index(best[0]), dc.index(best[1])
        neighbours = [evaluate(hc[i - 1], best[1])] if i > 0 else []
        neighbours += [evaluate(best[0], dc[j - 1])] if j > 0 else []
        if any(nb[4] for nb in neighbours):
            best = search(False)
            i, j = hc.index(best[0]), dc.index(best[1])
            neighbours = ([evaluate(hc[i - 1], best[1])] if i > 0 else []) + ([evaluate(best[0], dc[j - 1])] if j > 0 else [])
    out = {"kind": kind, "transmittance_tolerance": transmittance_tolerance, "radiance_tolerance": radiance_tolerance,
           "height_candidates": hc, "distance_candidates": dc, "neighbours": neighbours, "evaluated": list(cache.values())}
    if best is None:
        out.update(height_points=None, distance_points=None, transmittance_error=None, radiance_error=None, passed=False)
    else:
        out.update(height_points=best[0], distance_points=best[1], transmittance_error=best[2], radiance_error=best[3], passed=True)
    return out


def view_sample_errors(atm: Atmosphere, rays: RadianceRays, radiance_ref: Tensor, view_samples: int, rule: str = "trapezoid",
                       light_samples: int = REFERENCE_LIGHT_SAMPLES) -> float:
    """Max relative radiance error of ``view_samples`` outer samples with the reference optical depth. [1]"""
    rad = render_rays(atm, rays, GaussOpticalDepth(light_samples), view_samples, rule)
    return relative_radiance_error(rad, radiance_ref)


def select_view_samples(atm: Atmosphere, rays: RadianceRays, radiance_ref: Tensor, radiance_tolerance: float,
                        rule: str = "trapezoid", candidates=VIEW_CANDIDATES, light_samples: int = REFERENCE_LIGHT_SAMPLES) -> dict:
    """The least view-sample count (ascending scan of ``candidates``) whose radiance error meets the tolerance.

    Returns:
        {"view_samples", "rule", "radiance_error", "passed", "evaluated": [[N, error], ...]}.
    """
    evaluated = []
    for n in sorted(int(c) for c in candidates):
        e = view_sample_errors(atm, rays, radiance_ref, n, rule, light_samples)
        evaluated.append([n, e])
        if e <= radiance_tolerance:
            return {"view_samples": n, "rule": rule, "radiance_error": e, "passed": True, "evaluated": evaluated}
    return {"view_samples": None, "rule": rule, "radiance_error": None, "passed": False, "evaluated": evaluated}


# --------------------------------------------------------------------------
# Everything for one atmosphere
# --------------------------------------------------------------------------
def _fit_dict(fit: TaylorFit) -> dict:
    return {"a": fit.a, "b": fit.b, "error": fit.error, "layer_error": fit.layer_error, "seconds": fit.seconds,
            "evaluations": fit.evaluations}


def calibrate_integrators(
    atm: Atmosphere,
    tolerance: float = TOLERANCE_DEFAULT,
    transmittance_tolerance: float = TRANSMITTANCE_TOLERANCE_DEFAULT,
    metric: str = "transmittance",
    n_d: int = 101,
    n_t: int = 100,
    d_spacing: str = "view",
    view_rule: str = "trapezoid",
    spline_kind: str = "natural_cubic",
    rays: RadianceRays | dict | None = None,
    fit_rays: RadianceRays | dict | None = None,
    height_candidates=HEIGHT_CANDIDATES,
    distance_candidates=DISTANCE_CANDIDATES,
    view_candidates=VIEW_CANDIDATES,
    spline: bool = True,
) -> dict:
    """Taylor (a, b), spline grid and view samples for ``atm``, as the JSON of ``skyfit calibrate-integrator``.

    Args:
        atm: the atmosphere; give it in float64 (references are computed in its dtype).
        tolerance: relative radiance tolerance, split in halves between the spline
            grid and the view samples (module docstring). [1]
        transmittance_tolerance: max per-layer transmittance error of the spline. [1]
        metric, n_d, n_t, d_spacing: the Taylor objective (:func:`layer_errors`, :func:`galaj_domain`).
        view_rule: outer quadrature rule of the view samples.
        spline_kind: spline kind of the grid search.
        rays: radiance evaluation rays (spline, view samples, reported Taylor radiance errors),
            or keyword arguments of :func:`radiance_rays` (default: its defaults).
        fit_rays: rays of the "radiance" metric's fit (default :data:`FIT_RAYS`).
        spline: False skips the spline grid (e.g. while the spline module is unavailable).

    Returns:
        A JSON-ready dict (docs/integrator_calibration.md describes the fields).
    """
    if not (0 < tolerance < 1) or not (0 < transmittance_tolerance < 1):
        raise ValueError(f"tolerances must lie in (0, 1), got {tolerance} and {transmittance_tolerance}")
    if atm.dtype != torch.float64:
        raise ValueError(f"calibrate in float64: the references need it, got an atmosphere in {atm.dtype}")
    _validate("metric", metric, CALIBRATION_METRICS)
    domain = galaj_domain(atm.bottom_radius, atm.top_radius, n_d, n_t, d_spacing, atm.dtype, atm.device)
    column_ref = reference_columns(domain, atm.scale_heights.detach())
    if metric == "radiance":
        obj = RadianceObjective(atm, fit_rays if isinstance(fit_rays, RadianceRays) else radiance_rays(atm, **(fit_rays or FIT_RAYS)))
    else:
        obj = TaylorObjective(atm, domain, metric, column_ref)
    k = obj.scale_heights.shape[0]
    default_err, default_layer = obj.rms(TAYLOR_A_DEFAULT, TAYLOR_B_DEFAULT)
    shared = fit_taylor(obj, per_layer=False)
    per_layer = fit_taylor(obj, per_layer=True)
    names = LAYER_NAMES[:k]
    layer = lambda errs, i: errs[i] if errs else None  # noqa: E731  (the radiance metric has no per-layer split)
    taylor = {
        "a": shared.a[0],
        "b": shared.b[0],
        "error": shared.error,
        "layer_error": dict(zip(names, shared.layer_error)) if shared.layer_error else None,
        "default_a": TAYLOR_A_DEFAULT,
        "default_b": TAYLOR_B_DEFAULT,
        "default_error": default_err,
        "default_layer_error": dict(zip(names, default_layer)) if default_layer else None,
        "per_layer": {nm: {"a": per_layer.a[i], "b": per_layer.b[i], "error": layer(per_layer.layer_error, i),
                            "default_error": layer(default_layer, i), "scale_height_m": float(obj.scale_heights[i])}
                      for i, nm in enumerate(names)},
        "per_layer_error": per_layer.error,
        "fit": {"method": "Adam then L-BFGS on a = sigmoid(theta_a), b = sigmoid(theta_b), from (0.45, 0.45)",
                "shared_seconds": shared.seconds, "per_layer_seconds": per_layer.seconds,
                "shared_evaluations": shared.evaluations, "per_layer_evaluations": per_layer.evaluations},
    }

    if not isinstance(rays, RadianceRays):
        rays = radiance_rays(atm, **(rays or {}))
    rad_ref = radiance_reference(atm, rays)
    rad_ref_half = radiance_reference(atm, rays, REFERENCE_LIGHT_SAMPLES // 2, REFERENCE_VIEW_SAMPLES // 2)
    view = select_view_samples(atm, rays, rad_ref, 0.5 * tolerance, view_rule, view_candidates)

    taylor_rad = {}
    for label, a, b in (("default", TAYLOR_A_DEFAULT, TAYLOR_B_DEFAULT), ("shared", shared.a[0], shared.b[0]),
                        ("per_layer", per_layer.a, per_layer.b)):
        rad = render_rays(atm, rays, TaylorOpticalDepth(a, b), REFERENCE_VIEW_SAMPLES, "gauss")
        rel = (rad - rad_ref) / rad_ref
        taylor_rad[label] = {"max": float(rel.abs().max()), "rms": float(rel.pow(2).mean().sqrt())}
    taylor["radiance_error"] = taylor_rad

    out = {
        "atmosphere": atm.name,
        "metric": METRIC_DESCRIPTIONS[metric],
        "metric_name": metric,
        "tolerance": tolerance,
        "transmittance_tolerance": transmittance_tolerance,
        "taylor": taylor,
        "view_samples": view["view_samples"],
        "view": view,
        "domain": {"n_d": n_d, "n_t": n_t, "d_spacing": d_spacing, "points": domain.size},
        "reference": {
            "columns": f"gauss, {REFERENCE_COLUMN_SAMPLES} nodes, float64",
            "radiance": f"gauss optical depth {REFERENCE_LIGHT_SAMPLES} nodes, gauss view integral {REFERENCE_VIEW_SAMPLES} nodes, float64",
            "radiance_convergence": relative_radiance_error(rad_ref_half, rad_ref),
        },
        "rays": rays.description,
        "wavelengths_nm": atm.wavelengths.tolist(),
    }
    if spline:
        sp = select_spline_grid(atm, domain, column_ref, rays, rad_ref, 0.5 * tolerance, transmittance_tolerance, spline_kind,
                                height_candidates, distance_candidates)
        if sp["passed"] and view["passed"]:
            spl = SplineOpticalDepth(height_points=sp["height_points"], distance_points=sp["distance_points"], kind=spline_kind)
            rad = render_rays(atm, rays, spl, view["view_samples"], view_rule)
            sp["combined_radiance_error"] = relative_radiance_error(rad, rad_ref)
        out["spline"] = sp
    return out
