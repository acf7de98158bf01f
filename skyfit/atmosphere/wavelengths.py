"""Wavelength grids as users write them: ``START:STOP:STEP`` or a comma list [nm]."""
from __future__ import annotations

import numpy as np

DEFAULT_WAVELENGTHS = "400:700:20"
"""The model grid of renders and of RGB data without a grid of their own [nm]: 16 samples of the visible."""
MIN_WAVELENGTH_NM: float = 200.0
MAX_WAVELENGTH_NM: float = 3000.0
"""The solar spectrum skyfit ships (ASTM G-173) and the Rayleigh/ozone tables cover this range [nm]."""
MAX_WAVELENGTHS: int = 10_000
"""Most wavelengths in a grid: 200-3000 nm every 0.28 nm, finer than any spectrum skyfit ships resolves
(ASTM G-173 samples every 0.5-5 nm); a finer grid is a typo, not a model."""


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
            count = (stop - start) / step + 1
            if not np.all(np.isfinite(parts)):
                lam = np.array(parts)  # refused below: outside 200-3000 nm
            elif count > MAX_WAVELENGTHS:
                raise OverflowError
            else:
                lam = np.arange(start, stop + step * 1e-9, step)
        else:
            lam = np.array([float(p) for p in text.split(",") if p.strip()])
    except ValueError:
        raise ValueError(f"--wavelengths must be START:STOP:STEP or a comma list in nm, got {text!r}") from None
    except OverflowError:
        raise ValueError(f"--wavelengths {text!r} gives {count:.3g} wavelengths, more than {MAX_WAVELENGTHS} "
                         "(finer than any shipped spectrum resolves)") from None
    if lam.size > MAX_WAVELENGTHS:
        raise ValueError(f"--wavelengths gives {lam.size} wavelengths, more than {MAX_WAVELENGTHS}")
    if lam.size == 0 or np.any(~np.isfinite(lam)) or np.any(lam < MIN_WAVELENGTH_NM) or np.any(lam > MAX_WAVELENGTH_NM):
        raise ValueError(f"--wavelengths must lie in 200-3000 nm, got {text!r}")
    if np.unique(lam).size != lam.size:
        raise ValueError(f"--wavelengths has duplicates: {text!r}")
    return lam
