"""Exact column of the ozone tent profile along a straight segment in a spherical atmosphere.

The ozone number density relative to its peak is a *tent* in altitude h (Bruneton 2017,
demo.cc ozone layers; :func:`skyfit.scattering.bruneton_tables.ozone_tent_density`)::

    f(h) = 0                                  h <= bottom or h >= top
           (h - bottom) / (peak - bottom)     bottom <= h <= peak
           (top - h) / (top - peak)           peak <= h <= top

Along a ray from radius r with zenith cosine mu the distance to the centre is
rho(t) = sqrt(r^2 + 2 r mu t + t^2) = sqrt(u^2 + c) with u = t + r mu and c = r^2 (1 - mu^2),
so on each part of the segment between two crossings of the shells R + bottom, R + peak,
R + top (quadratic roots) the density is ``b (rho - rho_0)``, linear in rho, and

    int rho du = (u sqrt(u^2 + c) + c asinh(u / sqrt(c))) / 2

integrates it exactly. That textbook form cancels catastrophically (every term is ~R^2
while the column is ~km) and is 0 * inf at c = 0 (vertical rays); we use the
equivalent, for a piece [u1, u2] with rho_i = rho(u_i) and Delta = u2 - u1,

    int_{u1}^{u2} rho du = Delta (rho1 + rho2) / 2 + c (asinh z - z) / 2,
    z = Delta (1 + (u1^2 + u2^2 + c) / (rho1 rho2 + u1 u2)) / (rho1 + rho2)        (u1 u2 >= 0)
    z = Delta (c + rho1 rho2 - u1 u2) / (c (rho1 + rho2))                          (u1 u2 < 0)

(from asinh a - asinh b = asinh(a sqrt(1 + b^2) - b sqrt(1 + a^2)) and
rho1 rho2 - u1 u2 = c (u1^2 + u2^2 + c) / (rho1 rho2 + u1 u2)): the trapezoid rule in rho
plus the sagitta term, with asinh z - z from its Taylor series for |z| < 0.1. No division
by c except where u1 u2 < 0, i.e. the piece passes the ray's closest point to the centre,
which lies inside the layer (so c >= (R + bottom)^2 > 0). The density offsets rho - rho_0
are formed from altitudes (h(t) = (r - R) + (2 r mu t + t^2) / (rho + r)), not radii.

Piece order: along any ray rho(t) decreases to its minimum at t* = -r mu, then increases,
so the crossings come in the fixed order top-, peak-, bottom-, t*, bottom+, peak+, top+
(a shell the ray misses is "crossed" at t*). Clamped to [0, L], these eight points cut
the segment into pieces of known density: above top, falling, rising, below bottom
(twice), rising, falling, above top. Only four pieces carry ozone.

Gradients: the crossing points are detached. This is exact, not an approximation: the
tent is continuous, so the derivative of the integral with respect to a split point
(the integrand on its left minus on its right) is zero; only the segment ends 0 and L
carry a boundary term. It also keeps the 1 / sqrt(discriminant) of tangent crossings out
of the graph, so gradients are finite for every ray (vertical, horizontal, tangent to a
shell, starting on a shell). Gradients flow to r, mu, length and to the layer altitudes
when they are tensors.

Accuracy (tests/test_ozone.py, docs/ozone.md): against scipy quad in float64 to ~1e-12
relative; in float32 the altitude of a point, r - R, is itself resolved to ~0.5 m at
Earth's radius, which bounds the column's relative accuracy at ~1e-4 on short segments.
"""
from __future__ import annotations

import torch
from torch import Tensor

from ..geometry import safe_sqrt

ASINH_SERIES_Z: float = 0.1
"""Below this |z|, asinh z - z is summed from its Taylor series (to z^13: relative error < 1e-13);
above it the direct difference loses at most 6 eps / z^2 relative (2e-14 in float64). [1]"""

# asinh z - z = sum_k (-1)^k (2k)! / (4^k (k!)^2 (2k + 1)) z^(2k + 1), k >= 1
_ASINH_COEFFS = (-1.0 / 6.0, 3.0 / 40.0, -5.0 / 112.0, 35.0 / 1152.0, -63.0 / 2816.0, 231.0 / 13312.0)


def asinh_minus_identity(z: Tensor) -> Tensor:
    """``asinh(z) - z`` without cancellation for small |z| (odd Taylor series below ASINH_SERIES_Z). [1]"""
    small = z.abs() < ASINH_SERIES_Z
    zs = torch.where(small, z, torch.zeros_like(z))
    z2 = zs * zs
    poly = torch.zeros_like(z)
    for a in reversed(_ASINH_COEFFS):
        poly = poly * z2 + a
    series = poly * z2 * zs
    return torch.where(small, series, torch.asinh(z) - z)


def _crossings(r: Tensor, rmu: Tensor, alt0: Tensor, h: Tensor, bottom_radius: float) -> tuple[Tensor, Tensor]:
    """Distances (t-, t+) where the ray meets the shell at altitude h; both t* = -r mu if it misses. [m]

    Stable root forms (the product of the roots is r^2 - rho_k^2): no cancellation for any sign of mu.
    """
    rho_k = bottom_radius + h
    dr = h - alt0  # rho_k - r, from altitudes
    prod = -dr * (rho_k + r)  # r^2 - rho_k^2
    disc = dr * (rho_k + r) + rmu * rmu  # rho_k^2 - r^2 (1 - mu^2)
    sq = safe_sqrt(disc)
    up = rmu > 0
    big = torch.where(up, -(rmu + sq), -rmu + sq)  # the root without cancellation
    big_safe = torch.where(big != 0, big, torch.ones_like(big))
    small = torch.where(big != 0, prod / big_safe, -rmu)
    t_minus = torch.where(up, big, small)
    t_plus = torch.where(up, small, big)
    miss = disc <= 0
    return torch.where(miss, -rmu, t_minus), torch.where(miss, -rmu, t_plus)


def ozone_column(r: Tensor, mu: Tensor, length: Tensor, bottom_radius: float, layer_m) -> Tensor:
    """Column of the ozone tent profile relative to its peak density along a segment (exact). [m]

    ``int_0^L f(h(t)) dt`` with f the tent of module docstring, h(t) = |x + t v| - R.
    Optical depth = this column times ``ozone_absorption`` (the absorption coefficient at
    peak density [1/m]).

    Args:
        r: start radius (any: on the ground, inside or above the layer, in space), shape (...). [m]
        mu: cosine of the segment's zenith angle at its start, shape (...). [1]
        length: segment length >= 0, shape (...). [m]
        bottom_radius: planet radius R. [m]
        layer_m: (bottom, peak, top) altitudes of the tent, floats or tensors of shape ()
            (0 <= bottom < peak < top). [m]

    Returns:
        Column, shape broadcast of (r, mu, length); follows their dtype and device. [m]
    """
    r, mu, length = torch.broadcast_tensors(r, mu, length)
    lo, pk, hi = (torch.as_tensor(v, dtype=r.dtype, device=r.device) for v in layer_m)
    R = bottom_radius
    alt0 = r - R
    rmu = r * mu
    c = r * r * (1.0 - mu) * (1.0 + mu)  # r^2 (1 - mu^2), accurate near the horizon

    # Split points (detached: see module docstring), clamped to the segment.
    with torch.no_grad():
        rd, rmud, a0d = r.detach(), rmu.detach(), alt0.detach()
        minus, plus = [], []
        for h in (hi, pk, lo):
            tm, tp = _crossings(rd, rmud, a0d, h.detach(), R)
            minus.append(tm)
            plus.append(tp)
        pts = minus + [-rmud] + plus[::-1]  # top-, peak-, bottom-, t*, bottom+, peak+, top+
        p = torch.stack(pts, dim=-1).clamp_min(0.0)
        p = torch.cummax(p, dim=-1).values  # monotone despite rounding
    L = length.unsqueeze(-1)
    p = torch.minimum(p, L)  # the ones clamped to L carry L's gradient
    # Ozone-carrying pieces: (top-, peak-) falling, (peak-, bottom-) rising, (bottom+, peak+) rising,
    # (peak+, top+) falling.
    t1 = torch.stack([p[..., 0], p[..., 1], p[..., 4], p[..., 5]], dim=-1)
    t2 = torch.stack([p[..., 1], p[..., 2], p[..., 5], p[..., 6]], dim=-1)
    re, rmue, a0e, ce = (v.unsqueeze(-1) for v in (r, rmu, alt0, c))

    def at(t):
        q = 2.0 * rmue * t + t * t  # rho^2 - r^2
        rho = safe_sqrt(re * re + q)
        return rho, a0e + q / (rho + re)  # rho, altitude

    rho1, h1 = at(t1)
    rho2, h2 = at(t2)
    delta = t2 - t1
    u1, u2 = t1 + rmue, t2 + rmue
    uu = u1 * u2
    same = uu >= 0
    s = rho1 + rho2
    den = rho1 * rho2 + uu
    den = torch.where(same & (den > 0), den, torch.ones_like(den))
    k_same = 1.0 + (u1 * u1 + u2 * u2 + ce) / den
    c_safe = torch.where(same | (ce <= 0), torch.ones_like(ce), ce)
    k_cross = (ce + rho1 * rho2 - uu) / c_safe
    z = delta * torch.where(same, k_same, k_cross) / s
    sag = 0.5 * ce * asinh_minus_identity(z)  # int rho du - trapezoid in rho
    # Falling pieces: f = (top - h) / (top - peak); rising: (h - bottom) / (peak - bottom).
    fall = ((hi - h1) + (hi - h2)) * 0.5 * delta - sag
    rise = ((h1 - lo) + (h2 - lo)) * 0.5 * delta + sag
    col = (fall[..., 0] + fall[..., 3]) / (hi - pk) + (rise[..., 1] + rise[..., 2]) / (pk - lo)
    return col


def ozone_vertical_column(layer_m) -> float:
    """Column of the tent from the ground to space along the vertical, (top - bottom) / 2. [m]"""
    lo, _, hi = (float(v) for v in layer_m)
    return 0.5 * (hi - lo)
