"""Ray geometry in a spherical atmosphere, safe for values and gradients everywhere.

Conventions (Bruneton & Neyret 2008, Sec. 4; Bruneton 2017): a point is at
distance ``r`` from the planet centre; ``mu`` is the cosine of the angle
between the ray and the local vertical (1 straight up, -1 straight down),
``mu_s`` the same for the sun, ``nu`` the cosine of the view-sun angle.

Square roots of quantities that are non-negative in exact arithmetic are
taken with :func:`safe_sqrt`, whose value clamps rounding negatives to 0 and
whose gradient stays finite at 0 (``torch.sqrt`` has an infinite derivative
there and ``clamp`` alone gives NaN through ``0 * inf``).

Directions as unit vectors in the local East-North-Up (ENU) frame, zenith angle
from Up and azimuth clockwise from North (CONTRACT.md): :func:`zenith_azimuth_to_enu`
and :func:`enu_to_zenith_azimuth`.
"""
from __future__ import annotations

import math

import torch
from torch import Tensor


def safe_sqrt(x: Tensor, eps: float | None = None) -> Tensor:
    """``sqrt(max(x, 0))`` with a finite gradient at and below 0.

    The gradient is that of ``sqrt(max(x, eps))`` where x > eps and 0 below,
    so NaN never appears through ``torch.where``'s untaken branch.
    """
    if eps is None:
        eps = torch.finfo(x.dtype).tiny ** 0.5 if x.is_floating_point() else 1e-30
    pos = x > eps
    xs = torch.where(pos, x, torch.ones_like(x))
    return torch.where(pos, torch.sqrt(xs), torch.zeros_like(x))


def discriminant(r: Tensor, mu: Tensor, radius) -> Tensor:
    """``r^2 (mu^2 - 1) + radius^2``: >= 0 iff the ray's line meets the sphere. [m^2]

    Written as ``radius^2 - r^2 (1 - mu^2)`` with ``(1 - mu)(1 + mu)`` for accuracy
    near the horizon (mu -> 0 at r ~ radius cancels catastrophically otherwise).
    """
    return (radius - r) * (radius + r) + r * r * mu * mu


def distance_to_top(r: Tensor, mu: Tensor, top_radius) -> Tensor:
    """Distance along the ray to the top-of-atmosphere sphere, for r <= top (Bruneton 2017). [m]

    Uses the numerically stable root form: for mu < 0 the difference
    ``-r mu + sqrt(D)`` is fine; for mu > 0 we use ``(top^2 - r^2) / (r mu + sqrt(D))``.
    Values are clamped at 0 (an observer exactly at or above the top looking up).
    """
    d = safe_sqrt(discriminant(r, mu, top_radius))
    up = (top_radius - r) * (top_radius + r)
    denom = r * mu + d
    ok = denom > 0
    stable = up / torch.where(ok, denom, torch.ones_like(denom))
    return torch.clamp_min(torch.where(ok & (mu > 0), stable, -r * mu + d), 0.0)


def distance_to_bottom(r: Tensor, mu: Tensor, bottom_radius) -> Tensor:
    """Distance along the ray to the first ground intersection (only meaningful if it hits). [m]"""
    d = safe_sqrt(discriminant(r, mu, bottom_radius))
    # -r mu - d == (r^2 - R^2) / (-r mu + d): stable when -r mu > 0.
    num = (r - bottom_radius) * (r + bottom_radius)
    denom = -r * mu + d
    ok = denom > 0
    return torch.clamp_min(num / torch.where(ok, denom, torch.ones_like(denom)), 0.0) * ok


def ray_hits_ground(r: Tensor, mu: Tensor, bottom_radius) -> Tensor:
    """True where the ray from (r, mu) meets the planet (Bruneton 2017, RayIntersectsGround)."""
    return (mu < 0) & (discriminant(r, mu, bottom_radius) >= 0)


def atmosphere_segment(r: Tensor, mu: Tensor, bottom_radius, top_radius) -> tuple[Tensor, Tensor, Tensor]:
    """The part of a ray inside the atmosphere, for observers on the ground, inside, at the top or in space.

    Args:
        r: observer distance from the planet centre, shape (...). [m]
        mu: cosine of the view zenith angle, shape (...). [1]

    Returns:
        (start, end, hits_ground): distances along the ray where the segment
        starts and ends (start = end = 0 for a ray that misses the
        atmosphere), and whether it ends on the ground. [m]
    """
    r, mu = torch.broadcast_tensors(r, mu)
    disc_top = discriminant(r, mu, top_radius)
    sq_top = safe_sqrt(disc_top)
    inside = r <= top_radius
    # From space the ray enters where -r mu - sqrt(D) >= 0; it must point towards the planet and meet the sphere.
    enters = (~inside) & (mu < 0) & (disc_top > 0)
    start = torch.where(enters, torch.clamp_min(-r * mu - sq_top, 0.0), torch.zeros_like(r))
    far_top = torch.where(inside, distance_to_top(r, mu, top_radius), torch.clamp_min(-r * mu + sq_top, 0.0))
    hits = ray_hits_ground(r, mu, bottom_radius) & (inside | enters)
    end = torch.where(hits, distance_to_bottom(r, mu, bottom_radius), far_top)
    valid = inside | enters
    end = torch.where(valid, end, torch.zeros_like(end))
    start = torch.minimum(start, end)
    return start, end, hits


def point_along_ray(r: Tensor, mu: Tensor, s: Tensor) -> tuple[Tensor, Tensor]:
    """Radius and view cosine at distance s along a ray from (r, mu) (Bruneton 2017, eq. for r_d, mu_d).

    Returns:
        (r_s, mu_s_view): shape broadcast of inputs. [m], [1]
    """
    r_s = safe_sqrt(r * r + 2.0 * r * mu * s + s * s)
    r_s = torch.clamp_min(r_s, 1.0)
    return r_s, torch.clamp((r * mu + s) / r_s, -1.0, 1.0)


def sun_cosine_along_ray(r: Tensor, mu_s: Tensor, nu: Tensor, s: Tensor, r_s: Tensor) -> Tensor:
    """Sun zenith cosine at distance s along a view ray: ``(r mu_s + s nu) / r_s``. [1]"""
    return torch.clamp((r * mu_s + s * nu) / r_s, -1.0, 1.0)


# -- directions in the East-North-Up frame ----------------------------------------
def safe_norm2(a: Tensor, b: Tensor) -> Tensor:
    """hypot(a, b) with gradient 0 (not NaN) at a = b = 0; exact elsewhere."""
    s = a * a + b * b
    pos = s > 0
    return torch.where(pos, torch.sqrt(torch.where(pos, s, torch.ones_like(s))), torch.zeros_like(s))


def zenith_azimuth_to_enu(zenith: Tensor, azimuth: Tensor) -> Tensor:
    """Unit vectors in the East-North-Up frame.

    Args:
        zenith: angle from the local vertical, shape (...). [rad]
        azimuth: clockwise from North (East = pi/2), shape (...). [rad]

    Returns:
        (E, N, U), shape (..., 3). [1]
    """
    s = torch.sin(zenith)
    return torch.stack([s * torch.sin(azimuth), s * torch.cos(azimuth), torch.cos(zenith)], -1)


def zenith_angle_deg(v) -> float:
    """The zenith angle [deg] of one unit vector in ENU, shape (3,) (a tensor, array or sequence; its up component
    clamped to [-1, 1] against rounding)."""
    return math.degrees(math.acos(max(-1.0, min(1.0, float(v[2])))))


def enu_to_zenith_azimuth(v: Tensor) -> tuple[Tensor, Tensor]:
    """Zenith angle [rad] and azimuth [rad, clockwise from North, in [0, 2 pi)] of vectors (..., 3) in ENU.

    Both angles are singular at the zenith and nadir (E = N = 0): there the azimuth is 0 and both
    gradients are set to 0 instead of NaN. For gradients through the zenith use the vectors themselves.
    """
    e, n, u = v.unbind(-1)
    pos = (e * e + n * n) > 0
    zenith = torch.atan2(safe_norm2(e, n), u)
    azimuth = torch.atan2(torch.where(pos, e, torch.zeros_like(e)), torch.where(pos, n, torch.ones_like(n)))
    return zenith, torch.remainder(azimuth, 2 * math.pi)
