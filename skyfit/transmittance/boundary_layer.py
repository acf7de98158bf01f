"""Columns of a boundary-layer profile from an integrator's exponential columns, by an exact split.

The boundary-layer density (:func:`skyfit.atmosphere.profiles.boundary_layer_density`) is 1 up to
the mixing height h_mix and exp(-(h - h_mix) / H) above. Along a straight segment (r, mu, L) the
part inside the layer, |p(s)| < R_m = R_bottom + h_mix, is one interval [a, b] of s (a ball is
convex); there the density is the constant 1, so its column is the length b - a. Outside it,
exp(-(h - h_mix) / H) = exp(h_mix / H) exp(-h / H), the exponential layer's density times a
constant, so

    column = (b - a) + exp(h_mix / H) [C(r, mu, a) + C(r_b, mu_b, L - b)],

with C the integrator's exponential column (base.py) and (r_b, mu_b) the point at s = b. The split
is exact: the result is as accurate as C on the two pieces above the layer (Chapman, Taylor,
spline, LUT and height-fog keep their own accuracy), and differentiable in h_mix through a, b and
the factor. [a, b] is where s^2 + 2 r mu s + (r^2 - R_m^2) < 0 (Bruneton 2017's ray-sphere
intersection), clipped to [0, L]; the roots use the non-cancelling forms of
:func:`skyfit.geometry.distance_to_top`.

Valid while exp(h_mix / H) and the column above, ~exp(-h_mix / H), are both representable:
h_mix / H <= :data:`MAX_MIXING_RATIO` x ln(largest float) (40 in float32, 350 in float64);
beyond it the wrapper refuses (a quadrature integrator evaluates the profile directly).
"""
from __future__ import annotations

import math
from typing import Callable, Mapping

import torch
from torch import Tensor

from ..geometry import discriminant, point_along_ray, safe_sqrt

ColumnFn = Callable[[Tensor, Tensor, Tensor], Tensor]  # as skyfit.transmittance.base (which imports this module)

MAX_MIXING_RATIO: float = 0.5
"""h_mix / H may reach this fraction of ln(finfo(dtype).max) (float32: 44, float64: 354) [1]."""


def layer_interval(r: Tensor, mu: Tensor, length: Tensor, layer_radius: Tensor) -> tuple[Tensor, Tensor]:
    """The part [a, b] of the segment (r, mu, length) inside the sphere of radius ``layer_radius``.

    Args:
        r: start radius, shape (...). [m]
        mu: zenith cosine at the start, shape (...). [1]
        length: segment length >= 0, shape (...). [m]
        layer_radius: R_m = R_bottom + h_mix, shape () or broadcastable. [m]

    Returns:
        (a, b), each shape broadcast(...), 0 <= a <= b <= length; a = b = length when the segment
        misses the sphere. [m]
    """
    c = (r - layer_radius) * (r + layer_radius)  # r^2 - R_m^2, without cancellation
    disc = discriminant(r, mu, layer_radius)  # (r mu)^2 - c
    meets = disc > 0
    sq = safe_sqrt(disc)
    rm = r * mu
    q = rm.abs() + sq  # > 0 where the line meets the sphere (unless r = 0)
    q_safe = torch.where(q > 0, q, torch.ones_like(q))
    # roots of s^2 + 2 r mu s + c: -r mu -+ sqrt(disc); the one that cancels from c / (the other)
    far = torch.where(mu >= 0, -c / q_safe, -rm + sq)
    near = torch.where(mu >= 0, -rm - sq, c / q_safe)
    a = torch.minimum(torch.clamp_min(near, 0.0), length)
    b = torch.minimum(torch.clamp_min(far, 0.0), length)
    a = torch.where(meets, a, length)
    b = torch.where(meets, torch.maximum(a, b), length)
    return a, b


def check_mixing_ratio(mixing_height: Tensor, scale_height: Tensor, dtype: torch.dtype) -> None:
    """ValueError when exp(h_mix / H) would leave ``dtype``'s range (module docstring)."""
    limit = MAX_MIXING_RATIO * math.log(torch.finfo(dtype).max)
    with torch.no_grad():
        ratio = float(mixing_height.reshape(()) / scale_height.reshape(()))
    if not ratio <= limit:
        raise ValueError(
            f"boundary layer: h_mix / H = {ratio:.4g} exceeds {limit:.3g} in {str(dtype).replace('torch.', '')}; the split "
            "column exp(h_mix/H) x C loses its precision (use a quadrature integrator: gauss, trapezoid, midpoint, simpson)"
        )


def boundary_layer_columns(column_fn: ColumnFn, scale_heights: Tensor, mixing_heights: Mapping[int, Tensor],
                           bottom_radius: float) -> ColumnFn:
    """A column function whose layers ``k in mixing_heights`` have the boundary-layer profile.

    Args:
        column_fn: exponential columns ``(r, mu, length) -> (..., K)`` of ``scale_heights``.
        scale_heights: shape (K,). [m]
        mixing_heights: layer index -> h_mix, shape (). [m]
        bottom_radius: the ground's radius. [m]

    Returns:
        ``(r, mu, length) -> (..., K)``: the exponential layers as ``column_fn``'s, the others split
        at the layer top (module docstring). [m]
    """
    for k, h in mixing_heights.items():
        check_mixing_ratio(h, scale_heights[k], scale_heights.dtype)

    def fn(r: Tensor, mu: Tensor, length: Tensor) -> Tensor:
        r, mu, length = torch.broadcast_tensors(r, mu, length)
        full = column_fn(r, mu, length)
        cols = list(full.unbind(-1))
        for k, h in mixing_heights.items():
            h = h.to(dtype=r.dtype, device=r.device)
            a, b = layer_interval(r, mu, length, bottom_radius + h)
            r_b, mu_b = point_along_ray(r, mu, b)
            above = column_fn(r, mu, a)[..., k] + column_fn(r_b, mu_b, length - b)[..., k]
            cols[k] = (b - a) + torch.exp(h / scale_heights[k]) * above
        return torch.stack(cols, -1)

    return fn
