"""The Python API (skyfit.api): observations from arrays, fit from an Atmosphere or a config, the result round trip.

Expected values come from the library's lower layers called directly (render_vectors, the EXR
loader's masks) or from the truth a synthetic sky was rendered with.
"""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

import skyfit
from skyfit.export import load_luts
from skyfit.fit.data import DataError
from skyfit.render.sky import render_vectors
from skyfit.transmittance import make_integrator

LAM = "450,550,650"
SUN = (45.0, 120.0)


@pytest.fixture(scope="module")
def scene():
    atm = skyfit.load_atmosphere("earth", LAM)
    cam = skyfit.FisheyeCamera(16)
    return atm, cam, skyfit.render(atm, cam, sun=SUN)


def test_render_along_directions_is_render_vectors(scene):
    atm = scene[0]
    views = torch.tensor([[0.0, 0.0, 1.0], [0.6, 0.0, 0.8], [0.0, -0.8, 0.6]], dtype=torch.float64)
    sky = skyfit.render(atm, views, sun=SUN)
    sun = skyfit.sun_vector(SUN)
    # the accurate default is skyfit render's (RENDER_DEFAULTS: gauss:samples=16, 24 geometrically spaced Gauss nodes)
    ref = render_vectors(atm, views, sun, make_integrator("gauss", samples=16), view_samples=24, rule="gauss",
                         spacing="geometric")
    torch.testing.assert_close(sky.radiance, ref, rtol=0, atol=0)
    assert sky.valid.all() and sky.rgb.shape == (3, 3)


def test_sun_vector_from_angles_and_errors():
    v = skyfit.sun_vector((90.0, 90.0))  # on the horizon, due East
    torch.testing.assert_close(v, torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64), rtol=0, atol=1e-15)
    with pytest.raises(ValueError, match="sun="):
        skyfit.sun_vector(None)
    with pytest.raises(ValueError, match="not both"):
        skyfit.sun_vector(SUN, time="2013-05-27T12:00:00-04:00", location="42.4,-76.5")


def test_observation_from_arrays_uses_the_cameras_sky_and_the_masks(scene):
    atm, cam, sky = scene
    obs = skyfit.Observation.from_arrays(sky.radiance, cam, sun=SUN, wavelengths=atm.wavelengths, sun_disc_deg=10)
    vec, valid = cam.pixel_vectors()
    vec = vec[valid]
    sun = skyfit.sun_vector(SUN)
    expected = int(((vec @ sun) < math.cos(math.radians(10))).sum())  # field of view minus the 10° sun disc
    assert obs.n_samples == expected and obs.kind == "spectral" and obs.channels == ("L450", "L550", "L650")
    mask = np.zeros(cam.shape, bool)
    mask[:8] = True  # keep the upper half of the image only
    half = skyfit.Observation.from_arrays(sky.radiance, cam, sun=SUN, wavelengths=atm.wavelengths, mask=mask)
    assert 0 < half.n_samples < obs.n_samples
    rgb = skyfit.Observation.from_arrays(sky.rgb, cam, sun=SUN)
    assert rgb.kind == "rgb" and rgb.channels == ("R", "G", "B")


@pytest.mark.parametrize("kwargs, match", [
    ({"sun": (95.0, 0.0)}, "below the horizon"),
    ({"sun": None}, "give the sun"),
    ({"sun": SUN, "wavelengths": [450.0, 550.0]}, "2 wavelengths for 3 channels"),
    ({"sun": SUN, "mask": np.zeros((16, 16), bool)}, "no usable value"),
])
def test_observation_from_arrays_refuses_bad_input(scene, kwargs, match):
    _, cam, sky = scene
    with pytest.raises(DataError, match=match):
        skyfit.Observation.from_arrays(sky.radiance, cam, **kwargs)


def test_observation_from_arrays_refuses_shapes_that_do_not_fit(scene):
    _, cam, sky = scene
    with pytest.raises(DataError, match="does not fit the camera"):
        skyfit.Observation.from_arrays(sky.radiance[:8], cam, sun=SUN)
    with pytest.raises(DataError, match="do not fit radiance"):
        skyfit.Observation.from_arrays(torch.ones(4, 3), torch.ones(5, 3), sun=SUN)


def test_fit_from_an_atmosphere_equals_fit_from_its_config_and_round_trips(scene, tmp_path):
    atm, cam, sky = scene
    obs = skyfit.Observation.from_arrays(sky.radiance, cam, sun=SUN, wavelengths=atm.wavelengths)
    kw = dict(free=["mie_g", "exposure"], starts=1)
    a = skyfit.fit(obs, atm, **kw)
    b = skyfit.fit(obs, "earth", **kw)
    assert a.parameters == b.parameters
    assert abs(a.parameters["mie_g"] - float(atm.mie_g.mean())) < 5e-3  # the truth, up to the fit renderer's error
    # an Atmosphere that no longer equals its config is refused (its result could not be rebuilt)
    with pytest.raises(ValueError, match="mie_g"):
        skyfit.fit(obs, atm.replace(mie_g=atm.mie_g * 0.5), **kw)
    path = a.save(tmp_path / "r.json")
    again = skyfit.load_result(path)
    assert again.parameters == a.parameters and again.metrics == a.metrics
    torch.testing.assert_close(again.render(cam, sun=SUN).radiance, a.render(cam, sun=SUN).radiance, rtol=0, atol=0)
    with pytest.raises(ValueError, match="no observations"):
        again.predict()
    assert len(a.predict()) == 1


def test_fit_result_carries_the_corrected_estimate(scene):
    """FitResult.corrected is the budget's estimate at the reference's optimum: the fitted values plus the numerical
    shift, its sigma the total's without the shift (never wider); the earth config's Cornette-Shanks phase has no
    phase term, and the budget says why."""
    atm, cam, sky = scene
    obs = skyfit.Observation.from_arrays(sky.radiance, cam, sun=SUN, wavelengths=atm.wavelengths)
    fit = skyfit.fit(obs, "earth", free=["mie_beta_550", "mie_g", "exposure"], starts=1, laplace=True)
    cor, budget = fit.corrected, fit.result["laplace"]["budget"]
    assert set(cor["values"]) == set(fit.free)
    for n in fit.free:
        assert cor["values"][n] == pytest.approx(fit.parameters[n] + budget["numerical_shift"][n], rel=1e-9, abs=1e-15)
        assert cor["sigma"][n] <= fit.sigma[n] * (1 + 1e-12)
    assert "cornette_shanks" in budget["phase_note"]
    assert skyfit.fit(obs, "earth", free=["exposure"], starts=1).corrected is None  # no laplace, no estimate


def test_fit_refuses_an_unknown_setting(scene):
    atm, cam, sky = scene
    obs = skyfit.Observation.from_arrays(sky.radiance, cam, sun=SUN, wavelengths=atm.wavelengths)
    with pytest.raises(ValueError, match="unknown key.*max_iterations"):
        skyfit.fit(obs, "earth", max_iterations=3)


def test_export_luts_in_memory_equals_the_written_files(scene, tmp_path):
    atm = scene[0]
    tables = skyfit.export_luts(atm, tmp_path / "luts", orders=2, table_sizes=(4, 8, 4, 4), format="npz")
    back = load_luts(tmp_path / "luts")
    torch.testing.assert_close(back.single_rayleigh, tables.single_rayleigh.double(), rtol=1e-6, atol=0)
    torch.testing.assert_close(back.multiple, tables.multiple.double(), rtol=1e-6, atol=0)
