"""The interface every optical-depth integrator implements.

An integrator computes, for an exponential density layer of scale height H,
the *column* (optical length) along a straight segment::

    column(r, mu, L; H) = int_0^L exp(-(r(s) - R_bottom) / H) ds,   r(s) = sqrt(r^2 + 2 r mu s + s^2)

(Gałaj 2021 eq. 9; Bruneton & Neyret 2008 eq. 5 without the coefficient).
The optical depth of a species is its sea-level extinction times its column,
so every coefficient beta enters linearly and its gradient is exact.
"""
from __future__ import annotations

import abc
from typing import Callable, ClassVar, Mapping

from torch import Tensor

from .boundary_layer import boundary_layer_columns

ColumnFn = Callable[[Tensor, Tensor, Tensor], Tensor]


class OpticalDepthIntegrator(abc.ABC):
    """A named, configurable optical-depth method.

    Subclasses implement :meth:`column`; methods with precomputation (spline
    grids, LUTs) override :meth:`prepare` to build it once per atmosphere.
    """

    name: ClassVar[str]

    @abc.abstractmethod
    def column(self, r: Tensor, mu: Tensor, length: Tensor, scale_heights: Tensor, bottom_radius: float, top_radius: float) -> Tensor:
        """Column of each layer along the segment.

        Args:
            r: start radius, shape (...). [m]
            mu: cosine of the segment's zenith angle at its start, shape (...). [1]
            length: segment length >= 0, shape (...). [m]
            scale_heights: shape (K,). [m]
            bottom_radius, top_radius: planet and atmosphere radii. [m]

        Returns:
            shape (..., K). [m]
        """

    def prepare(self, scale_heights: Tensor, bottom_radius: float, top_radius: float) -> ColumnFn:
        """A function ``(r, mu, length) -> column (..., K)`` for fixed layers (precomputation goes here)."""

        def fn(r: Tensor, mu: Tensor, length: Tensor) -> Tensor:
            return self.column(r, mu, length, scale_heights, bottom_radius, top_radius)

        return fn

    def prepare_layers(self, scale_heights: Tensor, bottom_radius: float, top_radius: float,
                       mixing_heights: Mapping[int, Tensor] | None = None) -> ColumnFn:
        """:meth:`prepare` for layers that may have a boundary-layer profile (docs/aerosol.md).

        Args:
            scale_heights: shape (K,). [m]
            bottom_radius, top_radius: [m]
            mixing_heights: layer index -> mixing height h_mix, shape (), for the layers whose density is
                1 up to h_mix and exp(-(h - h_mix) / H) above; None or empty: all exponential. [m]

        Returns:
            ``(r, mu, length) -> (..., K)``: this integrator's exponential columns split exactly at the
            layer top (:mod:`skyfit.transmittance.boundary_layer`); :meth:`prepare` itself when every
            layer is exponential. The quadrature family overrides it to integrate the profile directly.
        """
        fn = self.prepare(scale_heights, bottom_radius, top_radius)
        if not mixing_heights:
            return fn
        return boundary_layer_columns(fn, scale_heights, mixing_heights, bottom_radius)

    def settings(self) -> dict:
        """Name and hyperparameters, for result JSON and EXR headers."""
        return {"name": self.name}

    def __repr__(self) -> str:
        s = ", ".join(f"{k}={v!r}" for k, v in self.settings().items() if k != "name")
        return f"{type(self).__name__}({s})"
