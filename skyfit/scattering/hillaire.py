"""Hillaire 2020 multiple-scattering LUT, differentiable in torch.

S. Hillaire, "A Scalable and Production Ready Sky and Atmosphere Rendering Technique",
EGSR 2020, Sec. 5.5. Every order >= 2 is approximated from a 2D table Psi_ms(h, mu_s):
at each texel the light arriving after one scattering (or one ground bounce) is averaged
over the sphere with an isotropic phase function,

    L_2nd = oint L'(x, -w) p_u dw                       (eq. 5-6)
    f_ms  = oint L_f(x, -w) p_u dw,  L_f = int T sigma_s dt   (eq. 7-8)
    Psi_ms = L_2nd / (1 - f_ms)                          (eq. 9, the geometric series)

and the render adds ``sigma_s(y) Psi_ms(h(y), mu_s(y)) E_sun`` to the in-scattering at
each sample y of the view ray (eq. 10-11).

Choices, with their reasons:

- Directions: a Fibonacci lattice of ``directions`` points (equal-area cells, so the sphere
  integral with p_u = 1 / 4 pi is the plain mean); the paper uses 64 directions on the GPU.
- Marching in the LUT: ``samples`` midpoint steps per direction (the paper: 20), optical
  depth accumulated along the ray (Rayleigh, Mie and ozone tent); the sun's transmittance
  from a small optical-length table (:func:`.multiple.transmittance_columns_table`) times the
  visible fraction of its disc.
- Ground: Lambertian bounce of the attenuated direct sun in L' (the paper's LUT does the
  same); f_ms has no ground term (as the paper's reference code).
- LUT axes: altitude h in [0, top - bottom] and mu_s in [-1, 1], texel centres on the end
  points (the paper's ``fromSubUvsToUnit``); bilinear lookup, clamped.
- Render: single scattering is :func:`.single.single_scattering` (its integrator, rule and
  ground), the multiple term uses the same integrator for T(x, y). Ozone is seen
  everywhere: by the LUT (its tent in the marched optical depth and the sun's table) and
  by the render, whose T(x, y) and T(y, sun) add the exact ozone column
  (:func:`.single.path_columns`). Psi is stored per unit solar irradiance.
"""
from __future__ import annotations

import collections
import dataclasses
import math
import time

import torch
from torch import Tensor
from torch.utils.checkpoint import checkpoint

from ..atmosphere import Atmosphere
from ..atmosphere.profiles import profile_densities, with_mie_profile
from ..geometry import distance_to_bottom, distance_to_top, point_along_ray, ray_hits_ground, sun_cosine_along_ray
from ..quadrature import nodes_weights, validate_rule
from ..transmittance import ColumnFn, OpticalDepthIntegrator, prepare_columns
from .bruneton_tables import TableSizes, corner_plan, extinction_matrix3, interpolate_planned, transmittance_index, transmittance_texel_params
from .multiple import _columns, _Ctx, _trapezoid, transmittance_columns_table
from .single import path_columns, path_extinction, single_scattering, sun_ray_cosine, sun_visible_fraction, view_ray_samples

__all__ = ["LUT_METHODS", "HillaireLUT", "fibonacci_sphere", "hillaire_lut", "hillaire_multiple", "hillaire_sky_radiance",
           "lookup_psi"]

LUT_METHODS = ("cached", "rows")
"""How :func:`hillaire_lut` evaluates the same sums: ``cached`` takes the parameter-free geometry (ray
steps, sun cosines, table lookup corners, visible sun fractions) from :func:`_lut_geometry`, built once
per planet and LUT size, and sums each texel's directions and steps as one batched matrix product;
``rows`` is the original loop over altitude rows that rebuilds the geometry on every call (the
reference; equal to 1e-12, tests/test_fit_speed_paths.py)."""


class HillaireLUT:
    """Psi_ms on a (n_h, n_mu_s) grid.

    Attributes:
        psi: shape (n_h, n_mu_s, W), multiple-scattering radiance per unit solar
            irradiance and unit scattering coefficient. [1/sr]
        l_2nd, f_ms: the two sphere averages, shapes (n_h, n_mu_s, W). [1/sr], [1]
        height: top - bottom radius, the altitude span of the h axis. [m]
    """

    def __init__(self, psi: Tensor, l_2nd: Tensor, f_ms: Tensor, height: float, seconds: float = 0.0):
        self.psi, self.l_2nd, self.f_ms, self.height, self.seconds = psi, l_2nd, f_ms, height, seconds


def fibonacci_sphere(n: int, dtype, device) -> Tensor:
    """``n`` unit vectors of a Fibonacci lattice (equal-area cells), shape (n, 3), z = zenith. [1]"""
    i = torch.arange(n, dtype=dtype, device=device) + 0.5
    z = 1.0 - 2.0 * i / n
    phi = math.pi * (3.0 - math.sqrt(5.0)) * i
    s = torch.sqrt(torch.clamp_min(1.0 - z * z, 0.0))
    return torch.stack([s * torch.cos(phi), s * torch.sin(phi), z], dim=-1)


def _texel_row(atm: Atmosphere, ctx: _Ctx, r: Tensor, mu_s: Tensor, dirs: Tensor, samples: int):
    """L' and L_f averaged over ``dirs`` for texels (r, mu_s), shapes (n,) each -> (n, W) x 2."""
    Rb, Rt = atm.bottom_radius, atm.top_radius
    ext3 = extinction_matrix3(atm)  # (3, W)
    scat2 = torch.stack([atm.rayleigh_scattering, atm.mie_scattering])  # (2, W)
    n, k = r.shape[0], dirs.shape[0]
    sin_s = torch.sqrt(torch.clamp_min(1.0 - mu_s * mu_s, 0.0))
    mu = dirs[:, 2].expand(n, k)
    nu = dirs[:, 0] * sin_s.unsqueeze(-1) + dirs[:, 2] * mu_s.unsqueeze(-1)  # sun in the x-z plane
    re, mse = r.unsqueeze(-1).expand(n, k), mu_s.unsqueeze(-1).expand(n, k)
    hits = ray_hits_ground(re, mu, Rb)
    length = torch.where(hits, distance_to_bottom(re, mu, Rb), distance_to_top(re, mu, Rt))  # (n, k)
    x = (torch.arange(samples, dtype=r.dtype, device=r.device) + 0.5) / samples
    dt = (length / samples).unsqueeze(-1)  # (n, k, 1)
    s = length.unsqueeze(-1) * x  # (n, k, S)
    r3, mu3, mus3, nu3 = (t.unsqueeze(-1) for t in (re, mu, mse, nu))
    r_j, _ = point_along_ray(r3, mu3, s)
    r_j = torch.clamp(r_j, Rb, Rt)
    mus_j = sun_cosine_along_ray(r3, mus3, nu3, s, r_j)
    dens = profile_densities(r_j - Rb, atm)  # (n, k, S, 3)
    # Optical depth from x to the midpoint of step j: all earlier steps plus half of this one.
    cum = torch.cumsum(dens, dim=-2) - 0.5 * dens
    t_view = torch.exp(-(cum * dt.unsqueeze(-1)) @ ext3)  # (n, k, S, W)
    sigma_s = dens[..., :2] @ scat2  # (n, k, S, W)
    mus_c = sun_ray_cosine(r_j, mus_j, Rb)
    t_sun = torch.exp(-_columns(ctx, r_j, mus_c) @ ext3) * sun_visible_fraction(r_j, mus_j, Rb, atm.sun_angular_radius).unsqueeze(-1)
    w = t_view * sigma_s * dt.unsqueeze(-1)  # (n, k, S, W)
    l_f = w.sum(-2)  # (n, k, W)
    l_1 = (w * t_sun).sum(-2) / (4.0 * math.pi)
    # Ground bounce of the attenuated direct sun (Lambertian, albedo / pi).
    t_ground = torch.exp(-(cum[..., -1, :] + 0.5 * dens[..., -1, :]) * dt @ ext3)  # (n, k, W)
    r_g = torch.full_like(re, Rb)
    mus_g = sun_cosine_along_ray(re, mse, nu, length, r_g)
    e_g = torch.exp(-_columns(ctx, r_g, sun_ray_cosine(r_g, mus_g, Rb)) @ ext3)
    e_g = e_g * (sun_visible_fraction(r_g, mus_g, Rb, atm.sun_angular_radius) * torch.clamp_min(mus_g, 0.0)).unsqueeze(-1)
    l_1 = l_1 + hits.unsqueeze(-1) * t_ground * e_g * (atm.ground_albedo / math.pi)
    return l_1.mean(1), l_f.mean(1)


@dataclasses.dataclass(frozen=True)
class _LutGeometry:
    """What :func:`_texel_row` computes without the atmosphere's coefficients, for every texel at once.

    T texels (altitude-major), K directions, S steps; the sun's optical-length table has n_r x n_mu
    texels with Q trapezoid nodes each.

    Attributes:
        alt: altitude of each step's midpoint, shape (T, K, S). [m]
        dt: step length, shape (T, K). [m]
        vis: visible fraction of the sun's disc at each step, shape (T, K, S). [1]
        sun_plan: :func:`corner_plan` of the sun's column lookups at the steps (index, weight, batch).
        ground: Lambertian factor ``hits x visible fraction x max(mu_s, 0)`` at the ray's end, shape (T, K). [1]
        ground_plan: the sun's column lookups at the ground points.
        table_alt: altitudes of the optical-length table's nodes, shape (n_r n_mu, Q). [m]
        table_d: length of each table ray, shape (n_r n_mu, 1). [m]
        table_w: trapezoid weights, shape (Q,). [1]
    """

    alt: Tensor
    dt: Tensor
    vis: Tensor
    sun_plan: tuple
    ground: Tensor
    ground_plan: tuple
    table_alt: Tensor
    table_d: Tensor
    table_w: Tensor


_GEOMETRY_CACHE: "collections.OrderedDict[tuple, _LutGeometry]" = collections.OrderedDict()
_GEOMETRY_CACHE_SIZE = 4
"""Geometries kept (least recently used dropped): a fit uses one; a deterministic function of its key."""


def _lut_geometry(atm: Atmosphere, n_h: int, n_s: int, directions: int, samples: int, sizes: TableSizes,
                  transmittance_samples: int) -> _LutGeometry:
    """The parameter-free part of :func:`hillaire_lut`, built as :func:`_texel_row` and
    :func:`.multiple.transmittance_columns_table` do, cached by planet radii, sun radius, sizes, dtype, device."""
    dtype, device = atm.dtype, atm.device
    key = (float(atm.bottom_radius), float(atm.top_radius), float(atm.sun_angular_radius), n_h, n_s, directions, samples,
           sizes.transmittance_r, sizes.transmittance_mu, transmittance_samples, dtype, str(device))
    hit = _GEOMETRY_CACHE.get(key)
    if hit is not None:
        _GEOMETRY_CACHE.move_to_end(key)
        return hit
    with torch.no_grad():
        Rb, Rt, a_sun = atm.bottom_radius, atm.top_radius, atm.sun_angular_radius
        height = Rt - Rb
        h = torch.linspace(0.0, 1.0, n_h, dtype=dtype, device=device) * height
        r = torch.clamp((Rb + h)[:, None].expand(n_h, n_s), Rb, Rt).reshape(-1)  # (T,) as hillaire_lut's rows
        mu_s = torch.linspace(-1.0, 1.0, n_s, dtype=dtype, device=device).repeat(n_h)
        dirs = fibonacci_sphere(directions, dtype, device)
        n, k = r.shape[0], dirs.shape[0]
        sin_s = torch.sqrt(torch.clamp_min(1.0 - mu_s * mu_s, 0.0))
        mu = dirs[:, 2].expand(n, k)
        nu = dirs[:, 0] * sin_s.unsqueeze(-1) + dirs[:, 2] * mu_s.unsqueeze(-1)
        re, mse = r.unsqueeze(-1).expand(n, k), mu_s.unsqueeze(-1).expand(n, k)
        hits = ray_hits_ground(re, mu, Rb)
        length = torch.where(hits, distance_to_bottom(re, mu, Rb), distance_to_top(re, mu, Rt))
        x = (torch.arange(samples, dtype=dtype, device=device) + 0.5) / samples
        dt = length / samples
        s = length.unsqueeze(-1) * x
        r3, mu3, mus3, nu3 = (t.unsqueeze(-1) for t in (re, mu, mse, nu))
        r_j, _ = point_along_ray(r3, mu3, s)
        r_j = torch.clamp(r_j, Rb, Rt)
        mus_j = sun_cosine_along_ray(r3, mus3, nu3, s, r_j)
        grid = (sizes.transmittance_r, sizes.transmittance_mu)
        sun_plan = corner_plan(grid, transmittance_index(r_j, sun_ray_cosine(r_j, mus_j, Rb), Rb, Rt, sizes))
        vis = sun_visible_fraction(r_j, mus_j, Rb, a_sun)
        r_g = torch.full_like(re, Rb)
        mus_g = sun_cosine_along_ray(re, mse, nu, length, r_g)
        ground_plan = corner_plan(grid, transmittance_index(r_g, sun_ray_cosine(r_g, mus_g, Rb), Rb, Rt, sizes))
        ground = hits * sun_visible_fraction(r_g, mus_g, Rb, a_sun) * torch.clamp_min(mus_g, 0.0)
        tr, tm = transmittance_texel_params(Rb, Rt, sizes, dtype, device)
        tr, tm = tr.reshape(-1, 1), tm.reshape(-1, 1)
        xq, wq = _trapezoid(transmittance_samples, dtype, device)
        d = distance_to_top(tr, tm, Rt)
        sq = d * xq
        table_alt = torch.sqrt(torch.clamp_min(sq * sq + 2.0 * tr * tm * sq + tr * tr, 0.0)) - Rb
    geo = _LutGeometry(r_j - Rb, dt, vis, sun_plan, ground, ground_plan, table_alt, d, wq)
    _GEOMETRY_CACHE[key] = geo
    while len(_GEOMETRY_CACHE) > _GEOMETRY_CACHE_SIZE:
        _GEOMETRY_CACHE.popitem(last=False)
    return geo


def _planned_columns(tc: Tensor, plan: tuple, lo: int, hi: int, per: int) -> Tensor:
    """Columns of the texels lo:hi from the optical-length table ``tc`` (n_r, n_mu, 3) at a cached plan
    whose points are ``per`` per texel, shape (hi - lo, *plan batch[1:], 3). [m]"""
    index, weight, batch = plan
    return interpolate_planned([tc], index[lo * per:hi * per], weight[lo * per:hi * per], (hi - lo, *batch[1:]))[0]


def _texel_sums(atm: Atmosphere, geo: _LutGeometry, tc: Tensor, lo: int, hi: int) -> tuple[Tensor, Tensor]:
    """L' and L_f of texels lo:hi (the sums of :func:`_texel_row` on the cached geometry), (hi - lo, W) x 2."""
    ext3 = extinction_matrix3(atm)  # (3, W)
    scat2 = torch.stack([atm.rayleigh_scattering, atm.mie_scattering])  # (2, W)
    _, k, s = geo.alt.shape
    t = hi - lo
    dens = profile_densities(geo.alt[lo:hi], atm)  # (t, K, S, 3)
    dt = geo.dt[lo:hi]
    cum = torch.cumsum(dens, dim=-2) - 0.5 * dens
    col_view = cum * dt[..., None, None]  # optical lengths from the texel to each step's midpoint
    col_sun = _planned_columns(tc, geo.sun_plan, lo, hi, k * s)
    t_view = torch.exp(-col_view @ ext3).reshape(t, k * s, -1)  # (t, KS, W)
    t_path = torch.exp(-(col_view + col_sun) @ ext3).reshape(t, k * s, -1)  # texel <- step <- sun
    # sigma_s dt = (dens_R dt) beta_R + (dens_M dt) beta_M: sum over directions and steps as (t, 2, KS) @ (t, KS, W)
    dd = dens[..., :2] * dt[..., None, None]  # (t, K, S, 2)
    a_f = dd.reshape(t, k * s, 2).transpose(1, 2)
    a_1 = (dd * geo.vis[lo:hi].unsqueeze(-1)).reshape(t, k * s, 2).transpose(1, 2)
    l_f = (torch.bmm(a_f, t_view) * scat2).sum(1) / k
    l_1 = (torch.bmm(a_1, t_path) * scat2).sum(1) / (k * 4.0 * math.pi)
    # ground bounce: the view column to the ground plus the sun's column there
    col_g = (cum[..., -1, :] + 0.5 * dens[..., -1, :]) * dt.unsqueeze(-1)  # (t, K, 3)
    e_g = torch.exp(-(col_g + _planned_columns(tc, geo.ground_plan, lo, hi, k)) @ ext3)  # (t, K, W)
    l_1 = l_1 + torch.bmm(geo.ground[lo:hi].unsqueeze(1), e_g).squeeze(1) / k * (atm.ground_albedo / math.pi)
    return l_1, l_f


PHASE_ONLY_FIELDS = frozenset({"mie_g", "mie_g2", "mie_hg_weight", "mie_phase", "solar_irradiance", "name", "config"})
"""Atmosphere fields the LUT does not read: its sphere averages use an isotropic phase (eq. 5-8) and Psi
is per unit solar irradiance. Every other field is part of :func:`_lut_memo_key`."""

_LAST_LUTS: list = []
"""The last :data:`_LAST_LUTS_SIZE` LUTs built without gradients, with their keys (:func:`hillaire_lut`),
most recent last: a fit's finite-difference column of ``mie_g`` asks again for the LUT of the point it
differentiates at. Deterministic: a hit returns what a rebuild would."""
_LAST_LUTS_SIZE = 8


def _lut_memo_key(atm: Atmosphere, settings: tuple) -> tuple:
    """(settings and non-tensor fields, tensor fields) of everything but :data:`PHASE_ONLY_FIELDS`."""
    plain, tensors = [settings, atm.dtype, str(atm.device)], []
    for f in dataclasses.fields(atm):
        if f.name in PHASE_ONLY_FIELDS:
            continue
        v = getattr(atm, f.name)
        if isinstance(v, Tensor):
            tensors.append((f.name, v))
        else:
            plain.append((f.name, v))
    return tuple(plain), tensors


def _memo_hit(key: tuple) -> "HillaireLUT | None":
    for k, ((plain, tensors), lut) in enumerate(_LAST_LUTS):
        if plain != key[0] or [n for n, _ in tensors] != [n for n, _ in key[1]]:
            continue
        if all(a.shape == b.shape and torch.equal(a, b) for (_, a), (_, b) in zip(tensors, key[1])):
            _LAST_LUTS.append(_LAST_LUTS.pop(k))
            return lut
    return None


_CHUNK_ELEMENTS = 1 << 20
"""Texel x direction x step x wavelength elements per chunk of the cached LUT (8 MB in float64): the Kider
LUT (16 x 16 texels, 32 x 12 steps, 36 wavelengths) built in 0.055 s in chunks of 2^20, 0.11 s in one of 2^22."""
_CHECKPOINT_ELEMENTS = 1 << 23
"""Above this many elements (64 MB in float64 per (texels, K, S, W) tensor), chunks are checkpointed when
gradients are recorded, so that backward holds one chunk's intermediates at a time."""


def _lut_cached(atm: Atmosphere, n_h: int, n_s: int, directions: int, samples: int, sizes: TableSizes,
                transmittance_samples: int, checkpointing: bool) -> tuple[Tensor, Tensor]:
    geo = _lut_geometry(atm, n_h, n_s, directions, samples, sizes, transmittance_samples)
    dens = profile_densities(geo.table_alt, atm)  # as transmittance_columns_table
    tc = (torch.einsum("nsk,s->nk", dens, geo.table_w) * geo.table_d).reshape(sizes.transmittance_r,
                                                                              sizes.transmittance_mu, 3)
    n_t = n_h * n_s
    per = directions * samples * int(atm.wavelengths.numel())
    step = max(1, _CHUNK_ELEMENTS // max(per, 1))
    ckpt = checkpointing and step < n_t and n_t * per > _CHECKPOINT_ELEMENTS  # small: keep, do not recompute
    ls, fs = [], []
    for lo in range(0, n_t, step):
        hi = min(lo + step, n_t)
        l1, lf = (checkpoint(_texel_sums, atm, geo, tc, lo, hi, use_reentrant=False) if ckpt
                  else _texel_sums(atm, geo, tc, lo, hi))
        ls.append(l1)
        fs.append(lf)
    w = atm.wavelengths.numel()
    return torch.cat(ls).reshape(n_h, n_s, w), torch.cat(fs).reshape(n_h, n_s, w)


def hillaire_lut(
    atm: Atmosphere,
    size: tuple[int, int] = (32, 32),
    directions: int = 64,
    samples: int = 20,
    transmittance_sizes: TableSizes | None = None,
    transmittance_samples: int = 100,
    checkpointing: bool | None = None,
    method: str = "cached",
) -> HillaireLUT:
    """Psi_ms(h, mu_s) of Hillaire 2020 eq. 9, differentiable w.r.t. the atmosphere's tensors.

    Args:
        atm: the atmosphere (its dtype and device are used).
        size: (n_h, n_mu_s) texels, each >= 2; the paper uses 32 x 32.
        directions: directions on the sphere per texel (Fibonacci lattice); paper: 64.
        samples: midpoint steps along each direction; paper: 20.
        transmittance_sizes: the sun's optical-length table (only its transmittance_* used);
            default 256 mu x 64 r (Bruneton 2017).
        transmittance_samples: trapezoid intervals of that table.
        checkpointing: checkpoint each altitude row (``rows``) or chunk of texels (``cached``, above
            :data:`_CHECKPOINT_ELEMENTS`) so that backward holds one at a time; default when gradients are recorded.
        method: one of :data:`LUT_METHODS` (the same sums, equal to 1e-12).

    Returns:
        A :class:`HillaireLUT`.
    """
    n_h, n_s = (int(v) for v in size)
    if n_h < 2 or n_s < 2 or directions < 1 or samples < 1:
        raise ValueError(f"need size >= (2, 2), directions >= 1, samples >= 1; got {size}, {directions}, {samples}")
    if method not in LUT_METHODS:
        raise ValueError(f"unknown Hillaire LUT method {method!r}; valid: {', '.join(LUT_METHODS)}")
    t0 = time.perf_counter()
    dtype, device = atm.dtype, atm.device
    sizes = transmittance_sizes or TableSizes()
    if checkpointing is None:
        checkpointing = torch.is_grad_enabled() and any(getattr(atm, f).requires_grad for f in atm.tensor_fields())
    if method == "cached":
        graph = torch.is_grad_enabled() and any(getattr(atm, f).requires_grad for f in atm.tensor_fields())
        key = None if graph else _lut_memo_key(atm, (n_h, n_s, directions, samples, sizes.transmittance_r,
                                                     sizes.transmittance_mu, transmittance_samples))
        hit = None if key is None else _memo_hit(key)
        if hit is not None:
            return hit
        l_2nd, f_ms = _lut_cached(atm, n_h, n_s, directions, samples, sizes, transmittance_samples, checkpointing)
        lut = HillaireLUT(l_2nd / (1.0 - f_ms), l_2nd, f_ms, atm.top_radius - atm.bottom_radius, time.perf_counter() - t0)
        if key is not None:
            _LAST_LUTS.append((key, lut))
            del _LAST_LUTS[:-_LAST_LUTS_SIZE]
        return lut
    tc = transmittance_columns_table(atm, sizes, transmittance_samples, 128e6, checkpointing)
    ctx = _Ctx(tc, atm, sizes, -0.5)
    height = atm.top_radius - atm.bottom_radius
    h = torch.linspace(0.0, 1.0, n_h, dtype=dtype, device=device) * height
    mu_s = torch.linspace(-1.0, 1.0, n_s, dtype=dtype, device=device)
    dirs = fibonacci_sphere(directions, dtype, device)
    rows_l, rows_f = [], []
    for i in range(n_h):
        r = torch.clamp((atm.bottom_radius + h[i]).expand(n_s), atm.bottom_radius, atm.top_radius)
        if checkpointing:
            l2, fm = checkpoint(_texel_row, atm, ctx, r, mu_s, dirs, samples, use_reentrant=False)
        else:
            l2, fm = _texel_row(atm, ctx, r, mu_s, dirs, samples)
        rows_l.append(l2)
        rows_f.append(fm)
    l_2nd, f_ms = torch.stack(rows_l), torch.stack(rows_f)
    psi = l_2nd / (1.0 - f_ms)
    return HillaireLUT(psi, l_2nd, f_ms, height, time.perf_counter() - t0)


def lookup_psi(lut: HillaireLUT, r: Tensor, mu_s: Tensor, bottom_radius: float) -> Tensor:
    """Bilinear Psi_ms at radius r and sun cosine mu_s (clamped to the grid), shape (..., W). [1/sr]"""
    n_h, n_s = lut.psi.shape[:2]
    u = torch.clamp((r - bottom_radius) / lut.height, 0.0, 1.0) * (n_h - 1)
    v = torch.clamp((mu_s + 1.0) * 0.5, 0.0, 1.0) * (n_s - 1)
    i0 = torch.clamp(torch.floor(u).long(), 0, n_h - 2)
    j0 = torch.clamp(torch.floor(v).long(), 0, n_s - 2)
    a = (u - i0).unsqueeze(-1)
    b = (v - j0).unsqueeze(-1)
    p = lut.psi
    return ((1 - a) * ((1 - b) * p[i0, j0] + b * p[i0, j0 + 1]) + a * ((1 - b) * p[i0 + 1, j0] + b * p[i0 + 1, j0 + 1]))


def hillaire_multiple(
    atm: Atmosphere,
    r,
    mu,
    mu_s,
    nu,
    integrator: OpticalDepthIntegrator,
    view_samples: int = 32,
    rule: str = "trapezoid",
    lut: HillaireLUT | None = None,
    column_fn: ColumnFn | None = None,
) -> Tensor:
    """The multiple-scattering term alone, ``E_sun int T(x, y) sigma_s(y) Psi_ms dy`` (eq. 11), (..., W).

    Arguments as :func:`hillaire_sky_radiance`.
    """
    validate_rule(rule)
    dtype, device = atm.dtype, atm.device
    lut = hillaire_lut(atm) if lut is None else lut
    r, mu, mu_s, nu = (torch.as_tensor(t, dtype=dtype, device=device) for t in (r, mu, mu_s, nu))
    r, mu, mu_s, nu = torch.broadcast_tensors(r, mu, mu_s, nu)
    batch = r.shape
    r, mu, mu_s, nu = (t.reshape(-1) for t in (r, mu, mu_s, nu))
    if column_fn is None:
        column_fn = prepare_columns(integrator, atm)
    Rb = atm.bottom_radius
    x, w = nodes_weights(rule, view_samples, dtype, device)
    _, seg, r0, mu0, _, s, r_j, mus_j = view_ray_samples(atm, r, mu, mu_s, nu, x)
    # T(x, y) with the ozone column when the atmosphere has ozone (as in single scattering).
    trans = torch.exp(path_columns(column_fn, atm, r0.unsqueeze(-1), mu0.unsqueeze(-1), s) @ -path_extinction(atm))  # (n, N, W)
    dens = with_mie_profile(torch.exp((r_j - Rb).unsqueeze(-1) * -(1.0 / atm.scale_heights)), r_j - Rb, atm)  # (n, N, 2)
    sigma_s = dens @ torch.stack([atm.rayleigh_scattering, atm.mie_scattering])  # (n, N, W)
    psi = lookup_psi(lut, r_j, mus_j, Rb)
    wt = (w * seg.unsqueeze(-1)).unsqueeze(-1)
    out = (wt * trans * sigma_s * psi).sum(-2) * atm.solar_irradiance
    return out.reshape(*batch, -1)


def hillaire_sky_radiance(
    atm: Atmosphere,
    r,
    mu,
    mu_s,
    nu,
    integrator: OpticalDepthIntegrator,
    view_samples: int = 32,
    lut: HillaireLUT | None = None,
    rule: str = "trapezoid",
    ground: bool = True,
    sun_disk: bool = False,
) -> Tensor:
    """Total radiance: single scattering plus Hillaire's multiple-scattering term.

    Args:
        atm: the atmosphere (dtype and device followed).
        r: observer distance from the planet centre, shape (...). [m]
        mu, mu_s, nu: view zenith, sun zenith and view-sun cosines, shape (...). [1]
        integrator: optical-depth method for T(x, y) and T(y, sun) along the view ray (Rayleigh
            and Mie; the ozone column, when ``atm.ozone_absorption`` is set, is exact).
        view_samples: samples of the view-ray integral.
        lut: from :func:`hillaire_lut` (built with defaults if None).
        rule: outer quadrature rule.
        ground, sun_disk: as :func:`.single.single_scattering` (direct-sun ground only).

    Returns:
        Spectral radiance, shape (..., W). [W/(m^2 sr nm)]
    """
    lut = hillaire_lut(atm) if lut is None else lut
    column_fn = prepare_columns(integrator, atm)
    single = single_scattering(atm, r, mu, mu_s, nu, integrator, view_samples, rule, ground, sun_disk, column_fn=column_fn)
    return single + hillaire_multiple(atm, r, mu, mu_s, nu, integrator, view_samples, rule, lut, column_fn)
