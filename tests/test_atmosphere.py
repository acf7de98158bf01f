"""Shipped configs yield their documented values; validation refuses what is unphysical.

Expected numbers come from the papers' and reference implementations' own
tables (sources beside each), from closed forms, or from an independent
integration of the ASTM G-173 table.
"""
from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from skyfit.atmosphere import Atmosphere, ConfigError, atmosphere_from_config, load_atmosphere, solar_irradiance

SHARED_DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
CONFIGS = ("earth", "earth_clear_sky_eval", "earth_hazy", "mars")
LAM = np.arange(360.0, 801.0, 10.0)  # inside every shipped table's range
DTYPES = [(torch.float64, 1e-12), (torch.float32, 1e-6)]


def _np(t):
    return t.detach().cpu().double().numpy()


def _close(actual, expected, rtol, atol=0.0):
    torch.testing.assert_close(
        torch.as_tensor(actual, dtype=torch.float64), torch.as_tensor(expected, dtype=torch.float64), rtol=rtol, atol=atol
    )


@pytest.mark.parametrize("name", CONFIGS)
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_shipped_configs_load(name, dtype):
    atm = load_atmosphere(name, LAM, dtype=dtype)
    assert atm.dtype == dtype and atm.wavelengths.shape == (LAM.size,)
    for f in atm.tensor_fields():
        t = getattr(atm, f)
        assert t.dtype == dtype and bool(torch.isfinite(t).all()), f
    # the repository's configs/ and the packaged skyfit/configs/ are the same files
    repo = Path(__file__).resolve().parents[1]
    assert (repo / "configs" / f"{name}.yaml").read_text() == (repo / "skyfit" / "configs" / f"{name}.yaml").read_text()


@pytest.mark.parametrize("dtype, rtol", DTYPES)
def test_earth_bruneton_2017(dtype, rtol):
    lam = np.array([440.0, 550.0, 680.0])
    atm = load_atmosphere("earth", lam, dtype=dtype)
    # Bruneton 2017 demo.cc: kRayleigh = 1.24062e-6 / m * lambda[um]^-4.
    _close(_np(atm.rayleigh_scattering), 1.24062e-6 * (lam / 1000.0) ** -4, rtol)
    # Bruneton & Neyret 2008 Sec. 2.1 publish beta_R = (5.8, 13.5, 33.1) 1e-6 /m for
    # (680, 550, 440) nm: agreement to 3 digits.
    _close(_np(atm.rayleigh_scattering)[::-1].copy(), [5.8e-6, 13.5e-6, 33.1e-6], rtol=5e-3)
    # kMieAngstromBeta 5.328e-3 / kMieScaleHeight 1200 m = 4.44e-6 /m, alpha 0: flat;
    # kMieSingleScatteringAlbedo 0.9.
    _close(_np(atm.mie_extinction), [4.44e-6] * 3, rtol)
    _close(_np(atm.mie_scattering), [0.9 * 4.44e-6] * 3, rtol)
    assert float(atm.mie_g) == pytest.approx(0.8, rel=rtol) and atm.mie_phase == "cornette_shanks"
    assert float(atm.rayleigh_scale_height) == 8000.0 and float(atm.mie_scale_height) == 1200.0
    assert (atm.bottom_radius, atm.top_radius) == (6_360_000.0, 6_420_000.0)
    _close(_np(atm.ground_albedo), [0.1] * 3, rtol)
    assert atm.sun_angular_radius == pytest.approx(0.00935 / 2)


# Bruneton 2017, precomputed_atmospheric_scattering demo.cc, kOzoneCrossSection [m^2]:
# Serdyuchenko et al. 2014 at 233 K, averaged over the 10 nm bins [360, 370), [370, 380) ...
BRUNETON_OZONE = [
    1.18e-27, 2.182e-28, 2.818e-28, 6.636e-28, 1.527e-27, 2.763e-27, 5.52e-27, 8.451e-27, 1.582e-26, 2.316e-26,
    3.669e-26, 4.924e-26, 7.752e-26, 9.016e-26, 1.48e-25, 1.602e-25, 2.139e-25, 2.755e-25, 3.091e-25, 3.5e-25,
    4.266e-25, 4.672e-25, 4.398e-25, 4.701e-25, 5.019e-25, 4.305e-25, 3.74e-25, 3.215e-25, 2.662e-25, 2.238e-25,
    1.852e-25, 1.473e-25, 1.209e-25, 9.423e-26, 7.455e-26, 6.566e-26, 5.105e-26, 4.15e-26, 4.228e-26, 3.237e-26,
    2.451e-26, 2.801e-26, 2.534e-26, 1.624e-26, 1.465e-26, 2.078e-26, 1.383e-26, 7.105e-27,
]


def test_earth_ozone_peak_density():
    # 300 DU * 2.687e20 molecules/m^2/DU spread over the 10-25-40 km tent (integral 15 km).
    peak = 300 * 2.687e20 / 15_000.0
    assert peak == pytest.approx(5.374e18)  # [1/m^3], Bruneton 2017 kMaxOzoneNumberDensity
    centres = 365.0 + 10.0 * np.arange(len(BRUNETON_OZONE))  # bin centres
    atm = load_atmosphere("earth", centres)
    _close(_np(atm.ozone_absorption), peak * np.array(BRUNETON_OZONE), rtol=1e-12)
    assert atm.ozone_layer_m == (10_000.0, 25_000.0, 40_000.0)
    assert load_atmosphere("mars", LAM).ozone_absorption is None


def test_clear_sky_eval_mie_angstrom():
    # Bruneton's clear-sky evaluation (clear-sky-models atmosphere.h): alpha 0.8, beta 0.04,
    # H_M 1200 m, g 0.7: extinction = 0.04 / 1200 m * (lambda / 1 um)^-0.8.
    atm = load_atmosphere("earth_clear_sky_eval", LAM)
    _close(_np(atm.mie_extinction), 0.04 / 1200.0 * (LAM / 1000.0) ** -0.8, rtol=1e-12)
    assert float(atm.mie_g) == pytest.approx(0.7)


# Penndorf 1957 Table III sea-level Rayleigh scattering at 0 °C [1/m], 360-830 nm every 10 nm,
# as transcribed in clear-sky-models atmosphere.cc (kPenndorf), scaled by T0/T = 273.16/288.16
# to 15 °C (Penndorf eq. 12).
PENNDORF_0C = [
    70.45e-6, 62.82e-6, 56.20e-6, 50.43e-6, 45.40e-6, 40.98e-6, 37.08e-6, 33.65e-6, 30.60e-6, 27.89e-6, 25.48e-6,
    23.33e-6, 21.40e-6, 19.66e-6, 18.10e-6, 16.69e-6, 15.42e-6, 14.26e-6, 13.21e-6, 12.26e-6, 11.39e-6, 10.60e-6,
    9.876e-6, 9.212e-6, 8.604e-6, 8.045e-6, 7.531e-6, 7.057e-6, 6.620e-6, 6.217e-6, 5.844e-6, 5.498e-6, 5.178e-6,
    4.881e-6, 4.605e-6, 4.348e-6, 4.109e-6, 3.886e-6, 3.678e-6, 3.484e-6, 3.302e-6, 3.132e-6, 2.973e-6, 2.824e-6,
    2.684e-6, 2.583e-6, 2.481e-6, 2.380e-6,
]
PENNDORF_LAM = 360.0 + 10.0 * np.arange(len(PENNDORF_0C))


def test_clear_sky_eval_penndorf_nodes_and_interpolation():
    ref = np.array(PENNDORF_0C) * 273.16 / 288.16
    at_nodes = load_atmosphere("earth_clear_sky_eval", PENNDORF_LAM[:45])  # grass albedo ends at 800 nm
    _close(_np(at_nodes.rayleigh_scattering), ref[:45], rtol=1e-12)
    mid = PENNDORF_LAM[:44] + 2.5  # a quarter of the way between nodes: linear interpolation
    between = load_atmosphere("earth_clear_sky_eval", mid)
    _close(_np(between.rayleigh_scattering), 0.75 * ref[:44] + 0.25 * ref[1:45], rtol=1e-12)


def test_penndorf_agrees_with_bodhaine_1999():
    """Independent physics: Bodhaine et al. 1999 (J. Atmos. Oceanic Technol. 16, 1854) eq. 29
    cross-section of air times the number density at 15 °C, 1013.25 hPa. Penndorf's older
    refractive index sits 0.8-1.3 % higher over 360-800 nm."""
    lam_um = PENNDORF_LAM[:45] / 1000.0
    sigma_cm2 = (1.0455996 - 341.29061 * lam_um**-2 - 0.90230850 * lam_um**2) / (
        1 + 0.0027059889 * lam_um**-2 - 85.968563 * lam_um**2) * 1e-28
    n = 101325.0 / (1.380649e-23 * 288.15)  # [1/m^3]
    beta = n * sigma_cm2 * 1e-4  # [1/m]
    atm = load_atmosphere("earth_clear_sky_eval", PENNDORF_LAM[:45])
    _close(_np(atm.rayleigh_scattering), beta, rtol=0.015)


def test_hazy_and_mars_documented_values():
    hazy = load_atmosphere("earth_hazy", LAM)
    _close(_np(hazy.mie_extinction), 0.2 / 2000.0 * (LAM / 1000.0) ** -1.3, rtol=1e-12)
    _close(_np(hazy.mie_scattering), 0.85 * 0.2 / 2000.0 * (LAM / 1000.0) ** -1.3, rtol=1e-12)
    mars = load_atmosphere("mars", LAM)
    # CO2 at the surface: n = 610 Pa / (k 210 K), sigma(550 nm) = 1.2e-30 m^2 (Sneep & Ubachs 2005).
    beta_550 = 610.0 / (1.380649e-23 * 210.0) * 1.2e-30
    i550 = int(np.argmin(abs(LAM - 550)))
    assert float(mars.rayleigh_scattering[i550]) == pytest.approx(beta_550, rel=0.01)
    _close(_np(mars.mie_extinction), [0.5 / 11_000.0] * LAM.size, rtol=1e-12)
    assert mars.mie_phase == "henyey_greenstein" and mars.bottom_radius == 3_389_500.0
    # irradiance falls as 1 / d^2 with d = 1.524 AU
    _close(_np(mars.solar_irradiance), solar_irradiance(LAM) / 1.524**2, rtol=1e-12)


# -- ASTM G-173 band averages ---------------------------------------------------
def _etr_colour():
    from colour.plotting.datasets import SD_ASTMG173_ETR

    return np.asarray(SD_ASTMG173_ETR.wavelengths, float), np.asarray(SD_ASTMG173_ETR.values, float)


def _box_mean_on_nodes(wl, val, lo, hi):
    """Mean over [lo, hi] when both ends are table nodes: plain trapezoid of the table's own rows."""
    m = (wl >= lo - 1e-9) & (wl <= hi + 1e-9)
    assert abs(wl[m][0] - lo) < 1e-9 and abs(wl[m][-1] - hi) < 1e-9
    x, y = wl[m], val[m]
    return float(np.sum((y[1:] + y[:-1]) / 2 * np.diff(x)) / (hi - lo))


def test_solar_band_averages_vs_direct_trapezoid():
    lam = np.arange(400.0, 701.0, 20.0)  # default box: the spacing capped at 10 nm -> [395, 405], ...
    wl, val = _etr_colour()
    want = [_box_mean_on_nodes(wl, val, c - 5, c + 5) for c in lam]
    _close(solar_irradiance(lam), want, rtol=1e-12)
    want20 = [_box_mean_on_nodes(wl, val, c - 10, c + 10) for c in lam]
    _close(solar_irradiance(lam, 20.0), want20, rtol=1e-12)
    # boxes off the nodes: adaptive quadrature of the linearly interpolated table
    from scipy.integrate import quad

    for centre, width in ((412.3, 7.3), (361.1, 2.2), (550.0, 0.3)):
        lo, hi = centre - width / 2, centre + width / 2
        inner = wl[(wl > lo) & (wl < hi)]
        q = quad(lambda x: np.interp(x, wl, val), lo, hi, points=inner if inner.size else None, limit=500,
                 epsabs=0, epsrel=1e-12)[0]
        assert solar_irradiance([centre], width)[0] == pytest.approx(q / width, rel=1e-9)


def test_solar_band_averages_vs_shared_astm_file():
    path = SHARED_DATA / "astm-g173.txt"
    if not path.is_file():
        pytest.skip(f"shared data absent: {path} (a fresh clone has no ../shared)")
    table = np.loadtxt(path)
    wl, val = table[:, 0], table[:, 1]  # column 2: extraterrestrial [W/(m^2 nm)]
    lam = np.arange(360.0, 831.0, 10.0)
    want = [_box_mean_on_nodes(wl, val, c - 5, c + 5) for c in lam]
    _close(solar_irradiance(lam), want, rtol=1e-9)


def test_solar_single_wavelength_and_range():
    wl, val = _etr_colour()
    assert solar_irradiance([550.0])[0] == pytest.approx(_box_mean_on_nodes(wl, val, 545, 555), rel=1e-12)
    with pytest.raises(ValueError, match="ASTM G-173 covers"):
        solar_irradiance([250.0, 550.0])
    with pytest.raises(ValueError, match="band width"):
        solar_irradiance([550.0], 0.0)


# -- validation -------------------------------------------------------------------
def _valid_kwargs(dtype=torch.float64):
    lam = torch.tensor([440.0, 550.0, 680.0], dtype=dtype)
    T = lambda v: torch.tensor(v, dtype=dtype)  # noqa: E731
    return dict(
        wavelengths=lam, bottom_radius=6.36e6, top_radius=6.42e6,
        rayleigh_scattering=T([3.3e-5, 1.35e-5, 5.8e-6]), rayleigh_scale_height=T(8000.0),
        mie_scattering=T([4e-6] * 3), mie_extinction=T([4.44e-6] * 3), mie_scale_height=T(1200.0),
        mie_g=T(0.8), ground_albedo=T([0.1] * 3), solar_irradiance=T([1.9, 1.85, 1.5]),
        ozone_absorption=T([1e-7, 1.9e-6, 8e-7]),
    )


def test_valid_kwargs_are_valid():
    Atmosphere(**_valid_kwargs())


@pytest.mark.parametrize(
    "change, match",
    [
        (dict(mie_g=torch.tensor(1.0, dtype=torch.float64)), "mie_g"),
        (dict(mie_g=torch.tensor(-1.0, dtype=torch.float64)), "mie_g"),
        (dict(mie_g=torch.tensor(1.5, dtype=torch.float64)), "mie_g"),
        (dict(mie_g=torch.tensor(float("nan"), dtype=torch.float64)), "mie_g"),
        (dict(rayleigh_scale_height=torch.tensor(0.0, dtype=torch.float64)), "rayleigh_scale_height"),
        (dict(mie_scale_height=torch.tensor(-1200.0, dtype=torch.float64)), "mie_scale_height"),
        (dict(rayleigh_scattering=torch.tensor([3.3e-5, -1e-6, 5.8e-6], dtype=torch.float64)), "rayleigh_scattering must be >= 0"),
        (dict(mie_extinction=torch.tensor([-1.0] * 3, dtype=torch.float64)), "mie_extinction must be >= 0"),
        (dict(mie_scattering=torch.tensor([5e-6] * 3, dtype=torch.float64)), "mie_scattering must not exceed mie_extinction"),
        (dict(top_radius=6.36e6), "top_radius"),
        (dict(top_radius=6.0e6), "top_radius"),
        (dict(bottom_radius=0.0, top_radius=1.0), "bottom_radius"),
        (dict(rayleigh_scattering=torch.tensor([3.3e-5, 1.35e-5], dtype=torch.float64)), "rayleigh_scattering must have shape"),
        (dict(ground_albedo=torch.ones(3, 1, dtype=torch.float64) * 0.1), "ground_albedo must have shape"),
        (dict(mie_g=torch.tensor([0.8, 0.8], dtype=torch.float64)), "mie_g must be a scalar"),
        (dict(wavelengths=torch.ones(3, 1, dtype=torch.float64)), "wavelengths must be a 1-D"),
        (dict(ground_albedo=torch.tensor([0.1, 1.2, 0.1], dtype=torch.float64)), "ground_albedo"),
        (dict(solar_irradiance=torch.tensor([1.0, float("inf"), 1.0], dtype=torch.float64)), "solar_irradiance must be finite"),
        (dict(ozone_absorption=torch.tensor([1e-7, -1e-7, 1e-7], dtype=torch.float64)), "ozone_absorption"),
        (dict(ozone_layer_m=(25_000.0, 10_000.0, 40_000.0)), "ozone_layer_m"),
        (dict(mie_phase="rayleigh"), "mie_phase"),
        (dict(rayleigh_scattering=[3.3e-5, 1.35e-5, 5.8e-6]), "must be a torch.Tensor"),
    ],
)
def test_validation_refuses(change, match):
    kw = _valid_kwargs()
    kw.update(change)
    with pytest.raises(ValueError, match=match):
        Atmosphere(**kw)


def test_replace_validates():
    atm = Atmosphere(**_valid_kwargs())
    with pytest.raises(ValueError, match="mie_g"):
        atm.replace(mie_g=torch.tensor(1.2, dtype=torch.float64))


@pytest.mark.parametrize("name", CONFIGS)
def test_to_float32_keeps_values(name):
    a64 = load_atmosphere(name, LAM, dtype=torch.float64)
    a32 = a64.to(torch.float32)
    for f in dataclasses.fields(a64):
        v64, v32 = getattr(a64, f.name), getattr(a32, f.name)
        if isinstance(v64, torch.Tensor):
            assert v32.dtype == torch.float32, f.name
            torch.testing.assert_close(v32.double(), v64, rtol=1e-6, atol=0)
        else:
            assert v32 == v64, f.name
    back = a32.to(torch.float64)
    assert back.dtype == torch.float64


# -- config errors ------------------------------------------------------------------
@pytest.mark.parametrize(
    "cfg, match",
    [
        ({"mie": {"g": 1.5}}, "mie_g"),
        ({"rayleigh": {"scale_height_m": -8000}}, "rayleigh.scale_height_m must be > 0"),
        ({"mie": {"scale_height_m": 0}}, "mie.scale_height_m must be > 0"),
        ({"mie": {"angstrom_beta": -0.1}}, "mie.angstrom_beta must be >= 0"),
        ({"mie": {"extinction_550": -1e-5}}, "mie.extinction_550 must be >= 0"),
        ({"rayleigh": {"coefficient": -1e-6}}, "rayleigh.coefficient must be >= 0"),
        ({"mie": {"single_scattering_albedo": 1.2}}, "single_scattering_albedo"),
        ({"planet": {"bottom_radius_m": 6.42e6, "top_radius_m": 6.36e6}}, "top_radius"),
        ({"atmosfere": {}}, "unknown config section"),
        ({"mie": {"gg": 0.7}}, "unknown key"),
        ({"planet": 5}, "must be a mapping"),
        ({"mie": {"g": "high"}}, "mie.g must be a number"),
        ({"ozone": {"layer_m": [1, 2]}}, "ozone.layer_m"),
        ({"rayleigh": {"table": "nope"}}, "unknown spectral table"),
        ({"sun": {"distance_au": 0}}, "distance_au"),
        ({"sun": {"bandwidth_nm": -5}}, "bandwidth_nm"),
    ],
)
def test_config_errors(cfg, match):
    with pytest.raises(ConfigError, match=match):
        atmosphere_from_config(cfg, LAM)


def test_tables_refuse_wavelengths_they_do_not_cover():
    # Penndorf covers 360-830 nm (+- half a step): 900 nm would otherwise be held at 830's value.
    with pytest.raises(ConfigError, match="penndorf_rayleigh_sea_level_15C.*900"):
        atmosphere_from_config({"rayleigh": {"table": "penndorf_rayleigh_sea_level_15C"}}, [550.0, 900.0])
    ok = {"rayleigh": {"table": "penndorf_rayleigh_sea_level_15C"}, "sun": {"bandwidth_nm": 10.0}}
    atm = atmosphere_from_config(ok, [355.0, 835.0])  # half a step beyond the ends: end values held
    _close(_np(atm.rayleigh_scattering), np.array([PENNDORF_0C[0], PENNDORF_0C[-1]]) * 273.16 / 288.16, rtol=1e-12)


def test_load_atmosphere_names_the_file(tmp_path):
    p = tmp_path / "bad.yaml"
    p.write_text("mie: {g: 1.5}\n")
    with pytest.raises(ConfigError, match="bad.yaml.*mie_g"):
        load_atmosphere(p, LAM)
    with pytest.raises(ConfigError, match="not found"):
        load_atmosphere(tmp_path / "missing.yaml", LAM)
    p.write_text("mie: {g: [0.7\n")
    with pytest.raises(ConfigError, match="bad YAML in .*bad.yaml"):
        load_atmosphere(p, LAM)


def test_defaults_are_bruneton_earth():
    """An empty config is Bruneton 2017's Earth (constants.py) without ozone."""
    a = atmosphere_from_config({}, [550.0])
    b = load_atmosphere("earth", [550.0])
    for f in ("rayleigh_scattering", "mie_extinction", "mie_scattering", "mie_g", "ground_albedo", "solar_irradiance"):
        torch.testing.assert_close(getattr(a, f), getattr(b, f), rtol=1e-12, atol=0)
    assert a.ozone_absorption is None and math.isclose(a.top_radius, b.top_radius)


def test_a_fit_config_also_builds_an_atmosphere():
    """The shipped kider config carries a ``fit`` section (skyfit.fit reads it): the atmosphere ignores it,
    so ``skyfit render kider`` works, and the result equals the config without that section."""
    import copy

    from skyfit.atmosphere import load_yaml
    from skyfit.atmosphere.config import SHIPPED_CONFIGS

    cfg = load_yaml(str(SHIPPED_CONFIGS / "kider.yaml"))
    assert "fit" in cfg
    bare = {k: v for k, v in copy.deepcopy(cfg).items() if k not in ("fit", "sample")}
    a, b = atmosphere_from_config(cfg, [450.0, 550.0]), atmosphere_from_config(bare, [450.0, 550.0])
    assert torch.equal(a.mie_scattering, b.mie_scattering) and torch.equal(a.rayleigh_scattering, b.rayleigh_scattering)
