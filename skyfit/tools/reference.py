"""Independent float64 references (scipy), for tests, accuracy tables and benchmarks.

Nothing here is used by the renderer: these are slow, careful integrations
written straight from the definitions, to measure our integrators against.
"""
from __future__ import annotations

import math

import numpy as np
from scipy.integrate import quad


def column_quad(r: float, mu: float, length: float, scale_height: float, bottom_radius: float, epsrel: float = 1e-10) -> float:
    """``int_0^L exp(-(sqrt(r^2 + 2 r mu s + s^2) - R) / H) ds`` by scipy.integrate.quad. [m]

    The tangent point (lowest altitude, s = -r mu) is passed as a break point
    when it lies inside the segment, where the integrand peaks sharply for
    small H.
    """
    if length <= 0:
        return 0.0

    def f(s):
        rr = math.sqrt(max(r * r + 2 * r * mu * s + s * s, 0.0))
        return math.exp(-(rr - bottom_radius) / scale_height)

    pts = []
    s_star = -r * mu
    if 0 < s_star < length:
        pts.append(s_star)
        # the peak has width ~ sqrt(2 r H): add points around it for quad's bisection
        w = math.sqrt(2 * r * scale_height)
        pts += [p for p in (s_star - 3 * w, s_star + 3 * w, s_star - 10 * w, s_star + 10 * w) if 0 < p < length]
    val, _ = quad(f, 0.0, length, epsrel=epsrel, epsabs=0.0, limit=1000, points=sorted(pts) or None)
    return val


def segment_to_boundary(r: float, mu: float, bottom_radius: float, top_radius: float) -> float:
    """Length of the ray from (r, mu) inside the atmosphere to the ground or the top (float64). [m]"""
    disc_b = r * r * (mu * mu - 1) + bottom_radius**2
    if mu < 0 and disc_b >= 0:
        return max(-r * mu - math.sqrt(disc_b), 0.0)
    disc_t = r * r * (mu * mu - 1) + top_radius**2
    return max(-r * mu + math.sqrt(max(disc_t, 0.0)), 0.0)


COLUMN_ERROR_FLOOR_M: float = 1e-3
"""Columns are compared relative to max(reference, this) [m]: a column error below 1 mm of
sea-level-equivalent path changes transmittance by < 1e-5 for any beta <= 1e-2 /m, so relative
error is not meaningful for the near-empty segments at the top of the atmosphere."""


def relative_column_error(column, reference):
    """|column - reference| / max(reference, COLUMN_ERROR_FLOOR_M), elementwise."""
    column, reference = np.asarray(column, float), np.asarray(reference, float)
    return np.abs(column - reference) / np.maximum(reference, COLUMN_ERROR_FLOOR_M)


def accuracy_cases(bottom_radius: float, top_radius: float) -> list[tuple[float, float, float, str]]:
    """The (r, mu, length, label) grid of docs/accuracy.md.

    Radii: ground, ground + 1 m, + 1 km, top - 1 m, top. Cosines: straight up
    and down, 0.5, 0.1, -0.1, the horizontal (0) and +-1e-6 around it, and the
    geometric horizon mu_h = -sqrt(1 - (R/r)^2) and mu_h +- 1e-6. Segments run
    to the top of the atmosphere or to the ground; a second set ends half way.
    """
    radii = [
        (bottom_radius, "ground"),
        (bottom_radius + 1.0, "ground+1m"),
        (bottom_radius + 1000.0, "ground+1km"),
        (top_radius - 1.0, "top-1m"),
        (top_radius, "top"),
    ]
    cases = []
    for r, rl in radii:
        mu_h = -math.sqrt(max(1 - (bottom_radius / r) ** 2, 0.0))
        mus = [(1.0, "up"), (0.5, "0.5"), (0.1, "0.1"), (1e-6, "+1e-6"), (0.0, "0"), (-1e-6, "-1e-6"), (-0.1, "-0.1"), (-1.0, "down")]
        if mu_h < 0:
            mus += [(mu_h, "horizon"), (mu_h + 1e-6, "horizon+1e-6"), (mu_h - 1e-6, "horizon-1e-6")]
        for mu, ml in mus:
            L = segment_to_boundary(r, mu, bottom_radius, top_radius)
            if L <= 1e-3:  # rays that leave the atmosphere at once (rounding-level lengths)
                continue
            cases.append((r, mu, L, f"r={rl}, mu={ml}, to boundary"))
            cases.append((r, mu, 0.5 * L, f"r={rl}, mu={ml}, half way"))
    return cases


def lognormal_mie_quad(r_g: float, sigma_g: float, lam_nm: float, m: tuple[float, float]) -> tuple[float, float, float]:
    """C_ext, C_sca [m^2] and <g> of the truncated log-normal of :mod:`skyfit.atmosphere.mie`, straight from
    the definitions: scipy quad_vec over ln r (+-7 ln sigma_g around the area-weighted median, beyond which
    less than 1e-11 of the area lies) of miepython's efficiencies at each radius (no table).

    ``m`` = (n, k) with k > 0 absorbing (miepython's sign convention is m = n - ik).
    """
    import miepython
    from scipy.integrate import quad_vec

    from ..atmosphere.mie import LOGNORMAL_RADIUS_RANGE_M

    s = math.log(sigma_g)
    lo, hi = (math.log(v) for v in LOGNORMAL_RADIUS_RANGE_M)
    centre = math.log(r_g) + 2 * s * s  # area-weighted median
    a, b = max(lo, centre - 7 * s), min(hi, centre + 7 * s)
    mm = complex(m[0], -m[1])

    def f(t):
        r = math.exp(t)
        n = math.exp(-0.5 * ((t - math.log(r_g)) / s) ** 2) / (s * math.sqrt(2 * math.pi))
        qe, qs, _, g = miepython.efficiencies_mx(mm, 2 * math.pi * r / (lam_nm * 1e-9))
        area = math.pi * r * r * n
        return np.array([area * qe, area * qs, area * qs * g])

    val, _ = quad_vec(f, a, b, epsrel=1e-7, epsabs=0, limit=400)
    number = 0.5 * (math.erf((hi - math.log(r_g)) / (s * math.sqrt(2))) - math.erf((lo - math.log(r_g)) / (s * math.sqrt(2))))
    return val[0] / number, val[1] / number, val[2] / val[1]

