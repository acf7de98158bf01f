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
from .bruneton_tables import TableSizes, extinction_matrix3
from .multiple import _columns, _Ctx, transmittance_columns_table
from .single import path_columns, path_extinction, single_scattering, sun_ray_cosine, sun_visible_fraction, view_ray_samples

__all__ = ["HillaireLUT", "fibonacci_sphere", "hillaire_lut", "hillaire_multiple", "hillaire_sky_radiance", "lookup_psi"]


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


def hillaire_lut(
    atm: Atmosphere,
    size: tuple[int, int] = (32, 32),
    directions: int = 64,
    samples: int = 20,
    transmittance_sizes: TableSizes | None = None,
    transmittance_samples: int = 100,
    checkpointing: bool | None = None,
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
        checkpointing: checkpoint each altitude row (memory O(one row) for backward);
            default when gradients are being recorded.

    Returns:
        A :class:`HillaireLUT`.
    """
    n_h, n_s = (int(v) for v in size)
    if n_h < 2 or n_s < 2 or directions < 1 or samples < 1:
        raise ValueError(f"need size >= (2, 2), directions >= 1, samples >= 1; got {size}, {directions}, {samples}")
    t0 = time.perf_counter()
    dtype, device = atm.dtype, atm.device
    sizes = transmittance_sizes or TableSizes()
    if checkpointing is None:
        checkpointing = torch.is_grad_enabled() and any(getattr(atm, f).requires_grad for f in atm.tensor_fields())
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
