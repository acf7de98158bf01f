"""Extraterrestrial solar spectral irradiance (ASTM G-173)."""
from __future__ import annotations

import functools

import numpy as np

_trapezoid = getattr(np, "trapezoid", None) or np.trapz  # numpy < 2 (pyproject admits 1.26) lacks trapezoid


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
    ``bandwidth_nm`` centred on the wavelength (default: the grid spacing, at most 10 nm;
    10 nm for a single wavelength).

    Args:
        wavelengths_nm: shape (W,). [nm]
        bandwidth_nm: box width. [nm]

    Returns:
        Spectral irradiance, shape (W,). [W/(m^2 nm)]
    """
    lam = np.atleast_1d(np.asarray(wavelengths_nm, float))
    if bandwidth_nm is None:
        # At most 10 nm: enough to smooth the Fraunhofer lines (data README), and a
        # sparse list such as 440,550,680 must not average the sun over 120 nm.
        bandwidth_nm = min(float(np.median(np.diff(np.sort(lam)))), 10.0) if lam.size > 1 else 10.0
    if not bandwidth_nm > 0:
        raise ValueError(f"solar band width must be > 0 nm, got {bandwidth_nm}")
    wl, val = _astm_g173_etr()
    outside = lam[(lam - bandwidth_nm / 2 < wl[0]) | (lam + bandwidth_nm / 2 > wl[-1])]
    if outside.size:
        raise ValueError(
            f"ASTM G-173 covers {wl[0]:g}-{wl[-1]:g} nm; the {bandwidth_nm:g} nm band(s) at {outside.tolist()} nm reach outside it"
        )
    out = np.empty_like(lam)
    for i, centre in enumerate(lam):
        lo, hi = centre - bandwidth_nm / 2, centre + bandwidth_nm / 2
        # The table's own nodes plus the box ends: exact for the piecewise-linear table.
        grid = np.concatenate(([lo], wl[(wl > lo) & (wl < hi)], [hi]))
        out[i] = _trapezoid(np.interp(grid, wl, val), grid) / (hi - lo)
    return out
