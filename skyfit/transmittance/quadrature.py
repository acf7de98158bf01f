"""Optical depth by fixed quadrature along the segment (Gałaj 2019, Sec. 3; Gałaj 2021 Sec. III).

The classic approach of Nishita 1993 and Bruneton & Neyret 2008 (Sec. 4,
trapezoid) with the rules compared by Gałaj 2019: trapezoid, midpoint,
Simpson and Gauss-Legendre.
"""
from __future__ import annotations

import torch
from torch import Tensor

from ..atmosphere.profiles import boundary_layer_density
from ..geometry import safe_sqrt
from ..quadrature import nodes_weights, validate_rule
from .base import OpticalDepthIntegrator


class QuadratureOpticalDepth(OpticalDepthIntegrator):
    """``samples``-point quadrature of the exponential density along the segment."""

    def __init__(self, samples: int = 64):
        if int(samples) < 1:
            raise ValueError(f"samples must be >= 1, got {samples}")
        self.samples = int(samples)

    def column(self, r, mu, length, scale_heights, bottom_radius, top_radius) -> Tensor:
        x, w = nodes_weights(self.name, self.samples, r.dtype, r.device)
        r_, mu_, L_ = (t.unsqueeze(-1) for t in torch.broadcast_tensors(r, mu, length))
        s = L_ * x  # (..., M)
        # r(s)^2 = r^2 + 2 r mu s + s^2, the point's radius (Bruneton 2017, r_d).
        alt = safe_sqrt(r_ * r_ + 2.0 * r_ * mu_ * s + s * s) - bottom_radius
        dens = torch.exp(-alt.unsqueeze(-1) / scale_heights)  # (..., M, K)
        return torch.einsum("...mk,m->...k", dens, w) * L_

    def prepare_layers(self, scale_heights, bottom_radius, top_radius, mixing_heights=None):
        """Columns of exponential and boundary-layer profiles alike: the rule samples the density itself
        (:func:`skyfit.atmosphere.profiles.boundary_layer_density` for the layers in ``mixing_heights``).

        The boundary-layer density has a kink at h_mix, so the rule converges there at its low-order
        rate (docs/aerosol.md); :meth:`prepare` when every layer is exponential.
        """
        if not mixing_heights:
            return self.prepare(scale_heights, bottom_radius, top_radius)
        layers = dict(mixing_heights)

        def fn(r: Tensor, mu: Tensor, length: Tensor) -> Tensor:
            x, w = nodes_weights(self.name, self.samples, r.dtype, r.device)
            r_, mu_, L_ = (t.unsqueeze(-1) for t in torch.broadcast_tensors(r, mu, length))
            s = L_ * x
            alt = safe_sqrt(r_ * r_ + 2.0 * r_ * mu_ * s + s * s) - bottom_radius  # (..., M)
            dens = torch.exp(-alt.unsqueeze(-1) / scale_heights)  # (..., M, K)
            rows = list(dens.unbind(-1))
            for k, h in layers.items():
                rows[k] = boundary_layer_density(alt, h, scale_heights[k])
            return torch.einsum("...mk,m->...k", torch.stack(rows, -1), w) * L_

        return fn

    def settings(self) -> dict:
        return {"name": self.name, "samples": self.samples}


class TrapezoidOpticalDepth(QuadratureOpticalDepth):
    name = "trapezoid"


class MidpointOpticalDepth(QuadratureOpticalDepth):
    name = "midpoint"


class SimpsonOpticalDepth(QuadratureOpticalDepth):
    name = "simpson"


class GaussOpticalDepth(QuadratureOpticalDepth):
    name = "gauss"


for _cls in (TrapezoidOpticalDepth, MidpointOpticalDepth, SimpsonOpticalDepth, GaussOpticalDepth):
    validate_rule(_cls.name)
