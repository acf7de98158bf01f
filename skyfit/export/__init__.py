"""What leaves skyfit for renderers (docs/luts.md, docs/envmap.md).

- :mod:`.lut`: Bruneton tables as OpenEXR or npz (skyfit's layout) and their reader;
- :mod:`.bruneton2017`: the textures, raw .dat files and GLSL (:mod:`.glsl`) an unmodified Bruneton 2017
  shader samples, with :mod:`.shader_reference`, the GLSL's NumPy transcription;
- :mod:`.unreal`: Unreal SkyAtmosphere parameters and Hillaire 2020's LUT set;
- :mod:`.envmap`: HDR environment maps (lat-long, cubemap) for image-based lighting.
"""
from .lut import FORMATS, LUT_VERSION, LutError, export_luts, load_luts

__all__ = ["FORMATS", "LUT_VERSION", "LutError", "export_luts", "load_luts"]
