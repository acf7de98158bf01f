"""Single scattering of a batch of atmospheres along fixed rays: a leading "walker" axis B.

:class:`skyfit.fit.batched.BatchedLikelihood` evaluates the sky of B parameter vectors
(emcee's half-ensemble) in one torch pass over the same rays. This module holds the
physics it needs, split into what the atmosphere's coefficients do not change (built once
per set of rays: :class:`RayGeometry`) and what they do (:func:`batched_single_scattering`
with :class:`BatchCoefficients`, B rows).

It mirrors :mod:`skyfit.scattering.single` (Bruneton & Neyret 2008 eqs. 1-7; Gałaj 2019
eq. 9) operation for operation, in the same order, so that each row equals
:func:`skyfit.scattering.single_scattering` of that row's atmosphere to rounding
(tests/test_sample.py checks the log-likelihood to 1e-10):

===============================  ==============================================================
here                             mirrors
===============================  ==============================================================
:func:`column_up`                :func:`skyfit.transmittance.chapman.chapman_column_up`
:class:`ChapmanColumns`          :func:`skyfit.transmittance.chapman.chapman_segment_column`
:class:`QuadratureColumns`       :class:`skyfit.transmittance.quadrature.QuadratureOpticalDepth`
:class:`LayerColumns`            the integrator's ``column_fn`` of
                                 :func:`skyfit.scattering.single.path_columns`, one layer at a time
:class:`RayGeometry`             :func:`skyfit.scattering.single.view_ray_samples` and the
                                 geometry of ``_render_chunk`` (sun rays, ground, ozone columns)
:func:`batched_single_scattering`  ``skyfit.scattering.single._render_chunk`` (no sun disc)
===============================  ==============================================================

Only the scale heights H enter the columns; they are the one atmospheric quantity
inside the geometry, so columns take H as a batched argument and layers whose H is
fixed are computed once. Supported integrators: ``chapman`` and the quadratures
(``gauss``, ``trapezoid``, ``midpoint``, ``simpson``).
"""
from __future__ import annotations

import dataclasses
import math

import torch
from torch import Tensor

from ..atmosphere import Atmosphere
from ..geometry import distance_to_top, point_along_ray, safe_sqrt, sun_cosine_along_ray
from ..quadrature import nodes_weights
from ..transmittance import ozone_column
from ..transmittance.chapman import ChapmanOpticalDepth, segment_geometry
from ..transmittance.quadrature import QuadratureOpticalDepth
from .phase import mie_phase, rayleigh_phase
from .single import ray_parameters, sun_ray_cosine, sun_visible_fraction, view_ray_samples


# -- columns of segments with the scale height as a batched argument ----------------------------
def column_up(h: Tensor, r: Tensor, mu: Tensor, H: Tensor) -> Tensor:
    """Fitzmaurice 1964 column to infinity (as :func:`skyfit.transmittance.chapman.chapman_column_up`). [m]

    Args:
        h, r, mu: altitude [m], radius [m], zenith cosine >= 0 [1], shape S (broadcastable with H).
        H: scale heights, shape broadcastable against S (e.g. (B, 1, ..., 1)). [m]

    Returns:
        The column of a unit-density exponential layer, shape broadcast(S, H). [m]
    """
    X = r / H
    return H * torch.exp(-h / H) * math.sqrt(math.pi / 2.0) * torch.sqrt(X) * torch.special.erfcx(torch.sqrt(X / 2.0) * mu)


@dataclasses.dataclass
class ChapmanColumns:
    """Arguments of :func:`skyfit.transmittance.chapman.chapman_segment_column` for fixed segments.

    The three column terms A (start), B (end) and the tangent term are evaluated only
    where the branch that uses them occurs; ``a`` may have a smaller (broadcastable)
    shape than the segments (e.g. one start per view ray).

    Attributes:
        a: (altitude [m], radius [m], |mu| [1]) of the segment starts, shape S or broadcastable.
        b: the same for the segment ends, shape S.
        t: (altitude [m], radius [m]) of the tangent points, None when no segment passes one.
        up: the segment goes up (shape S, bool).
        before: the segment ends before its tangent point (shape S, bool).
        all_up: every segment goes up (the A - B branch only).
    """

    a: tuple[Tensor, Tensor, Tensor]
    b: tuple[Tensor, Tensor, Tensor]
    t: tuple[Tensor, Tensor] | None
    up: Tensor
    before: Tensor
    all_up: bool

    @classmethod
    def build(cls, r: Tensor, mu: Tensor, length: Tensor, bottom_radius: float, start_shape=None) -> "ChapmanColumns":
        """Segments from radius r [m] with zenith cosine mu [1] and length [m] (broadcastable, shape S).

        ``start_shape``: truthy when every segment of a row (last axis) starts at the same point,
        so that one start per row is kept.
        """
        rb, mub, lb = torch.broadcast_tensors(r, mu, length)
        g = segment_geometry(rb, mub, lb, bottom_radius)
        a_mu = torch.where(g.up, mub, -mub)
        if start_shape is not None:  # every segment of a row starts at the same point: keep one per row
            a = tuple(t[..., :1] for t in (g.h, rb, a_mu))
        else:
            a = (g.h, rb, a_mu)
        b = (g.h_d, g.r_d, torch.where(g.before, -g.mu_d, g.mu_d))
        t = (g.h_t, g.r_t) if bool(g.through.any()) else None
        up, before = g.up, g.before
        return cls(a, b, t, up, before, bool(up.all()))

    def column(self, H: Tensor) -> Tensor:
        """Column for scale height(s) H, shape H's batch shape + segment shape S. [m]

        Args:
            H: shape (B, 1, ..., 1) with as many trailing ones as the segments have dims, or (). [m]
        """
        a = column_up(*self.a, H)
        b = column_up(*self.b, H)
        if self.all_up:
            return a - b
        t = column_up(self.t[0], self.t[1], torch.zeros_like(self.t[1]), H) if self.t is not None else torch.zeros_like(b)
        return torch.where(self.up, a - b, torch.where(self.before, b - a, 2.0 * t - a - b))


@dataclasses.dataclass
class QuadratureColumns:
    """Quadrature column sum_m w_m exp(-alt_m / H) L (as :class:`QuadratureOpticalDepth`) at fixed altitudes.

    Attributes:
        alt: altitudes of the M inner samples of each segment, shape S + (M,). [m]
        w: the rule's weights on [0, 1], shape (M,). [1]
        length: segment lengths, shape S. [m]
    """

    alt: Tensor
    w: Tensor
    length: Tensor

    @classmethod
    def build(cls, integ: QuadratureOpticalDepth, r: Tensor, mu: Tensor, length: Tensor, bottom_radius: float,
              start_shape=None) -> "QuadratureColumns":
        """Segments from radius r [m] with zenith cosine mu [1] and length [m] (broadcastable, shape S);
        ``start_shape`` is accepted for symmetry with :meth:`ChapmanColumns.build` and unused."""
        x, w = nodes_weights(integ.name, integ.samples, r.dtype, r.device)
        r_, mu_, L_ = (t.unsqueeze(-1) for t in torch.broadcast_tensors(r, mu, length))
        s = L_ * x
        alt = safe_sqrt(r_ * r_ + 2.0 * r_ * mu_ * s + s * s) - bottom_radius
        return cls(alt, w, L_.squeeze(-1))

    def column(self, H: Tensor) -> Tensor:
        """Column for scale height(s) H of shape (B, 1, ..., 1) or (), shape H's batch shape + S. [m]"""
        dens = torch.exp(-self.alt / H.unsqueeze(-1))  # (B, ..., M)
        return (dens * self.w).sum(-1) * self.length


def column_plan(integ, r: Tensor, mu: Tensor, length: Tensor, bottom_radius: float,
                start_shape=None) -> ChapmanColumns | QuadratureColumns:
    """The fixed-segment column evaluator of ``integ`` (``chapman`` or a quadrature) for these segments."""
    if isinstance(integ, ChapmanOpticalDepth):
        return ChapmanColumns.build(r, mu, length, bottom_radius, start_shape)
    return QuadratureColumns.build(integ, r, mu, length, bottom_radius, start_shape)


class LayerColumns:
    """Columns (B, *S, K) of K layers along fixed segments; layers with a fixed scale height are cached.

    Args:
        plan: a :func:`column_plan` of the segments (shape S).
        fixed_heights: scale height [m] of each layer index whose H is the same for every row.
        K: number of layers (2: Rayleigh, Mie).
        ndim: number of segment dims, len(S).
    """

    def __init__(self, plan, fixed_heights: dict[int, float], K: int, ndim: int):
        self.plan, self.K, self.ndim = plan, K, ndim
        self.cache: dict[int, Tensor] = {}
        self.fixed = fixed_heights

    def __call__(self, H: Tensor) -> Tensor:
        """H: (B, K) scale heights [m] -> columns (B, *S, K) [m]."""
        B = H.shape[0]
        out = []
        for k in range(self.K):
            if k in self.fixed:
                if k not in self.cache:
                    self.cache[k] = self.plan.column(H.new_tensor(self.fixed[k]))
                c = self.cache[k]
                out.append(c.expand(B, *c.shape))
            else:
                out.append(self.plan.column(H[:, k].reshape(B, *([1] * self.ndim))))
        return torch.stack(out, -1)


# -- the rays' fixed geometry and the batched radiance -------------------------------------------
@dataclasses.dataclass
class BatchCoefficients:
    """Per-row atmosphere coefficients (B rows, W wavelengths, K = 2 layers: Rayleigh, Mie)."""

    rayleigh_scattering: Tensor  # (B, W) [1/m]
    mie_extinction: Tensor  # (B, W) [1/m]
    mie_scattering: Tensor  # (B, W) [1/m]
    mie_g: Tensor  # (B,) [1]
    ground_albedo: Tensor  # (B, W) [1]
    scale_heights: Tensor  # (B, K) [m]

    @property
    def extinction_matrix(self) -> Tensor:
        """(B, K, W) rows (Rayleigh, Mie), as :attr:`Atmosphere.extinction_matrix`. [1/m]"""
        return torch.stack([self.rayleigh_scattering, self.mie_extinction], 1)


class RayGeometry:
    """Everything about n view rays that the coefficients (and scale heights, via cached columns) do not change.

    The observer at ``altitude`` looks along ``view`` with the sun along ``sun`` (unit
    vectors in the local East-North-Up frame, as :func:`skyfit.render.sky.render_vectors`
    takes them). Built once; :func:`batched_single_scattering` then renders any batch
    of coefficients on these rays.

    Args:
        atm: the atmosphere whose radii, sun size, Mie phase model and ozone (not fitted) are used.
        view: unit view directions, shape (n, 3). [1]
        sun: unit direction to the sun, shape (3,) or (n, 3). [1]
        altitude: observer height above the ground. [m]
        integrator: ``chapman`` or a quadrature optical-depth integrator.
        view_samples: N, nodes of the outer (view-ray) integral.
        rule: outer quadrature rule (trapezoid, midpoint, simpson, gauss).
        fixed_heights: scale height [m] of each layer index (0 Rayleigh, 1 Mie) that is the same for every row.

    Attributes (n rays, N samples each):
        view_cols, sun_cols: :class:`LayerColumns` observer -> sample and sample -> top of atmosphere, S = (n, N).
        ozone: the atmosphere has ozone; then ``oz_j`` (n, N) is its column along both [m] and
            ``ozone_row`` (W,) its absorption at peak density [1/m].
        alt_j: sample altitudes (n, N). [m]
        wvis: outer weight x segment length x visible sun fraction, (n, N). [m]
        nu: view-sun cosines (n,); p_r: Rayleigh phase (n, 1) [1/sr].
        hits, ground: rays that end on the ground (n,), and whether any does; then ``g_cols`` and
            ``gs_cols`` (S = (n,)) are the columns to the ground point and from it to the sun,
            ``e_g_factor`` (n, 1) its visible sun fraction x cos(sun zenith), and with ozone
            ``oz_g``, ``oz_gs`` (n,) the ozone columns of those two paths [m].
        n, N: number of rays and of samples per ray.
    """

    def __init__(self, atm: Atmosphere, view: Tensor, sun: Tensor, altitude, integrator, view_samples: int, rule: str,
                 fixed_heights: dict[int, float]):
        r, mu, mu_s, nu = ray_parameters(atm, view, sun, altitude)
        r, mu, mu_s, nu = (t.reshape(-1) for t in torch.broadcast_tensors(r, mu, mu_s, nu))
        Rb, Rt = atm.bottom_radius, atm.top_radius
        x, w = nodes_weights(rule, view_samples, atm.dtype, atm.device)
        hits, seg, r0, mu0, mus0, s, r_j, mus_j = view_ray_samples(atm, r, mu, mu_s, nu, x)
        r0e, mu0e = r0.unsqueeze(-1), mu0.unsqueeze(-1)
        mus_c = sun_ray_cosine(r_j, mus_j, Rb)
        K = 2
        self.view_cols = LayerColumns(column_plan(integrator, r0e, mu0e, s, Rb, start_shape=True), fixed_heights, K, 2)
        self.sun_cols = LayerColumns(column_plan(integrator, r_j, mus_c, distance_to_top(r_j, mus_c, Rt), Rb), fixed_heights, K, 2)
        # Ozone (when the atmosphere has it): its exact tent-layer column is geometry only (the ozone
        # spectrum is not fitted), appended as the last column as skyfit.scattering.single.path_columns does.
        self.ozone = atm.ozone_absorption is not None
        if self.ozone:
            oz = lambda r_, mu_, l_: ozone_column(r_, mu_, l_, Rb, atm.ozone_layer_m)  # noqa: E731
            ov = oz(r0e, mu0e, s)
            self.oz_j = (ov.expand(r_j.shape) if ov.shape != r_j.shape else ov) + oz(r_j, mus_c, distance_to_top(r_j, mus_c, Rt))
            self.ozone_row = atm.ozone_absorption
        vis = sun_visible_fraction(r_j, mus_j, Rb, atm.sun_angular_radius)
        self.alt_j = r_j - Rb  # (n, N)
        self.wvis = vis * (w * seg.unsqueeze(-1))  # (n, N)
        self.nu = nu
        self.p_r = rayleigh_phase(nu).unsqueeze(-1)  # (n, 1)
        self.mie_phase = atm.mie_phase
        self.hits = hits
        self.ground = bool(hits.any())
        if self.ground:
            self.hitsf = hits.unsqueeze(-1)
            self.g_cols = LayerColumns(column_plan(integrator, r0, mu0, seg, Rb), fixed_heights, K, 1)
            r_g = torch.full_like(r, Rb)
            mus_g = sun_cosine_along_ray(r0, mus0, nu, seg, torch.clamp_min(point_along_ray(r0, mu0, seg)[0], Rb))
            mu_c = sun_ray_cosine(r_g, mus_g, Rb)
            self.gs_cols = LayerColumns(column_plan(integrator, r_g, mu_c, distance_to_top(r_g, mu_c, Rt), Rb), fixed_heights, K, 1)
            vis_g = sun_visible_fraction(r_g, mus_g, Rb, atm.sun_angular_radius)
            self.e_g_factor = vis_g.unsqueeze(-1) * torch.clamp_min(mus_g, 0.0).unsqueeze(-1)  # (n, 1)
            if self.ozone:
                self.oz_g = oz(r0, mu0, seg)
                self.oz_gs = oz(r_g, mu_c, distance_to_top(r_g, mu_c, Rt))
        self.n, self.N = r_j.shape


def batched_single_scattering(geo: RayGeometry, c: BatchCoefficients, solar_irradiance: Tensor) -> Tensor:
    """Single-scattering radiance of every row of ``c`` on the rays of ``geo`` (no sun disc).

    The same operations, in the same order, as ``skyfit.scattering.single._render_chunk``
    with ``ground=True, sun_disk=False``, with the row axis B in front.

    Args:
        geo: the rays.
        c: B rows of coefficients.
        solar_irradiance: extraterrestrial solar spectral irradiance, shape (W,). [W/(m^2 nm)]

    Returns:
        shape (B, n, W). [W/(m^2 sr nm)]
    """
    B = c.mie_g.shape[0]
    ext = c.extinction_matrix  # (B, K, W)
    H = c.scale_heights
    col = geo.view_cols(H) + geo.sun_cols(H)  # (B, n, N, K)
    n, N = geo.n, geo.N
    if geo.ozone:  # (B, n, N, K + 1) and (B, K + 1, W): ozone last (skyfit.scattering.single.path_extinction)
        col = torch.cat([col, geo.oz_j.expand(B, n, N).unsqueeze(-1)], -1)
        ext = torch.cat([ext, geo.ozone_row.expand(B, 1, -1)], 1)
    W = ext.shape[-1]
    trans = torch.matmul(col.reshape(B, n * N, -1), -ext).exp_().reshape(B * n, N, W)
    dens = torch.exp(geo.alt_j.unsqueeze(-1) * -(1.0 / H)[:, None, None, :])  # (B, n, N, K)
    wd = dens * geo.wvis.unsqueeze(-1)
    ray_int = torch.bmm(wd.reshape(B * n, N, -1).transpose(1, 2), trans).reshape(B, n, -1, W)  # (B, n, K, W)
    p_m = mie_phase(geo.nu, c.mie_g[:, None], geo.mie_phase).unsqueeze(-1)  # (B, n, 1)
    rad = ray_int[:, :, 0] * c.rayleigh_scattering[:, None] * geo.p_r + ray_int[:, :, 1] * c.mie_scattering[:, None] * p_m
    rad = rad * solar_irradiance
    if geo.ground:
        cg, cgs = geo.g_cols(H), geo.gs_cols(H)
        if geo.ozone:
            cg = torch.cat([cg, geo.oz_g.expand(B, n).unsqueeze(-1)], -1)
            cgs = torch.cat([cgs, geo.oz_gs.expand(B, n).unsqueeze(-1)], -1)
        t_g = torch.exp(-torch.matmul(cg, ext))  # (B, n, W)
        e_g = torch.exp(-torch.matmul(cgs, ext)) * geo.e_g_factor
        rad = rad + geo.hitsf * t_g * c.ground_albedo[:, None] / math.pi * e_g * solar_irradiance
    return rad
