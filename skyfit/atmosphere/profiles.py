"""Density profiles of the absorbing and scattering layers, relative to their reference density.

* Rayleigh and Mie: exponential, exp(-h / H) with the layer's scale height H
  (Bruneton & Neyret 2008 eqs. 1, 3).
* Mie, ``mie_profile: boundary_layer``: a well-mixed layer of constant density up to the
  mixing height h_mix and exponential above, 1 for h <= h_mix and exp(-(h - h_mix) / H_M)
  above (the mixed-layer aerosol of Stull 1988, "An Introduction to Boundary Layer
  Meteorology", Sec. 1.6; the constant-plus-exponential layer pair of Bruneton 2017's
  DensityProfile). Its vertical column is h_mix + H_M (docs/aerosol.md).
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


def boundary_layer_density(altitude: Tensor, mixing_height: Tensor, scale_height: Tensor) -> Tensor:
    """Boundary-layer density relative to the ground's: 1 for h <= h_mix, exp(-(h - h_mix) / H) above. [1]

    Continuous in h with a kink at h_mix; below the ground (rounding of the geometry) it stays 1.
    Differentiable in h_mix and H (d/dh_mix = rho / H above the layer, 0 inside).

    Args:
        altitude: height above the ground h, shape (...). [m]
        mixing_height: h_mix > 0, shape () or broadcastable. [m]
        scale_height: H > 0, shape () or broadcastable. [m]
    """
    return torch.exp(-torch.relu(altitude - mixing_height) / scale_height)


def with_mie_profile(dens: Tensor, altitude: Tensor, atm: Atmosphere) -> Tensor:
    """Exponential densities ``dens`` (..., K >= 2) with the Mie column (index 1) replaced by the atmosphere's
    Mie profile: ``dens`` itself (the same tensor) for ``mie_profile == "exponential"``. [1]

    Args:
        dens: (Rayleigh, Mie[, ...]) exponential densities at ``altitude``, shape (..., K).
        altitude: shape (...). [m]
        atm: the atmosphere (``mie_profile``, ``mie_mixing_height``, ``mie_scale_height``).
    """
    if atm.mie_profile == "exponential":
        return dens
    mie = boundary_layer_density(altitude, atm.mie_mixing_height.reshape(()), atm.mie_scale_height.reshape(()))
    return torch.cat([dens[..., :1], mie.unsqueeze(-1).to(dens.dtype), dens[..., 2:]], dim=-1)


def profile_densities(altitude: Tensor, atm: Atmosphere, ozone: bool = True) -> Tensor:
    """Rayleigh, Mie (and ozone) densities relative to their reference, shape (..., 2 or 3). [1]

    exp(-h / H_R), exp(-h / H_M) (Bruneton & Neyret 2008 eqs. 1, 3) or the boundary layer's
    (:func:`boundary_layer_density`, for ``atm.mie_profile == "boundary_layer"``) and the ozone tent.

    Args:
        altitude: height above the ground, shape (...). [m]
        atm: the atmosphere (scale heights, ozone layer).
        ozone: append the ozone tent as the last density.
    """
    h = altitude.unsqueeze(-1)
    dens = with_mie_profile(torch.exp(-h / atm.scale_heights), altitude, atm)
    if not ozone:
        return dens
    return torch.cat([dens, ozone_tent_density(altitude, atm.ozone_layer_m).unsqueeze(-1)], dim=-1)
