"""Single-scattering radiance (Gałaj 2019 eq. 9; Bruneton & Neyret 2008 eqs. 1-7).

    L(x, v, s) = E_sun  int_0^{l}  T(x, y) T(y, sun) sum_i beta_i(y) P_i(nu) dy     (+ ground)

with T = exp(-sum_i beta_i^e column_i) from an optical-depth integrator (Rayleigh and Mie
exponential layers) and, when the atmosphere has ozone, the exact column of the ozone tent
layer times ``ozone_absorption`` (:func:`skyfit.transmittance.ozone_column`, closed form,
the same for every integrator): T(x, y), T(y, sun), the ground's two paths and the solar
disc all include it. The outer integral over the view ray is a fixed rule with N samples. The sun is
attenuated by the fraction of its disc above the horizon seen from each
point (Bruneton 2017, GetTransmittanceToSun), which makes the shadow edge
smooth and sun-below-horizon skies well defined.
"""
from __future__ import annotations

import math
from typing import NamedTuple

import torch
from torch import Tensor

from ..atmosphere import Atmosphere
from ..atmosphere.profiles import with_mie_profile
from ..geometry import atmosphere_segment, distance_to_top, point_along_ray, safe_sqrt, sun_cosine_along_ray
from ..quadrature import nodes_weights, validate_rule
from ..transmittance import ColumnFn, OpticalDepthIntegrator, ozone_column, prepare_columns
from ..transmittance.quadrature import QuadratureOpticalDepth
from .phase import rayleigh_phase, spectral_mie_phase

CHUNK_BYTES_CPU: float = 64e6
"""Default working memory per chunk of rays on the CPU [bytes]: large enough that the
per-operation overhead is small, small enough to bound memory (docs/benchmarks.md)."""
CHUNK_BYTES_ACCELERATOR: float = 1e9
"""Default on other devices [bytes]: a 256 x 256 sky in one chunk, since there the cost is
one kernel launch per operation and chunk."""


def _cos_horizon(r: Tensor, bottom_radius: float) -> Tensor:
    """|cos| of the horizon's zenith angle at radius r: sqrt(1 - (R/r)^2), >= 0. [1]

    Written as sqrt((r - R)(r + R)) / r: ``1 - (R/r)^2`` loses about 3e-4 in float32 within
    metres of the ground (docs/stability.md), which moved the visible fraction of a sun at
    90.27 deg by 14 % at 1 m.
    """
    d = torch.clamp(r - bottom_radius, min=0.0)
    return safe_sqrt(d * (r + bottom_radius)) / r


def sun_visible_fraction(r: Tensor, mu_s: Tensor, bottom_radius: float, sun_angular_radius: float) -> Tensor:
    """Fraction of the solar disc above the planet's horizon seen from radius r (Bruneton 2017). [1]

    ``smoothstep(-sin_h * alpha_s, sin_h * alpha_s, mu_s - cos_h)`` with the
    horizon's angle from the zenith given by sin_h = R / r.
    """
    sin_h = torch.clamp(bottom_radius / r, max=1.0)
    cos_h = -_cos_horizon(r, bottom_radius)
    w = sin_h * sun_angular_radius
    x = torch.clamp((mu_s - cos_h + w) / (2.0 * w), 0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)


def sun_ray_cosine(r: Tensor, mu_s: Tensor, bottom_radius: float) -> Tensor:
    """Zenith cosine of the ray whose column attenuates the sun: mu_s, raised to the horizon's cos_h. [1]

    Inside the smoothstep band of :func:`sun_visible_fraction` the sun's centre may
    be below the horizon while part of its disc is still seen, along rays at or
    above the horizon. Their transmittance is taken as that of the horizon ray, as
    Bruneton 2017's table does (it is clamped to mu >= cos_h). A line through the
    planet instead has a density exp(depth / H) that overflows for small H (e.g.
    e^9600 for H = 10 m, sun 10° below the horizon), and inf * 0 gives NaN values
    (beta = 0) and NaN gradients where the sun is hidden (vis = 0).
    """
    return torch.maximum(mu_s, -_cos_horizon(r, bottom_radius))


def path_columns(column_fn: ColumnFn, atm: Atmosphere, r: Tensor, mu: Tensor, length: Tensor) -> Tensor:
    """Columns of every absorber along segments: the integrator's (Rayleigh, Mie) and, when
    ``atm.ozone_absorption`` is set, the exact ozone tent column last, shape (..., K [+ 1]). [m]

    Args:
        column_fn: a prepared integrator, ``(r, mu, length) -> (..., K)``.
        r, mu, length: segment start radius [m], zenith cosine [1] and length [m], broadcastable.

    Optical depth = ``path_columns(...) @ path_extinction(atm)``.
    """
    col = column_fn(r, mu, length)
    if atm.ozone_absorption is None:
        return col
    oz = ozone_column(r, mu, length, atm.bottom_radius, atm.ozone_layer_m)
    return torch.cat([col, oz.unsqueeze(-1).expand(*col.shape[:-1], 1)], dim=-1)


def path_extinction(atm: Atmosphere) -> Tensor:
    """Rows matching :func:`path_columns`: (Rayleigh scattering, Mie extinction[, ozone
    absorption at peak density]), shape (K [+ 1], W). [1/m]"""
    if atm.ozone_absorption is None:
        return atm.extinction_matrix
    return torch.cat([atm.extinction_matrix, atm.ozone_absorption.unsqueeze(0)], dim=0)


def transmittance_to_sun(column_fn: ColumnFn, atm: Atmosphere, r: Tensor, mu_s: Tensor) -> Tensor:
    """Transmittance from radius r to the sun (ozone included), times its visible fraction, shape (..., W). [1]"""
    mu_c = sun_ray_cosine(r, mu_s, atm.bottom_radius)
    col = path_columns(column_fn, atm, r, mu_c, distance_to_top(r, mu_c, atm.top_radius))  # (..., K [+ 1])
    vis = sun_visible_fraction(r, mu_s, atm.bottom_radius, atm.sun_angular_radius)
    return torch.exp(-col @ path_extinction(atm)) * vis.unsqueeze(-1)


class ViewRaySamples(NamedTuple):
    """Sample points of the outer (view-ray) integral; per-ray fields (n,), per-sample fields (n, N)."""

    hits: Tensor  # the ray ends on the ground
    seg: Tensor  # length of the part inside the atmosphere [m]
    r0: Tensor  # radius where that part starts (the observer, or the entry from space) [m]
    mu0: Tensor  # view cosine there [1]
    mus0: Tensor  # sun cosine there [1]
    s: Tensor  # distances of the samples from the start [m]
    r_j: Tensor  # radii of the samples [m]
    mus_j: Tensor  # sun cosines at the samples [1]


def ray_parameters(atm: Atmosphere, view: Tensor, sun: Tensor, altitude) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """(r, mu, mu_s, nu) of view and sun vectors seen from ``altitude``, in the atmosphere's dtype and device.

    Args:
        view: unit view directions East-North-Up, shape (..., 3). [1]
        sun: unit direction to the sun, shape (3,) or (..., 3). [1]
        altitude: observer height above the ground, scalar or shape (...). [m]

    Returns:
        r (distance from the planet centre) [m], mu, mu_s (the Up components) and nu = view . sun [1],
        each clamped to [-1, 1]; nu needs no angles, so it is smooth at the zenith.
    """
    view = torch.as_tensor(view, dtype=atm.dtype, device=atm.device)
    sun = torch.as_tensor(sun, dtype=atm.dtype, device=atm.device)
    mu = torch.clamp(view[..., 2], -1.0, 1.0)
    mu_s = torch.clamp(sun[..., 2], -1.0, 1.0)
    nu = torch.clamp((view * sun).sum(-1), -1.0, 1.0)
    r = atm.bottom_radius + torch.as_tensor(altitude, dtype=atm.dtype, device=atm.device)
    return r, mu, mu_s, nu


def _segment_start(atm: Atmosphere, r: Tensor, mu: Tensor, mu_s: Tensor, nu: Tensor):
    """(hits, seg, r0, mu0, mus0) of :class:`ViewRaySamples`: the in-atmosphere part of each view ray."""
    Rb, Rt = atm.bottom_radius, atm.top_radius
    start, end, hits = atmosphere_segment(r, mu, Rb, Rt)
    seg = end - start
    # Start of the segment (the observer, or where a ray from space enters).
    r0, mu0 = point_along_ray(r, mu, start)
    # A ray from space that misses the atmosphere has seg = 0 and r0 = r > top; keep the
    # (zero-length) segments the integrators see inside the atmosphere, which tables require.
    r0 = torch.clamp_max(r0, Rt)
    mus0 = sun_cosine_along_ray(r, mu_s, nu, start, r0)
    return hits, seg, r0, mu0, mus0


def view_ray_samples(atm: Atmosphere, r: Tensor, mu: Tensor, mu_s: Tensor, nu: Tensor, x: Tensor) -> ViewRaySamples:
    """Place the nodes ``x`` (on [0, 1]) of the outer rule on the in-atmosphere part of each view ray.

    Args:
        r, mu, mu_s, nu: observer radius and cosines, shape (n,). [m], [1]
        x: quadrature nodes on [0, 1] as fractions of each segment, shape (N,), or per ray (n, N)
            (:func:`geometric_nodes`).
    """
    hits, seg, r0, mu0, mus0 = _segment_start(atm, r, mu, mu_s, nu)
    s = seg.unsqueeze(-1) * x
    r0e, mu0e, mus0e, nue = (t.unsqueeze(-1) for t in (r0, mu0, mus0, nu))
    r_j, _ = point_along_ray(r0e, mu0e, s)
    mus_j = sun_cosine_along_ray(r0e, mus0e, nue, s, r_j)
    return ViewRaySamples(hits, seg, r0, mu0, mus0, s, r_j, mus_j)


SPACINGS: tuple[str, ...] = ("uniform", "geometric")
"""How the outer rule's nodes are spread along a view ray: ``uniform`` in distance, or ``geometric``
(:func:`geometric_nodes`; docs/accuracy.md, "Render defaults")."""

GEOMETRIC_MIN_RATE: float = 1e-6
"""Smallest rate ``a`` of :func:`geometric_nodes` [1]: at a -> 0 the spacing is uniform, and
expm1(a x) / expm1(a) stays exact in float32 at this value."""

GEOMETRIC_FALLING_MU: tuple[float, float] = (-0.02, -0.01)
""":func:`geometric_nodes` goes over to uniform spacing as the view cosine at the segment's start falls from
-0.01 to -0.02 (linearly in ``a``), so that the nodes and the radiance stay continuous across the horizon. [1]"""


def validate_spacing(spacing: str) -> str:
    if spacing not in SPACINGS:
        raise ValueError(f"unknown view-ray spacing {spacing!r}; valid: {', '.join(SPACINGS)}")
    return spacing


def _distance_to_climb(r: Tensor, mu: Tensor, height: Tensor) -> Tensor:
    """Distance along a ray from (r, mu) until it is ``height`` >= 0 higher than r, ``sqrt((r mu)^2 + h (2 r + h)) - r mu``
    (through the tangent point for mu < 0); for mu >= 0 in the quotient form, without cancellation. Smooth in mu. [m]"""
    b = r * mu
    up = height * (2.0 * r + height)
    root = safe_sqrt(b * b + up)
    rising = up / torch.clamp_min(root + torch.clamp_min(b, 0.0), torch.finfo(r.dtype).tiny)
    return torch.where(b >= 0.0, rising, root - b)


def geometric_nodes(atm: Atmosphere, r: Tensor, mu: Tensor, mu_s: Tensor, nu: Tensor, x: Tensor) -> tuple[Tensor, Tensor]:
    """Nodes of the outer rule spaced geometrically along each view ray: fractions of the segment and their Jacobian.

    A uniform rule in distance wastes its nodes on a long ray whose integrand lives in the first
    kilometres: a 1.2 km Mie layer seen at 5° elevation from the ground, or a hazy sky whose
    transmittance T(x, y) falls by e within 3 km. Nodes x uniform in ``log(1 + s / l)`` instead,

        s(x) = seg expm1(a x) / expm1(a),   a = log(1 + seg / l),

    are spaced like the density they sample: about ``l`` apart near the start, growing
    geometrically beyond, so that every layer thinner than the ray, at any elevation, gets nodes.
    The length ``l`` is the distance along the ray to climb the thinnest scale height ``H_min``,
    shortened by the extinction at the start (``l_H / (1 + l_H beta_max)``, beta_max over
    wavelengths), plus, with the sun below the observer's horizon, the distance to climb out of
    the planet's shadow (to ``R / cos(depression)``, where the light starts). Rays that go down
    from their start (the ground or a tangent point is where the density peaks) keep the uniform
    spacing (a -> 0 as mu0 falls through :data:`GEOMETRIC_FALLING_MU`).

    Args:
        r, mu, mu_s, nu: observer radius and cosines, shape (n,). [m], [1]
        x: nodes of the rule on [0, 1], shape (N,).

    Returns:
        (u, du_dx): node fractions of each ray's segment and d u / d x, shape (n, N) each. [1]
        ``int_0^seg f(s) ds = seg sum_j w_j du_dx_j f(seg u_j)``.
    """
    Rb = atm.bottom_radius
    _, seg, r0, mu0, mus0 = _segment_start(atm, r, mu, mu_s, nu)
    h0 = torch.clamp_min(r0 - Rb, 0.0)
    l_h = _distance_to_climb(r0, mu0, atm.scale_heights.min())
    dens0 = with_mie_profile(torch.exp(h0.unsqueeze(-1) * -(1.0 / atm.scale_heights)), h0, atm)  # (n, K)
    beta = (dens0 @ atm.extinction_matrix).amax(-1)  # largest extinction at the start [1/m]
    ell = l_h / (1.0 + l_h * beta)
    # Sun below the horizon: the ray is dark until it rises above the shadow, R / cos(depression) - r0.
    m = torch.clamp_max(mus0, 0.0)
    cos_d = safe_sqrt(1.0 - m * m)
    shadow = Rb * (m * m) / torch.clamp_min(cos_d * (1.0 + cos_d), 1e-6)  # R (1 / cos - 1), stable at m = 0
    # (rising form: exactly 0 in daylight, where the climb of 0 m of a falling ray, 2 r0 |mu0|, would put a kink in mu0)
    ell = ell + _distance_to_climb(r0, torch.clamp_min(mu0, 0.0), torch.clamp_min(shadow - h0, 0.0))
    lo, hi = GEOMETRIC_FALLING_MU
    rising = torch.clamp((mu0 - lo) / (hi - lo), 0.0, 1.0)
    a = torch.clamp_min(rising * torch.log1p(seg / ell), GEOMETRIC_MIN_RATE).unsqueeze(-1)
    den = torch.expm1(a)
    return torch.expm1(a * x) / den, a * torch.exp(a * x) / den


def _render_chunk(atm, column_fn, r, mu, mu_s, nu, x, w, ground, sun_disk, spacing="uniform"):
    Rb, Rt = atm.bottom_radius, atm.top_radius
    if spacing == "geometric":
        x, du_dx = geometric_nodes(atm, r, mu, mu_s, nu, x)
        w = w * du_dx  # (n, N)
    hits, seg, r0, mu0, mus0, s, r_j, mus_j = view_ray_samples(atm, r, mu, mu_s, nu, x)
    r0e, mu0e = r0.unsqueeze(-1), mu0.unsqueeze(-1)
    # T(x, y_j) T(y_j, sun) = exp(-(column(x, y_j) + column(y_j, sun)) @ extinction): one
    # matmul and one exp over wavelengths; the sun's visible fraction goes into the weights.
    mus_c = sun_ray_cosine(r_j, mus_j, Rb)
    col = path_columns(column_fn, atm, r0e, mu0e, s) + path_columns(column_fn, atm, r_j, mus_c, distance_to_top(r_j, mus_c, Rt))
    ext = path_extinction(atm)  # (K [+ 1], W); the ozone column is the last of col's (n, N, K [+ 1])
    trans = torch.matmul(col, -ext).exp_()  # (n, N, W)
    vis = sun_visible_fraction(r_j, mus_j, Rb, atm.sun_angular_radius)  # (n, N)
    dens = with_mie_profile(torch.exp((r_j - Rb).unsqueeze(-1) * -(1.0 / atm.scale_heights)), r_j - Rb, atm)  # (n, N, 2)
    wd = dens * (vis * (w * seg.unsqueeze(-1))).unsqueeze(-1)  # quadrature weight x density x sun fraction
    ray_int = torch.bmm(wd.transpose(1, 2), trans)  # (n, 2, W)
    p_r = rayleigh_phase(nu).unsqueeze(-1)
    p_m = spectral_mie_phase(nu, atm)  # (n, 1), or (n, W) for lognormal_mie
    radiance = ray_int[:, 0] * atm.rayleigh_scattering * p_r + ray_int[:, 1] * atm.mie_scattering * p_m
    radiance = radiance * atm.solar_irradiance
    if ground:
        # Lambertian ground lit by the attenuated direct sun (its single-bounce term).
        col_g = path_columns(column_fn, atm, r0, mu0, seg)
        t_g = torch.exp(-col_g @ ext)
        r_g = torch.full_like(r, Rb)
        mus_g = sun_cosine_along_ray(r0, mus0, nu, seg, torch.clamp_min(point_along_ray(r0, mu0, seg)[0], Rb))
        e_g = transmittance_to_sun(column_fn, atm, r_g, mus_g) * torch.clamp_min(mus_g, 0.0).unsqueeze(-1)
        radiance = radiance + hits.unsqueeze(-1) * t_g * atm.ground_albedo / math.pi * e_g * atm.solar_irradiance
    if sun_disk:
        col_t = path_columns(column_fn, atm, r0, mu0, seg)
        t_top = torch.exp(-col_t @ ext)
        in_disk = (nu > math.cos(atm.sun_angular_radius)) & ~hits
        disk = atm.solar_irradiance / (math.pi * atm.sun_angular_radius**2)
        radiance = radiance + in_disk.unsqueeze(-1) * t_top * disk
    return radiance


def single_scattering(
    atm: Atmosphere,
    r: Tensor,
    mu: Tensor,
    mu_s: Tensor,
    nu: Tensor,
    integrator: OpticalDepthIntegrator,
    view_samples: int = 32,
    rule: str = "trapezoid",
    ground: bool = True,
    sun_disk: bool = False,
    chunk_bytes: float | None = None,
    column_fn: ColumnFn | None = None,
    spacing: str = "uniform",
) -> Tensor:
    """Spectral single-scattering radiance for a batch of rays.

    Args:
        atm: the atmosphere (its dtype and device are used throughout).
        r: observer distance from the planet centre, shape (...). [m]
        mu: cosine of the view zenith angle, shape (...). [1]
        mu_s: cosine of the sun zenith angle at the observer, shape (...). [1]
        nu: cosine of the angle between view and sun, shape (...). [1]
        integrator: optical-depth method for the Rayleigh and Mie columns of T(x, y) and
            T(y, sun); the ozone column (when ``atm.ozone_absorption`` is set) is exact.
        view_samples: N, samples of the outer integral.
        rule: outer quadrature rule (trapezoid, midpoint, simpson, gauss).
        ground: add the Lambertian ground lit by the direct sun for rays that hit it.
        sun_disk: add the attenuated solar disc.
        chunk_bytes: working memory per chunk of rays, bounding memory for large images
            (default CHUNK_BYTES_CPU on the CPU, CHUNK_BYTES_ACCELERATOR elsewhere). [bytes]
        column_fn: a prepared integrator (to reuse precomputation across calls).
        spacing: ``uniform`` (nodes spread evenly in distance) or ``geometric`` (:func:`geometric_nodes`:
            dense where the thinnest layer is; ``skyfit render``'s default, docs/accuracy.md).

    Returns:
        Spectral radiance, shape (..., W). [W/(m^2 sr nm)]
    """
    validate_rule(rule)
    validate_spacing(spacing)
    dtype, device = atm.dtype, atm.device
    r, mu, mu_s, nu = (torch.as_tensor(t, dtype=dtype, device=device) for t in (r, mu, mu_s, nu))
    r, mu, mu_s, nu = torch.broadcast_tensors(r, mu, mu_s, nu)
    batch_shape = r.shape
    r, mu, mu_s, nu = (t.reshape(-1) for t in (r, mu, mu_s, nu))
    x, w = nodes_weights(rule, view_samples, dtype, device)
    if column_fn is None:
        column_fn = prepare_columns(integrator, atm)
    n_w = atm.wavelengths.shape[0]
    # Working set per sample point: ~6 (W,)-vectors and ~24 scalars, plus a quadrature
    # integrator's (M, K) density grids for its M inner samples.
    inner = 8 * integrator.samples * atm.scale_heights.shape[0] if isinstance(integrator, QuadratureOpticalDepth) else 0
    inner += 120 if atm.ozone_absorption is not None else 0  # the ozone column's 4 pieces x ~30 temporaries
    per_ray = x.shape[0] * (6 * n_w + 24 + inner) * torch.finfo(dtype).bits // 8
    if chunk_bytes is None:
        chunk_bytes = CHUNK_BYTES_CPU if torch.device(device).type == "cpu" else CHUNK_BYTES_ACCELERATOR
    step = max(1, int(chunk_bytes // per_ray))
    out = [
        _render_chunk(atm, column_fn, r[i : i + step], mu[i : i + step], mu_s[i : i + step], nu[i : i + step], x, w, ground, sun_disk, spacing)
        for i in range(0, r.shape[0], step)
    ]
    res = torch.cat(out, 0) if out else torch.zeros(0, n_w, dtype=dtype, device=device)
    return res.reshape(*batch_shape, n_w)
