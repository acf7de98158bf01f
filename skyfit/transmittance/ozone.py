"""Exact column of the ozone tent profile along a straight segment in a spherical atmosphere.

The ozone number density relative to its peak is a *tent* in altitude h (Bruneton 2017,
demo.cc ozone layers; :func:`skyfit.atmosphere.profiles.ozone_tent_density`)::

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
    z = Delta (1 + (u1^2 + u2^2 + c) / (rho1 rho2 + u1 u2)) / (rho1 + rho2)

(from asinh a - asinh b = asinh(a sqrt(1 + b^2) - b sqrt(1 + a^2)) and the identity
rho1 rho2 - u1 u2 = c (u1^2 + u2^2 + c) / (rho1 rho2 + u1 u2)): the trapezoid rule in rho
plus the sagitta term, with asinh z - z from its Taylor series for |z| < 0.1. There is no
division by c, so vertical rays (c = 0) need no special case; rho1 rho2 + u1 u2 > 0 for
every ray that does not pass through the planet's centre, and the form cancels only where
u1 u2 < 0 and |u1 u2| ~ rho1 rho2, which the pieces below never have (none straddles the
ray's closest point to the centre, u = 0). The density offsets rho - rho_0 are formed from
altitudes (h(t) = (r - R) + (2 r mu t + t^2) / (rho + r)), not radii.

Piece order: along any ray rho(t) decreases to its minimum at t* = -r mu, then increases,
so the crossings t = -r mu -+ sqrt(rho_k^2 - c) come in the fixed order top-, peak-,
bottom-, t*, bottom+, peak+, top+ (a shell the ray misses is "crossed" at t*: the square
root of a negative discriminant is taken as 0). Clamped to [0, L], these seven points cut
the segment into pieces of known density: above top, falling, rising, below bottom
(twice), rising, falling, above top. Only four pieces carry ozone; no sorting, no branches.

Gradients: the crossing points are detached. This is exact, not an approximation: the
tent is continuous, so the derivative of the integral with respect to a split point
(the integrand on its left minus on its right) is zero; only the segment ends 0 and L
carry a boundary term. It also keeps the 1 / sqrt(discriminant) of tangent crossings out
of the graph, so gradients are finite for every ray (vertical, horizontal, tangent to a
shell, starting on a shell). Gradients flow to r, mu, length and to the layer altitudes
when they are tensors.

Accuracy (tests/test_ozone.py, docs/ozone.md): against scipy quad in float64 to ~1e-11
relative; in float32 to ~1e-4 of max(column, 1 m) at float32 inputs (r itself is resolved
to ~0.5 m at Earth's radius, so a grazing ray's column can move by 0.2 % from rounding its
inputs alone). Cost: docs/ozone.md (about as much as the two exponential layers of a
cheap integrator).
"""
from __future__ import annotations

import torch
from torch import Tensor


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


_PIECE_ENDS = (0, 1, 4, 5, 1, 2, 5, 6)
"""Starts then ends, indices into the seven split points (top-, peak-, bottom-, t*, bottom+, peak+,
top+), of the four ozone-carrying pieces: falling, rising, rising, falling."""


def ozone_column(r: Tensor, mu: Tensor, length: Tensor, bottom_radius: float, layer_m) -> Tensor:
    """Column of the ozone tent profile relative to its peak density along a segment (exact). [m]

    ``int_0^L f(h(t)) dt`` with f the tent of the module docstring, h(t) = |x + t v| - R.
    Optical depth = this column times ``ozone_absorption`` (the absorption coefficient at
    peak density [1/m]).

    Args:
        r: start radius (any: on the ground, inside or above the layer, in space), shape (...). [m]
        mu: cosine of the segment's zenith angle at its start, shape (...). [1]
        length: segment length >= 0, shape (...). [m]
        bottom_radius: planet radius R. [m]
        layer_m: (bottom, peak, top) altitudes of the tent, floats or tensors of shape ()
            (0 <= bottom < peak < top; checked for floats, ValueError otherwise). [m]

    Returns:
        Column, shape broadcast of (r, mu, length); follows their dtype and device. [m]
    """
    if all(isinstance(v, (int, float)) for v in layer_m) and not (len(layer_m) == 3 and 0 <= layer_m[0] < layer_m[1] < layer_m[2]):
        raise ValueError(f"ozone layer_m must be (bottom, peak, top) with 0 <= bottom < peak < top, got {tuple(layer_m)}")
    # The split points depend on (r, mu) only: computed on their shape, so that segments of one ray
    # with many lengths (the view-ray samples, r and mu of shape (n, 1), length (n, N)) share them.
    r, mu = torch.broadcast_tensors(r, mu)
    dtype, device = r.dtype, r.device
    lo, pk, hi = (torch.as_tensor(v, dtype=dtype, device=device) for v in layer_m)
    R = bottom_radius
    alt0 = (r - R).unsqueeze(-1)  # altitude of the start, (..., 1)
    rmu = (r * mu).unsqueeze(-1)
    re = r.unsqueeze(-1)
    c = (r * r * (1.0 - mu) * (1.0 + mu)).unsqueeze(-1)  # r^2 (1 - mu^2), accurate near the horizon

    # Split points t = -r mu -+ sqrt(rho_k^2 - c) of the shells (top, peak, bottom), detached (module
    # docstring). A missed shell (negative discriminant) gives sqrt(0): both at t*. The plain root form
    # may lose ~eps r in a root; the tent is continuous, so a split point off by d changes the
    # column by O(d^2 / layer thickness), nothing.
    with torch.no_grad():
        h_k = torch.stack([hi.detach(), pk.detach(), lo.detach()])  # (3,)
        a0d, rmud = alt0.detach(), rmu.detach()
        disc = (h_k - a0d) * (2.0 * R + h_k + a0d) + rmud * rmud  # rho_k^2 - c, (..., 3)
        sq = torch.sqrt(torch.clamp_min(disc, 0.0))
        p = torch.cat([-rmud - sq, -rmud, (sq - rmud).flip(-1)], dim=-1)  # (..., 7), in ray order
        p = torch.cummax(p.clamp_min(0.0), dim=-1).values  # monotone despite rounding
        p = p.index_select(-1, torch.tensor(_PIECE_ENDS, device=device))  # (..., 8): starts, ends
    p = torch.minimum(p, length.unsqueeze(-1))  # the points clamped to L carry L's gradient
    # Altitude and radius at the split points (h from the start's altitude: no R-sized cancellation).
    q = p * (2.0 * rmu + p)  # rho^2 - r^2
    rho = torch.sqrt(re * re + q)
    h = alt0 + q / (rho + re)
    t1, t2, rho1, rho2, h1, h2 = p[..., :4], p[..., 4:], rho[..., :4], rho[..., 4:], h[..., :4], h[..., 4:]
    delta = t2 - t1
    u1, u2 = t1 + rmu, t2 + rmu
    # z of the module docstring; rho1 rho2 + u1 u2 > 0 for every ray that does not pass through the
    # planet's centre (and a piece never straddles t*, where u changes sign, by more than rounding).
    z = delta * (1.0 + (u1 * u1 + u2 * u2 + c) / (rho1 * rho2 + u1 * u2)) / (rho1 + rho2)
    sag = 0.5 * c * asinh_minus_identity(z)  # int rho du - trapezoid in rho
    # Piece k: f = slope_k (h - h0_k): falling (top - h) / (top - peak), rising (h - bottom) / (peak - bottom).
    h0 = torch.stack([hi, lo, lo, hi])
    slope = torch.stack([-1.0 / (hi - pk), 1.0 / (pk - lo), 1.0 / (pk - lo), -1.0 / (hi - pk)])
    return ((delta * (0.5 * (h1 + h2) - h0) + sag) * slope).sum(-1)


def ozone_vertical_column(layer_m) -> float:
    """Column of the tent from the ground to space along the vertical, (top - bottom) / 2. [m]"""
    lo, _, hi = (float(v) for v in layer_m)
    return 0.5 * (hi - lo)
