"""Directions in, radiance and colour out."""
from .colour import delta_e_1976, luminance, spectral_to_xyz, spectral_to_xyz_matrix, tonemap_srgb8, xyz_to_linear_srgb
from .sky import SkyImage, render_directions, render_fisheye, render_vectors

__all__ = [
    "SkyImage",
    "delta_e_1976",
    "luminance",
    "render_directions",
    "render_fisheye",
    "render_vectors",
    "spectral_to_xyz",
    "spectral_to_xyz_matrix",
    "tonemap_srgb8",
    "xyz_to_linear_srgb",
]
