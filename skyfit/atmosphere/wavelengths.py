"""Wavelength grids as users write them: ``START:STOP:STEP`` or a comma list [nm]."""
from __future__ import annotations

import numpy as np

DEFAULT_WAVELENGTHS = "400:700:20"
"""The model grid of renders and of RGB data without a grid of their own [nm]: 16 samples of the visible."""
MIN_WAVELENGTH_NM: float = 200.0
MAX_WAVELENGTH_NM: float = 3000.0
"""The solar spectrum skyfit ships (ASTM G-173) and the Rayleigh/ozone tables cover this range [nm]."""


def parse_wavelengths(text: str) -> np.ndarray:
    """``START:STOP:STEP`` (inclusive of STOP when it falls on the grid) or a comma list -> wavelengths [nm].

    Raises:
        ValueError: one line naming the text, when it is not a grid of distinct wavelengths in 200-3000 nm.
    """
    try:
        if ":" in text:
            parts = [float(p) for p in text.split(":")]
            if len(parts) != 3 or parts[2] <= 0 or parts[1] < parts[0]:
                raise ValueError
            start, stop, step = parts
            lam = np.arange(start, stop + step * 1e-9, step)
        else:
            lam = np.array([float(p) for p in text.split(",") if p.strip()])
    except ValueError:
        raise ValueError(f"--wavelengths must be START:STOP:STEP or a comma list in nm, got {text!r}") from None
    if lam.size == 0 or np.any(~np.isfinite(lam)) or np.any(lam < MIN_WAVELENGTH_NM) or np.any(lam > MAX_WAVELENGTH_NM):
        raise ValueError(f"--wavelengths must lie in 200-3000 nm, got {text!r}")
    if np.unique(lam).size != lam.size:
        raise ValueError(f"--wavelengths has duplicates: {text!r}")
    return lam
