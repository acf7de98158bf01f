"""LUT writers and readers: Bruneton tables as OpenEXR or npz for shaders (docs/luts.md)."""
from .lut import FORMATS, LUT_VERSION, LutError, export_luts, load_luts

__all__ = ["FORMATS", "LUT_VERSION", "LutError", "export_luts", "load_luts"]
