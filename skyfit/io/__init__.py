"""File formats: OpenEXR, Radiance .hdr, Kider et al. 2014 spectroradiometer captures, photos (any format, brackets)."""
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
from .photo import PHOTO_EXTENSIONS, LinearPhoto, PhotoError, is_photo_path, read_photo

__all__ = [
    "METADATA_KEY",
    "ExrError",
    "HdrError",
    "KiderCapture",
    "KiderError",
    "LinearPhoto",
    "PHOTO_EXTENSIONS",
    "PhotoError",
    "is_kider_capture_name",
    "is_photo_path",
    "load_kider_capture",
    "read_exr",
    "read_hdr",
    "read_photo",
    "ring_symmetry_azimuths",
    "symmetry_azimuth",
    "write_exr",
    "write_hdr",
]
