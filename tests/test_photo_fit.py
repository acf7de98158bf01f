"""The photo fit's own pieces: the camera's response in the fit, censoring, blocks, the fitted camera."""
from __future__ import annotations


import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

import skyfit
from skyfit.camera import FisheyeCamera
from skyfit.fit.data import Observation
from skyfit.fit.photo import fitted_camera, scaled_camera


def test_fitted_camera_sees_what_the_fit_sees():
    """fitted_camera(cam, offset, tilt_n, tilt_e) maps pixels to A(-offset) T (cam's directions), with T built by scipy."""
    rng = np.random.default_rng(1)
    worst = 0.0
    for k in range(12):
        cam = FisheyeCamera(200, projection=("equidistant", "equisolid", "stereographic", "orthographic")[k % 4],
                            cx=98.3, cy=101.2, radius=90.0, up_azimuth_deg=float(rng.uniform(0, 360)),
                            tilt_deg=list(rng.uniform(-3, 3, 2)))
        d, tn, te = rng.uniform(-0.5, 0.5), rng.uniform(-0.05, 0.05), rng.uniform(-0.05, 0.05)
        f = fitted_camera(cam, d, tn, te)
        x, y = torch.tensor(rng.uniform(40, 160, 50)), torch.tensor(rng.uniform(40, 160, 50))
        v0 = cam.pixel_to_direction(x, y).numpy()
        T = Rotation.from_rotvec([0, te, 0]).as_matrix() @ Rotation.from_rotvec([-tn, 0, 0]).as_matrix()
        v1 = v0 @ T.T
        az, zen = np.arctan2(v1[:, 0], v1[:, 1]) - d, np.arccos(np.clip(v1[:, 2], -1, 1))
        v2 = np.stack([np.sin(zen) * np.sin(az), np.sin(zen) * np.cos(az), np.cos(zen)], -1)
        vf = f.pixel_to_direction(x, y).numpy()
        worst = max(worst, float(np.degrees(np.arccos(np.clip((vf * v2).sum(-1), -1, 1))).max()))
    assert worst < 1e-4


def test_block_camera_looks_where_the_block_centre_does():
    cam = FisheyeCamera((240, 300), projection="equisolid", cx=151.7, cy=118.2, radius=104.0, up_azimuth_deg=33.0,
                        tilt_deg=(1.0, -0.5))
    step = 6
    small = scaled_camera(cam, step, (240 // step, 300 // step))
    i, j = torch.tensor([12.0, 20.0, 33.0]), torch.tensor([20.0, 25.0, 30.0])
    a = small.pixel_to_direction(j, i)
    b = cam.pixel_to_direction(j * step + (step - 1) / 2, i * step + (step - 1) / 2)
    assert bool(torch.isfinite(a).all()) and torch.allclose(a, b, atol=1e-12)


def _rgb_sky(size=48, sun=(55.0, 120.0)):
    cam = FisheyeCamera(size, projection="equidistant")
    atm = skyfit.load_atmosphere("earth")
    sky = skyfit.render(atm, cam, sun=sun, accuracy="de=1")
    return cam, np.nan_to_num(sky.rgb.numpy())


def test_gains_and_vignetting_are_recovered():
    """An image with white balance gains (1.25, 0.8) and 1 - 0.22 r^2 vignetting: the fit finds them (atmosphere fixed)."""
    cam, rgb = _rgb_sky()
    xx, yy = np.meshgrid(np.arange(48.0), np.arange(48.0))
    r = np.hypot(xx - float(cam.cx), yy - float(cam.cy)) / float(cam.r90)
    photo = 3.0 * rgb * np.array([1.25, 1.0, 0.8]) * (1 - 0.22 * r**2)[..., None]
    obs = Observation.from_arrays(photo, cam, sun=(55.0, 120.0), min_elevation_deg=5.0)
    assert obs.image_radius is not None and float(obs.image_radius.max()) <= 1.0 + 1e-9
    res = skyfit.fit(obs, "earth", free=["exposure", "gain_red", "gain_blue", "vignetting"], starts=1)
    p = res.parameters
    assert p["gain_red"] == pytest.approx(1.25, rel=2e-3)
    assert p["gain_blue"] == pytest.approx(0.8, rel=2e-3)
    assert p["vignetting"] == pytest.approx(-0.22, abs=3e-3)
    assert p["exposure"] == pytest.approx(3.0, rel=3e-3)


def test_a_satisfied_bound_costs_nothing_and_a_violated_one_pulls():
    cam, rgb = _rgb_sky(32)
    obs = Observation.from_arrays(rgb, cam, sun=(55.0, 120.0), min_elevation_deg=5.0)
    prep = skyfit.fit.problem.prepare([obs], skyfit.atmosphere.read_config("earth")[0],
                                      skyfit.fit.problem.fit_settings({}, {"free": ["exposure"]}))
    problem = prep.fit_problem()
    x = problem.param.initial_vector()
    with torch.no_grad():
        own = problem.predict(x)[0]
    o = problem.observations[0] = Observation(**{**problem.observations[0].__dict__, "values": own})
    assert float(problem.objective(x)) == pytest.approx(0.0, abs=1e-15)  # the data are the model
    n = o.values.shape[0]
    cens = torch.zeros((n, 3), dtype=torch.int8)
    cens[:5] = 1  # saturated: the values are lower bounds
    lowered = o.values.clone()
    lowered[:5] *= 0.5  # the bound lies below the model: satisfied
    problem.observations[0] = Observation(**{**o.__dict__, "values": lowered, "censored": cens})
    assert float(problem.objective(x)) * problem.n_elements == pytest.approx(0.0, abs=1e-12)
    raised = o.values.clone()
    raised[:5] *= 1.5  # the bound lies above the model: violated, the loss grows and pulls the exposure up
    problem.observations[0] = Observation(**{**o.__dict__, "values": raised, "censored": cens})
    xg = x.clone().requires_grad_(True)
    loss = problem.objective(xg)
    loss.backward()
    assert float(loss) > 0 and float(xg.grad[0]) < 0
