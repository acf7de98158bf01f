"""Spectra to CIE XYZ, linear sRGB and luminance (CONTRACT.md: CIE 1931 2°, 683 lm/W).

The colour-matching functions and the sRGB matrix come from colour-science.
What it does not do is integrate a *sparsely sampled* spectrum: we take the
spectrum as piecewise linear between the rendered wavelengths (constant
beyond the ends) and integrate that against the 1 nm CMFs exactly, which
reduces to a (W, 3) matrix computed once per wavelength grid.
"""
from __future__ import annotations

import functools

import numpy as np
import torch
from torch import Tensor

from ..atmosphere.constants import LUMINOUS_EFFICACY_LM_PER_W


@functools.lru_cache(maxsize=1)
def _cmfs() -> tuple[np.ndarray, np.ndarray]:
    import colour

    c = colour.MSDS_CMFS["CIE 1931 2 Degree Standard Observer"]
    return np.asarray(c.wavelengths, float), np.asarray(c.values, float)


@functools.lru_cache(maxsize=64)
def _xyz_matrix(wavelengths: tuple[float, ...]) -> np.ndarray:
    wl, cmf = _cmfs()
    lam = np.asarray(wavelengths, float)
    if lam.size == 1:
        basis = np.ones((1, wl.size))
    else:
        order = np.argsort(lam)
        basis = np.zeros((lam.size, wl.size))
        for k, i in enumerate(order):
            e = np.zeros(lam.size)
            e[k] = 1.0
            basis[i] = np.interp(wl, lam[order], e)  # hat function of sample i
    dl = np.gradient(wl)  # 1 nm table: trapezoid-like weights
    return LUMINOUS_EFFICACY_LM_PER_W * (basis * dl) @ cmf  # (W, 3)


def spectral_to_xyz_matrix(wavelengths_nm: Tensor) -> Tensor:
    """Matrix M with XYZ = L @ M for spectral radiance L on ``wavelengths_nm``.

    Args:
        wavelengths_nm: shape (W,). [nm]

    Returns:
        shape (W, 3), on the input's dtype and device; Y in cd/m^2 for L in W/(m^2 sr nm).
    """
    m = _xyz_matrix(tuple(float(v) for v in wavelengths_nm.detach().cpu().tolist()))
    return torch.as_tensor(m, dtype=wavelengths_nm.dtype, device=wavelengths_nm.device)


def spectral_to_xyz(radiance: Tensor, wavelengths_nm: Tensor) -> Tensor:
    """CIE XYZ of spectral radiance, shape (..., W) -> (..., 3). [cd/m^2 for Y]"""
    return radiance @ spectral_to_xyz_matrix(wavelengths_nm).to(radiance.dtype)


@functools.lru_cache(maxsize=1)
def xyz_to_srgb_matrix() -> np.ndarray:
    """XYZ -> linear sRGB, derived from the sRGB primaries and D65 (IEC 61966-2-1).

    colour's ``matrix_XYZ_to_RGB`` is the standard's 4-digit rounding, which maps
    D65 white to R, G, B unequal by 1.6e-4; the derived matrix keeps neutrals neutral.
    """
    import colour

    cs = colour.models.RGB_COLOURSPACE_sRGB
    return np.linalg.inv(colour.normalised_primary_matrix(cs.primaries, cs.whitepoint))


@functools.lru_cache(maxsize=1)
def srgb_luminance_weights() -> np.ndarray:
    """Linear sRGB -> luminance Y: the Y row of :func:`xyz_to_srgb_matrix`'s inverse, shape (3,) (0.2126, 0.7152,
    0.0722 to the standard's 4 digits)."""
    return np.linalg.inv(xyz_to_srgb_matrix())[1]


def xyz_to_linear_srgb(xyz: Tensor) -> Tensor:
    """Linear sRGB (D65) from XYZ, shape (..., 3)."""
    m = torch.as_tensor(xyz_to_srgb_matrix(), dtype=xyz.dtype, device=xyz.device)
    return xyz @ m.T


def luminance(xyz: Tensor) -> Tensor:
    """Luminance Y [cd/m^2] from XYZ (..., 3)."""
    return xyz[..., 1]


def delta_e_1976(xyz_a: np.ndarray, xyz_b: np.ndarray, white_y: float) -> np.ndarray:
    """CIE 1976 colour difference (Gałaj 2021 eq. 18) of two XYZ images.

    Both are scaled by ``1 / white_y`` (e.g. the reference image's 99th
    percentile luminance) and converted to CIELAB with the D65 white point.
    """
    import colour

    wp = colour.CCS_ILLUMINANTS["CIE 1931 2 Degree Standard Observer"]["D65"]
    lab_a = colour.XYZ_to_Lab(np.asarray(xyz_a) / white_y, wp)
    lab_b = colour.XYZ_to_Lab(np.asarray(xyz_b) / white_y, wp)
    return colour.delta_E(lab_a, lab_b, method="CIE 1976")


def tonemap_srgb8(rgb: np.ndarray, exposure: float | None = None) -> np.ndarray:
    """8-bit display image: ``1 - exp(-k L)`` tone map (Gałaj 2021 Fig. 7) then the sRGB curve."""
    import colour

    rgb = np.clip(np.nan_to_num(np.asarray(rgb, float)), 0.0, None)
    if exposure is None:
        y = rgb.mean(-1)
        ref = np.percentile(y[y > 0], 90) if np.any(y > 0) else 1.0
        exposure = 1.0 / max(ref, 1e-12)
    mapped = 1.0 - np.exp(-exposure * rgb)
    return (np.clip(colour.cctf_encoding(mapped, function="sRGB"), 0, 1) * 255 + 0.5).astype(np.uint8)
