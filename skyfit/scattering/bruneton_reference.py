"""The precomputation as it was before the geometry-cached rewrite (kept as a reference).

:func:`precompute_reference` is :func:`skyfit.scattering.multiple.precompute` as of commit
b03e766: the same 2008 Algorithm 4.1 with 2017's parametrisation, but every lookup
recomputes its texel coordinates and 16 interpolation corners in every order, and the
Rayleigh and Mie phase matrices of Delta J are evaluated in full. The fast path must
reproduce it to rounding (``tests/test_bruneton_speed.py``; float64, max relative
difference measured in docs/benchmarks.md); ``scripts/bruneton_speed.py`` times the two
side by side. Not for production use: it is slower by the ratio given there.
"""
from __future__ import annotations

import math
import time

import torch
from torch import Tensor

from ..atmosphere import Atmosphere
from ..atmosphere.profiles import profile_densities
from ..geometry import distance_to_bottom, ray_hits_ground, safe_sqrt
from .bruneton_tables import (
    MU_S_MIN_DEFAULT,
    TableSizes,
    extinction_matrix3,
    interpolate,
    irradiance_index,
    irradiance_texel_params,
    scattering_texel_params,
)
from .multiple import (
    PrecomputedAtmosphere,
    Quadrature,
    _chunked,
    _columns,
    _Ctx,
    _density_directions,
    _direct_irradiance_table,
    _group_ray_samples,
    _order_radiance,
    _scat_index,
    _segment_columns,
    _step,
    _trapezoid,
    _view_groups,
    transmittance_columns_table,
)
from .phase import rayleigh_phase, spectral_mie_phase
from .single import sun_visible_fraction


def _single_scattering_table(ctx, texels, quad: Quadrature, chunk_bytes: float, use_ckpt: bool) -> tuple[Tensor, Tensor]:
    """Single Rayleigh and Mie scattering without phase function (2017 ComputeSingleScattering).

    Trapezoid rule with ``quad.single_samples`` intervals from the texel's point to the
    nearest boundary; at each sample T(x, y) T(y, sun) (times the sun's visible fraction)
    times the density; times E_sun beta_s at the end. The view-ray quantities (sample
    radii, T(x, y)) are shared by the MU_S x NU texels of each (r, mu).
    Shapes (R, MU, MU_S, NU, W) each. [W/(m^2 nm)]
    """
    atm = ctx.atm
    dtype, device = atm.dtype, atm.device
    shape = texels.r.shape
    r, mu, g, mus, nu = _view_groups(texels)
    n_t = mus.shape[1]
    x, w = _trapezoid(quad.single_samples, dtype, device)
    n_w = atm.wavelengths.shape[0]

    def fn(i: int, j: int) -> Tensor:
        ext = extinction_matrix3(atm)
        dist, _, col_v, r_d, _, mus_d, _ = _group_ray_samples(ctx, r, mu, g, mus, nu, i, j, x)
        r_dt = r_d[:, None, :].expand_as(mus_d)
        col_s = _columns(ctx, r_dt, mus_d)  # (G, T, S, 3)
        vis = sun_visible_fraction(r_dt, mus_d, atm.bottom_radius, atm.sun_angular_radius)
        trans = torch.exp(-(col_v[:, None] + col_s) @ ext) * vis.unsqueeze(-1)  # (G, T, S, W)
        dens = profile_densities(r_d - atm.bottom_radius, atm, ozone=False)  # (G, S, 2)
        integ = torch.einsum("gsk,gtsw->gtkw", dens * (w * dist).unsqueeze(-1), trans)
        ray = integ[:, :, 0] * (atm.solar_irradiance * atm.rayleigh_scattering)
        mie = integ[:, :, 1] * (atm.solar_irradiance * atm.mie_scattering)
        return torch.cat([ray, mie], dim=-1)  # (G, T, 2W)

    step = _step(chunk_bytes, n_t * (quad.single_samples + 1) * (3 * n_w + 40), torch.finfo(dtype).bits // 8)
    out = _chunked(fn, r.shape[0], step, use_ckpt)
    return out[..., :n_w].reshape(*shape, n_w), out[..., n_w:].reshape(*shape, n_w)




def _indirect_irradiance_table(ctx, tables, order: int, quad: Quadrature, chunk_bytes: float, use_ckpt: bool) -> Tensor:
    """Delta E of ``order`` >= 1 bounces on a horizontal surface (2017 ComputeIndirectIrradiance).

    Midpoint rule over the upper hemisphere: sum of L_order(r, omega_z, mu_s, omega . s) omega_z d omega.
    Shape (n_r, n_mu_s, W). [W/(m^2 nm)]
    """
    atm, sizes = ctx.atm, ctx.sizes
    dtype, device = atm.dtype, atm.device
    r, mu_s = irradiance_texel_params(atm.bottom_radius, atm.top_radius, sizes, dtype, device)
    shape = r.shape
    r, mu_s = r.reshape(-1), mu_s.reshape(-1)
    nt, nph = quad.irradiance_theta, quad.irradiance_phi
    dth, dph = (math.pi / 2) / nt, (2 * math.pi) / nph
    th = (torch.arange(nt, dtype=dtype, device=device) + 0.5) * dth
    ph = (torch.arange(nph, dtype=dtype, device=device) + 0.5) * dph
    th, ph = torch.meshgrid(th, ph, indexing="ij")
    oz = torch.cos(th).reshape(-1)
    ox = (torch.sin(th) * torch.cos(ph)).reshape(-1)
    dom = (torch.sin(th) * dth * dph).reshape(-1)
    n_w = atm.wavelengths.shape[0]

    def fn(i: int, j: int) -> Tensor:
        rr, ss = r[i:j, None], mu_s[i:j, None]
        sin_s = safe_sqrt(1.0 - ss * ss)
        nu = torch.clamp(ox * sin_s + oz * ss, -1.0, 1.0)
        rr, ss = rr.expand_as(nu), ss.expand_as(nu)
        mu = oz.expand_as(nu)
        hits = torch.zeros_like(nu, dtype=torch.bool)
        L = _order_radiance(ctx, tables, order, rr, mu, ss, nu, hits)  # (n, D, W)
        return torch.einsum("ndw,d->nw", L, oz * dom)

    step = _step(chunk_bytes, nt * nph * (20 * n_w + 40), torch.finfo(dtype).bits // 8)
    return _chunked(fn, r.shape[0], step, use_ckpt).reshape(*shape, n_w)




def _scattering_density_table(
    ctx, texels, prev_tables, order: int, prev_irradiance: Tensor, quad: Quadrature, chunk_bytes: float, use_ckpt: bool
) -> Tensor:
    """Delta J of ``order`` >= 2 (2017 ComputeScatteringDensity), shape (R, MU, MU_S, NU, W). [W/(m^3 sr nm)]

    J(r, mu, mu_s, nu) = sum_i L_in(r, mu_s, omega_i) [beta_R rho_R(r) P_R(omega . omega_i)
    + beta_M rho_M(r) P_M(omega . omega_i)] d omega_i  (2008 eq. 7), with L_in the radiance of
    order - 1 bounces from the tables plus, for omega_i towards the ground, the ground's
    Lambertian reflection T alpha / pi Delta E_{order-2} (2008 Algorithm 4.1, first line of the loop).
    The incident directions are sampled in the sun's frame, so L_in is evaluated once per
    (r, mu_s) and shared by all view directions (mu, nu).
    """
    atm, sizes = ctx.atm, ctx.sizes
    dtype, device = atm.dtype, atm.device
    R, MU, MUS, NU = sizes.scattering_shape
    om, dom = _density_directions(quad, dtype, device)  # (D, 3), (D,)
    n_d = om.shape[0]
    n_w = atm.wavelengths.shape[0]
    # groups (r, mu_s), flattened as g = ir * MUS + ims
    r_g = texels.r[:, 0, :, 0].reshape(-1)
    mus_g = texels.mu_s[:, 0, :, 0].reshape(-1)
    mu_v = texels.mu[:, :, 0, :]  # (R, MU, NU), same for every mu_s
    nu_v = texels.nu.permute(0, 2, 1, 3)  # (R, MUS, MU, NU)

    def fn(i: int, j: int) -> Tensor:
        ext = extinction_matrix3(atm)
        rr, ss = r_g[i:j, None], mus_g[i:j, None]  # (G, 1)
        sin_s = safe_sqrt(1.0 - ss * ss)
        cz = om[:, 2].expand(rr.shape[0], n_d)
        nu1 = torch.clamp(om[:, 0] * sin_s + om[:, 2] * ss, -1.0, 1.0)  # (G, D)
        rr_, ss_ = rr.expand_as(nu1), ss.expand_as(nu1)
        hits = ray_hits_ground(rr_, cz, atm.bottom_radius)
        L = _order_radiance(ctx, prev_tables, order - 1, rr_, cz, ss_, nu1, hits)  # (G, D, W)
        # Light of order - 1 bounces whose last bounce is on the ground.
        d_g = torch.where(hits, distance_to_bottom(rr_, cz, atm.bottom_radius), torch.zeros_like(cz))
        col_g, r_d, _ = _segment_columns(ctx, rr_, cz, d_g, hits)
        mus_ground = torch.clamp((rr_ * ss_ + d_g * nu1) / r_d, -1.0, 1.0)
        e_g = interpolate([prev_irradiance], irradiance_index(torch.full_like(mus_ground, atm.bottom_radius), mus_ground,
                                                              atm.bottom_radius, atm.top_radius, sizes))[0]
        L = L + hits.unsqueeze(-1) * torch.exp(-col_g @ ext) * (atm.ground_albedo / math.pi) * e_g
        # View directions of the group's texels in the sun frame.
        ir = torch.div(torch.arange(i, j, device=device), MUS, rounding_mode="floor")
        ims = torch.arange(i, j, device=device) % MUS
        mu = mu_v[ir].reshape(j - i, MU * NU)  # (G, V)
        nu = nu_v[ir, ims].reshape(j - i, MU * NU)
        safe_sin = torch.where(sin_s > 0, sin_s, torch.ones_like(sin_s))
        vx = torch.where(sin_s > 0, (nu - mu * ss) / safe_sin, torch.zeros_like(nu))
        vy = safe_sqrt(1.0 - mu * mu - vx * vx)
        cosang = vx.unsqueeze(-1) * om[:, 0] + vy.unsqueeze(-1) * om[:, 1] + mu.unsqueeze(-1) * om[:, 2]  # (G, V, D)
        cosang = torch.clamp(cosang, -1.0, 1.0)
        dens = profile_densities(rr[:, 0] - atm.bottom_radius, atm, ozone=False)  # (G, 2)
        j_r = torch.bmm(rayleigh_phase(cosang) * dom, L)  # (G, V, W)
        pm = spectral_mie_phase(cosang, atm)  # (G, V, D, 1), or (G, V, D, W) for lognormal_mie
        j_m = torch.bmm(pm[..., 0] * dom, L) if pm.shape[-1] == 1 else torch.einsum("gvdw,gdw->gvw", pm * dom.unsqueeze(-1), L)
        out = j_r * (dens[:, 0, None, None] * atm.rayleigh_scattering) + j_m * (dens[:, 1, None, None] * atm.mie_scattering)
        return out  # (G, V, W)

    step = _step(chunk_bytes, MU * NU * n_d * 4 + n_d * 40 * n_w, torch.finfo(dtype).bits // 8)
    out = _chunked(fn, R * MUS, step, use_ckpt)  # (R*MUS, MU*NU, W)
    return out.reshape(R, MUS, MU, NU, n_w).permute(0, 2, 1, 3, 4).contiguous()


def _multiple_scattering_table(ctx, texels, density: Tensor, quad: Quadrature, chunk_bytes: float, use_ckpt: bool) -> Tensor:
    """Delta S of one order from its Delta J (2017 ComputeMultipleScattering), (R, MU, MU_S, NU, W).

    Trapezoid rule with ``quad.multiple_samples`` intervals of T(x, y) Delta J(y, v, s)
    from the texel's point to the nearest boundary (2008 eq. 11), T(x, y) shared by the
    MU_S x NU texels of each (r, mu). [W/(m^2 sr nm)]
    """
    atm = ctx.atm
    dtype, device = atm.dtype, atm.device
    shape = texels.r.shape
    r, mu, g, mus, nu = _view_groups(texels)
    n_t = mus.shape[1]
    x, w = _trapezoid(quad.multiple_samples, dtype, device)
    n_w = atm.wavelengths.shape[0]

    def fn(i: int, j: int) -> Tensor:
        ext = extinction_matrix3(atm)
        dist, _, col_v, r_d, mu_d, mus_d, nn = _group_ray_samples(ctx, r, mu, g, mus, nu, i, j, x)
        t_view = torch.exp(-col_v @ ext) * (w * dist).unsqueeze(-1)  # (G, S, W), with the weights
        idx = _scat_index(ctx, r_d[:, None, :], mu_d[:, None, :], mus_d, nn, g[i:j, :, None])
        dj = interpolate([density], idx)[0]  # (G, T, S, W)
        return torch.einsum("gtsw,gsw->gtw", dj, t_view)

    step = _step(chunk_bytes, n_t * (quad.multiple_samples + 1) * (3 * n_w + 60), torch.finfo(dtype).bits // 8)
    return _chunked(fn, r.shape[0], step, use_ckpt).reshape(*shape, n_w)




def precompute_reference(
    atm: Atmosphere,
    orders: int = 4,
    sizes: TableSizes | None = None,
    quadrature: Quadrature | None = None,
    mu_s_min: float = MU_S_MIN_DEFAULT,
    keep_orders: bool = False,
    chunk_bytes: float | None = None,
    checkpointing: bool | None = None,
) -> PrecomputedAtmosphere:
    """:func:`skyfit.scattering.multiple.precompute` before the rewrite (same arguments, same result to rounding)."""
    if not (isinstance(orders, int) and orders >= 1):
        raise ValueError(f"orders must be an integer >= 1, got {orders!r}")
    if not (-1.0 < mu_s_min < 0.0):
        raise ValueError(f"mu_s_min must be in (-1, 0), got {mu_s_min}")
    sizes = TableSizes() if sizes is None else sizes
    quad = Quadrature() if quadrature is None else quadrature
    if chunk_bytes is None:
        chunk_bytes = 2e9 if atm.device.type == "cuda" else 128e6
    if checkpointing is None:
        checkpointing = torch.is_grad_enabled() and any(getattr(atm, f).requires_grad for f in atm.tensor_fields())
    sync = torch.cuda.synchronize if atm.device.type == "cuda" else (lambda: None)
    timings: dict[str, float] = {}
    t_all = t0 = time.perf_counter()

    def lap(name: str) -> None:
        nonlocal t0
        sync()
        t = time.perf_counter()
        timings[name] = t - t0
        t0 = t

    tc = transmittance_columns_table(atm, sizes, quad.transmittance_samples, chunk_bytes, checkpointing)
    ctx = _Ctx(tc, atm, sizes, mu_s_min)
    lap("transmittance")
    direct = _direct_irradiance_table(ctx, sizes)
    lap("direct_irradiance")
    texels = scattering_texel_params(atm.bottom_radius, atm.top_radius, mu_s_min, sizes, atm.dtype, atm.device)
    s_r, s_m = _single_scattering_table(ctx, texels, quad, chunk_bytes, checkpointing)
    lap("single_scattering")
    irradiance = torch.zeros_like(direct)
    multiple = None
    kept_s: list[Tensor] = []
    kept_e: list[Tensor] = []
    prev_tables: tuple[Tensor, ...] = (s_r, s_m)
    prev_e = direct
    for n in range(2, orders + 1):
        dj = _scattering_density_table(ctx, texels, prev_tables, n, prev_e, quad, chunk_bytes, checkpointing)
        lap(f"order_{n}_density")
        prev_e = _indirect_irradiance_table(ctx, prev_tables, n - 1, quad, chunk_bytes, checkpointing)
        irradiance = irradiance + prev_e
        lap(f"order_{n}_irradiance")
        ds = _multiple_scattering_table(ctx, texels, dj, quad, chunk_bytes, checkpointing)
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
    )

