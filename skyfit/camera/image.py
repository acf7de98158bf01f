"""Fisheye sky images: render every pixel of a :class:`~skyfit.camera.fisheye.FisheyeCamera`.

The camera layer's renderer: it asks the camera for each pixel's view direction and
:func:`skyfit.render.sky.render_vectors` for the radiance along it, so that the
render layer below needs no camera.
"""
from __future__ import annotations

import dataclasses
import math

import torch
from torch import Tensor

from ..atmosphere import Atmosphere
from ..geometry import zenith_azimuth_to_enu
from ..render.colour import spectral_to_xyz, xyz_to_linear_srgb
from ..render.sky import render_vectors
from ..transmittance import OpticalDepthIntegrator
from .fisheye import FisheyeCamera


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
    """Render a fisheye sky image; pixels outside the camera's field of view are 0.

    ``**kwargs`` go to :func:`skyfit.render.sky.render_vectors` (orders, tables, view_samples ...).
    """
    view, valid = camera.pixel_vectors(atm.dtype, atm.device)
    sun = zenith_azimuth_to_enu(
        torch.tensor(math.radians(sun_zenith_deg), dtype=atm.dtype, device=atm.device),
        torch.tensor(math.radians(sun_azimuth_deg), dtype=atm.dtype, device=atm.device),
    )
    spectral = torch.zeros(*valid.shape, atm.wavelengths.shape[0], dtype=atm.dtype, device=atm.device)
    vals = render_vectors(atm, view[valid], sun, integrator, altitude, **kwargs)
    spectral = spectral.index_put((valid,), vals)
    xyz = spectral_to_xyz(spectral, atm.wavelengths)
    return SkyImage(spectral, xyz, xyz_to_linear_srgb(xyz), valid, atm.wavelengths, camera)
