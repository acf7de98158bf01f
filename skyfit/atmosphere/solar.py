"""Extraterrestrial solar spectral irradiance (ASTM G-173)."""
from __future__ import annotations

import functools

import numpy as np


@functools.lru_cache(maxsize=1)
def _astm_g173_etr() -> tuple[np.ndarray, np.ndarray]:
    # colour-science ships the ASTM G-173 extraterrestrial spectrum; its module
    # lives under colour.plotting and needs matplotlib to import.
    from colour.plotting.datasets import SD_ASTMG173_ETR

    return np.asarray(SD_ASTMG173_ETR.wavelengths, float), np.asarray(SD_ASTMG173_ETR.values, float)


def solar_irradiance(wavelengths_nm, bandwidth_nm: float | None = None) -> np.ndarray:
    """Band-averaged ASTM G-173 extraterrestrial irradiance at 1 AU.

    Point samples of a 1 nm solar table carry Fraunhofer-line structure; each
    value is therefore the mean of the table over a box of width
    ``bandwidth_nm`` centred on the wavelength (default: the grid spacing,
    10 nm for a single wavelength).

    Args:
        wavelengths_nm: shape (W,). [nm]
        bandwidth_nm: box width. [nm]

    Returns:
        Spectral irradiance, shape (W,). [W/(m^2 nm)]
    """
    lam = np.atleast_1d(np.asarray(wavelengths_nm, float))
    if bandwidth_nm is None:
        bandwidth_nm = float(np.median(np.diff(np.sort(lam)))) if lam.size > 1 else 10.0
    wl, val = _astm_g173_etr()
    out = np.empty_like(lam)
    for i, centre in enumerate(lam):
        lo, hi = centre - bandwidth_nm / 2, centre + bandwidth_nm / 2
        grid = np.linspace(lo, hi, max(int(np.ceil((hi - lo) / 0.25)) + 1, 3))
        out[i] = np.trapezoid(np.interp(grid, wl, val), grid) / (hi - lo) if hi > lo else np.interp(centre, wl, val)
    return out
