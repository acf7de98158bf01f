"""Ishiyama 2018 analytic height fog: the column of an exponential layer over flat ground.

With the density decaying along the vertical axis only (Ishiyama 2018,
eqs. 9-10, height h(s) = h0 + mu s), the column of a segment of length L
starting at height h0 = r - R_bottom with vertical direction cosine mu is
(Ishiyama 2018 eq. 14; eq. 23 is its transmittance)::

    col = H / mu * exp(-h0 / H) * (1 - exp(-L mu / H))
        = L * exp(-h_low / H) * phi(L |mu| / H),      phi(y) = (1 - e^{-y}) / y,

the second form (h_low = min(h0, h0 + L mu), the lower end) being the one
evaluated: it has no 0/0 at mu = 0 (phi(0) = 1, taken from its series
1 - y/2 + y^2/6 - y^3/24 for y < 1e-3) and no overflow for descending rays.
Values and gradients are finite for every mu in [-1, 1].

Regime: the flat-Earth approximation. Along the true (spherical) ray the
height exceeds the flat one by

    Delta(s) = r(s) - (r + mu s) = s^2 (1 - mu^2) / (r(s) + r + mu s) <= L^2 (1 - mu^2) / (2 R - L)

for a segment above the ground, so the flat column is never below the true
one and exceeds it by a relative amount of at most
1 - exp(-delta) <= delta, with the curvature fraction

    delta = L^2 (1 - mu^2) / ((2 R - L) H).

This is the brief's criterion L^2 / (2 R) <= f H, tightened by (1 - mu^2)
(vertical rays are exact) and 2 R - L (a strict bound). Segments with
delta > ``max_curvature_fraction`` (default 0.01: at most 1% too large) for
the smallest scale height raise ValueError, so a full-sky render with long
horizon rays is refused instead of returning a flat-Earth column (e.g. a
horizontal ray of 100 km with H = 1.2 km has delta = 0.66). The height fog
has no top of the atmosphere: the column is that of the segment given.
"""
from __future__ import annotations

import torch
from torch import Tensor

from .base import ColumnFn, OpticalDepthIntegrator

FOG_MAX_CURVATURE_FRACTION_DEFAULT: float = 0.01
"""Largest accepted curvature fraction delta = L^2 (1 - mu^2) / ((2R - L) H) [1]; bounds the relative error by 1%."""

_SERIES_BELOW = 1e-3


def _phi(y: Tensor) -> Tensor:
    """(1 - e^{-y}) / y for y >= 0, with its series near 0 (finite value and gradient at y = 0). [1]"""
    small = y < _SERIES_BELOW
    y_big = torch.where(small, torch.ones_like(y), y)
    direct = -torch.expm1(-y_big) / y_big
    series = 1.0 - y * (0.5 - y * (1.0 / 6.0 - y / 24.0))
    return torch.where(small, series, direct)


def height_fog_column(r: Tensor, mu: Tensor, length: Tensor, scale_heights: Tensor, bottom_radius: float) -> Tensor:
    """Ishiyama 2018 eq. 14 column over flat ground, in the stable form of the module docstring.

    Args:
        r: start radius (height h0 = r - R_bottom), shape (...). [m]
        mu: vertical direction cosine, shape (...). [1]
        length: segment length >= 0, shape (...). [m]
        scale_heights: shape (K,). [m]

    Returns:
        shape (..., K). [m]
    """
    r, mu, length = (t.unsqueeze(-1) for t in torch.broadcast_tensors(r, mu, length))
    H = scale_heights
    h0 = r - bottom_radius
    up = mu >= 0
    h_low = torch.where(up, h0, h0 + length * mu)
    y = length * torch.where(up, mu, -mu) / H
    return length * torch.exp(-h_low / H) * _phi(y)


def curvature_fraction(mu: Tensor, length: Tensor, scale_height: float, bottom_radius: float) -> Tensor:
    """delta = L^2 (1 - mu^2) / ((2 R - L) H): bound on the flat-Earth relative column error, shape (...). [1]"""
    den = (2.0 * bottom_radius - length) * scale_height
    return torch.where(den > 0, length * length * (1.0 - mu) * (1.0 + mu) / torch.where(den > 0, den, torch.ones_like(den)), torch.full_like(den, float("inf")))


class HeightFogOpticalDepth(OpticalDepthIntegrator):
    """Ishiyama 2018 flat analytic height fog, refused where Earth's curvature matters.

    Args:
        max_curvature_fraction: largest accepted delta (see module docstring); the
            relative error of the column is at most this. [1]
    """

    name = "height_fog"

    def __init__(self, max_curvature_fraction: float = FOG_MAX_CURVATURE_FRACTION_DEFAULT):
        if not float(max_curvature_fraction) > 0:
            raise ValueError(f"max_curvature_fraction must be > 0, got {max_curvature_fraction}")
        self.max_curvature_fraction = float(max_curvature_fraction)

    def _check(self, mu: Tensor, length: Tensor, scale_heights: Tensor, bottom_radius: float) -> None:
        if scale_heights.dim() != 1:
            raise ValueError(f"scale_heights must have shape (K,), got {tuple(scale_heights.shape)}")
        with torch.no_grad():
            h_min = float(scale_heights.min())
            if h_min <= 0:
                raise ValueError("scale heights must be > 0")
            if length.numel() == 0:
                return
            mu, length = torch.broadcast_tensors(mu, length)
            if bool((length < 0).any()) or bool((mu.abs() > 1.0 + 1e-6).any()):
                raise ValueError("height_fog: need |mu| <= 1 and length >= 0")
            mu = torch.clamp(mu, -1.0, 1.0)
            delta = float(curvature_fraction(mu, length, h_min, bottom_radius).max())
        if delta > self.max_curvature_fraction:
            raise ValueError(
                f"height_fog: flat-Earth curvature fraction L^2(1-mu^2)/((2R-L)H) = {delta:.3g} exceeds "
                f"max_curvature_fraction = {self.max_curvature_fraction:g} (H = {h_min:g} m); the segments are too long "
                "for the flat height-fog model (use a spherical integrator, e.g. 'gauss' or 'chapman')"
            )

    def column(self, r, mu, length, scale_heights, bottom_radius, top_radius) -> Tensor:
        self._check(mu, length, scale_heights, bottom_radius)
        return height_fog_column(r, mu, length, scale_heights, bottom_radius)

    def prepare(self, scale_heights: Tensor, bottom_radius: float, top_radius: float) -> ColumnFn:
        def fn(r: Tensor, mu: Tensor, length: Tensor) -> Tensor:
            return self.column(r, mu, length, scale_heights, bottom_radius, top_radius)

        return fn

    def settings(self) -> dict:
        return {"name": self.name, "max_curvature_fraction": self.max_curvature_fraction}
