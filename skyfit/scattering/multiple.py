"""Precomputed multiple scattering (Bruneton & Neyret 2008, Algorithm 4.1), differentiable in torch.

Tables (parametrisation in :mod:`.bruneton_tables`, after Bruneton's 2017 reference
implementation):

=============================  ======================  ==========================================
table                          shape                   content
=============================  ======================  ==========================================
``transmittance_columns``      (64 r, 256 mu, 3)       optical length to the top of the atmosphere
                                                       of the Rayleigh, Mie and ozone profiles [m]
``direct_irradiance``          (16 r, 64 mu_s, W)      Delta E after 0 bounces [W/(m^2 nm)]
``irradiance``                 (16 r, 64 mu_s, W)      sum of Delta E, orders 1..N-1 [W/(m^2 nm)]
``single_rayleigh``/``_mie``   (32, 128, 32, 8, W)     single scattering without phase function
                                                       [W/(m^2 nm)]
``multiple``                   (32, 128, 32, 8, W)     sum of Delta S, orders 2..N [W/(m^2 sr nm)]
=============================  ======================  ==========================================

Choices, with their reasons:

- *Transmittance as optical length.* 2017 stores T(r, mu) per wavelength; we store the
  three columns (Rayleigh, Mie, ozone tent), so ``T = exp(-columns @ [beta_R; beta_M^e;
  beta_O3])``. Lookups cost the same for any W, interpolation is log-linear in T, and the
  extinction coefficients enter exactly (their gradients need no table). T(x, y) between
  two points is ``exp(-(c(x) - c(y)) @ beta)``, 2008's T(x, v) / T(y, v).
- *Mie storage.* Single Rayleigh and single Mie are separate tables (2017's
  non-combined option, 2008 Sec. 4 "Angular precision"), both without phase function,
  which is applied at lookup (2017 ``GetSkyRadiance``). Orders >= 2 are stored as
  radiance, phase functions included, in their own table (2017 adds them to the
  Rayleigh table divided by P_R(nu); separate storage gives ``orders=1`` for free).
- *Scattering density Delta J* (2017 ``ComputeScatteringDensity``): the incident
  radiance at (r, mu_s) does not depend on the view direction, so we sample the
  16 x 32 incident directions in a frame aligned with the sun, evaluate the incident
  radiance once per (r, mu_s) and get Delta J for all (mu, nu) with one matrix product
  by the phase matrix. Same midpoint rule in (theta, phi) as 2017 (whose phi origin is
  the view's azimuth rather than the sun's).
- *Order bookkeeping* follows 2017 ``Model::Precompute``: S and Delta S exclude paths
  whose last bounce is on the ground; Delta J of order n adds the ground bounce of
  Delta E of order n - 2; the render adds T alpha / pi (E_direct + E) for rays that hit
  the ground, with the albedo of the atmosphere passed at render time.
- *Autograd.* Every table is a differentiable function of the Atmosphere's tensors.
  Work is done in chunks of texels; when gradients are needed each chunk runs under
  ``torch.utils.checkpoint`` (non-reentrant), so the graph keeps only the tables
  (inputs and outputs of each order) and the backward pass recomputes one chunk at a
  time: memory stays O(tables + one chunk) for any number of orders.
"""
from __future__ import annotations

import dataclasses
import math
import sys
import time
from typing import Callable, NamedTuple

import torch
import torch.nn.functional as F
from torch import Tensor
from torch.utils.checkpoint import checkpoint
from tqdm import tqdm

from ..atmosphere import Atmosphere
from ..atmosphere.profiles import profile_densities
from ..geometry import distance_to_bottom, distance_to_top, ray_hits_ground, safe_sqrt
from ..quadrature import nodes_weights
from .bruneton_tables import (
    MU_S_MIN_DEFAULT,
    ScatteringTexels,
    TableSizes,
    corner_plan,
    extinction_matrix3,
    grid_coordinate,
    interpolate,
    interpolate_planned,
    irradiance_index,
    irradiance_texel_params,
    FULL_MU_S,
    mu_s_index,
    mu_s_window,
    scattering_index,
    scattering_texel_params,
    transmittance_index,
    transmittance_texel_params,
)
from .phase import atmosphere_mie_phase, rayleigh_phase, spectral_mie_phase
from .single import sun_visible_fraction

BELOW_MU_S_MIN = ("raise", "clamp", "zero")


class SunBelowTables(ValueError):
    """:func:`sky_radiance` asked for a sun lower than its tables reach (``below_mu_s_min="raise"``): ``mu_s`` the
    lowest sun zenith cosine asked, ``mu_s_min`` the tables'. A ValueError, so callers that catch those still do; the
    CLI says it in its own terms."""

    def __init__(self, mu_s: float, mu_s_min: float):
        self.mu_s, self.mu_s_min = mu_s, mu_s_min
        super().__init__(f"sun zenith cosine {mu_s:.4f} at the observer is below the tables' mu_s_min = {mu_s_min}; "
                         "precompute with a lower mu_s_min or pass below_mu_s_min='clamp' or 'zero'")


@dataclasses.dataclass(frozen=True)
class Quadrature:
    """Fixed sample counts of the precomputation integrals (Bruneton 2017 defaults).

    Attributes:
        transmittance_samples: trapezoid intervals for the optical length (2017: 500).
        single_samples: trapezoid intervals along the view ray for single scattering (50).
        multiple_samples: same for Delta S of orders >= 2 (50).
        density_theta, density_phi: midpoint rule over the sphere for Delta J, theta in
            [0, pi], phi in [0, 2 pi] (2017: 16 x 32).
        density_zenith: the first this many of the ``density_theta`` bands from the zenith are each
            split in two (2017: 0, none). A view near the zenith has the forward peak of a hazy
            aerosol's phase (g 0.8) at the grid's pole, where the midpoint rule's nearest nodes sit
            half a band away on one ring: 16 x 32 put a hazy sky's orders >= 2 16 % high at the zenith
            (sun at 23 deg), 2 split bands (576 directions instead of 512) within 1 %, as 32 x 32 (1024)
            does (docs/multiple_scattering.md, "The density directions' pole").
        irradiance_theta, irradiance_phi: midpoint rule over the upper hemisphere for the
            indirect irradiance, theta in [0, pi/2] (2017: 16 x 64).
        ray_rule: the rule of the two view-ray integrals (single scattering and Delta S), on
            ``single_samples + 1`` and ``multiple_samples + 1`` nodes: ``"trapezoid"`` (2017's,
            equal steps) or ``"gauss"`` (Gauss-Legendre, whose nodes crowd at both ends of the ray,
            where a ground observer's ray crosses the aerosol layer and a downward ray ends in it:
            :func:`ray_nodes`).
    """

    transmittance_samples: int = 500
    single_samples: int = 50
    multiple_samples: int = 50
    density_theta: int = 16
    density_phi: int = 32
    density_zenith: int = 0
    irradiance_theta: int = 16
    irradiance_phi: int = 64
    ray_rule: str = "trapezoid"

    def __post_init__(self) -> None:
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            if f.name == "ray_rule":
                if v not in RAY_RULES:
                    raise ValueError(f"Quadrature.ray_rule must be one of {', '.join(RAY_RULES)}, got {v!r}")
            elif f.name == "density_zenith":
                if not isinstance(v, int) or isinstance(v, bool) or not 0 <= v <= self.density_theta:
                    raise ValueError(f"Quadrature.density_zenith must be an integer in [0, density_theta], got {v!r}")
            elif not isinstance(v, int) or v < 1:
                raise ValueError(f"Quadrature.{f.name} must be a positive integer, got {v!r}")

    @property
    def density_directions(self) -> tuple[int, int, int]:
        """(density_theta, density_phi, density_zenith): the form of ``SkyModel.density_directions`` and
        ``fit.density_directions``."""
        return (self.density_theta, self.density_phi, self.density_zenith)


RAY_RULES = ("trapezoid", "gauss")

ACCURATE_QUADRATURE = Quadrature(ray_rule="gauss", density_zenith=2)
"""2017's sample counts with Gauss-Legendre view rays and the two density bands nearest the zenith split (12.5 % more
density directions; a build 1.1-1.3x 2017's): what skyfit's one-sun renders, photo fits and the error budget's
reference use, and the LUT exports and every fit's Bruneton tables (fit.ray_rule, fit.density_directions) since
session 20. 2017's equal steps along the view ray put a hazy sky's orders >= 2 1.4-2.2x too high (docs/photos.md,
"The view ray's rule"); against 32 x 64 density directions this rule is within about 1 % (docs/luts.md, "The view-ray
rule of an exported LUT"; docs/uncertainty.md, "The reference's view-ray rule")."""


def ray_nodes(n: int, rule: str, dtype, device) -> tuple[Tensor, Tensor]:
    """n + 1 nodes on [0, 1] and their weights for a view ray's integral (:attr:`Quadrature.ray_rule`).

    The trapezoid's equal steps under-resolve an exponential layer much thinner than the ray: a ground
    observer's ray at 10 deg elevation runs ~340 km to the top in 50 steps of 6.8 km while it leaves a
    1.2 km aerosol layer within ~7 km, and the trapezoid's sum of a decay exp(-d/L) in steps h is
    (h/2L) coth(h/2L) times the integral (+8 % at h = L, +31 % at h = 2L). Gauss-Legendre's nodes crowd at
    both ends (the first at ~1.4/(n+1)^2 of the ray, 0.2 km there), where such layers sit."""
    if rule == "trapezoid":
        return _trapezoid(n, dtype, device)
    # Gauss-Legendre: numpy's leggauss mapped to [0, 1], cached by skyfit.quadrature (a build asked for them ~300
    # times, once per chunk: 6 % of a photo fit's build, docs/benchmarks.md "Third pass: the Gauss nodes cached")
    return nodes_weights("gauss", n + 1, dtype, device)


@dataclasses.dataclass
class PrecomputedAtmosphere:
    """Bruneton tables for one atmosphere; build with :func:`precompute`.

    Attributes:
        atm: the atmosphere the tables were computed from.
        orders: number of scattering orders N included (1 = single only).
        sizes, quadrature, mu_s_min: the settings used.
        mu_s_range, mu_s_window: the sun zenith cosines the scattering tables span when built for one sun's
            (:func:`precompute`'s ``mu_s_range``; None: mu_s_min to 1) and that range in
            :func:`~skyfit.scattering.bruneton_tables.mu_s_unit`'s coordinate.
        transmittance_columns: (n_r, n_mu, 3) optical lengths to the top. [m]
        direct_irradiance: (n_r, n_mu_s, W) Delta E of order 0. [W/(m^2 nm)]
        irradiance: (n_r, n_mu_s, W) sum of indirect Delta E, orders 1..N-1 (zeros if N = 1).
        single_rayleigh, single_mie: (R, MU, MU_S, NU, W) without phase function. [W/(m^2 nm)]
        multiple: (R, MU, MU_S, NU, W) sum of Delta S of orders 2..N, or None if N = 1. [W/(m^2 sr nm)]
        order_scattering: [Delta S_2, ..., Delta S_N] if built with ``keep_orders``.
        order_irradiance: [Delta E_1, ..., Delta E_{N-1}] if built with ``keep_orders``.
        timings: seconds per stage and ``total``.
    """

    atm: Atmosphere
    orders: int
    sizes: TableSizes
    quadrature: Quadrature
    mu_s_min: float
    transmittance_columns: Tensor
    direct_irradiance: Tensor
    irradiance: Tensor
    single_rayleigh: Tensor
    single_mie: Tensor
    multiple: Tensor | None
    order_scattering: list[Tensor] | None = None
    order_irradiance: list[Tensor] | None = None
    timings: dict = dataclasses.field(default_factory=dict)
    mu_s_window: tuple[float, float] = FULL_MU_S
    mu_s_range: tuple[float, float] | None = None

    def sky_radiance(self, r, mu, mu_s, nu, **kwargs) -> Tensor:
        """:func:`sky_radiance` with this table's atmosphere."""
        return sky_radiance(self, None, r, mu, mu_s, nu, **kwargs)

    def transmittance(self, r: Tensor, mu: Tensor, atm: Atmosphere | None = None) -> Tensor:
        """Transmittance to the top of the atmosphere, shape (..., W) (rays not hitting the ground). [1]"""
        ctx = self._ctx(atm)
        return torch.exp(-_columns(ctx, r, mu) @ extinction_matrix3(ctx.atm))

    def scattering(self, r: Tensor, mu: Tensor, mu_s: Tensor, nu: Tensor) -> tuple[Tensor, Tensor, Tensor | None]:
        """Quadrilinear lookup of (single Rayleigh, single Mie, multiple) at (r, mu, mu_s, nu), each (..., W).

        The single-scattering values have no phase function (multiply by P_R(nu), P_M(nu));
        r in [bottom, top] (no move from space here, see :func:`sky_radiance`). The ray's
        ground intersection, which picks the half of the mu axis, is computed from (r, mu).
        """
        hits = ray_hits_ground(r, mu, self.atm.bottom_radius)
        idx = _scat_index(self._ctx(), r, mu, mu_s, nu, hits)
        tabs = [self.single_rayleigh, self.single_mie] + ([self.multiple] if self.multiple is not None else [])
        vals = interpolate(tabs, idx)
        return vals[0], vals[1], (vals[2] if self.multiple is not None else None)

    def ground_irradiance(self, r: Tensor, mu_s: Tensor) -> tuple[Tensor, Tensor]:
        """(direct, indirect) irradiance on a horizontal surface at radius r, each (..., W). [W/(m^2 nm)]

        Direct from the transmittance (2017 ComputeDirectIrradiance), indirect bilinear in the
        ``irradiance`` table (orders 1..N-1).
        """
        atm = self.atm
        direct = _direct_irradiance_from(self._ctx(), r, mu_s)
        indirect = interpolate([self.irradiance], irradiance_index(r, mu_s, atm.bottom_radius, atm.top_radius, self.sizes))[0]
        return direct, indirect

    def check_every_sun(self, what: str) -> None:
        """ValueError unless the tables span every sun (not built for one sun, :func:`precompute`'s ``mu_s_range``):
        ``what`` (an exporter's output) spans every sun elevation."""
        if self.mu_s_range is not None:
            raise ValueError(f"tables built for one sun (precompute's mu_s_range) cannot be exported: {what} spans "
                             "every sun elevation; precompute without mu_s_range")

    def _ctx(self, atm: Atmosphere | None = None) -> "_Ctx":
        return _Ctx(self.transmittance_columns, self.atm if atm is None else atm, self.sizes, self.mu_s_min, self.mu_s_window)

    def nbytes(self) -> int:
        ts = [self.transmittance_columns, self.direct_irradiance, self.irradiance, self.single_rayleigh, self.single_mie]
        ts += [self.multiple] if self.multiple is not None else []
        ts += (self.order_scattering or []) + (self.order_irradiance or [])
        return sum(t.numel() * t.element_size() for t in ts)


# ----------------------------------------------------------------------------------------
# helpers


def _chunked(fn: Callable[[int, int], Tensor], n: int, step: int, use_ckpt: bool) -> Tensor:
    """``cat([fn(i, j) for chunks])``; each chunk checkpointed when gradients are recorded."""
    outs = []
    for i in range(0, n, step):
        j = min(i + step, n)
        outs.append(checkpoint(fn, i, j, use_reentrant=False) if use_ckpt else fn(i, j))
    return torch.cat(outs, 0)


_TEMPORARIES = 4.0
"""Measured ratio of a chunk's peak working memory to the floats counted per item below."""


def _step(chunk_bytes: float, per_item_floats: float, itemsize: int) -> int:
    """Items per chunk so that a chunk's working memory stays near ``chunk_bytes``."""
    return max(1, int(chunk_bytes // max(_TEMPORARIES * per_item_floats * itemsize, 1)))


class _Ctx(NamedTuple):
    """What lookups need: the optical-length table, the atmosphere, the sizes, mu_s_min and the mu_s axis's window."""

    tc: Tensor
    atm: Atmosphere
    sizes: TableSizes
    mu_s_min: float
    mu_s_window: tuple[float, float] = FULL_MU_S


def _columns(ctx: _Ctx, r: Tensor, mu: Tensor) -> Tensor:
    """Optical lengths (Rayleigh, Mie, ozone) from (r, mu) to the top, shape (..., 3). [m]"""
    return interpolate([ctx.tc], transmittance_index(r, mu, ctx.atm.bottom_radius, ctx.atm.top_radius, ctx.sizes))[0]


def _segment_columns(ctx: _Ctx, r: Tensor, mu: Tensor, d: Tensor, hits: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Optical lengths between (r, mu) and the point at distance d along the ray (2017 GetTransmittance).

    Returns:
        (columns (..., 3), r_d, mu_d): the segment's columns [m], and radius [m] and view cosine at d.
    """
    atm = ctx.atm
    r_d = torch.clamp(torch.sqrt(torch.clamp_min(d * d + 2.0 * r * mu * d + r * r, 0.0)), atm.bottom_radius, atm.top_radius)
    mu_d = torch.clamp((r * mu + d) / r_d, -1.0, 1.0)
    sign = 1.0 - 2.0 * hits.to(r.dtype)
    c0 = _columns(ctx, r, sign * mu)
    c1 = _columns(ctx, r_d, sign * mu_d)
    col = torch.where(hits.unsqueeze(-1), c1 - c0, c0 - c1)
    return col, r_d, mu_d


def _distance_to_boundary(r: Tensor, mu: Tensor, hits: Tensor, atm: Atmosphere) -> Tensor:
    """2017 DistanceToNearestAtmosphereBoundary. [m]"""
    return torch.where(hits, distance_to_bottom(r, mu, atm.bottom_radius), distance_to_top(r, mu, atm.top_radius))


def _trapezoid(n: int, dtype, device) -> tuple[Tensor, Tensor]:
    """Nodes i/n (i = 0..n) and trapezoid weights on [0, 1]."""
    x = torch.linspace(0.0, 1.0, n + 1, dtype=dtype, device=device)
    w = torch.full((n + 1,), 1.0 / n, dtype=dtype, device=device)
    w[0] *= 0.5
    w[-1] *= 0.5
    return x, w


def _direct_irradiance_from(ctx: _Ctx, r: Tensor, mu_s: Tensor) -> Tensor:
    """Direct irradiance on a horizontal surface (2017 ComputeDirectIrradiance), shape (..., W).

    E_sun T(r, mu_s) times the cosine factor averaged over the visible part of the sun disc.
    """
    atm = ctx.atm
    a = atm.sun_angular_radius
    cos_f = torch.where(mu_s < -a, torch.zeros_like(mu_s), torch.where(mu_s > a, mu_s, (mu_s + a) ** 2 / (4.0 * a)))
    t = torch.exp(-_columns(ctx, r, mu_s) @ extinction_matrix3(atm))
    return atm.solar_irradiance * t * cos_f.unsqueeze(-1)


def _scat_index(ctx: _Ctx, r, mu, mu_s, nu, hits):
    atm = ctx.atm
    return scattering_index(r, mu, mu_s, nu, hits, atm.bottom_radius, atm.top_radius, ctx.mu_s_min, ctx.sizes, ctx.mu_s_window)


def _order_radiance(ctx, tables: tuple[Tensor, ...], order: int, r, mu, mu_s, nu, hits) -> Tensor:
    """Radiance of exactly ``order`` bounces from the tables (2017 GetScattering with order), (..., W).

    ``tables`` is (single_rayleigh, single_mie) for order 1, (Delta S_order,) otherwise.
    """
    atm = ctx.atm
    idx = _scat_index(ctx, r, mu, mu_s, nu, hits)
    if order == 1:
        s_r, s_m = interpolate(list(tables), idx)
        return s_r * rayleigh_phase(nu).unsqueeze(-1) + s_m * spectral_mie_phase(nu, atm)
    return interpolate(list(tables), idx)[0]


# ----------------------------------------------------------------------------------------
# the precomputation stages (2008 Algorithm 4.1; 2017 functions named in each docstring)


def transmittance_columns_table(atm: Atmosphere, sizes: TableSizes, samples: int, chunk_bytes: float, use_ckpt: bool) -> Tensor:
    """Optical lengths to the top at the transmittance texels, shape (n_r, n_mu, 3). [m]

    2017 ComputeOpticalLengthToTopAtmosphereBoundary: trapezoid rule with ``samples``
    intervals of each density profile (Rayleigh, Mie exponential; ozone tent).
    """
    dtype, device = atm.dtype, atm.device
    r, mu = transmittance_texel_params(atm.bottom_radius, atm.top_radius, sizes, dtype, device)
    r, mu = r.reshape(-1), mu.reshape(-1)
    x, w = _trapezoid(samples, dtype, device)

    def fn(i: int, j: int) -> Tensor:
        rr, mm = r[i:j, None], mu[i:j, None]
        d = distance_to_top(rr, mm, atm.top_radius)
        s = d * x
        r_s = torch.sqrt(torch.clamp_min(s * s + 2.0 * rr * mm * s + rr * rr, 0.0))
        dens = profile_densities(r_s - atm.bottom_radius, atm)  # (n, S, 3)
        return torch.einsum("nsk,s->nk", dens, w) * d

    step = _step(chunk_bytes, (samples + 1) * 8, torch.finfo(dtype).bits // 8)
    return _chunked(fn, r.shape[0], step, use_ckpt).reshape(sizes.transmittance_r, sizes.transmittance_mu, 3)


def _view_groups(texels) -> tuple[Tensor, ...]:
    """Texel parameters grouped by view ray: (r, mu, hits) of shape (G, 1) for the G = R MU rays,
    (mu_s, nu) of shape (G, T) for their T = MU_S NU sun configurations."""
    R, MU, MUS, NU = texels.r.shape
    g = lambda t: t[:, :, 0, 0].reshape(R * MU, 1)  # noqa: E731
    t = lambda x: x.reshape(R * MU, MUS * NU)  # noqa: E731
    return g(texels.r), g(texels.mu), g(texels.hits_ground), t(texels.mu_s), t(texels.nu)


def _group_ray_samples(ctx: _Ctx, r, mu, g, mus, nu, i: int, j: int, x: Tensor):
    """Samples along the rays of view groups i:j, shared by the single and multiple scattering integrals.

    Returns (dist (G, 1), d (G, S), col_v (G, S, 3), r_d (G, S), mu_d (G, S), mus_d (G, T, S), nu (G, T, 1)):
    the distance to the nearest boundary, the sample distances, the view columns T(x, y) is made of, the
    samples' radius and view cosine, their sun cosines for the T (mu_s, nu) texels of each group, and nu.
    """
    rr, mm, gg = r[i:j], mu[i:j], g[i:j]  # (G, 1)
    dist = _distance_to_boundary(rr, mm, gg, ctx.atm)
    d = dist * x  # (G, S)
    col_v, r_d, mu_d = _segment_columns(ctx, rr.expand_as(d), mm.expand_as(d), d, gg.expand_as(d))
    ss, nn = mus[i:j, :, None], nu[i:j, :, None]  # (G, T, 1)
    mus_d = torch.clamp((rr[:, :, None] * ss + d[:, None, :] * nn) / r_d[:, None, :], -1.0, 1.0)  # (G, T, S)
    return dist, d, col_v, r_d, mu_d, mus_d, nn


class _Geometry(NamedTuple):
    """Parameter-free quantities of the precomputation, computed once and shared by every order.

    The texel coordinates of the lookups, their interpolation corners and the view vectors
    of Delta J depend on the table sizes, the radii and the quadrature only (never on a
    fitted parameter), so a float64 table is the same whether they are computed once or
    per order; memory: :func:`geometry_bytes`.
    """

    texels: ScatteringTexels
    rays: tuple[Tensor, ...]  # _view_groups: r, mu, hits (G, 1); mu_s, nu (G, T)
    density_dirs: tuple[Tensor, Tensor]  # om (D, 3), dom (D,)
    density_nu: Tensor  # (G2, D) cosine between the incident direction and the sun
    density_plan: tuple[Tensor, Tensor, Tensor]  # where the (G2, D) incident directions sample the tables
    ground_plan: tuple[Tensor, Tensor, tuple[int, ...]]  # irradiance corners where those rays meet the ground
    ground_rays: tuple[Tensor, Tensor, Tensor]  # r, mu, hits of the incident rays, (G2, D)
    views: Tensor  # (G2, MU NU, 3) view directions of each (r, mu_s) group in the sun frame
    irradiance_nu: Tensor  # (n_irr, Dh)
    irradiance_plan: tuple[Tensor, Tensor, Tensor]  # where the hemisphere directions sample the tables
    irradiance_weight: Tensor  # (Dh,) omega_z d omega
    sun_grid: Tensor | None  # (G, S, T) grid_sample coordinate of the mu_s of the Delta S samples


def _plan(ctx: _Ctx, r, mu, mu_s, nu, hits) -> tuple[Tensor, Tensor, Tensor]:
    """Where a scattering-table lookup samples, for :func:`_sample_scattering` (2017's layout).

    As 2017 GetScattering: the 4-D table is a 3-D texture (r, mu, nu block x mu_s) read at the
    two nu blocks around the point and mixed linearly in nu; each read is a trilinear
    ``grid_sample`` (no corner arrays). Returns the two grids (1, n, 1, 1, 3) and the nu
    weight (n, 1) for the n = prod(batch) points.
    """
    R, MU, MUS, NU = ctx.sizes.scattering_shape
    i_r, i_mu, i_mus, i_nu = (t.reshape(-1) for t in torch.broadcast_tensors(*_scat_index(ctx, r, mu, mu_s, nu, hits)))
    i_nu = torch.clamp(i_nu, 0.0, float(NU - 1))
    lo = torch.clamp(torch.floor(i_nu), 0.0, float(NU - 2))
    col = torch.clamp(i_mus, 0.0, float(MUS - 1))
    y, z = grid_coordinate(i_mu, MU), grid_coordinate(i_r, R)
    grids = [torch.stack([grid_coordinate(b * MUS + col, NU * MUS), y, z], -1).view(1, -1, 1, 1, 3) for b in (lo, lo + 1.0)]
    return grids[0], grids[1], (i_nu - lo).unsqueeze(-1)


class _Texture(NamedTuple):
    """(R, MU, MU_S, NU, C) tables laid out once as the 3-D texture :func:`_plan` reads (2017's layout)."""

    tex: Tensor  # (1, sum C, R, MU, NU MU_S)
    channels: list[int]


def _texture(tables) -> _Texture:
    """The :class:`_Texture` of ``tables``: built once per stage, not per chunk (a copy of every table)."""
    R, MU, MUS, NU, _ = tables[0].shape
    tex = torch.cat([t.permute(4, 0, 1, 3, 2) for t in tables], 0).reshape(1, -1, R, MU, NU * MUS)
    return _Texture(tex, [t.shape[-1] for t in tables])


def _sample_scattering(texture: _Texture, plan) -> list[Tensor]:
    """Quadrilinear lookups of (R, MU, MU_S, NU, C) tables, as their :func:`_texture`, at a :func:`_plan`, each (n, C)."""
    g0, g1, f = plan
    tex, channels = texture
    v0, v1 = (F.grid_sample(tex, g, mode="bilinear", padding_mode="border", align_corners=True).reshape(tex.shape[1], -1).T
              for g in (g0, g1))
    v = v0 * (1.0 - f) + v1 * f
    return list(v.split(channels, -1))


def _geometry(ctx: _Ctx, texels: ScatteringTexels, quad: Quadrature, orders: bool = True) -> _Geometry:
    """The parameter-free part of every order's lookups (see :class:`_Geometry`); only the view
    rays when ``orders`` is False (single scattering only)."""
    atm, sizes = ctx.atm, ctx.sizes
    dtype, device = atm.dtype, atm.device
    R, MU, MUS, NU = sizes.scattering_shape
    if not orders:
        return _Geometry(texels, _view_groups(texels), *([None] * 10))
    with torch.no_grad():
        # Delta J: incident directions of each (r, mu_s) group, g = ir * MUS + ims
        om, dom = _density_directions(quad, dtype, device)
        n_d = om.shape[0]
        r_g = texels.r[:, 0, :, 0].reshape(-1, 1)
        mus_g = texels.mu_s[:, 0, :, 0].reshape(-1, 1)
        sin_s = safe_sqrt(1.0 - mus_g * mus_g)
        cz = om[:, 2].expand(r_g.shape[0], n_d)
        nu1 = torch.clamp(om[:, 0] * sin_s + om[:, 2] * mus_g, -1.0, 1.0)
        rr, ss = r_g.expand_as(nu1), mus_g.expand_as(nu1)
        hits = ray_hits_ground(rr, cz, atm.bottom_radius)
        density_plan = _plan(ctx, rr, cz, ss, nu1, hits)
        d_g = torch.where(hits, distance_to_bottom(rr, cz, atm.bottom_radius), torch.zeros_like(cz))
        r_d = torch.clamp(torch.sqrt(torch.clamp_min(d_g * d_g + 2.0 * rr * cz * d_g + rr * rr, 0.0)), atm.bottom_radius, atm.top_radius)
        mus_ground = torch.clamp((rr * ss + d_g * nu1) / r_d, -1.0, 1.0)
        ground_plan = corner_plan((sizes.irradiance_r, sizes.irradiance_mu_s),
                                  irradiance_index(torch.full_like(mus_ground, atm.bottom_radius), mus_ground,
                                                   atm.bottom_radius, atm.top_radius, sizes))
        # view directions of each group's (mu, nu) texels in the sun frame
        mu = texels.mu[:, :, 0, :].reshape(R, 1, MU * NU)  # (R, 1, V)
        nu = texels.nu.permute(0, 2, 1, 3).reshape(R, MUS, MU * NU)
        ss3 = texels.mu_s[0, 0, :, 0].reshape(1, MUS, 1)
        sin3 = safe_sqrt(1.0 - ss3 * ss3)
        safe_sin = torch.where(sin3 > 0, sin3, torch.ones_like(sin3))
        vx = torch.where(sin3 > 0, (nu - mu * ss3) / safe_sin, torch.zeros_like(nu))
        mu = mu.expand_as(vx)
        vy = safe_sqrt(1.0 - mu * mu - vx * vx)
        views = torch.stack([vx, vy, mu], -1).reshape(R * MUS, MU * NU, 3)
        # indirect irradiance: hemisphere directions of each irradiance texel
        r_i, mus_i = irradiance_texel_params(atm.bottom_radius, atm.top_radius, sizes, dtype, device)
        r_i, mus_i = r_i.reshape(-1, 1), mus_i.reshape(-1, 1)
        oz, ox, dom_h = _irradiance_directions(quad, dtype, device)
        sin_i = safe_sqrt(1.0 - mus_i * mus_i)
        nu_i = torch.clamp(ox * sin_i + oz * mus_i, -1.0, 1.0)
        rr_i, ss_i = r_i.expand_as(nu_i), mus_i.expand_as(nu_i)
        irradiance_plan = _plan(ctx, rr_i, oz.expand_as(nu_i), ss_i, nu_i, torch.zeros_like(nu_i, dtype=torch.bool))
        rays = _view_groups(texels)
        sun_grid = _sun_grid(ctx, rays, quad, 0, rays[0].shape[0])
    return _Geometry(texels, rays, (om, dom), nu1, density_plan, ground_plan, (rr, cz, hits), views,
                     nu_i, irradiance_plan, oz * dom_h, sun_grid)


def _ray_samples(ctx: _Ctx, rays, quad: Quadrature, i: int, j: int) -> tuple[Tensor, Tensor, Tensor]:
    """(d, r_d, mu_d), each (G, S): the Delta S samples of view rays i:j (as :func:`_group_ray_samples`)."""
    atm = ctx.atm
    r, mu, g = rays[0][i:j], rays[1][i:j], rays[2][i:j]
    x, _ = ray_nodes(quad.multiple_samples, quad.ray_rule, atm.dtype, atm.device)
    d = _distance_to_boundary(r, mu, g, atm) * x
    r_d = torch.clamp(torch.sqrt(torch.clamp_min(d * d + 2.0 * r * mu * d + r * r, 0.0)), atm.bottom_radius, atm.top_radius)
    mu_d = torch.clamp((r * mu + d) / r_d, -1.0, 1.0)
    return d, r_d, mu_d


_GRID_BLOCK = 1 << 16
"""Elements of the Delta S mu_s grid computed at once: the chain of elementwise passes stays in cache."""


def _sun_grid(ctx: _Ctx, rays, quad: Quadrature, i: int, j: int) -> Tensor:
    """grid_sample coordinate on the mu_s axis of the Delta S samples of view rays i:j, (G, S, T)."""
    MUS = ctx.sizes.scattering_mu_s
    r, mus, nu = rays[0][i:j], rays[3][i:j], rays[4][i:j]
    d, r_d, _ = _ray_samples(ctx, rays, quad, i, j)
    out = torch.empty(j - i, d.shape[1], mus.shape[1], dtype=d.dtype, device=d.device)
    step = max(1, _GRID_BLOCK // out[0].numel())
    for a in range(0, j - i, step):  # bounded temporaries
        b = min(a + step, j - i)
        mus_d = torch.clamp((r[a:b, :, None] * mus[a:b, None, :] + d[a:b, :, None] * nu[a:b, None, :]) / r_d[a:b, :, None], -1.0, 1.0)
        out[a:b] = grid_coordinate(mu_s_index(mus_d, ctx.atm.bottom_radius, ctx.atm.top_radius, ctx.mu_s_min, MUS, ctx.mu_s_window), MUS)
    return out


def geometry_bytes(geo: _Geometry) -> int:
    """Memory held by the shared geometry of :func:`precompute` (interpolation corners mostly). [bytes]"""
    seen: dict[int, int] = {}

    def add(t):
        if isinstance(t, Tensor):
            seen[id(t)] = t.numel() * t.element_size()
        elif isinstance(t, (tuple, list)):
            for u in t:
                add(u)
        elif isinstance(t, ScatteringTexels):
            add([t.r, t.mu, t.mu_s, t.nu, t.hits_ground])

    add(list(geo))
    return sum(seen.values())


def _slice_plan(plan, i: int, j: int, per: int):
    """Rows of a :func:`_plan` for groups i:j of ``per`` points each."""
    g0, g1, f = plan
    return g0[:, i * per : j * per], g1[:, i * per : j * per], f[i * per : j * per]


def _slice_corners(plan, i: int, j: int, per: int):
    """Rows of a :func:`corner_plan` for groups i:j of ``per`` points each."""
    ix, w, batch = plan
    return ix[i * per : j * per], w[i * per : j * per], (j - i, *batch[1:])


def _planned_order_radiance(ctx: _Ctx, tex: _Texture, order: int, plan, nu: Tensor) -> Tensor:
    """:func:`_order_radiance` at a precomputed :func:`_plan` from the order's :func:`_texture`, (*nu.shape, W)."""
    atm = ctx.atm
    if order == 1:
        s_r, s_m = (v.reshape(*nu.shape, -1) for v in _sample_scattering(tex, plan))
        return s_r * rayleigh_phase(nu).unsqueeze(-1) + s_m * spectral_mie_phase(nu, atm)
    return _sample_scattering(tex, plan)[0].reshape(*nu.shape, -1)


def _columns_sampled(ctx: _Ctx, r: Tensor, mu: Tensor) -> Tensor:
    """:func:`_columns` by ``grid_sample`` (no corner arrays), r and mu broadcastable; shape (..., 3). [m]"""
    sizes = ctx.sizes
    i_r, i_mu = transmittance_index(r, mu, ctx.atm.bottom_radius, ctx.atm.top_radius, sizes)
    batch = torch.broadcast_shapes(i_r.shape, i_mu.shape)
    grid = torch.stack([grid_coordinate(i_mu, sizes.transmittance_mu).expand(batch),
                        grid_coordinate(i_r, sizes.transmittance_r).expand(batch)], -1).reshape(1, -1, 1, 2)
    tab = ctx.tc.permute(2, 0, 1).unsqueeze(0)  # (1, 3, n_r, n_mu)
    out = F.grid_sample(tab, grid, mode="bilinear", padding_mode="border", align_corners=True)  # (1, 3, N, 1)
    return out.reshape(3, -1).transpose(0, 1).reshape(*batch, 3)


def _single_scattering_table(ctx, geo: _Geometry, quad: Quadrature, chunk_bytes: float, use_ckpt: bool) -> tuple[Tensor, Tensor]:
    """Single Rayleigh and Mie scattering without phase function (2017 ComputeSingleScattering).

    Trapezoid rule with ``quad.single_samples`` intervals from the texel's point to the
    nearest boundary; at each sample T(x, y) T(y, sun) (times the sun's visible fraction)
    times the density; times E_sun beta_s at the end. The view-ray quantities (sample
    radii, T(x, y)) are shared by the MU_S x NU texels of each (r, mu); T(y, sun) is a
    bilinear ``grid_sample`` of the optical-length table.
    Shapes (R, MU, MU_S, NU, W) each. [W/(m^2 nm)]
    """
    atm = ctx.atm
    dtype, device = atm.dtype, atm.device
    shape = geo.texels.r.shape
    r, mu, g, mus, nu = geo.rays
    n_t = mus.shape[1]
    x, w = ray_nodes(quad.single_samples, quad.ray_rule, dtype, device)
    n_w = atm.wavelengths.shape[0]

    def fn(i: int, j: int) -> Tensor:
        ext = extinction_matrix3(atm)
        dist, _, col_v, r_d, _, mus_d, _ = _group_ray_samples(ctx, r, mu, g, mus, nu, i, j, x)
        col_s = _columns_sampled(ctx, r_d[:, None, :], mus_d)  # (G, T, S, 3)
        vis = sun_visible_fraction(r_d[:, None, :], mus_d, atm.bottom_radius, atm.sun_angular_radius)
        trans = torch.exp(-(col_v[:, None] + col_s) @ ext) * vis.unsqueeze(-1)  # (G, T, S, W)
        dens = profile_densities(r_d - atm.bottom_radius, atm, ozone=False)  # (G, S, 2)
        integ = torch.einsum("gsk,gtsw->gtkw", dens * (w * dist).unsqueeze(-1), trans)
        ray = integ[:, :, 0] * (atm.solar_irradiance * atm.rayleigh_scattering)
        mie = integ[:, :, 1] * (atm.solar_irradiance * atm.mie_scattering)
        return torch.cat([ray, mie], dim=-1)  # (G, T, 2W)

    step = _step(chunk_bytes, n_t * (quad.single_samples + 1) * (3 * n_w + 24), torch.finfo(dtype).bits // 8)
    out = _chunked(fn, r.shape[0], step, use_ckpt)
    return out[..., :n_w].reshape(*shape, n_w), out[..., n_w:].reshape(*shape, n_w)


def _direct_irradiance_table(ctx, sizes: TableSizes) -> Tensor:
    """Delta E of order 0 at the irradiance texels (2017 ComputeDirectIrradianceTexture), (n_r, n_mu_s, W)."""
    atm = ctx.atm
    r, mu_s = irradiance_texel_params(atm.bottom_radius, atm.top_radius, sizes, atm.dtype, atm.device)
    return _direct_irradiance_from(ctx, r, mu_s)


def _irradiance_directions(quad: Quadrature, dtype, device) -> tuple[Tensor, Tensor, Tensor]:
    """Midpoint rule over the upper hemisphere: (omega_z, omega_x, d omega), each (Dh,)."""
    nt, nph = quad.irradiance_theta, quad.irradiance_phi
    dth, dph = (math.pi / 2) / nt, (2 * math.pi) / nph
    th = (torch.arange(nt, dtype=dtype, device=device) + 0.5) * dth
    ph = (torch.arange(nph, dtype=dtype, device=device) + 0.5) * dph
    th, ph = torch.meshgrid(th, ph, indexing="ij")
    return torch.cos(th).reshape(-1), (torch.sin(th) * torch.cos(ph)).reshape(-1), (torch.sin(th) * dth * dph).reshape(-1)


def _indirect_irradiance_table(ctx, geo: _Geometry, tables, order: int, quad: Quadrature, chunk_bytes: float, use_ckpt: bool) -> Tensor:
    """Delta E of ``order`` >= 1 bounces on a horizontal surface (2017 ComputeIndirectIrradiance).

    Midpoint rule over the upper hemisphere: sum of L_order(r, omega_z, mu_s, omega . s) omega_z d omega,
    with the lookups' corners from ``geo``. Shape (n_r, n_mu_s, W). [W/(m^2 nm)]
    """
    atm, sizes = ctx.atm, ctx.sizes
    n_i, n_h = geo.irradiance_nu.shape
    n_w = atm.wavelengths.shape[0]
    tex = _texture(tables)

    def fn(i: int, j: int) -> Tensor:
        L = _planned_order_radiance(ctx, tex, order, _slice_plan(geo.irradiance_plan, i, j, n_h), geo.irradiance_nu[i:j])
        return torch.einsum("ndw,d->nw", L, geo.irradiance_weight)

    step = _step(chunk_bytes, n_h * (40 * n_w + 40), torch.finfo(atm.dtype).bits // 8)
    return _chunked(fn, n_i, step, use_ckpt).reshape(sizes.irradiance_r, sizes.irradiance_mu_s, n_w)


def _density_directions(quad: Quadrature, dtype, device) -> tuple[Tensor, Tensor]:
    """Incident directions (D, 3) of the Delta J sphere rule in the sun frame, and their solid angles (D,).

    The midpoint rule in (theta, phi): ``density_theta`` bands of pi / density_theta from the zenith, the first
    ``density_zenith`` of them each split in two (:attr:`Quadrature.density_zenith`), times ``density_phi``
    sectors; D = (density_theta + density_zenith) x density_phi."""
    nt, nph, split = quad.density_theta, quad.density_phi, quad.density_zenith
    band, dph = math.pi / nt, 2 * math.pi / nph
    fine = (torch.arange(2 * split, dtype=dtype, device=device) + 0.5) * (band / 2)
    th = torch.cat([fine, (torch.arange(split, nt, dtype=dtype, device=device) + 0.5) * band])
    dth = torch.cat([torch.full_like(fine, band / 2), torch.full((nt - split,), band, dtype=dtype, device=device)])
    ph = (torch.arange(nph, dtype=dtype, device=device) + 0.5) * dph
    th, ph = torch.meshgrid(th, ph, indexing="ij")
    om = torch.stack([torch.sin(th) * torch.cos(ph), torch.sin(th) * torch.sin(ph), torch.cos(th)], -1).reshape(-1, 3)
    return om, (torch.sin(th) * dth[:, None] * dph).reshape(-1)


_PHASE_BLOCK = 1 << 16
"""Elements of the (view x incident) phase matrix evaluated at once in Delta J: small enough that
the in-place passes of the phase stay in cache (512 KB in float64; 1 << 20 was 2x slower once the
power became rsqrt), large enough that per-call overhead does not matter (docs/benchmarks.md)."""


def _ground_factor(ctx: _Ctx, geo: _Geometry) -> Tensor:
    """T(x, ground) alpha / pi for the incident rays of Delta J that hit the ground (0 elsewhere), (G2, D, W).

    Depends on the atmosphere but not on the order: computed once per precomputation.
    """
    atm = ctx.atm
    rr, cz, hits = geo.ground_rays
    d_g = torch.where(hits, distance_to_bottom(rr, cz, atm.bottom_radius), torch.zeros_like(cz))
    col_g, _, _ = _segment_columns(ctx, rr, cz, d_g, hits)
    return hits.unsqueeze(-1) * torch.exp(-col_g @ extinction_matrix3(atm)) * (atm.ground_albedo / math.pi)


def _mie_phase_parts(atm: Atmosphere):
    """(f, k) with ``atmosphere_mie_phase(c, atm) = k f(c)`` (the same formula, k applied after the sum).

    ``f`` takes ownership of its argument (a fresh tensor of clamped cosines) and may overwrite it.
    It evaluates only the branch of the non-cancelling ``1 + g^2 - 2 g c`` that a scalar g selects,
    and the power q^(-3/2) as rsqrt(q)^3 (a square root and two products instead of exp(1.5 log q):
    5x faster on the (view x incident) matrix, equal to 1e-15 relative; docs/benchmarks.md), in place
    unless g needs a gradient. A g with dimensions, and the two-term phase, fall back to
    :func:`atmosphere_mie_phase` itself (k = 1).
    """
    g, name = atm.mie_g, atm.mie_phase
    if name == "lognormal_mie":  # per wavelength: (..., W), contracted with einsum by the caller
        return (lambda c: spectral_mie_phase(c, atm)), 1.0
    if g.dim() or name not in ("cornette_shanks", "henyey_greenstein"):
        return (lambda c: atmosphere_mie_phase(c, atm)), 1.0
    # q = a + b (1 + sgn c): (1 - g)^2 + 2 g (1 - c) for g >= 0, (1 + g)^2 - 2 g (1 + c) for g < 0,
    # the forms of 1 + g^2 - 2 g c that do not cancel at the phase's peak
    if bool(g >= 0):
        a, b, sgn = (1.0 - g) ** 2, 2.0 * g, -1.0
    else:
        a, b, sgn = (1.0 + g) ** 2, -2.0 * g, 1.0
    cs = name == "cornette_shanks"
    k = 3.0 / (8.0 * math.pi) * (1.0 - g * g) / (2.0 + g * g) if cs else (1.0 / (4.0 * math.pi)) * (1.0 - g * g)

    def f(c: Tensor) -> Tensor:
        if torch.is_grad_enabled() and g.requires_grad:
            s = torch.rsqrt(a + b * (1.0 + sgn * c))
            p = s * s * s
            return p * (1.0 + c * c) if cs else p
        c2 = c * c if cs else None
        s = c.mul_(sgn).add_(1.0).mul_(b).add_(a).rsqrt_()  # c is consumed
        p = s * s
        p.mul_(s)
        return p.mul_(c2.add_(1.0)) if cs else p

    return f, k


def _scattering_density_table(
    ctx, geo: _Geometry, prev_tables, order: int, prev_irradiance: Tensor, ground: Tensor, quad: Quadrature,
    chunk_bytes: float, use_ckpt: bool,
) -> Tensor:
    """Delta J of ``order`` >= 2 (2017 ComputeScatteringDensity), shape (R, MU, MU_S, NU, W). [W/(m^3 sr nm)]

    J(r, mu, mu_s, nu) = sum_i L_in(r, mu_s, omega_i) [beta_R rho_R(r) P_R(omega . omega_i)
    + beta_M rho_M(r) P_M(omega . omega_i)] d omega_i  (2008 eq. 7), with L_in the radiance of
    order - 1 bounces from the tables plus, for omega_i towards the ground, the ground's
    Lambertian reflection T alpha / pi Delta E_{order-2} (2008 Algorithm 4.1, first line of the loop;
    ``ground`` is T alpha / pi, :func:`_ground_factor`).
    The incident directions are sampled in the sun's frame, so L_in is evaluated once per
    (r, mu_s) and shared by all view directions (mu, nu). The Rayleigh phase is a quadratic in
    the view vector v: sum_i P_R(v . omega_i) L_i d omega_i = 3 / (16 pi) (m_0 + v^T M v) with the
    moments m_0 = sum L_i d omega_i, M = sum omega_i omega_i^T L_i d omega_i, so only the Mie
    phase needs the (view x incident) matrix, evaluated in cache-sized blocks.
    """
    atm, sizes = ctx.atm, ctx.sizes
    R, MU, MUS, NU = sizes.scattering_shape
    om, dom = geo.density_dirs
    n_d = om.shape[0]
    n_v = MU * NU
    n_w = atm.wavelengths.shape[0]
    # Rayleigh moments: [1, x^2, y^2, z^2, 2xy, 2xz, 2yz] of the incident directions, weighted by d omega
    ox, oy, oz = om.unbind(-1)
    quad_o = torch.stack([torch.ones_like(ox), ox * ox, oy * oy, oz * oz, 2 * ox * oy, 2 * ox * oz, 2 * oy * oz], 0) * dom  # (7, D)
    r_g = geo.texels.r[:, 0, :, 0].reshape(-1)
    block = max(1, _PHASE_BLOCK // (n_v * n_d))  # groups per phase block
    sub_v = n_v if _PHASE_BLOCK >= n_v * n_d else max(1, _PHASE_BLOCK // n_d)

    tex = _texture(prev_tables)

    def fn(i: int, j: int) -> Tensor:
        L = _planned_order_radiance(ctx, tex, order - 1, _slice_plan(geo.density_plan, i, j, n_d), geo.density_nu[i:j])
        e_g = interpolate_planned([prev_irradiance], *_slice_corners(geo.ground_plan, i, j, n_d))[0]
        L = L + ground[i:j] * e_g  # (G, D, W)
        v = geo.views[i:j]  # (G, V, 3)
        vx, vy, vz = v.unbind(-1)
        quad_v = torch.stack([torch.ones_like(vx), vx * vx, vy * vy, vz * vz, vx * vy, vx * vz, vy * vz], -1)  # (G, V, 7)
        j_r = (3.0 / (16.0 * math.pi)) * torch.bmm(quad_v, torch.matmul(quad_o, L))  # (G, V, W)
        Ld = L * dom.unsqueeze(-1)
        phase, k_m = _mie_phase_parts(atm)
        parts = []
        for a in range(0, j - i, block):
            b = min(a + block, j - i)
            rows = []
            for c in range(0, n_v, sub_v):
                e = min(c + sub_v, n_v)
                cosang = torch.clamp(torch.matmul(v[a:b, c:e], om.T), -1.0, 1.0)  # (g, v, D)
                pc = phase(cosang)  # (g, v, D), or (g, v, D, W) for a phase per wavelength
                rows.append(torch.bmm(pc, Ld[a:b]) if pc.dim() == 3 else torch.einsum("gvdw,gdw->gvw", pc, Ld[a:b]))
            parts.append(torch.cat(rows, 1) if len(rows) > 1 else rows[0])
        j_m = (torch.cat(parts, 0) if len(parts) > 1 else parts[0]) * k_m
        dens = profile_densities(r_g[i:j] - atm.bottom_radius, atm, ozone=False)  # (G, 2)
        return j_r * (dens[:, 0, None, None] * atm.rayleigh_scattering) + j_m * (dens[:, 1, None, None] * atm.mie_scattering)

    step = _step(chunk_bytes, n_d * (16 * 2 + 20 * n_w) + n_v * (12 + 4 * n_w), torch.finfo(atm.dtype).bits // 8)
    out = _chunked(fn, R * MUS, step, use_ckpt)  # (R*MUS, MU*NU, W)
    return out.reshape(R, MUS, MU, NU, n_w).permute(0, 2, 1, 3, 4).contiguous()


def _view_transmittance(ctx: _Ctx, geo: _Geometry, quad: Quadrature) -> Tensor:
    """T(x, y) times the trapezoid weight at the Delta S samples of every view ray, (G, S, W).

    Depends on the atmosphere but not on the order: computed once per precomputation.
    """
    atm = ctx.atm
    r, mu, g, mus, nu = geo.rays
    x, w = ray_nodes(quad.multiple_samples, quad.ray_rule, atm.dtype, atm.device)
    dist = _distance_to_boundary(r, mu, g, atm)
    d = dist * x
    col_v, _, _ = _segment_columns(ctx, r.expand_as(d), mu.expand_as(d), d, g.expand_as(d))
    return torch.exp(-col_v @ extinction_matrix3(atm)) * (w * dist).unsqueeze(-1)


def _multiple_scattering_table(ctx, geo: _Geometry, density: Tensor, t_view: Tensor, quad: Quadrature,
                               chunk_bytes: float, use_ckpt: bool) -> Tensor:
    """Delta S of one order from its Delta J (2017 ComputeMultipleScattering), (R, MU, MU_S, NU, W).

    Trapezoid rule with ``quad.multiple_samples`` intervals of T(x, y) Delta J(y, v, s)
    from the texel's point to the nearest boundary (2008 eq. 11), T(x, y) (``t_view``, with
    the weights) shared by the MU_S x NU texels of each (r, mu). The 4-D lookup is separable:
    the sample's (r, mu) depend on the view ray only, so Delta J is first interpolated in
    (r, mu) at the G x S samples for all its MU_S x NU x W values at once (4 contiguous rows
    per sample), weighted by T(x, y), then in (mu_s, nu) at the T texels of each sample (a
    bilinear ``grid_sample`` at ``geo.sun_grid``) and summed over the samples: 8 corners per
    sample and texel instead of 16. [W/(m^2 sr nm)]
    """
    atm, sizes = ctx.atm, ctx.sizes
    R, MU, MUS, NU = sizes.scattering_shape
    r, mu, g, mus, nu = geo.rays
    n_t = mus.shape[1]
    n_s = quad.multiple_samples + 1
    n_w = atm.wavelengths.shape[0]
    n_c = MUS * NU * n_w
    rows = density.reshape(R * MU, n_c)
    gx_nu = grid_coordinate((nu + 1.0) / 2.0 * (NU - 1), NU)  # (G, T), nu's index as in scattering_index

    def fn(i: int, j: int) -> Tensor:
        n_g = j - i
        with torch.no_grad():  # geometry
            _, r_d, mu_d = _ray_samples(ctx, geo.rays, quad, i, j)
            i_r, i_mu, _, _ = scattering_index(r_d, mu_d, mus[i:j, :1], nu[i:j, :1], g[i:j].expand_as(r_d),
                                               atm.bottom_radius, atm.top_radius, ctx.mu_s_min, sizes, ctx.mu_s_window)
            ix, w, _ = corner_plan((R, MU), (i_r, i_mu))  # (G S, 4)
            gy = geo.sun_grid[i:j]  # (G, S, T)
            grid_sn = torch.stack([gx_nu[i:j, None, :].expand_as(gy), gy], -1).reshape(n_g * n_s, n_t, 1, 2)
        a = torch.bmm(w.unsqueeze(1), rows.index_select(0, ix.reshape(-1)).view(n_g * n_s, 4, n_c))  # (G S, 1, MUS NU W)
        a = a.view(n_g, n_s, MUS, NU, n_w).permute(0, 1, 4, 2, 3) * t_view[i:j, :, :, None, None]  # (G, S, W, MUS, NU)
        b = F.grid_sample(a.reshape(n_g * n_s, n_w, MUS, NU), grid_sn, mode="bilinear", padding_mode="border",
                          align_corners=True)  # (G S, W, T, 1)
        return b.reshape(n_g, n_s, n_w, n_t).sum(1).transpose(1, 2)  # (G, T, W)

    step = _step(chunk_bytes, n_s * (7 * n_c + n_t * (4 + 2 * n_w)), torch.finfo(atm.dtype).bits // 8)
    return _chunked(fn, r.shape[0], step, use_ckpt).reshape(R, MU, MUS, NU, n_w)


def precompute(
    atm: Atmosphere,
    orders: int = 4,
    sizes: TableSizes | None = None,
    quadrature: Quadrature | None = None,
    mu_s_min: float = MU_S_MIN_DEFAULT,
    mu_s_range: tuple[float, float] | None = None,
    keep_orders: bool = False,
    chunk_bytes: float | None = None,
    checkpointing: bool | None = None,
    progress: bool | None = None,
) -> PrecomputedAtmosphere:
    """Bruneton & Neyret 2008 Algorithm 4.1: transmittance, irradiance and scattering tables.

    The texel coordinates and interpolation corners of every lookup are computed once and
    shared by all orders (they depend on the sizes and radii only); the result equals
    :func:`skyfit.scattering.bruneton_reference.precompute_reference`, which recomputes them,
    to rounding (docs/benchmarks.md: speed, memory and the measured difference).

    Args:
        atm: the atmosphere; every table follows its dtype and device and is differentiable
            with respect to its tensors (scattering and extinction coefficients, scale
            heights, mie_g, ground_albedo, ozone_absorption, solar_irradiance).
        orders: N >= 1, the number of scattering orders (bounces) in the tables (2017: 4).
        sizes: table resolutions (default :class:`TableSizes`, 2017's).
        quadrature: sample counts (default :class:`Quadrature`, 2017's).
        mu_s_min: lowest sun zenith cosine in the scattering tables, in (-1, 0). [1]
        mu_s_range: (lo, hi) sun zenith cosines the scattering tables' mu_s axis spans instead of mu_s_min to 1
            (:func:`~skyfit.scattering.bruneton_tables.mu_s_index`): tables for one sun, whose texels all lie near
            it. Lookups outside the range take its edge's value (:func:`sky_radiance` refuses an observer's sun
            outside it unless told to clamp); the orders' own lookups leave it along long rays high in the
            atmosphere, so give a margin around the sun (:data:`skyfit.fit.photo.MS_SUN_MARGIN_DEG`). None: 2017's
            axis. [1]
        keep_orders: also keep every order's Delta S and Delta E (for analysis).
        chunk_bytes: approximate working memory per chunk of texels, which bounds peak memory;
            default 128 MB on CPU, 2 GB on CUDA (with 128 MB chunks an H200 took 40 s instead of 4 s).
        checkpointing: checkpoint each chunk; default: when gradients are being recorded.
        progress: a tqdm bar over the stages on stderr; default (None): on when stderr is a
            terminal, shown once the precomputation has taken 2 s.

    Returns:
        The tables, with ``timings`` in seconds per stage (``geometry``: the shared lookup corners).
    """
    if not (isinstance(orders, int) and orders >= 1):
        raise ValueError(f"orders must be an integer >= 1, got {orders!r}")
    if not (-1.0 < mu_s_min < 0.0):
        raise ValueError(f"mu_s_min must be in (-1, 0), got {mu_s_min}")
    sizes = TableSizes() if sizes is None else sizes
    quad = Quadrature() if quadrature is None else quadrature
    window = FULL_MU_S
    if mu_s_range is not None:
        lo, hi = (float(v) for v in mu_s_range)
        if not (mu_s_min <= lo < hi <= 1.0):
            raise ValueError(f"mu_s_range must be (lo, hi) with mu_s_min = {mu_s_min} <= lo < hi <= 1, got {mu_s_range!r}")
        mu_s_range = (lo, hi)
        window = mu_s_window(lo, hi, atm.bottom_radius, atm.top_radius, mu_s_min)
    if chunk_bytes is None:
        chunk_bytes = 2e9 if atm.device.type == "cuda" else 128e6
    if checkpointing is None:
        checkpointing = torch.is_grad_enabled() and any(getattr(atm, f).requires_grad for f in atm.tensor_fields())
    sync = torch.cuda.synchronize if atm.device.type == "cuda" else (lambda: None)
    timings: dict[str, float] = {}
    t_all = t0 = time.perf_counter()
    bar = tqdm(total=3 + 3 * (orders - 1), desc="Bruneton tables", unit="stage", file=sys.stderr, leave=False,
               disable=not (sys.stderr.isatty() if progress is None else progress), delay=2.0 if progress is None else 0.0)

    def lap(name: str) -> None:
        nonlocal t0
        sync()
        t = time.perf_counter()
        timings[name] = t - t0
        t0 = t
        if name != "geometry":
            bar.set_postfix_str(name, refresh=False)
            bar.update()

    with bar:
        tc = transmittance_columns_table(atm, sizes, quad.transmittance_samples, chunk_bytes, checkpointing)
        ctx = _Ctx(tc, atm, sizes, mu_s_min, window)
        lap("transmittance")
        direct = _direct_irradiance_table(ctx, sizes)
        lap("direct_irradiance")
        texels = scattering_texel_params(atm.bottom_radius, atm.top_radius, mu_s_min, sizes, atm.dtype, atm.device, window)
        geo = _geometry(ctx, texels, quad, orders >= 2)
        lap("geometry")
        s_r, s_m = _single_scattering_table(ctx, geo, quad, chunk_bytes, checkpointing)
        lap("single_scattering")
        irradiance = torch.zeros_like(direct)
        multiple = None
        kept_s: list[Tensor] = []
        kept_e: list[Tensor] = []
        prev_tables: tuple[Tensor, ...] = (s_r, s_m)
        prev_e = direct
        if orders >= 2:  # order-independent factors of the atmosphere
            ground = _ground_factor(ctx, geo)
            t_view = _view_transmittance(ctx, geo, quad)
        for n in range(2, orders + 1):
            dj = _scattering_density_table(ctx, geo, prev_tables, n, prev_e, ground, quad, chunk_bytes, checkpointing)
            lap(f"order_{n}_density")
            prev_e = _indirect_irradiance_table(ctx, geo, prev_tables, n - 1, quad, chunk_bytes, checkpointing)
            irradiance = irradiance + prev_e
            lap(f"order_{n}_irradiance")
            ds = _multiple_scattering_table(ctx, geo, dj, t_view, quad, chunk_bytes, checkpointing)
            del dj
            multiple = ds if multiple is None else multiple + ds
            lap(f"order_{n}_scattering")
            if keep_orders:
                kept_s.append(ds)
                kept_e.append(prev_e)
            prev_tables = (ds,)
    timings["total"] = time.perf_counter() - t_all
    return PrecomputedAtmosphere(
        atm=atm,
        orders=orders,
        sizes=sizes,
        quadrature=quad,
        mu_s_min=mu_s_min,
        transmittance_columns=tc,
        direct_irradiance=direct,
        irradiance=irradiance,
        single_rayleigh=s_r,
        single_mie=s_m,
        multiple=multiple,
        order_scattering=kept_s if keep_orders else None,
        order_irradiance=kept_e if keep_orders else None,
        timings=timings,
        mu_s_window=window,
        mu_s_range=mu_s_range,
    )


# ----------------------------------------------------------------------------------------
# lookup


def sky_radiance(
    tables: PrecomputedAtmosphere,
    atm: Atmosphere | None,
    r,
    mu,
    mu_s,
    nu,
    orders: int | None = None,
    ground: bool = True,
    sun_disk: bool = False,
    below_mu_s_min: str = "raise",
    chunk_bytes: float | None = None,
) -> Tensor:
    """Spectral sky radiance from the precomputed tables (2017 GetSkyRadiance; 2008 eq. 16).

    ``P_R(nu) S_R + P_M(nu) S_M + sum_{n=2..N} Delta S_n`` at the observer, with the phase
    functions of single scattering applied at lookup. An observer in space is first moved
    along the view ray to the top of the atmosphere (rays that miss it get 0). With
    ``ground``, rays that hit the ground add ``T alpha / pi (E_direct + E_indirect)`` at the
    ground point (2008 eq. 14 with a horizontal ground, R[L0] + R^[L*]).

    Args:
        tables: from :func:`precompute`.
        atm: atmosphere for the render-time terms (phase functions, ground albedo, solar
            disc); None for ``tables.atm``.
        r: observer distance from the planet centre, >= bottom_radius, shape (...). [m]
        mu, mu_s, nu: view zenith, sun zenith and view-sun cosines, shape (...). [1]
        orders: use orders 1..orders (<= tables.orders; intermediate values need tables
            built with ``keep_orders``); None for all. 1 gives single scattering.
        ground: add the light reflected by the Lambertian ground for rays that hit it.
        sun_disk: add the attenuated solar disc.
        below_mu_s_min: where the sun at the (moved) observer is below the table's
            ``mu_s_min``: "raise" (ValueError), "clamp" (the table's value at mu_s_min, 2017's
            behaviour) or "zero".
        chunk_bytes: approximate working memory per chunk of rays; default 64 MB on CPU, 1 GB on CUDA.

    Returns:
        Spectral radiance, shape (..., W). [W/(m^2 sr nm)]
    """
    atm = tables.atm if atm is None else atm
    if below_mu_s_min not in BELOW_MU_S_MIN:
        raise ValueError(f"below_mu_s_min must be one of {BELOW_MU_S_MIN}, got {below_mu_s_min!r}")
    n_orders = tables.orders if orders is None else int(orders)
    if not 1 <= n_orders <= tables.orders:
        raise ValueError(f"orders must be in [1, {tables.orders}] for these tables, got {orders}")
    if 1 < n_orders < tables.orders and tables.order_scattering is None:
        raise ValueError(f"orders={n_orders} < {tables.orders} needs tables built with keep_orders=True")
    dtype, device = tables.single_rayleigh.dtype, tables.single_rayleigh.device
    if chunk_bytes is None:
        chunk_bytes = 1e9 if device.type == "cuda" else 64e6
    r, mu, mu_s, nu = (torch.as_tensor(t, dtype=dtype, device=device) for t in (r, mu, mu_s, nu))
    r, mu, mu_s, nu = torch.broadcast_tensors(r, mu, mu_s, nu)
    batch = r.shape
    r, mu, mu_s, nu = (t.reshape(-1) for t in (r, mu, mu_s, nu))
    Rb, Rt = atm.bottom_radius, atm.top_radius
    if bool((r < Rb - 1.0).any()):
        raise ValueError(f"observer below the ground: min r = {float(r.min()):.1f} m < bottom_radius {Rb} m")
    # Observer in space: move it to where the view ray enters the atmosphere (2017 GetSkyRadiance).
    rmu = r * mu
    disc = rmu * rmu - r * r + Rt * Rt
    d_in = -rmu - safe_sqrt(disc)
    outside = r > Rt
    enters = outside & (disc >= 0) & (d_in > 0)
    valid = ~outside | enters
    d_in = torch.where(enters, d_in, torch.zeros_like(d_in))
    r1 = torch.where(enters, torch.full_like(r, Rt), r)
    mu1 = torch.where(enters, torch.clamp((rmu + d_in) / Rt, -1.0, 1.0), mu)
    mu_s1 = torch.where(enters, torch.clamp((r * mu_s + d_in * nu) / Rt, -1.0, 1.0), mu_s)
    r1 = torch.where(valid, r1, torch.full_like(r, Rt))
    below = valid & (mu_s1 < tables.mu_s_min)
    if below_mu_s_min == "raise" and bool(below.any()):
        raise SunBelowTables(float(mu_s1[below].min()), float(tables.mu_s_min))
    if tables.mu_s_range is not None and below_mu_s_min == "raise":
        lo, hi = tables.mu_s_range
        out = valid & ((mu_s1 < lo - 1e-9) | (mu_s1 > hi + 1e-9))
        if bool(out.any()):
            raise ValueError(f"sun zenith cosine {float(mu_s1[out][0]):.4f} at the observer is outside the tables' "
                             f"mu_s_range ({lo:.4f}, {hi:.4f}); precompute with a wider range or pass below_mu_s_min='clamp'")
    keep = valid & ~below if below_mu_s_min == "zero" else valid

    if n_orders == 1:
        mult: list[Tensor] = []
    elif n_orders == tables.orders:
        mult = [tables.multiple]
    else:
        mult = tables.order_scattering[: n_orders - 1]
    if n_orders == 1:
        e_ind = None
    elif n_orders == tables.orders:
        e_ind = tables.irradiance
    else:
        e_ind = sum(tables.order_irradiance[: n_orders - 1])
    ctx = tables._ctx(atm)
    n_w = tables.single_rayleigh.shape[-1]

    def fn(i: int, j: int) -> Tensor:
        rr, mm, ss, nn = r1[i:j], mu1[i:j], mu_s1[i:j], nu[i:j]
        hits = ray_hits_ground(rr, mm, Rb) & valid[i:j]
        idx = _scat_index(ctx, rr, mm, ss, nn, hits)
        vals = interpolate([tables.single_rayleigh, tables.single_mie] + mult, idx)
        out = vals[0] * rayleigh_phase(nn).unsqueeze(-1) + vals[1] * spectral_mie_phase(nn, atm)
        for v in vals[2:]:
            out = out + v
        ext = extinction_matrix3(atm)
        if ground:
            d_g = torch.where(hits, distance_to_bottom(rr, mm, Rb), torch.zeros_like(rr))
            col_g, r_g, _ = _segment_columns(ctx, rr, mm, d_g, hits)
            mus_g = torch.clamp((rr * ss + d_g * nn) / r_g, -1.0, 1.0)
            r_b = torch.full_like(rr, Rb)
            e = _direct_irradiance_from(ctx, r_b, mus_g)
            if e_ind is not None:
                e = e + interpolate([e_ind], irradiance_index(r_b, mus_g, Rb, Rt, tables.sizes))[0]
            out = out + hits.unsqueeze(-1) * torch.exp(-col_g @ ext) * (atm.ground_albedo / math.pi) * e
        out = out * keep[i:j].unsqueeze(-1)
        if sun_disk:
            in_disk = (nn > math.cos(atm.sun_angular_radius)) & ~hits
            t_top = torch.where(valid[i:j].unsqueeze(-1), torch.exp(-_columns(ctx, rr, mm) @ ext), torch.ones_like(out))
            out = out + in_disk.unsqueeze(-1) * t_top * (atm.solar_irradiance / (math.pi * atm.sun_angular_radius**2))
        return out

    step = _step(chunk_bytes, (3 + len(mult)) * 3 * n_w + 200, torch.finfo(dtype).bits // 8)
    if r1.shape[0] == 0:
        return torch.zeros(*batch, n_w, dtype=dtype, device=device)
    return _chunked(fn, r1.shape[0], step, False).reshape(*batch, n_w)
