"""Closed-form column by the Chapman grazing-incidence function (Fitzmaurice 1964 approximation).

The column of an exponential layer from radius r to infinity along a ray of
zenith cosine mu >= 0 is (Chapman 1931; notation of Huestis 2001, JQSRT 69, 709)::

    Col(r, mu) = H exp(-(r - R) / H) Ch(X, chi),     X = r / H,  mu = cos chi,

and we use the approximation of J. A. Fitzmaurice, "Simplification of the
Chapman function for atmospheric attenuation", Appl. Opt. 3, 640 (1964)
(also Smith & Smith 1972, JGR 77, 3592, who fit a rational function to its
erfc; reviewed by Huestis 2001)::

    Ch(X, chi) ~= sqrt(pi X / 2) exp(X mu^2 / 2) erfc(sqrt(X / 2) mu)
               =  sqrt(pi X / 2) erfcx(sqrt(X / 2) mu),          chi <= 90 deg,

written with the scaled complementary error function erfcx, which keeps
values and gradients finite for every mu in [0, 1]. It is exact to first
order in 1/X (the curvature enters through X only): the relative error is
-1/X at the zenith and about -3/(8 X) at the horizon (Ch(X, 90 deg) =
X e^X K_1(X) = sqrt(pi X / 2)(1 + 3/(8X) + ...)), i.e. 1.3e-3 for Earth's
Rayleigh layer (X ~ 795) and 1.9e-4 for its Mie layer (X ~ 5300); its mu
derivative at the horizon is exact to the same order (-X), so differences
of nearby columns stay accurate. (The graphics approximation
c / ((c - 1) cos chi + 1), c = sqrt(pi X / 2), is off by 11-15% at
X = 50-5300 and its horizon slope by 39-55%; see docs/lut_chapman_fog.md.)
Measured for segments (docs/lut_chapman_fog.md): max relative error 1.25e-3
(H = 8 km) and 1.9e-4 (H = 1.2 km) on every kind of segment, short ones and
the horizon included. float32 loses ~2e-4 of the larger column in the
difference (absolute ~1 cm), so sub-metre segments are coarse there.

Rays below the horizon use the tangent-point identity (the column is symmetric
about the ray's closest point to the centre; e.g. Smith & Smith 1972, Huestis 2001)::

    Col(r, mu < 0) = 2 Col(r_t, 0) - Col(r, -mu),     r_t = r sqrt(1 - mu^2),

and a segment's column is Col(start) - Col(end) along the same direction.
With A = Col(r, |mu|), B = Col(r_d, |mu_d|) at the start and end, this is

    mu >= 0:                A - B
    mu < 0, mu_d <= 0:      B - A       (before the tangent point; every ground-hitting segment)
    mu < 0, mu_d > 0:       2 Col(r_t, 0) - A - B   (the segment passes the tangent point)

so the column through the planet, which the identity would need for rays
that hit the ground, is never formed, and Col(r_t, 0) enters only where
r_t >= R. The infinite column ignores the top of the atmosphere, but the
difference removes the part beyond the segment's end exactly, so a segment
to the top carries no truncation error; Col(r, mu) itself exceeds the
column to the top by Col(top, mu_top), about exp(-(top - R) / H) relative
(5.5e-4 for H = 8 km, 2e-22 for H = 1.2 km, Earth).

Regime: X = R_bottom / H >= ``min_x`` (default 50, where the error is 1.9%);
segments must stay above the ground (their lowest radius >= R_bottom).
Outside it the class raises ValueError.
"""
from __future__ import annotations

import math
from typing import NamedTuple

import torch
from torch import Tensor

from ..geometry import safe_sqrt
from .base import ColumnFn, OpticalDepthIntegrator

CHAPMAN_MIN_X_DEFAULT: float = 50.0
"""Smallest X = R_bottom / H accepted [1]; the approximation's error is ~1/X (2% at 50, measured)."""


def chapman_column_up(altitude: Tensor, r: Tensor, mu: Tensor, scale_heights: Tensor) -> Tensor:
    """Column to infinity for mu >= 0 by Fitzmaurice 1964: H e^{-h/H} sqrt(pi X/2) erfcx(sqrt(X/2) mu).

    Args:
        altitude: h = r - R_bottom, passed separately for precision, shape (..., 1). [m]
        r: radius (enters through X = r / H only), same shape. [m]
        mu: zenith cosine in [0, 1], same shape. [1]
        scale_heights: shape (K,). [m]

    Returns:
        shape (..., K). [m]
    """
    H = scale_heights
    X = r / H
    return H * torch.exp(-altitude / H) * math.sqrt(math.pi / 2.0) * torch.sqrt(X) * torch.special.erfcx(torch.sqrt(X / 2.0) * mu)


class SegmentGeometry(NamedTuple):
    """Where a straight segment starts, ends and (if it passes one) has its tangent point."""

    h: Tensor  # start altitude r - R [m]
    r_d: Tensor  # end radius [m]
    h_d: Tensor  # end altitude [m]
    mu_d: Tensor  # zenith cosine of the ray at the end [1]
    up: Tensor  # the segment starts upwards (mu >= 0)
    before: Tensor  # downwards and ends before the tangent point
    through: Tensor  # downwards and passes the tangent point
    r_t: Tensor  # radius of the tangent point (meaningful where ``through``) [m]
    h_t: Tensor  # its altitude [m]


def segment_geometry(r: Tensor, mu: Tensor, length: Tensor, bottom_radius: float) -> SegmentGeometry:
    """The end and tangent points of segments (r, mu, length), shapes broadcast, without cancellation.

    End point: r_d - r = (2 r mu L + L^2) / (r_d + r) keeps the altitude accurate in float32,
    where r_d itself is only known to ~0.5 m. Tangent point (only where the segment passes it;
    elsewhere it may lie inside the planet): r_t - R = ((r - R)(r + R) - r^2 mu^2) / (r_t + R).
    """
    R = bottom_radius
    h = r - R
    r_d = safe_sqrt(r * r + 2.0 * r * mu * length + length * length)
    den = r_d + r
    den = torch.where(den > 0, den, torch.ones_like(den))
    h_d = h + length * (2.0 * r * mu + length) / den
    up = mu >= 0
    r_d_safe = torch.where(r_d > 0, r_d, torch.ones_like(r_d))
    mu_d = torch.where(r_d > 0, (r * mu + length) / r_d_safe, mu)
    before = (~up) & (mu_d <= 0)
    through = (~up) & (mu_d > 0)
    mu_t = torch.where(through, mu, torch.zeros_like(mu))
    r_t = r * safe_sqrt((1.0 - mu_t) * (1.0 + mu_t))
    h_t = (h * (r + R) - r * r * mu_t * mu_t) / (r_t + R)
    return SegmentGeometry(h, r_d, h_d, mu_d, up, before, through, r_t, h_t)


def chapman_segment_column(r: Tensor, mu: Tensor, length: Tensor, scale_heights: Tensor, bottom_radius: float) -> Tensor:
    """Column of a segment as a difference of Chapman columns (see the module docstring).

    Args:
        r: start radius, shape (...). [m]
        mu: view cosine at the start, shape (...). [1]
        length: segment length >= 0, shape (...). [m]
        scale_heights: shape (K,). [m]

    Returns:
        shape (..., K). [m]
    """
    r, mu, length = (t.unsqueeze(-1) for t in torch.broadcast_tensors(r, mu, length))
    g = segment_geometry(r, mu, length, bottom_radius)
    # Signed so that each branch has the derivative of its own formula at mu = 0 and mu_d = 0.
    a = chapman_column_up(g.h, r, torch.where(g.up, mu, -mu), scale_heights)
    b = chapman_column_up(g.h_d, g.r_d, torch.where(g.before, -g.mu_d, g.mu_d), scale_heights)
    t = chapman_column_up(g.h_t, g.r_t, torch.zeros_like(g.r_t), scale_heights)
    return torch.where(g.up, a - b, torch.where(g.before, b - a, 2.0 * t - a - b))


class ChapmanOpticalDepth(OpticalDepthIntegrator):
    """Segment columns from the Fitzmaurice 1964 Chapman-function approximation (no table, no loop).

    Args:
        min_x: smallest accepted X = R_bottom / H (regime of the approximation). [1]
    """

    name = "chapman"

    def __init__(self, min_x: float = CHAPMAN_MIN_X_DEFAULT, approximation: str = "fitzmaurice1964"):
        # ``approximation`` names the one formula implemented; accepted so that
        # ``make_integrator(**integrator.settings())`` round-trips (RESULT.json).
        if approximation != "fitzmaurice1964":
            raise ValueError(f"unknown Chapman approximation {approximation!r}; valid: fitzmaurice1964")
        if not float(min_x) > 0:
            raise ValueError(f"min_x must be > 0, got {min_x}")
        self.min_x = float(min_x)

    def _check_layers(self, scale_heights: Tensor, bottom_radius: float) -> None:
        if scale_heights.dim() != 1:
            raise ValueError(f"scale_heights must have shape (K,), got {tuple(scale_heights.shape)}")
        with torch.no_grad():
            h_min, h_max = float(scale_heights.min()), float(scale_heights.max())
        if h_min <= 0:
            raise ValueError("scale heights must be > 0")
        x = bottom_radius / h_max
        if x < self.min_x:
            raise ValueError(
                f"chapman: X = r/H = {x:.4g} (R = {bottom_radius:.6g} m, H = {h_max:.6g} m) is below min_x = {self.min_x:g}; "
                "the Chapman approximation's error grows like 1/X (use a quadrature integrator)"
            )

    def _check_segments(self, r: Tensor, mu: Tensor, length: Tensor, bottom_radius: float) -> None:
        if r.numel() == 0:
            return
        tol = max(1.0, 16.0 * torch.finfo(r.dtype).eps * bottom_radius)
        with torch.no_grad():
            r, mu, length = torch.broadcast_tensors(r, mu, length)
            # Lowest radius on the segment: the tangent radius if it lies inside, else an end.
            s_t = torch.clamp(-r * mu, min=torch.zeros_like(length), max=length)
            low = torch.sqrt(torch.clamp_min(r * r + 2.0 * r * mu * s_t + s_t * s_t, 0.0))
            lo = float(low.min())
            bad_mu = bool((mu.abs() > 1.0 + 1e-6).any()) or bool((length < 0).any())
        if lo < bottom_radius - tol:
            raise ValueError(
                f"chapman: a segment dips to radius {lo:.6g} m, below the ground R = {bottom_radius:.6g} m; "
                "the Chapman columns are valid only above the planet"
            )
        if bad_mu:
            raise ValueError("chapman: need |mu| <= 1 and length >= 0")

    def column(self, r, mu, length, scale_heights, bottom_radius, top_radius) -> Tensor:
        self._check_layers(scale_heights, bottom_radius)
        self._check_segments(r, mu, length, bottom_radius)
        return chapman_segment_column(r, mu, length, scale_heights, bottom_radius)

    def prepare(self, scale_heights: Tensor, bottom_radius: float, top_radius: float) -> ColumnFn:
        self._check_layers(scale_heights, bottom_radius)

        def fn(r: Tensor, mu: Tensor, length: Tensor) -> Tensor:
            self._check_segments(r, mu, length, bottom_radius)
            return chapman_segment_column(r, mu, length, scale_heights, bottom_radius)

        return fn

    def settings(self) -> dict:
        return {"name": self.name, "min_x": self.min_x, "approximation": "fitzmaurice1964"}
