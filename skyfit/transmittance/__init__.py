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

Boundary-layer aerosol (``mie.profile: boundary_layer``, docs/aerosol.md): every integrator
takes it through :meth:`OpticalDepthIntegrator.prepare_layers` (:func:`prepare_columns` of an
atmosphere). The quadrature family samples the profile directly; the closed forms (taylor,
spline, chapman), the LUT and height fog are split exactly at the layer top
(:mod:`.boundary_layer`): the constant part is a length, the part above their own
exponential column times exp(h_mix / H).
"""
from __future__ import annotations

import importlib
import inspect
import math

from ..atmosphere import Atmosphere
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
    except ValueError as e:  # a hyperparameter out of range: name the integrator
        raise ValueError(f"integrator {name!r}: {e}") from None


def parse_integrator(text: str) -> OpticalDepthIntegrator:
    """``NAME`` or ``NAME:key=value,key=value`` -> integrator instance (ValueError on a bad spec).

    A value ``v1/v2`` is a list, one per layer (Rayleigh/Mie), e.g. the per-layer
    Taylor pairs of ``skyfit calibrate-integrator``: ``taylor:a=0.367/0.424,b=0.359/0.116``.
    """

    name, _, opts = text.partition(":")
    name = name.strip()
    cls = integrator_class(name)
    params = {k: p for k, p in inspect.signature(cls.__init__).parameters.items() if k != "self"}
    settings: dict = {}
    for item in filter(None, opts.split(",")):
        key, eq, val = item.partition("=")
        if not eq:
            raise ValueError(f"integrator option must be key=value, got {item!r}")
        key = key.strip()
        if key not in params:
            raise ValueError(f"integrator {name!r} has no option {key!r}; its options: {', '.join(params) or 'none'}")
        kind = str(params[key].annotation)
        convert = (lambda v: _option_value(name, key, v, kind))  # noqa: E731
        settings[key] = [convert(v) for v in val.split("/")] if "/" in val else convert(val)
    return make_integrator(name, **settings)


def _option_value(name: str, key: str, text: str, kind: str):
    """One ``key=value`` of an integrator spec as its annotation says: int, float or str."""
    text = text.strip()
    if kind.startswith("int"):
        try:
            return int(text)
        except ValueError:
            raise ValueError(f"integrator {name!r}: option {key} must be an integer, got {text!r}") from None
    if kind.startswith("float"):
        try:
            v = float(text)
        except ValueError:
            raise ValueError(f"integrator {name!r}: option {key} must be a number, got {text!r}") from None
        if not math.isfinite(v):
            raise ValueError(f"integrator {name!r}: option {key} must be finite, got {text!r}")
        return v
    return text


def integrator_from_spec(spec: str | dict) -> OpticalDepthIntegrator:
    """An integrator from a spec string (:func:`parse_integrator`) or a settings dict with ``name``
    (as ``integrator.settings()`` and RESULT.json's ``integrator`` write it; unknown keys are ignored)."""
    if not isinstance(spec, dict):
        return parse_integrator(str(spec))
    d = dict(spec)
    name = d.pop("name", None)
    if name is None:
        raise ValueError("integrator settings lack a name")
    accepted = set(inspect.signature(integrator_class(name).__init__).parameters) - {"self"}
    return make_integrator(name, **{k: v for k, v in d.items() if k in accepted})


def prepare_columns(integrator: OpticalDepthIntegrator, atm: Atmosphere) -> ColumnFn:
    """The (Rayleigh, Mie) column function of ``atm`` with ``integrator``: its
    :meth:`~OpticalDepthIntegrator.prepare_layers` with the atmosphere's scale heights and, for a
    boundary-layer aerosol, its mixing height; ``(r, mu, length) -> (..., 2)``. [m]"""
    return integrator.prepare_layers(atm.scale_heights, atm.bottom_radius, atm.top_radius, atm.mixing_heights)


__all__ = [
    "INTEGRATORS",
    "ColumnFn",
    "OpticalDepthIntegrator",
    "integrator_class",
    "integrator_from_spec",
    "make_integrator",
    "ozone_column",
    "parse_integrator",
    "prepare_columns",
]
