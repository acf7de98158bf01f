"""Gałaj et al. 2021 spline optical depth (Sec. IV.C-IV.E, eqs. 11-14), with closed-form spline integrals.

A ray is described by its distance d from the planet centre and the signed
position t of a point relative to the ray's closest point P_o (Gałaj 2021
eq. 10), so that the radius is rho(t) = sqrt(d^2 + t^2) and the column is
(eq. 11)::

    column = int_{t0}^{t1} exp(-(sqrt(d^2 + t^2) - R_b) / H) dt  =  F(t1) - F(t0),

with F the odd antiderivative about P_o: eqs. 13 (end points on both sides of
P_o) and 14 (same side) are both F(t1) - F(t0) with F(t) = sign(t) G(|t|),
G(a) = int_{t_min}^{a} (eq. 12). The paper tabulates the integrand on two
rectangular grids, fits splines along the ray coordinate, "substitutes d in
spline 2d to get spline 1d" (step 3 of Sec. IV.E) and integrates that spline
in closed form (step 4). Here each row's spline is a cubic Hermite polynomial
per interval whose tangents define the kind (:data:`SPLINE_KINDS`); interval
integrals are exact, each row's tail integrals (from a node to the row's far
end, so that thin segments high up keep their relative accuracy) are summed
once per atmosphere in :meth:`SplineOpticalDepth.prepare`, and a ray's spline
is a weighted combination of neighbouring rows, which commutes with
integration: the integral of the interpolated spline is the interpolated row
integral. Everything is torch, vectorised over rays, and differentiable w.r.t.
the scale heights through the tables.

Two grid layouts (``grid=``):

``"paper"``
    Sec. IV.E literally. Region I: (t, d) in [0, sqrt(R_t^2 - R_b^2)] x [R_b, R_t],
    values exp(-(sqrt(d^2+t^2) - R_b)/H). Region II: (h, d) in [0, R_t - R_b] x
    {j R_b / M, j = 0..M-1}, values after the substitution h = sqrt(d^2+t^2) - R_b,
    exp(-h/H) (h + R_b) / sqrt((h + R_b)^2 - d^2). That integrand is singular
    at h = 0 as d -> R_b; the paper's d grid stops at (M-1) R_b / M, so it
    stays finite on the grid, and rays with d between the last row and R_b
    (low rays that hit the ground) are extrapolated. Max relative errors
    are O(1) (docs/spline.md); kept to measure the paper's method, with
    ``space="values", distance_interp="linear"``.

``"smooth"`` (default); deviations from the paper, each measured in docs/spline.md:

    1. Region I factors the density at P_o out exactly: rows hold
       g = exp(-(sqrt(d^2+t^2) - d)/H), nearly independent of d, and the ray's
       column is exp(-(d - R_b)/H) times the interpolated spline integral. The
       paper's rows differ by exp(-Δd/H) (x14 per row for H = 1.2 km at 20 rows).
       The integrand is even in t, so rows are splined through their mirror
       image on [-T, T]: zero slope at P_o for every kind, and F is C2 there.
    2. Region II uses the substitution u = t - t_min = sqrt((h+R_b)^2 - d^2) -
       sqrt(R_b^2 - d^2) (the "u substitution" started at the ground), in which
       the integrand exp(-h(u)/H) is smooth for every ray, instead of h, in which
       it is singular. Rows are parametrised by c = sqrt(R_b^2 - d^2) (the
       distance from P_o to the ground, c = R_b mu_ground), uniform in 1/c (the
       air mass, in which the ground-level column is nearly linear); rows are
       combined at the ray's altitude, each divided by its air-mass factor
       rho / t_j there and multiplied back by the ray's rho / t, so that the
       interpolated quantity is nearly H exp(-h/H) for every row.
    3. The regions overlap: region I extends below the ground to d = R_b - 2 H
       (its integrand, normalised at P_o, is at most e^2 larger inside the
       planet), region II covers R_b - d >= H, and a smoothstep in c^2 blends
       them for depths in [H, 2 H]. Grazing rays, the ground horizon included,
       are all in region I, where the column is smooth in (d, t); region II
       never meets the corner (h, d) -> (0, R_b) where its integrand is singular.
    4. ``space="log"`` (default, any grid): the kind's spline goes through the
       exactly computed log of the integrand, and each interval integrates
       y_i exp(-lam_i s) R_i(s) in closed form (exponentially fitted Hermite,
       :class:`_Rows`), exact where the integrand is exponential in the row
       coordinate (vertical rays): the paper's splines of values need spacing
       << H and reach 6 % error for H = 1.2 km at 50 points.
    5. Rows are combined with Catmull-Rom weights (C1 in d; ``distance_interp="linear"``
       for the paper's bilinear "spline 2d").

Validity: segments inside the atmosphere. End points may lie up to one table
interval (R_t - R_b)/(N - 1) above the top (the end pieces extend smoothly) and
segments may dip up to min(that, H) below the ground (integrated through the
planet as the same formula, as gradcheck's finite differences need); farther
out the call raises ValueError. Zero-length segments are accepted anywhere
(column exactly 0); negative lengths give the signed integral. Each call
synchronises with the device three times (the check, and the selection of the
rays each region needs). The along-ray resolution for vertical rays is
(R_t - R_b)/(N - 1) in altitude; ``space="log"`` makes that exact for pure
exponentials, ``space="values"`` needs H >> (R_t - R_b)/(N - 1).
"""
from __future__ import annotations

import functools
import math

import torch
from torch import Tensor

from .base import ColumnFn, OpticalDepthIntegrator

SPLINE_KINDS: tuple[str, ...] = ("linear", "natural_cubic", "catmull_rom", "hermite", "akima", "monotone_hermite")
"""Spline kinds along the ray coordinate (Gałaj 2021 Table 2 compares the same families)."""
SPLINE_GRIDS: tuple[str, ...] = ("smooth", "paper")
DISTANCE_INTERPS: tuple[str, ...] = ("linear", "catmull_rom")
SPLINE_SPACES: tuple[str, ...] = ("log", "values")

HEIGHT_POINTS_DEFAULT: int = 50
"""Nodes along the ray coordinate; Gałaj 2021 Sec. VI.A.1 chose 50 x 20 (Table 1)."""
DISTANCE_POINTS_DEFAULT: int = 20
"""Rows in the distance coordinate per region; Gałaj 2021 Sec. VI.A.1."""


def _validate(name: str, value: str, valid: tuple[str, ...]) -> str:
    if value not in valid:
        raise ValueError(f"unknown spline {name} {value!r}; valid: {', '.join(valid)}")
    return value


# --------------------------------------------------------------------------
# 1D splines on uniform nodes, in index units (node i at q = i)
# --------------------------------------------------------------------------
@functools.lru_cache(maxsize=16)
def _natural_system_inverse(k: int) -> Tensor:
    """Inverse of the k x k matrix tridiag(1, 4, 1), float64 on the CPU (cast by the caller)."""
    a = 4.0 * torch.eye(k, dtype=torch.float64)
    idx = torch.arange(k - 1)
    a[idx, idx + 1] = 1.0
    a[idx + 1, idx] = 1.0
    return torch.linalg.inv(a)


def _natural_second_derivatives(y: Tensor) -> Tensor:
    """Second derivatives M of the natural cubic spline through y (..., N): M_0 = M_{N-1} = 0.

    Solves M_{i-1} + 4 M_i + M_{i+1} = 6 (y_{i+1} - 2 y_i + y_{i-1}) (de Boor 2001, Ch. IV)
    with the inverse of the constant tridiagonal matrix.
    """
    n = y.shape[-1]
    out = torch.zeros_like(y)
    if n < 3:
        return out
    a_inv = _natural_system_inverse(n - 2).to(dtype=y.dtype, device=y.device)
    rhs = 6.0 * (y[..., 2:] - 2.0 * y[..., 1:-1] + y[..., :-2])
    m_int = rhs @ a_inv  # a is symmetric
    return torch.cat([out[..., :1], m_int, out[..., :1]], dim=-1)


def _fd4_tangents(y: Tensor) -> Tensor:
    """Fourth-order finite-difference derivatives at every node (Fornberg 1988 five-point stencils)."""
    c0 = (-25.0 * y[..., 0] + 48.0 * y[..., 1] - 36.0 * y[..., 2] + 16.0 * y[..., 3] - 3.0 * y[..., 4]) / 12.0
    c1 = (-3.0 * y[..., 0] - 10.0 * y[..., 1] + 18.0 * y[..., 2] - 6.0 * y[..., 3] + y[..., 4]) / 12.0
    cn1 = (25.0 * y[..., -1] - 48.0 * y[..., -2] + 36.0 * y[..., -3] - 16.0 * y[..., -4] + 3.0 * y[..., -5]) / 12.0
    cn2 = (3.0 * y[..., -1] + 10.0 * y[..., -2] - 18.0 * y[..., -3] + 6.0 * y[..., -4] - y[..., -5]) / 12.0
    mid = (y[..., :-4] - 8.0 * y[..., 1:-3] + 8.0 * y[..., 3:-1] - y[..., 4:]) / 12.0
    return torch.cat([c0[..., None], c1[..., None], mid, cn2[..., None], cn1[..., None]], dim=-1)


def _akima_tangents(y: Tensor) -> Tensor:
    """Akima 1970 tangents with his end extension of the slopes (as scipy's Akima1DInterpolator)."""
    s = y[..., 1:] - y[..., :-1]
    sm1 = 2.0 * s[..., :1] - s[..., 1:2]
    sm2 = 2.0 * sm1 - s[..., :1]
    sp1 = 2.0 * s[..., -1:] - s[..., -2:-1]
    sp2 = 2.0 * sp1 - s[..., -1:]
    m = torch.cat([sm2, sm1, s, sp1, sp2], dim=-1)  # node i uses m[i..i+3]
    dm = (m[..., 1:] - m[..., :-1]).abs()
    f1, f2 = dm[..., 2:], dm[..., :-2]
    f12 = f1 + f2
    fill = 0.5 * (m[..., 3:] + m[..., :-3])
    ok = f12 > 1e-9 * f12.amax(dim=-1, keepdim=True)
    den = torch.where(ok, f12, torch.ones_like(f12))
    akima = m[..., 1:-2] + (f2 / den) * (m[..., 2:-1] - m[..., 1:-2])
    return torch.where(ok, akima, fill)


def _fritsch_carlson_tangents(y: Tensor) -> Tensor:
    """Monotone cubic Hermite tangents, Fritsch & Carlson 1980 (SIAM J. Numer. Anal. 17, 238).

    Start from three-point tangents, set them to 0 at local extrema and flat
    intervals, and where alpha^2 + beta^2 > 9 scale them by tau = 3/sqrt(alpha^2+beta^2).
    The paper applies the scaling interval by interval in sequence; here every
    node is scaled by the smaller tau of its two intervals, which satisfies
    the same condition on every interval at once (no loop) and keeps C1.
    """
    s = y[..., 1:] - y[..., :-1]
    m = torch.cat([s[..., :1], 0.5 * (s[..., :-1] + s[..., 1:]), s[..., -1:]], dim=-1)
    interior_ext = torch.cat([torch.zeros_like(s[..., :1], dtype=torch.bool), s[..., :-1] * s[..., 1:] <= 0, torch.zeros_like(s[..., :1], dtype=torch.bool)], dim=-1)
    m = torch.where(interior_ext, torch.zeros_like(m), m)
    flat = s == 0
    s_safe = torch.where(flat, torch.ones_like(s), s)
    alpha, beta = m[..., :-1] / s_safe, m[..., 1:] / s_safe
    q = alpha * alpha + beta * beta
    big = (q > 9.0) & ~flat
    tau = torch.where(big, 3.0 / torch.sqrt(torch.where(big, q, torch.ones_like(q))), torch.ones_like(q))
    one = torch.ones_like(tau[..., :1])
    node_tau = torch.minimum(torch.cat([one, tau], dim=-1), torch.cat([tau, one], dim=-1))
    return m * node_tau


def spline_tangents(y: Tensor, kind: str) -> tuple[Tensor, Tensor]:
    """Left and right end tangents of every interval of the spline through uniform samples.

    Args:
        y: samples at nodes q = 0..N-1, shape (..., N).
        kind: one of :data:`SPLINE_KINDS`.

    Returns:
        (m0, m1): dy/dq at the left and right end of each interval, shape (..., N-1).
        For the C1 kinds m1[i] = m0[i+1]; for "linear" both equal the chord slope,
        which makes the cubic Hermite polynomial the straight chord.
    """
    _validate("kind", kind, SPLINE_KINDS)
    n = y.shape[-1]
    if n < 5:
        raise ValueError(f"a spline needs at least 5 nodes, got {n}")
    if kind == "linear":
        s = y[..., 1:] - y[..., :-1]
        return s, s
    if kind == "natural_cubic":
        mm = _natural_second_derivatives(y)
        s = y[..., 1:] - y[..., :-1]
        m = torch.cat([s - (2.0 * mm[..., :-1] + mm[..., 1:]) / 6.0, s[..., -1:] + (mm[..., -2:-1] + 2.0 * mm[..., -1:]) / 6.0], dim=-1)
    elif kind == "catmull_rom":
        # Catmull & Rom 1974: central differences, one-sided at the ends.
        m = torch.cat([y[..., 1:2] - y[..., :1], 0.5 * (y[..., 2:] - y[..., :-2]), y[..., -1:] - y[..., -2:-1]], dim=-1)
    elif kind == "hermite":
        m = _fd4_tangents(y)
    elif kind == "akima":
        m = _akima_tangents(y)
    else:
        m = _fritsch_carlson_tangents(y)
    return m[..., :-1], m[..., 1:]


def _hermite_left_integral(y0: Tensor, y1: Tensor, m0: Tensor, m1: Tensor, a: Tensor) -> Tensor:
    """``∫_0^a p(τ) dτ`` of the cubic Hermite polynomial with p(0)=y0, p(1)=y1, p'(0)=m0, p'(1)=m1."""
    a2 = a * a
    return y0 * a * (1.0 + a2 * (a * 0.5 - 1.0)) + m0 * a2 * (0.5 + a * (a * 0.25 - 2.0 / 3.0)) + y1 * a2 * a * (1.0 - 0.5 * a) + m1 * a2 * a * (0.25 * a - 1.0 / 3.0)


def _hermite_right_integral(y0: Tensor, y1: Tensor, m0: Tensor, m1: Tensor, tau: Tensor) -> Tensor:
    """``∫_τ^1 p``, written in b = 1 - τ (p(1 - σ) is the Hermite cubic of (y1, y0, -m1, -m0)), exact for small b."""
    return _hermite_left_integral(y1, y0, -m1, -m0, 1.0 - tau)


def _hermite_value(y0: Tensor, y1: Tensor, m0: Tensor, m1: Tensor, tau: Tensor) -> Tensor:
    t2 = tau * tau
    t3 = t2 * tau
    return y0 * (2.0 * t3 - 3.0 * t2 + 1.0) + m0 * (t3 - 2.0 * t2 + tau) + y1 * (3.0 * t2 - 2.0 * t3) + m1 * (t3 - t2)


def _phi3_series(terms: int) -> list[float]:
    return [(-1.0) ** n / (math.factorial(n) * (n + 4)) for n in range(terms)]


# (threshold, series) per precision: truncation z^T / T! below eps at |z| = threshold, and the
# upward recursion's amplification 3! / threshold^3 times eps small (48 eps in float64).
_PHI_SERIES = {torch.float64: (0.5, _phi3_series(15)), torch.float32: (1.0, _phi3_series(11))}


def _phi(z: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """``phi_k(z) = ∫_0^1 exp(-z v) v^k dv`` for k = 0..3, stable for every real z.

    |z| < z_s: phi_3 by its Taylor series and the downward recursion
    phi_{k-1} = (z phi_k + e^{-z}) / k, which damps errors. |z| >= z_s:
    phi_0 = (1 - e^{-z}) / z and the upward recursion phi_k = (k phi_{k-1} - e^{-z}) / z,
    which amplifies errors by at most 3! / z_s^3. z_s = 0.5 with 15 terms in float64,
    1 with 11 terms otherwise. Each branch sees a harmless z where it is not taken
    (no NaN through torch.where).
    """
    z_s, series = _PHI_SERIES.get(z.dtype, _PHI_SERIES[torch.float32])
    small = z.abs() < z_s
    zs = torch.where(small, z, torch.zeros_like(z))
    zb = torch.where(small, torch.ones_like(z), z)
    acc = torch.full_like(zs, series[-1])
    for a in reversed(series[:-1]):
        acc = acc * zs + a
    es = torch.exp(-zs)
    s3 = acc
    s2 = (zs * s3 + es) / 3.0
    s1 = (zs * s2 + es) / 2.0
    s0 = zs * s1 + es
    eb = torch.exp(-zb)
    b0 = -torch.expm1(-zb) / zb
    b1 = (b0 - eb) / zb
    b2 = (2.0 * b1 - eb) / zb
    b3 = (3.0 * b2 - eb) / zb
    return tuple(torch.where(small, a, b) for a, b in ((s0, b0), (s1, b1), (s2, b2), (s3, b3)))


def _exp_hermite_right_integral(y0: Tensor, lam: Tensor, p: Tensor, q: Tensor, tau: Tensor) -> Tensor:
    """``∫_τ^1 y0 exp(-lam s) R(s) ds`` with R the cubic of R(0) = R(1) = 1, R'(0) = p, R'(1) = q.

    With b = 1 - τ and the Taylor expansion of R about τ (exact for a cubic)::

        = y0 e^{-lam τ} sum_k R^(k)(τ)/k! b^{k+1} phi_k(lam b).
    """
    b = 1.0 - tau
    f0, f1, f2, f3 = _phi(lam * b)
    r3 = p + q
    r2 = -(2.0 * p + q) + 3.0 * r3 * tau
    r1 = p + tau * (-2.0 * (2.0 * p + q) + 3.0 * r3 * tau)
    r0 = 1.0 + tau * (p + tau * (-(2.0 * p + q) + r3 * tau))
    poly = b * (r0 * f0 + b * (r1 * f1 + b * (r2 * f2 + b * r3 * f3)))
    return y0 * torch.exp(-lam * tau) * poly


class _Rows:
    """Rows of 1D splines on N uniform nodes of a normalised coordinate x in [0, 1].

    Args:
        log_values: log of the integrand per unit x, shape (K, M, N) (layer, row, node),
            computed analytically so that nothing underflows before the exponential.
        kind: spline kind.
        space: ``"values"``: the spline interpolates the integrand y = exp(log_values)
            (Gałaj 2021). ``"log"``: exponentially fitted Hermite interpolation:
            on interval i the integrand is y_i exp(-lam_i s) R_i(s), lam_i = l_i - l_{i+1},
            R_i the cubic with R_i(0) = R_i(1) = 1 whose end slopes make the
            integrand's derivative y (dl/dx) with dl/dx the tangents of the spline
            of kind ``kind`` through l = log y. Exact for y = exp(linear), C1, and
            integrable in closed form (:func:`_phi`).

    ``tail(row, x)`` is ``∫_x^1 spline_row(x') dx'``: tails are summed from the far
    end so that thin segments high in the atmosphere keep their relative accuracy.
    ``even``: the integrand is even in x (region I rows, symmetric about P_o); the
    tangents are those of the spline through the mirrored samples on [-1, 1].
    """

    def __init__(self, log_values: Tensor, kind: str, space: str = "values", even: bool = False):
        self.k, self.m, self.n = log_values.shape
        self.space = space

        def tangents(v: Tensor) -> tuple[Tensor, Tensor]:
            if not even:
                return spline_tangents(v, kind)
            # Spline the even extension v(-x) = v(x) and keep x >= 0: zero slope at x = 0 for every kind.
            g0, g1 = spline_tangents(torch.cat([torch.flip(v[..., 1:], [-1]), v], dim=-1), kind)
            return g0[..., self.n - 1 :], g1[..., self.n - 1 :]

        if space == "values":
            y = torch.exp(log_values)
            m0, m1 = tangents(y)
            y0, y1 = y[..., :-1], y[..., 1:]
            coef = torch.stack([y0, y1, m0, m1], dim=-1)
            full = 0.5 * (y0 + y1) + (m0 - m1) / 12.0  # exact interval integrals
        else:
            l0, l1 = log_values[..., :-1], log_values[..., 1:]
            lam = l0 - l1
            g0, g1 = tangents(log_values)
            p, q = g0 + lam, g1 + lam
            y0 = torch.exp(l0)
            coef = torch.stack([y0, lam, p, q], dim=-1)
            full = _exp_hermite_right_integral(y0, lam, p, q, torch.zeros_like(lam))
        self.coef = coef.reshape(self.k, -1, 4)  # (K, M (N-1), 4)
        tails = torch.flip(torch.cumsum(torch.flip(full, [-1]), -1), [-1])
        self.tails = torch.cat([tails, torch.zeros_like(tails[..., :1])], dim=-1).reshape(self.k, -1)  # (K, M N)

    def to(self, dtype: torch.dtype, device: torch.device) -> _Rows:
        out = object.__new__(_Rows)
        out.k, out.m, out.n, out.space = self.k, self.m, self.n, self.space
        out.coef = self.coef.to(dtype=dtype, device=device)
        out.tails = self.tails.to(dtype=dtype, device=device)
        return out

    def total(self, row: Tensor) -> Tensor:
        """``∫_0^1`` of row ``row`` (long, (K, n)), from the precomputed tails."""
        return self.tails.gather(1, row * self.n) / (self.n - 1)

    def tail(self, row: Tensor, x: Tensor) -> Tensor:
        """Tail integral of row ``row`` (long, (K, n)) from x ((K, n)) to 1; outside [0, 1] the end pieces extend."""
        q = x * (self.n - 1)
        i = torch.clamp(torch.floor(q.detach()), 0, self.n - 2).long()
        tau = q - i
        c = self.coef.gather(1, (row * (self.n - 1) + i).unsqueeze(-1).expand(-1, -1, 4))
        if self.space == "values":
            part = _hermite_right_integral(c[..., 0], c[..., 1], c[..., 2], c[..., 3], tau)
        else:
            part = _exp_hermite_right_integral(c[..., 0], c[..., 1], c[..., 2], c[..., 3], tau)
        rest = self.tails.gather(1, row * self.n + i + 1)
        return (part + rest) / (self.n - 1)


def _row_stencil(y: Tensor, m: int, interp: str) -> list[tuple[Tensor, Tensor]]:
    """Rows and weights of the distance interpolation at fractional row coordinate y ((K, n)).

    ``linear``: the two neighbouring rows. ``catmull_rom``: cubic convolution
    (Keys 1981, a = -1/2; C1, exact for quadratics) on four rows, with
    linearly extrapolated ghost rows beyond the first and last.
    Outside [0, M-1] the end cell extrapolates.
    """
    j = torch.clamp(torch.floor(y.detach()), 0, m - 2).long()
    f = y - j
    if interp == "linear":
        return [(j, 1.0 - f), (j + 1, f)]
    f2, f3 = f * f, f * f * f
    wm = 0.5 * (-f3 + 2.0 * f2 - f)
    w0 = 0.5 * (3.0 * f3 - 5.0 * f2 + 2.0)
    w1 = 0.5 * (-3.0 * f3 + 4.0 * f2 + f)
    w2 = 0.5 * (f3 - f2)
    lo, hi = j == 0, j == m - 2
    zero = torch.zeros_like(f)
    w0, w1, wm = torch.where(lo, w0 + 2.0 * wm, w0), torch.where(lo, w1 - wm, w1), torch.where(lo, zero, wm)
    w1, w0, w2 = torch.where(hi, w1 + 2.0 * w2, w1), torch.where(hi, w0 - w2, w0), torch.where(hi, zero, w2)
    return [(torch.clamp(j - 1, min=0), wm), (j, w0), (j + 1, w1), (torch.clamp(j + 2, max=m - 1), w2)]


def _abs_sign(t: Tensor) -> tuple[Tensor, Tensor]:
    """(|t|, sign(t)) with sign(0) = +1, so that d/dt [sign(t) G(|t|)] = G'(|t|) also at t = 0."""
    pos = t >= 0
    return torch.where(pos, t, -t), torch.where(pos, torch.ones_like(t), -torch.ones_like(t))


def _odd_difference(tot: Tensor, tail0: Tensor, tail1: Tensor, s0: Tensor, s1: Tensor) -> Tensor:
    """F(t1) - F(t0) for F(t) = sign(t) (Tot - Tail(|t|)): Gałaj 2021 eqs. 13 (s0 != s1) and 14 (s0 == s1).

    Written so that Tot cancels exactly (coefficient 0) when both ends are on the same side.
    """
    return (s1 - s0) * tot + s0 * tail0 - s1 * tail1


# --------------------------------------------------------------------------
# The integrator
# --------------------------------------------------------------------------
class SplineOpticalDepth(OpticalDepthIntegrator):
    """Gałaj 2021 Sec. IV.E spline method: tabulated integrand, closed-form spline integrals.

    Args:
        height_points: N, nodes along the ray coordinate (t in region I, u or h in region II).
        distance_points: M, rows in the distance coordinate per region.
        kind: spline along the ray coordinate, one of :data:`SPLINE_KINDS`.
        grid: ``"smooth"`` (default) or ``"paper"`` (Sec. IV.E literally); see the module docstring.
        distance_interp: ``"catmull_rom"`` (default; C1 across rows) or ``"linear"``
            (the paper's bilinear "spline 2d").
        space: ``"log"`` (default; exponentially fitted, the spline kind applies to the
            log of the integrand) or ``"values"`` (the spline interpolates the integrand,
            as in the paper). The paper's method is
            ``SplineOpticalDepth(grid="paper", space="values", distance_interp="linear")``.
    """

    name = "spline"

    def __init__(
        self,
        height_points: int = HEIGHT_POINTS_DEFAULT,
        distance_points: int = DISTANCE_POINTS_DEFAULT,
        kind: str = "natural_cubic",
        grid: str = "smooth",
        distance_interp: str = "catmull_rom",
        space: str = "log",
    ):
        self.kind = _validate("kind", kind, SPLINE_KINDS)
        self.space = _validate("space", space, SPLINE_SPACES)
        self.grid = _validate("grid", grid, SPLINE_GRIDS)
        self.distance_interp = _validate("distance_interp", distance_interp, DISTANCE_INTERPS)
        if int(height_points) < 5:
            raise ValueError(f"height_points must be >= 5, got {height_points}")
        min_rows = 3 if distance_interp == "catmull_rom" else 2
        if int(distance_points) < min_rows:
            raise ValueError(f"distance_points must be >= {min_rows} for distance_interp={distance_interp!r}, got {distance_points}")
        self.height_points = int(height_points)
        self.distance_points = int(distance_points)

    def settings(self) -> dict:
        return {
            "name": self.name,
            "height_points": self.height_points,
            "distance_points": self.distance_points,
            "kind": self.kind,
            "grid": self.grid,
            "distance_interp": self.distance_interp,
            "space": self.space,
        }

    def column(self, r, mu, length, scale_heights, bottom_radius, top_radius) -> Tensor:
        return self.prepare(scale_heights, bottom_radius, top_radius)(r, mu, length)

    # ------------------------------------------------------------------
    def prepare(self, scale_heights: Tensor, bottom_radius: float, top_radius: float) -> ColumnFn:
        """Tabulate both regions for the layers ``scale_heights`` (K,) [m]; differentiable w.r.t. them.

        Returns:
            ``fn(r, mu, length) -> column`` of shape (..., K) [m], for inputs of shape (...)
            in [m], [1], [m]. The tables are cast to the inputs' dtype and device.
        """
        H = scale_heights
        if H.dim() != 1:
            raise ValueError(f"scale_heights must have shape (K,), got {tuple(H.shape)}")
        Rb, Rt = float(bottom_radius), float(top_radius)
        if not 0.0 < Rb < Rt:
            raise ValueError(f"need 0 < bottom_radius < top_radius, got {Rb}, {Rt}")
        if self.grid == "paper":
            tables = self._paper_tables(H, Rb, Rt)
            evaluate = self._paper_columns
        else:
            tables = self._smooth_tables(H, Rb, Rt)
            evaluate = self._smooth_columns
        cache: dict = {}
        # Tolerances of the validity check: one altitude interval of the table beyond the top
        # (the end pieces extend smoothly), and below the ground no deeper than region I
        # reaches (grid="smooth": R_b - 2H; through-planet segments integrate its formula).
        tol_top = (Rt - Rb) / (self.height_points - 1)
        tol_ground = min(tol_top, float(H.detach().min().clamp(max=Rb / 8.0))) if self.grid == "smooth" else tol_top

        def fn(r: Tensor, mu: Tensor, length: Tensor) -> Tensor:
            r, mu, length = torch.broadcast_tensors(r, mu, length)
            shape = r.shape
            key = (r.dtype, r.device)
            if key not in cache:
                cache[key] = {k: (v.to(dtype=r.dtype, device=r.device) if isinstance(v, (Tensor, _Rows)) else v) for k, v in tables.items()}
            tab = cache[key]
            geo = _segment_geometry(*(x.reshape(-1) for x in (r, mu, length)), Rb, Rt, tol_top, tol_ground)
            col = evaluate(tab, geo, Rb, Rt)  # (K, n)
            return col.transpose(0, 1).reshape(*shape, col.shape[0])

        return fn

    # ------------------------------------------------------------------
    # grid="smooth"
    # ------------------------------------------------------------------
    def _smooth_tables(self, H: Tensor, Rb: float, Rt: float) -> dict:
        N, M = self.height_points, self.distance_points
        opts = {"dtype": H.dtype, "device": H.device}
        Hk = H[:, None, None]  # (K, 1, 1)
        # Overlap depths below the ground (deviation 3), at most R_b / 8 for thick layers.
        # Grid positions follow H, so d(column)/dH is exact for the table actually used.
        depth_lo = torch.clamp(H, max=Rb / 8.0)
        depth_hi = 2.0 * depth_lo
        c2_lo = depth_lo * (2.0 * Rb - depth_lo)  # c^2 = R_b^2 - (R_b - depth)^2
        c2_hi = depth_hi * (2.0 * Rb - depth_hi)
        xs = torch.linspace(0.0, 1.0, N, **opts)
        frac = torch.linspace(0.0, 1.0, M, **opts)
        # Region I: rows d_j uniform in [R_b - depth_hi, R_t]; t in [0, T_I], T_I = sqrt(R_t^2 - d_min^2).
        d_min = Rb - depth_hi  # (K,)
        t_top = torch.sqrt((Rt - d_min) * (Rt + d_min))  # (K,)
        d = (d_min[:, None] + (Rt - d_min)[:, None] * frac)[:, :, None]  # (K, M, 1)
        t = t_top[:, None, None] * xs  # (K, 1, N)
        rise = t * t / (torch.sqrt(d * d + t * t) + d)  # sqrt(d^2+t^2) - d, without cancellation
        log_g = -rise / Hk + torch.log(t_top)[:, None, None]  # log of the integrand per unit x
        rows_1 = _Rows(log_g, self.kind, self.space, even=True)  # the integrand is even in t (eq. 11)
        # Region II: rows uniform in 1/c over c in [c_lo, R_b] (row 0 vertical); u in [0, S(c)], S = t_max - c.
        c_lo = torch.sqrt(c2_lo)
        zeta_step = (1.0 / c_lo - 1.0 / Rb) / (M - 1)  # (K,)
        c_rows = 1.0 / (1.0 / Rb + zeta_step[:, None] * torch.arange(M, **opts))  # (K, M)
        span = Rt * Rt - Rb * Rb
        s_rows = span / (torch.sqrt(span + c_rows * c_rows) + c_rows)  # (K, M)
        u = s_rows[:, :, None] * xs  # (K, M, N)
        c = c_rows[:, :, None]
        h = (2.0 * c * u + u * u) / (torch.sqrt(Rb * Rb + 2.0 * c * u + u * u) + Rb)
        log_phi = -h / Hk + torch.log(s_rows)[:, :, None]
        rows_2 = _Rows(log_phi, self.kind, self.space)
        return {
            "H": H, "rows_1": rows_1, "rows_2": rows_2, "d_min": d_min, "t_top": t_top,
            "c2_lo": c2_lo, "c2_hi": c2_hi, "c_rows": c_rows, "s_rows": s_rows, "zeta_step": zeta_step,
        }

    def _smooth_columns(self, tab: dict, geo: dict, Rb: float, Rt: float) -> Tensor:
        K = tab["H"].shape[0]
        n = geo["c2"].shape[0]
        c2_lo, c2_hi = tab["c2_lo"][:, None], tab["c2_hi"][:, None]
        s = torch.clamp((geo["c2"] - c2_lo) / (c2_hi - c2_lo), 0.0, 1.0)  # (K, n)
        # Each region is evaluated only on the rays (all layers) that need it.
        idx_1 = torch.nonzero((s < 1.0).any(0)).squeeze(1)
        idx_2 = torch.nonzero((s > 0.0).any(0)).squeeze(1)
        out = torch.zeros(K, n, dtype=geo["c2"].dtype, device=geo["c2"].device)
        if idx_1.numel():
            g = {k: v.index_select(0, idx_1) for k, v in geo.items()}
            out = out + torch.zeros_like(out).index_copy(1, idx_1, self._smooth_region_1(tab, g, s.index_select(1, idx_1), Rb, Rt))
        if idx_2.numel():
            g = {k: v.index_select(0, idx_2) for k, v in geo.items()}
            out = out + torch.zeros_like(out).index_copy(1, idx_2, self._smooth_region_2(tab, g, s.index_select(1, idx_2), Rb))
        return out

    def _smooth_region_1(self, tab: dict, geo: dict, s: Tensor, Rb: float, Rt: float) -> Tensor:
        """Region I (d >= R_b - 2H): G = exp(-(d - R_b)/H) times the interpolated row integral (deviation 1)."""
        H = tab["H"][:, None]
        M = self.distance_points
        use = s < 1.0  # (K, n)
        zero = torch.zeros_like(s)
        c2 = torch.where(use, geo["c2"], zero)  # inactive entries get a harmless ray (d = R_b, t = 0)
        d = torch.sqrt(Rb * Rb - c2)
        d_rel = -c2 / (d + Rb)  # d - R_b without cancellation
        d_min = tab["d_min"][:, None]
        y = (d - d_min) / (Rt - d_min) * (M - 1)
        a0, s0 = _abs_sign(torch.where(use, geo["t0"], zero))
        a1, s1 = _abs_sign(torch.where(use, geo["t1"], zero))
        t_top = tab["t_top"][:, None]
        tot, tail0, tail1 = _interp_tails(tab["rows_1"], _row_stencil(y, M, self.distance_interp), [(a0 / t_top, None), (a1 / t_top, None)])
        col = torch.exp(-d_rel / H) * _odd_difference(tot, tail0, tail1, s0, s1)
        blend = s * s * (3.0 - 2.0 * s)
        return torch.where(use, (1.0 - blend) * col, zero)

    def _smooth_region_2(self, tab: dict, geo: dict, s: Tensor, Rb: float) -> Tensor:
        """Region II (R_b - d >= H): rows in u = t - c, combined at equal altitude (deviation 2).

        Each row's tail at the ray's altitude is divided by the row's air-mass factor
        rho / t_j there and the ray's own factor rho / t is applied after the
        interpolation, so that rows are combined where they nearly agree
        (H exp(-h/H) in a plane-parallel layer).
        """
        M = self.distance_points
        use = s > 0.0
        zero = torch.zeros_like(s)
        full = torch.full_like(s, Rb)
        c2 = torch.where(use, geo["c2"], full * Rb)  # inactive entries: a vertical ray of zero length
        c = torch.sqrt(c2)
        y = (1.0 / c - 1.0 / Rb) / tab["zeta_step"][:, None]
        _, r0 = _abs_sign(torch.where(use, geo["t0"], full))
        _, r1 = _abs_sign(torch.where(use, geo["t1"], full))
        e0, e1 = torch.where(use, geo["e0"], zero), torch.where(use, geo["e1"], zero)  # rho^2 - R_b^2
        stencil = _row_stencil(y, M, self.distance_interp)
        c_rows, s_rows = tab["c_rows"], tab["s_rows"]

        def at_altitude(e: Tensor):
            t_ray = torch.sqrt(c2 + e)  # |t| of the end point

            def row_x(j: Tensor) -> tuple[Tensor, Tensor]:
                reps = j.shape[1] // e.shape[1]  # j holds the stencil's rows side by side
                cj, er = c_rows.gather(1, j), e.repeat(1, reps)
                tj = torch.sqrt(cj * cj + er)  # the same altitude on row j
                return er / (tj + cj) / s_rows.gather(1, j), tj / t_ray.repeat(1, reps)

            return row_x

        def tot_factor(j: Tensor) -> Tensor:
            return c_rows.gather(1, j) / c.repeat(1, j.shape[1] // c.shape[1])

        tot, tail0, tail1 = _interp_tails(tab["rows_2"], stencil, [at_altitude(e0), at_altitude(e1)], tot_factor)
        col = _odd_difference(tot, tail0, tail1, r0, r1)
        blend = s * s * (3.0 - 2.0 * s)
        return torch.where(use, blend * col, zero)

    # ------------------------------------------------------------------
    # grid="paper"
    # ------------------------------------------------------------------
    def _paper_tables(self, H: Tensor, Rb: float, Rt: float) -> dict:
        N, M = self.height_points, self.distance_points
        opts = {"dtype": H.dtype, "device": H.device}
        Hk = H[:, None, None]
        xs = torch.linspace(0.0, 1.0, N, **opts)
        t_top = math.sqrt(Rt * Rt - Rb * Rb)
        t = t_top * xs  # (N,)
        d = (Rb + (Rt - Rb) * torch.linspace(0.0, 1.0, M, **opts))[:, None]  # (M, 1)
        h1 = (d * d + t * t - Rb * Rb) / (torch.sqrt(d * d + t * t) + Rb)
        f1 = -h1 / Hk + math.log(t_top)  # log integrand, (K, M, N)
        h = (Rt - Rb) * xs
        d2 = (Rb / M * torch.arange(M, **opts))[:, None]  # paper: d in {j r / K, j = 0..K-1}
        geo = (h + Rb) / torch.sqrt(h * (2.0 * Rb + h) + (Rb - d2) * (Rb + d2))
        f2 = -h / Hk + torch.log(geo) + math.log(Rt - Rb)
        rows_1, rows_2 = _Rows(f1, self.kind, self.space), _Rows(f2, self.kind, self.space)
        return {"H": H, "rows_1": rows_1, "rows_2": rows_2, "t_top": t_top}

    def _paper_columns(self, tab: dict, geo: dict, Rb: float, Rt: float) -> Tensor:
        K = tab["H"].shape[0]
        M = self.distance_points
        c2, t0, t1, e0, e1 = (geo[k].expand(K, -1) for k in ("c2", "t0", "t1", "e0", "e1"))
        zero = torch.zeros_like(c2)
        full = torch.full_like(c2, Rb)
        reg1 = c2 <= 0.0
        # Region I: rows in d, x = |t| / sqrt(R_t^2 - R_b^2).
        c2_1 = torch.where(reg1, c2, zero)
        d1 = torch.sqrt(Rb * Rb - c2_1)
        y1 = (-c2_1 / (d1 + Rb)) / (Rt - Rb) * (M - 1)
        a0, s0 = _abs_sign(torch.where(reg1, t0, zero))
        a1, s1 = _abs_sign(torch.where(reg1, t1, zero))
        ends = [(a0 / tab["t_top"], None), (a1 / tab["t_top"], None)]
        col_1 = _odd_difference(*_interp_tails(tab["rows_1"], _row_stencil(y1, M, self.distance_interp), ends), s0, s1)
        # Region II: rows d_j = j R_b / M, x = h / (R_t - R_b).
        c2_2 = torch.where(reg1, full * Rb, c2)
        y2 = torch.sqrt(Rb * Rb - c2_2) / (Rb / M)
        _, r0 = _abs_sign(torch.where(reg1, full, t0))
        _, r1 = _abs_sign(torch.where(reg1, full, t1))
        e0, e1 = torch.where(reg1, zero, e0), torch.where(reg1, zero, e1)
        h0, h1 = e0 / (torch.sqrt(Rb * Rb + e0) + Rb), e1 / (torch.sqrt(Rb * Rb + e1) + Rb)
        ends = [(h0 / (Rt - Rb), None), (h1 / (Rt - Rb), None)]
        col_2 = _odd_difference(*_interp_tails(tab["rows_2"], _row_stencil(y2, M, self.distance_interp), ends), r0, r1)
        return torch.where(reg1, col_1, col_2)


def _interp_tails(rows: _Rows, stencil: list[tuple[Tensor, Tensor]], ends: list, tot_factor=None) -> tuple[Tensor, ...]:
    """Row-interpolated total and tail integrals, all rows and end points in one batched lookup.

    Args:
        rows: the region's rows.
        stencil: [(row index (K, n), weight (K, n))] from :func:`_row_stencil`.
        ends: per end point, either ``(x, None)`` with x (K, n) the same on every row, or a
            callable ``j -> (x_j, factor_j)`` giving the row's coordinate and a factor
            applied to its tail before the weighted sum.
        tot_factor: optional callable ``j -> factor`` for the total (x = 0) of each row.

    Returns:
        (total, tail at end 0, tail at end 1, ...), each (K, n).
    """
    js = [j for j, _ in stencil]
    ws = [w for _, w in stencil]
    n = ws[0].shape[1]
    r = len(stencil)
    j_all = torch.cat(js, dim=1)  # (K, R n)
    xs, fs = [], []
    for end in ends:
        if callable(end):
            x_j, f_j = end(j_all)
        else:
            x_j, f_j = end[0].repeat(1, r), None
        xs.append(x_j)
        fs.append(f_j)
    tails = rows.tail(j_all.repeat(1, len(ends)), torch.cat(xs, dim=1)).view(-1, len(ends), r, n)
    w = torch.stack(ws, dim=1)  # (K, R, n)
    tot = rows.total(j_all)
    if tot_factor is not None:
        tot = tot * tot_factor(j_all)
    out = [(tot.view(-1, r, n) * w).sum(1)]
    for e, f in enumerate(fs):
        te = tails[:, e] if f is None else tails[:, e] * f.view(-1, r, n)
        out.append((te * w).sum(1))
    return tuple(out)


def _segment_geometry(r: Tensor, mu: Tensor, length: Tensor, Rb: float, Rt: float, tol_top: float, tol_ground: float) -> dict:
    """Line parameters of Gałaj 2021 Figs. 2-4 for segments from (r, mu) of length L, shapes (n,).

    ``c2`` = R_b^2 - d^2 (> 0 iff the line meets the ground), ``t0, t1`` the signed
    positions of the ends relative to P_o (eq. 10), ``e0, e1`` = rho^2 - R_b^2 at the ends,
    all written without cancellation near the ground and the horizon.
    Refuses end points more than ``tol_top`` above the top, and segments reaching more than
    ``tol_ground`` below the ground, both [m]; zero-length segments are never refused.
    """
    t0 = r * mu
    t1 = t0 + length
    c2 = (Rb - r) * (Rb + r) + r * r * mu * mu
    e0 = (r - Rb) * (r + Rb)
    e1 = e0 + length * (2.0 * r * mu + length)
    moving = length != 0
    lo2, hi2 = (Rb - tol_ground) ** 2, (Rt + tol_top) ** 2
    rho0_2, rho1_2 = r * r, Rb * Rb + e1
    d2 = r * r * (1.0 - mu) * (1.0 + mu)
    crosses = (t0 < 0) & (t1 > 0)
    rmin2 = torch.where(crosses, d2, torch.minimum(rho0_2, rho1_2))
    outside = (moving & (torch.maximum(rho0_2, rho1_2) > hi2)).any()
    below = (moving & (rmin2 < lo2)).any()
    flags = torch.stack([outside, below]).tolist()
    if flags[0]:
        raise ValueError(f"spline: segment end points must lie in the atmosphere (radius <= top + {tol_top:.4g} m)")
    if flags[1]:
        raise ValueError(f"spline: segments must not pass below the ground (radius >= bottom - {tol_ground:.4g} m)")
    return {"t0": t0, "t1": t1, "c2": c2, "e0": e0, "e1": e1}


def integrate_uniform_spline(y: Tensor, kind: str, a: Tensor, b: Tensor, space: str = "values") -> Tensor:
    """``∫_a^b`` of the interpolant of kind ``kind`` through samples y at nodes 0..N-1 (index units).

    Args:
        y: samples, shape (N,); positive for ``space="log"``.
        a, b: limits in index units, shape (n,).
        space: "values" (spline of y) or "log" (exponentially fitted, see :class:`_Rows`).

    Returns:
        shape (n,). The tests use it to check what each kind reproduces exactly.
    """
    _validate("space", space, SPLINE_SPACES)
    rows = _Rows(torch.log(y).reshape(1, 1, -1), kind, "log") if space == "log" else _values_rows(y, kind)
    n = y.shape[-1]
    row = torch.zeros(1, a.shape[0], dtype=torch.long, device=y.device)
    ta = rows.tail(row, (a / (n - 1)).unsqueeze(0))
    tb = rows.tail(row, (b / (n - 1)).unsqueeze(0))
    return ((ta - tb) * (n - 1)).squeeze(0)


def _values_rows(y: Tensor, kind: str) -> _Rows:
    """A one-row ``_Rows`` of the plain spline through y (any sign), for tests."""
    out = object.__new__(_Rows)
    out.k, out.m, out.n, out.space = 1, 1, y.shape[-1], "values"
    m0, m1 = spline_tangents(y, kind)
    y0, y1 = y[:-1], y[1:]
    out.coef = torch.stack([y0, y1, m0, m1], dim=-1).reshape(1, -1, 4)
    full = 0.5 * (y0 + y1) + (m0 - m1) / 12.0
    tails = torch.flip(torch.cumsum(torch.flip(full, [-1]), -1), [-1])
    out.tails = torch.cat([tails, torch.zeros_like(tails[..., :1])]).reshape(1, -1)
    return out


def evaluate_uniform_spline(y: Tensor, kind: str, q: Tensor) -> Tensor:
    """Value at q (index units, shape (n,)) of the spline of kind ``kind`` through y (N,)."""
    m0, m1 = spline_tangents(y, kind)
    i = torch.clamp(torch.floor(q.detach()), 0, y.shape[-1] - 2).long()
    tau = q - i
    return _hermite_value(y[:-1][i], y[1:][i], m0[i], m1[i], tau)


__all__ = ["SPLINE_KINDS", "SPLINE_GRIDS", "SPLINE_SPACES", "DISTANCE_INTERPS", "SplineOpticalDepth", "spline_tangents", "integrate_uniform_spline", "evaluate_uniform_spline"]
