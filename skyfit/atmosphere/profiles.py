"""Density profiles of the absorbing and scattering layers, relative to their reference density.

* Rayleigh and Mie: exponential, exp(-h / H) with the layer's scale height H
  (Bruneton & Neyret 2008 eqs. 1, 3).
* Ozone: a tent, 0 below ``bottom``, rising linearly to 1 at ``peak`` and falling
  linearly to 0 at ``top`` (Bruneton 2017, demo.cc ozone layers).

The optical-depth integrators (:mod:`skyfit.transmittance`) integrate these profiles
along rays, in closed form or by quadrature; the scattering tables
(:mod:`skyfit.scattering.multiple`, :mod:`skyfit.scattering.hillaire`) sample them.
"""
from __future__ import annotations

import torch
from torch import Tensor

from .params import Atmosphere


def ozone_tent_density(altitude: Tensor, layer_m: tuple[float, float, float]) -> Tensor:
    """Ozone number density relative to its peak: 0 below ``bottom``, rising linearly to 1 at
    ``peak``, falling linearly to 0 at ``top`` (Bruneton 2017, demo.cc ozone layers). [1]

    The clamp acts on altitude (geometry), never on a fitted parameter.

    Args:
        altitude: shape (...). [m]
        layer_m: (bottom, peak, top). [m]
    """
    lo, peak, hi = layer_m
    rise = (altitude - lo) / (peak - lo)
    fall = (hi - altitude) / (hi - peak)
    return torch.clamp(torch.minimum(rise, fall), 0.0, 1.0)


def profile_densities(altitude: Tensor, atm: Atmosphere, ozone: bool = True) -> Tensor:
    """Rayleigh, Mie (and ozone) densities relative to their reference, shape (..., 2 or 3). [1]

    exp(-h / H_R), exp(-h / H_M) (Bruneton & Neyret 2008 eqs. 1, 3) and the ozone tent.

    Args:
        altitude: height above the ground, shape (...). [m]
        atm: the atmosphere (scale heights, ozone layer).
        ozone: append the ozone tent as the last density.
    """
    h = altitude.unsqueeze(-1)
    dens = torch.exp(-h / atm.scale_heights)
    if not ozone:
        return dens
    return torch.cat([dens, ozone_tent_density(altitude, atm.ozone_layer_m).unsqueeze(-1)], dim=-1)
