"""File formats: OpenEXR."""
from .exr import METADATA_KEY, ExrError, read_exr, write_exr

__all__ = ["METADATA_KEY", "ExrError", "read_exr", "write_exr"]
