"""Render skies: from directions, and as fisheye images."""
from __future__ import annotations

import dataclasses
import math

import torch
from torch import Tensor

from ..atmosphere import Atmosphere
from ..camera import FisheyeCamera
from ..scattering import single_scattering
from ..transmittance import OpticalDepthIntegrator
from .colour import spectral_to_xyz, xyz_to_linear_srgb


def render_directions(
    atm: Atmosphere,
    zenith: Tensor,
    azimuth: Tensor,
    sun_zenith: float | Tensor,
    sun_azimuth: float | Tensor,
    integrator: OpticalDepthIntegrator,
    altitude: float | Tensor = 0.0,
    orders: int = 1,
    **kwargs,
) -> Tensor:
    """Spectral radiance seen from ``altitude`` in directions (zenith, azimuth), all angles in rad.

    Args:
        zenith, azimuth: view directions (azimuth clockwise from North), shape (...). [rad]
        sun_zenith, sun_azimuth: sun direction, scalars or shape (...). [rad]
        altitude: observer height above the ground (may exceed the atmosphere). [m]
        orders: scattering orders; 1 = single scattering.
        **kwargs: passed to :func:`skyfit.scattering.single_scattering`.

    Returns:
        shape (..., W). [W/(m^2 sr nm)]
    """
    if orders != 1:
        raise ValueError(f"orders={orders}: only single scattering (orders=1) is implemented so far")
    T = lambda v: torch.as_tensor(v, dtype=atm.dtype, device=atm.device)  # noqa: E731
    zenith, azimuth, sz, sa, alt = (T(v) for v in (zenith, azimuth, sun_zenith, sun_azimuth, altitude))
    mu = torch.cos(zenith)
    mu_s = torch.cos(sz)
    # nu = v . s for directions given by (zenith, azimuth) in the local frame.
    nu = mu * mu_s + torch.sin(zenith) * torch.sin(sz) * torch.cos(azimuth - sa)
    nu = torch.clamp(nu, -1.0, 1.0)
    r = atm.bottom_radius + alt
    return single_scattering(atm, r, mu, mu_s, nu, integrator, **kwargs)


@dataclasses.dataclass
class SkyImage:
    """A rendered fisheye: spectral radiance (size, size, W), XYZ, linear sRGB, valid mask."""

    spectral: Tensor
    xyz: Tensor
    rgb: Tensor
    valid: Tensor
    wavelengths: Tensor
    camera: FisheyeCamera


def render_fisheye(
    atm: Atmosphere,
    camera: FisheyeCamera,
    sun_zenith_deg: float,
    sun_azimuth_deg: float,
    integrator: OpticalDepthIntegrator,
    altitude: float = 0.0,
    **kwargs,
) -> SkyImage:
    """Render a fisheye sky image; pixels outside the camera's disc are 0."""
    zen, az, valid = camera.pixel_directions(atm.dtype, atm.device)
    spectral = torch.zeros(*zen.shape, atm.wavelengths.shape[0], dtype=atm.dtype, device=atm.device)
    vals = render_directions(
        atm, zen[valid], az[valid], math.radians(sun_zenith_deg), math.radians(sun_azimuth_deg), integrator, altitude, **kwargs
    )
    spectral = spectral.index_put((valid,), vals)
    xyz = spectral_to_xyz(spectral, atm.wavelengths)
    return SkyImage(spectral, xyz, xyz_to_linear_srgb(xyz), valid, atm.wavelengths, camera)
