"""``export-lut --layout unreal`` (skyfit.export.unreal, docs/luts.md): SkyAtmosphere parameters and Hillaire's LUTs."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from skyfit.atmosphere import load_atmosphere
from skyfit.export.shader_reference import view_grid
from skyfit.export.unreal import (atmosphere_from_unreal, skyview_directions, transmittance_lut, unreal_parameters,
                                  unreal_render_errors)
from skyfit.io import read_exr
from skyfit.scattering.bruneton_tables import TableSizes
from skyfit.scattering.multiple import Quadrature, precompute

from _cli import minimal_result, run

RGB = [680.0, 550.0, 440.0]


@pytest.fixture(scope="module")
def earth():
    return load_atmosphere("earth", RGB)


def test_earth_gives_unreals_defaults(earth):
    """Unreal's SkyAtmosphere defaults are Bruneton 2017's Earth at 680/550/440 nm (USkyAtmosphereComponent
    constructor: RayleighScatteringScale 0.0331, RayleighScattering (0.175287, 0.409607, 1), 8 km; Mie 0.003996,
    absorption 0.000444, g 0.8, 1.2 km; absorption tent at 25 km, width 15 km; ground 6360 km, 60 km high)."""
    p = unreal_parameters(earth)["SkyAtmosphere"]
    assert p["BottomRadius"] == 6360.0 and p["AtmosphereHeight"] == 60.0
    assert p["RayleighScatteringScale"] == pytest.approx(0.0331, rel=1e-5)
    np.testing.assert_allclose(p["RayleighScattering"], [0.175287, 0.409607, 1.0], atol=2e-5)
    assert p["RayleighExponentialDistribution"] == 8.0 and p["MieExponentialDistribution"] == 1.2
    assert p["MieScatteringScale"] == pytest.approx(0.003996, rel=1e-6) and p["MieScattering"] == [1.0, 1.0, 1.0]
    assert p["MieAbsorptionScale"] == pytest.approx(0.000444, rel=1e-6) and p["MieAnisotropy"] == pytest.approx(0.8)
    assert p["OtherTentDistribution"] == {"TipAltitude": 25.0, "TipValue": 1.0, "Width": 15.0}
    # skyfit's ozone cross sections (Serdyuchenko 233 K) are not 2017's table: the green scale agrees to 6 %
    assert p["OtherAbsorptionScale"] == pytest.approx(0.001881, rel=0.07)
    assert p["GroundAlbedo"] == [89, 89, 89, 255]  # 0.1 linear -> sRGB 0.349 -> 89


def test_round_trip_and_what_cannot_be_held(earth):
    out = unreal_parameters(earth)
    back = atmosphere_from_unreal(out, earth)
    for name in ("rayleigh_scattering", "mie_scattering", "mie_extinction", "ozone_absorption"):
        torch.testing.assert_close(getattr(back, name), getattr(earth, name), rtol=1e-12, atol=1e-18)
    torch.testing.assert_close(back.ground_albedo, earth.ground_albedo, rtol=2e-3, atol=0.0)  # 8-bit sRGB
    assert back.mie_phase == "henyey_greenstein" and back.ozone_layer_m == earth.ozone_layer_m
    notes = " ".join(out["not_represented"])
    assert "cornette_shanks" in notes and "8-bit sRGB" in notes
    odd = earth.replace(ozone_layer_m=(10_000.0, 25_000.0, 45_000.0), mie_g=torch.tensor(-0.2, dtype=torch.float64))
    p = unreal_parameters(odd)
    assert p["SkyAtmosphere"]["OtherTentDistribution"]["Width"] == 17.5 and p["SkyAtmosphere"]["MieAnisotropy"] == 0.0
    assert any("asymmetric" in n for n in p["not_represented"]) and any("clamped" in n for n in p["not_represented"])


def test_transmittance_lut_against_scipy_quad(earth):
    """Texels (row j, column i) at x_mu = (i + 0.5) / 256, x_r = (j + 0.5) / 64; T from scipy quad (independent)."""
    from scipy.integrate import quad

    T = transmittance_lut(earth)
    assert T.shape == (64, 256, 3)
    b, t = earth.bottom_radius, earth.top_radius
    H = math.sqrt(t * t - b * b)
    hr, hm = float(earth.rayleigh_scale_height), float(earth.mie_scale_height)
    lo, peak, hi = earth.ozone_layer_m
    ext = np.stack([earth.rayleigh_scattering.numpy(), earth.mie_extinction.numpy(), earth.ozone_absorption.numpy()])
    for j, i in ((0, 0), (10, 200), (63, 255)):
        x_mu, x_r = (i + 0.5) / 256, (j + 0.5) / 64
        rho = H * x_r
        r = math.sqrt(rho * rho + b * b)
        d_max = (t - r) + x_mu * (rho + H - (t - r))
        mu = (H * H - rho * rho - d_max * d_max) / (2 * r * d_max)
        h = lambda s: math.sqrt(s * s + 2 * r * mu * s + r * r) - b  # noqa: E731
        col = [quad(lambda s: math.exp(-h(s) / hr), 0, d_max, epsrel=1e-12, limit=200)[0],
               quad(lambda s: math.exp(-h(s) / hm), 0, d_max, epsrel=1e-12, limit=200)[0],
               quad(lambda s: max(0.0, min((h(s) - lo) / (peak - lo), (hi - h(s)) / (hi - peak))), 0, d_max,
                    epsrel=1e-12, limit=400)[0]]
        np.testing.assert_allclose(T[j, i], np.exp(-np.asarray(col) @ ext), rtol=1e-3, atol=1e-12)


def test_skyview_mapping_is_hillaires():
    """Texel directions against Hillaire's SkyViewLutParamsToUv written here (non-linear, ground level, sun at azimuth 0)."""
    b = 6_360_000.0
    d = skyview_directions((192, 108), 40.0, 0.0, b)
    assert d.shape == (108, 192, 3)
    np.testing.assert_allclose(d[0, :, 2], 1.0, atol=1e-12)  # first row: the zenith
    np.testing.assert_allclose(d[-1, :, 2], -1.0, atol=1e-12)  # last row: the nadir
    for row, col in ((10, 5), (60, 100), (107, 191)):
        v = d[row, col]
        zen, az = math.acos(v[2]), math.atan2(v[0], v[1])
        beta, zh = math.pi / 2, math.pi / 2  # observer on the ground
        if zen < zh:
            y = 0.5 * (1 - math.sqrt(max(0.0, 1 - zen / zh)))
        else:
            y = 0.5 + 0.5 * math.sqrt((zen - zh) / beta)
        x = math.sqrt(max(0.0, -math.cos(az) * 0.5 + 0.5))
        # fromSubUvsToUnit at the texel centre gives i / (n - 1)
        assert x == pytest.approx(col / 191, abs=1e-9) and y == pytest.approx(row / 107, abs=1e-9)


SIZES = TableSizes(scattering_r=8, scattering_mu=32, scattering_mu_s=8, scattering_nu=4, transmittance_mu=64,
                   transmittance_r=16, irradiance_mu_s=16, irradiance_r=8)
QUAD = Quadrature(density_theta=8, density_phi=16, irradiance_theta=8, irradiance_phi=16, multiple_samples=20)


def test_render_from_the_parameters_against_skyfit(earth):
    """Hillaire's model on the exported parameters vs Bruneton's 4 orders of the atmosphere (small tables), sun 60 deg.

    Measured (docs/luts.md has 16 x 64 x 16 x 8 numbers from scripts/unreal_accuracy.py): median 1.4 %, max 8.0 %
    (unreal); the parameters alone (Bruneton on both) 0.39 % / 9.2 % (the Henyey-Greenstein phase near the sun).
    """
    with torch.no_grad():
        tables = precompute(earth, orders=4, sizes=SIZES, quadrature=QUAD)
    view = torch.as_tensor(view_grid(2.0, 30.0))
    view = view[view[:, 2] > 0.01]
    e = unreal_render_errors(earth, view, 60.0, tables=tables, hillaire_settings={"size": (16, 16)})
    assert float(np.median(e["unreal"])) < 1.5 * 0.0142 and float(e["unreal"].max()) < 1.5 * 0.080
    assert float(np.median(e["mapping"])) < 1.5 * 0.0039 and float(e["mapping"].max()) < 1.5 * 0.092


def test_cli_unreal(tmp_path, capsys):
    out = tmp_path / "ue"
    rc, o, e = run(["export-lut", minimal_result(tmp_path / "RESULT.json"), "--out", out, "--layout", "unreal",
                    "--sun-zenith", "30", "--json"], capsys)
    assert rc == 0, e
    params = json.loads((out / "unreal.json").read_text())
    assert params["SkyAtmosphere"]["MieAnisotropy"] == pytest.approx(0.7)  # the fitted g
    assert params["DirectionalLight"]["illuminance_lux"] > 1e5  # ~130 klx above the atmosphere
    ch, _ = read_exr(out / "skyview_sz030.0.exr")
    assert ch["R"].shape == (108, 192) and np.all(ch["G"] > 0)
    ch, _ = read_exr(out / "multiscattering.exr")
    assert ch["B"].shape == (32, 32)
    meta = json.loads((out / "lut.json").read_text())
    assert "per unit solar irradiance" in meta["units"]["multiscattering"]


def test_cli_unreal_bad_input(tmp_path, capsys):
    res = minimal_result(tmp_path / "RESULT.json")
    for argv, match in (
        (["--layout", "unreal", "--format", "npz"], "--format npz"),
        (["--layout", "unreal", "--precision", "f16"], "--precision applies"),
        (["--sun-zenith", "30"], "--layout unreal"),
        (["--layout", "unreal", "--sun-zenith", "200"], "[0, 180]"),
    ):
        before = sorted(p.name for p in tmp_path.rglob("*"))
        rc, _, err = run(["export-lut", res, "--out", tmp_path / "o", *argv], capsys)
        assert rc == 2 and err.count("\n") == 1 and match in err, err
        assert sorted(p.name for p in tmp_path.rglob("*")) == before
