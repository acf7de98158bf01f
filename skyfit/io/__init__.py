"""File formats: OpenEXR, Radiance .hdr, Kider et al. 2014 spectroradiometer captures."""
from .exr import METADATA_KEY, ExrError, read_exr, write_exr
from .hdr import HdrError, read_hdr, write_hdr
from .kider import (
    KiderCapture,
    KiderError,
    is_kider_capture_name,
    load_kider_capture,
    ring_symmetry_azimuths,
    symmetry_azimuth,
)

__all__ = [
    "METADATA_KEY",
    "ExrError",
    "HdrError",
    "KiderCapture",
    "KiderError",
    "is_kider_capture_name",
    "load_kider_capture",
    "read_exr",
    "read_hdr",
    "ring_symmetry_azimuths",
    "symmetry_azimuth",
    "write_exr",
    "write_hdr",
]
