"""Optical-depth (transmittance) integrators, one module per family, selectable by name.

=============== ================================================ =====================
name            method                                           module
=============== ================================================ =====================
trapezoid       composite trapezoid rule along the segment       quadrature
midpoint        composite midpoint rule                          quadrature
simpson         composite Simpson rule                           quadrature
gauss           Gauss-Legendre                                   quadrature
taylor          Gałaj 2021 eq. 17 Taylor approximation           taylor
spline          Gałaj 2021 Sec. IV.E splines, closed-form        spline
bruneton_lut    Bruneton & Neyret 2008 Sec. 4 2D LUT, bilinear   lut
height_fog      Ishiyama 2018 flat analytic height fog           fog
chapman         closed-form Chapman grazing-incidence approx.    chapman
=============== ================================================ =====================

Not an integrator but used with every one: :func:`ozone_column` (module ``ozone``), the
exact column of the ozone tent layer along a segment.
"""
from __future__ import annotations

import importlib

from .base import ColumnFn, OpticalDepthIntegrator
from .ozone import ozone_column

_REGISTRY: dict[str, tuple[str, str]] = {
    "trapezoid": ("quadrature", "TrapezoidOpticalDepth"),
    "midpoint": ("quadrature", "MidpointOpticalDepth"),
    "simpson": ("quadrature", "SimpsonOpticalDepth"),
    "gauss": ("quadrature", "GaussOpticalDepth"),
    "taylor": ("taylor", "TaylorOpticalDepth"),
    "spline": ("spline", "SplineOpticalDepth"),
    "bruneton_lut": ("lut", "BrunetonLUTOpticalDepth"),
    "height_fog": ("fog", "HeightFogOpticalDepth"),
    "chapman": ("chapman", "ChapmanOpticalDepth"),
}

INTEGRATORS: tuple[str, ...] = tuple(_REGISTRY)


def integrator_class(name: str) -> type[OpticalDepthIntegrator]:
    """The class registered under ``name`` (ValueError listing valid names otherwise)."""
    if name not in _REGISTRY:
        raise ValueError(f"unknown integrator {name!r}; valid: {', '.join(INTEGRATORS)}")
    mod, cls = _REGISTRY[name]
    return getattr(importlib.import_module(f".{mod}", __name__), cls)


def make_integrator(name: str, **settings) -> OpticalDepthIntegrator:
    """Instantiate an integrator by name with its hyperparameters (e.g. ``samples=64``)."""
    cls = integrator_class(name)
    try:
        return cls(**settings)
    except TypeError as e:
        raise ValueError(f"bad settings for integrator {name!r}: {e}") from None


__all__ = ["INTEGRATORS", "ColumnFn", "OpticalDepthIntegrator", "integrator_class", "make_integrator", "ozone_column"]
