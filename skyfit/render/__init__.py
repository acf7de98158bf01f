"""Directions in, radiance and colour out (fisheye images: :mod:`skyfit.camera.image`)."""
from .colour import delta_e_1976, luminance, spectral_to_xyz, spectral_to_xyz_matrix, tonemap_srgb8, xyz_to_linear_srgb
from .sky import render_directions, render_vectors

__all__ = [
    "delta_e_1976",
    "luminance",
    "render_directions",
    "render_vectors",
    "spectral_to_xyz",
    "spectral_to_xyz_matrix",
    "tonemap_srgb8",
    "xyz_to_linear_srgb",
]
