"""Spectra -> XYZ -> sRGB and CIE 1976 colour difference, against colour-science and closed forms.

CONTRACT.md: CIE 1931 2° CMFs, XYZ with 683 lm/W (Y in cd/m^2 for radiance in
W/(m^2 sr nm)), RGB = linear sRGB of that XYZ.
"""
from __future__ import annotations

import warnings

import colour
import numpy as np
import pytest
import torch

from skyfit.render import delta_e_1976, spectral_to_xyz, spectral_to_xyz_matrix, xyz_to_linear_srgb

CMFS = colour.MSDS_CMFS["CIE 1931 2 Degree Standard Observer"]  # 360-830 nm, 1 nm
FINE = np.arange(360.0, 831.0)
D65_XY = colour.CCS_ILLUMINANTS["CIE 1931 2 Degree Standard Observer"]["D65"]


def _colour_xyz(values: np.ndarray, wavelengths: np.ndarray) -> np.ndarray:
    """colour-science's own integration. With k given and the default illuminant E
    (100 everywhere), sd_to_XYZ_integration returns k * sum(S * cmf) * dλ * 100 / 100."""
    sd = colour.SpectralDistribution(values, wavelengths)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return colour.sd_to_XYZ(sd, cmfs=CMFS, k=683, method="Integration")


def _smooth_spectrum() -> np.ndarray:
    # A 5778 K blackbody scaled to sky-like radiance (~0.1 W/(m^2 sr nm) at 550 nm).
    bb = colour.sd_blackbody(5778, colour.SpectralShape(360, 830, 1)).values
    return 0.1 * bb / np.interp(550.0, FINE, bb)


@pytest.mark.parametrize("dtype, rtol", [(torch.float64, 1e-10), (torch.float32, 5e-6)])  # float32: 471-term sums
def test_1nm_spectrum_equals_colour_integration(dtype, rtol):
    rng = np.random.default_rng(1)
    spectra = np.stack([_smooth_spectrum(), rng.uniform(0.0, 0.2, FINE.size), np.ones(FINE.size)])
    got = spectral_to_xyz(torch.tensor(spectra, dtype=dtype), torch.tensor(FINE, dtype=dtype))
    assert got.dtype == dtype
    want = np.stack([_colour_xyz(s, FINE) for s in spectra])
    torch.testing.assert_close(got.double(), torch.tensor(want), rtol=rtol, atol=0)
    # closed form for the flat spectrum: Y = 683 * sum(ybar) * 1 nm
    assert got[2, 1].item() == pytest.approx(683 * CMFS.values[:, 1].sum(), rel=rtol)


def test_coarse_grid_of_smooth_spectrum_within_half_percent():
    """400:700:20 samples of a blackbody vs the 1 nm integral. The spectrum is
    taken piecewise linear between samples and held constant beyond 400/700 nm;
    for a 5778 K blackbody that costs < 0.1 % (measured: -0.03 %, -0.04 %, -0.08 %
    for X, Y, Z); we allow 0.5 %."""
    full = _smooth_spectrum()
    coarse_lam = np.arange(400.0, 701.0, 20.0)
    coarse = np.interp(coarse_lam, FINE, full)
    got = spectral_to_xyz(torch.tensor(coarse), torch.tensor(coarse_lam)).numpy()
    want = _colour_xyz(full, FINE)
    np.testing.assert_allclose(got, want, rtol=5e-3, atol=0)


def test_piecewise_linear_spectrum_is_integrated_exactly():
    """A spectrum that *is* piecewise linear between 10 nm knots (360-830) gives the same
    XYZ from its knots as colour's integration of its 1 nm resampling."""
    knots = np.arange(360.0, 831.0, 10.0)
    vals = np.random.default_rng(2).uniform(0.0, 1.0, knots.size)
    got = spectral_to_xyz(torch.tensor(vals), torch.tensor(knots)).numpy()
    np.testing.assert_allclose(got, _colour_xyz(np.interp(FINE, knots, vals), FINE), rtol=1e-10)


def test_unsorted_wavelengths_give_the_same_xyz():
    lam = np.array([550.0, 400.0, 700.0, 450.0, 600.0])
    vals = np.array([1.0, 0.3, 0.5, 0.8, 0.9])
    order = np.argsort(lam)
    a = spectral_to_xyz(torch.tensor(vals), torch.tensor(lam))
    b = spectral_to_xyz(torch.tensor(vals[order]), torch.tensor(lam[order]))
    torch.testing.assert_close(a, b, rtol=1e-12, atol=0)


def test_matrix_follows_input_dtype():
    m = spectral_to_xyz_matrix(torch.arange(400.0, 701.0, 50.0, dtype=torch.float32))
    assert m.dtype == torch.float32 and m.shape == (7, 3)


@pytest.mark.parametrize("dtype, atol", [(torch.float64, 1e-12), (torch.float32, 1e-6)])
def test_d65_white_is_neutral_in_srgb(dtype, atol):
    xyz = colour.xy_to_XYZ(D65_XY)  # Y = 1
    rgb = xyz_to_linear_srgb(torch.tensor(xyz, dtype=dtype))
    torch.testing.assert_close(rgb, torch.ones(3, dtype=dtype), rtol=0, atol=atol)


def test_srgb_primaries_from_published_matrix():
    """IEC 61966-2-1 sRGB: the XYZ of the red, green and blue primaries are the columns of
    [[0.4124, 0.3576, 0.1805], [0.2126, 0.7152, 0.0722], [0.0193, 0.1192, 0.9505]] (4 digits)."""
    m = np.array([[0.4124, 0.3576, 0.1805], [0.2126, 0.7152, 0.0722], [0.0193, 0.1192, 0.9505]])
    rgb = xyz_to_linear_srgb(torch.tensor(m.T))  # rows: XYZ of R, G, B
    torch.testing.assert_close(rgb, torch.eye(3, dtype=torch.float64), rtol=0, atol=5e-4)


def _lab(xyz, white):
    """CIE 1976 L*a*b* written out (CIE 15:2004 eq. 8.1-8.3)."""
    eps, kappa = 216 / 24389, 24389 / 27
    t = np.asarray(xyz) / white
    f = np.where(t > eps, np.cbrt(t), (kappa * t + 16) / 116)
    return np.stack([116 * f[..., 1] - 16, 500 * (f[..., 0] - f[..., 1]), 200 * (f[..., 1] - f[..., 2])], -1)


def test_delta_e_identical_images_is_zero():
    xyz = np.random.default_rng(3).uniform(10, 1000, (4, 5, 3))
    np.testing.assert_array_equal(delta_e_1976(xyz, xyz, white_y=1000.0), np.zeros((4, 5)))


def test_delta_e_of_a_known_lab_offset():
    white_y = 2000.0  # e.g. the 99th percentile luminance of the reference [cd/m^2]
    lab_a = np.array([[50.0, 10.0, -20.0], [70.0, -5.0, 30.0], [30.0, 0.0, 0.0]])
    offset = np.array([3.0, -4.0, 12.0])  # |offset| = 13
    wp = colour.xy_to_XYZ(D65_XY)
    xyz_a = colour.Lab_to_XYZ(lab_a, D65_XY) * white_y
    xyz_b = colour.Lab_to_XYZ(lab_a + offset, D65_XY) * white_y
    # the written-out Lab agrees with colour's (so the round trip is not colour against itself only)
    np.testing.assert_allclose(_lab(xyz_a / white_y, wp), lab_a, atol=1e-9)
    np.testing.assert_allclose(delta_e_1976(xyz_a, xyz_b, white_y), np.full(3, 13.0), rtol=1e-9)


def test_delta_e_matches_written_out_cielab():
    rng = np.random.default_rng(4)
    white_y = 500.0
    a, b = rng.uniform(0, 600, (2, 10, 3))
    wp = colour.xy_to_XYZ(D65_XY)
    want = np.linalg.norm(_lab(a / white_y, wp) - _lab(b / white_y, wp), axis=-1)
    np.testing.assert_allclose(delta_e_1976(a, b, white_y), want, rtol=1e-9)
