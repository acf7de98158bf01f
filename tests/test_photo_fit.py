"""The photo fit's own pieces: the camera's response in the fit, censoring, blocks, the fitted camera."""
from __future__ import annotations

import math


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


# -- the multiple-scattering factor on a few wavelengths; camera priors; lagged refreshes ---------------------
def test_wavelength_nodes_spread_evenly_with_both_ends():
    from skyfit.fit.photo import wavelength_nodes

    np.testing.assert_array_equal(wavelength_nodes(16, 6), [0, 3, 6, 9, 12, 15])  # 400, 460, ..., 700 nm of 400:700:20
    assert wavelength_nodes(16, None) is None and wavelength_nodes(6, 6) is None
    with pytest.raises(ValueError, match="wavelength nodes must be >= 2"):
        wavelength_nodes(16, 1)


def test_interpolation_matrix_is_exact_for_a_line_and_bounded_for_a_parabola():
    from skyfit.fit.photo import interpolation_matrix, wavelength_nodes

    lam = torch.arange(400.0, 701.0, 20.0, dtype=torch.float64)
    idx = wavelength_nodes(16, 6)
    m = interpolation_matrix(lam, idx)
    line = 3.0 - 0.002 * lam
    torch.testing.assert_close(line[idx] @ m, line, rtol=0, atol=1e-12)
    torch.testing.assert_close(m.sum(0), torch.ones(16, dtype=torch.float64), rtol=0, atol=1e-12)
    quad = (lam / 100.0) ** 2
    # linear interpolation error <= h^2/8 max|f''| (h = 60 nm, f'' = 2e-4 /nm^2): 0.09
    err = (quad[idx] @ m - quad).abs()
    assert float(err.max()) <= 60.0**2 / 8 * 2e-4 + 1e-12 and float(err.max()) > 0.05


def test_atmosphere_at_equals_the_config_loaded_on_those_wavelengths():
    from skyfit.fit.photo import atmosphere_at

    lam = np.arange(400.0, 701.0, 20.0)
    full = skyfit.load_atmosphere("earth", lam)
    idx = np.array([0, 5, 15])
    direct = skyfit.load_atmosphere("earth", lam[idx])
    sub = atmosphere_at(full, idx)
    for f in direct.tensor_fields():
        torch.testing.assert_close(getattr(sub, f), getattr(direct, f), msg=f)


def test_factor_on_six_nodes_matches_every_wavelength():
    """The all-orders / first-order factor from tables on 6 of 16 wavelengths, interpolated, against the tables on
    all 16 (small tables; the factor is smooth in wavelength)."""
    from skyfit.fit.photo import multiple_from_tables, wavelength_nodes, atmosphere_at
    from skyfit.fit.problem import fit_settings, prepare
    from skyfit.scattering.bruneton_tables import TableSizes
    from skyfit.scattering.multiple import precompute

    cam, rgb = _rgb_sky(24)
    obs = Observation.from_arrays(rgb, cam, sun=(40.0, 120.0), min_elevation_deg=5.0)
    prep = prepare([obs], skyfit.atmosphere.read_config("earth")[0], fit_settings({}, {"free": ["exposure"]}))
    problem = prep.fit_problem()
    x = problem.param.initial_vector()
    atm = problem.param.atmosphere(problem.param.to_physical(x))
    sizes = TableSizes(32, 16, 16, 4, 8, 16, 8, 4)
    idx = wavelength_nodes(int(atm.wavelengths.numel()), 6)
    with torch.no_grad():
        every = multiple_from_tables(problem, x, precompute(atm, orders=3, sizes=sizes, progress=False))[0]
        nodes = multiple_from_tables(problem, x, precompute(atmosphere_at(atm, idx), orders=3, sizes=sizes, progress=False), idx)[0]
    torch.testing.assert_close(nodes[:, idx], every[:, idx], rtol=1e-10, atol=0)  # the nodes themselves: same numbers
    assert float(every.min()) > 1.0  # multiple scattering adds light
    assert float((nodes / every - 1).abs().max()) < 0.01


def test_factor_change_is_the_largest_relative_change():
    from skyfit.fit.photo import factor_change

    a = [torch.ones(3, 2), torch.full((2, 2), 2.0)]
    b = [torch.ones(3, 2), torch.tensor([[2.0, 2.0], [2.0, 2.1]])]
    assert factor_change(a, b) == pytest.approx(0.05)
    assert factor_change(None, b) == float("inf")


def _flat_ring_problem(v_true=-0.6):
    """Blocks all at one image radius (0.8): the exposure and the vignetting are perfectly degenerate there."""
    import dataclasses as dc

    from skyfit.fit.problem import fit_settings, prepare

    cam, rgb = _rgb_sky(32)
    obs = Observation.from_arrays(rgb * 2.0 * (1 + v_true * 0.64), cam, sun=(55.0, 120.0), min_elevation_deg=5.0)
    obs = dc.replace(obs, image_radius=torch.full_like(obs.image_radius, 0.8))
    prep = prepare([obs], skyfit.atmosphere.read_config("earth")[0],
                   fit_settings({}, {"free": ["exposure", "vignetting"], "initial": {"vignetting": v_true}}))
    return prep.fit_problem()


def test_camera_prior_is_the_gaussian_negative_log_prior_over_n_elements():
    from skyfit.fit.photo import PhotoProblem, camera_priors

    base = _flat_ring_problem()
    priors = camera_priors(["exposure", "vignetting", "gain_red"])
    assert set(priors) == {"vignetting", "gain_red"}  # only the free camera nuisances
    prob = PhotoProblem.of(base, camera_priors(["vignetting"]))
    x = base.param.initial_vector()
    mean, sigma = skyfit.fit.photo.VIGNETTING_PRIOR
    expected = 0.5 * ((-0.6 - mean) / sigma) ** 2 / base.n_elements
    assert float(prob.objective(x) - base.objective(x)) == pytest.approx(expected, rel=1e-9)
    with pytest.raises(ValueError, match="kind must be linear or log"):
        PhotoProblem.of(base, {"vignetting": ("cubic", 0.0, 1.0)})


def test_vignetting_prior_decides_what_the_data_cannot():
    """Every block at one radius: without the prior the fit leaves v where it starts (-0.6), any v fits as well;
    with it v goes to the prior's mean, and exposure x (1 + v r^2) still matches the data."""
    from skyfit.fit.optimise import FitOptions, fit
    from skyfit.fit.photo import PhotoProblem, camera_priors

    base = _flat_ring_problem()
    opts = FitOptions(starts=1, adam_steps=0, max_iter=60)
    if hasattr(opts, "method"):  # the priors live in the objective: a gradient method (fit.photo does the same)
        opts.method = "lbfgs"
    free = fit(base, opts)
    assert free.parameters["vignetting"] == pytest.approx(-0.6, abs=1e-3)
    prob = PhotoProblem.of(_flat_ring_problem(), camera_priors(["vignetting"]))
    res = fit(prob, opts)
    v, e = res.parameters["vignetting"], res.parameters["exposure"]
    assert v == pytest.approx(skyfit.fit.photo.VIGNETTING_PRIOR[0], abs=2e-3)
    p = free.parameters
    assert e * (1 + v * 0.64) == pytest.approx(p["exposure"] * (1 + p["vignetting"] * 0.64), rel=1e-5)


def _scene_of(rgb, hi, lo):
    from skyfit.fit.photo import PhotoScene
    from skyfit.io.photo import LinearPhoto

    h, w = rgb.shape[:2]
    cam = FisheyeCamera((h, w), projection="equidistant", cx=(w - 1) / 2, cy=(h - 1) / 2, radius=10 * max(h, w))
    none = np.zeros((h, w), bool)
    photo = LinearPhoto(rgb, np.full(rgb.shape, 1e-6), hi, lo, ~none, rgb, hi.any(-1), "test", {})
    return PhotoScene(photo, 30.0, 0.0, 1.0, "2024-06-01T12:00:00+00:00", {}, cam, [], None, None,
                      {"outside": none, "horizon": none, "sun": none}, [], {})


def test_blocks_with_some_saturated_pixels_are_lower_bounds_and_mixed_ones_are_left_out():
    """A channel saturated in part of a block: its mean (clipped pixels at the clip level) is a lower bound on the
    block's true mean, censored +1; partly black, or saturated and black in one block: neither bound holds."""
    from skyfit.fit.photo import block_image

    rgb = np.full((16, 16, 3), 0.5)
    hi, lo = np.zeros((16, 16, 3), bool), np.zeros((16, 16, 3), bool)
    hi[0:4, 0:4, 0] = True  # block (0, 0): red saturated everywhere
    rgb[0:4, 0:4, 0] = 1.0
    hi[0, 4, 0] = True  # block (0, 1): one red pixel saturated
    rgb[0, 4, 0] = 1.0
    lo[0, 8, 1] = True  # block (0, 2): one green pixel black
    hi[4, 0, 0] = lo[4, 1, 1] = True  # block (1, 0): saturated red and black green
    b = block_image(_scene_of(rgb, hi, lo), step=4)
    assert b.censored[0, 0].tolist() == [1, 0, 0] and b.usable[0, 0]
    assert b.censored[0, 1].tolist() == [1, 0, 0] and b.usable[0, 1]
    assert b.rgb[0, 1, 0] == pytest.approx((15 * 0.5 + 1.0) / 16)  # the bound: the clipped pixel at its clip level
    assert not b.usable[0, 2] and not b.usable[1, 0]
    assert b.usable[0, 3] and b.censored[0, 3].tolist() == [0, 0, 0]  # an untouched block is a measurement


def test_channel_saturations_are_recovered_with_gains():
    """The fit's own sky with its red and blue contrasts against sRGB's luminance rendered at 0.45 and 0.8 of
    colorimetry (built here with numpy: Y + s_c (c - Y)), then white balanced (1.2, 0.85): the fit finds both saturations, the gains and
    the exposure with the atmosphere fixed; without the saturations the gains leave a misfit 5x larger."""
    import dataclasses

    cam, rgb = _rgb_sky()
    obs = Observation.from_arrays(rgb, cam, sun=(55.0, 120.0), min_elevation_deg=5.0)
    first = skyfit.fit(obs, "earth", free=["exposure"], starts=1)  # the fit's own colorimetric sky, exposure 1
    with torch.no_grad():
        c = first.problem.predict(first.x)[0].numpy() / first.parameters["exposure"]
    y = (c @ skyfit.render.colour.srgb_luminance_weights())[:, None]
    values = obs.values.clone()
    values[obs.mask] = torch.as_tensor(2.0 * (y + np.array([0.45, 1.0, 0.8]) * (c - y)) * np.array([1.2, 1.0, 0.85]))
    obs = dataclasses.replace(obs, values=values)
    res = skyfit.fit(obs, "earth", free=["exposure", "gain_red", "gain_blue", "saturation_red", "saturation_blue"],
                     starts=1)
    p = res.parameters
    assert p["saturation_red"] == pytest.approx(0.45, rel=1e-3)
    assert p["saturation_blue"] == pytest.approx(0.8, rel=1e-3)
    assert p["gain_red"] == pytest.approx(1.2, rel=3e-3) and p["gain_blue"] == pytest.approx(0.85, rel=3e-3)
    assert p["exposure"] == pytest.approx(2.0, rel=3e-3)
    res0 = skyfit.fit(obs, "earth", free=["exposure", "gain_red", "gain_blue"], starts=1)
    assert res0.metrics["rmse"] > 5 * res.metrics["rmse"]


def test_channel_saturation_gradient():
    """d prediction / d (saturation_red, saturation_blue) by autograd against central differences (float64)."""
    cam, rgb = _rgb_sky(size=24)
    obs = Observation.from_arrays(rgb, cam, sun=(55.0, 120.0), min_elevation_deg=5.0)
    res = skyfit.fit(obs, "earth", free=["saturation_red", "saturation_blue", "gain_red"], starts=1, max_iter=3)
    prob = res.problem
    x = res.x.detach().clone().double().requires_grad_(True)
    assert torch.autograd.gradcheck(lambda v: prob.predict(v)[0], (x,), eps=1e-6, atol=1e-8, rtol=1e-5)


def test_published_cameras_render_sky_colours_as_the_prior_says():
    """The measurement behind SATURATION_PRIOR_LOG_SIGMA, redone (skyfit.tools.photo_synth.colour_rendering): spectra
    D65 x (lambda/550)^-a, a = -0.5 ... 4.5, through each published camera's sensitivities and daylight white balance,
    then its rawtoaces matrix (``srgb``) or none (``camera_rgb``), against CIE -> sRGB with red and blue saturations and
    gains fitted on log chromaticity (docs: with the matrix red / blue 0.98 / 1.04 for the Canon 5D Mark II,
    0.79 / 0.74 for the Nikon D5100, 0.35 / 0.82 for the Sigma SD Merrill; without it 0.65 / 0.48, 0.67 / 0.41,
    0.40 / 0.23). The prior's sigma is the RMS of ln s over the six with the matrix (to 0.03); the Canon with it is near
    colorimetric; the Foveon renders a clear sky's red/green over 1.5x colorimetry's, and the saturations fit it 5x
    better than gains alone; without a matrix every camera is less saturated than colorimetry in both channels."""
    pytest.importorskip("colour")
    from skyfit.fit.photo import SATURATION_PRIOR_LOG_SIGMA
    from skyfit.tools.photo_synth import colour_rendering

    names = ("Canon EOS 5D Mark II (rawtoaces)", "Nikon 5100 (NPL)", "Sigma SDMerill (NPL)")
    found = {name: colour_rendering(name) for name in names}
    raw = {name: colour_rendering(name, output="camera_rgb") for name in names}
    logs = [math.log(r[k]) for r in found.values() for k in ("s_red", "s_blue")]
    assert math.sqrt(np.mean(np.square(logs))) == pytest.approx(SATURATION_PRIOR_LOG_SIGMA, abs=0.03)
    canon, sigma = found["Canon EOS 5D Mark II (rawtoaces)"], found["Sigma SDMerill (NPL)"]
    assert abs(canon["s_red"] - 1) < 0.1 and abs(canon["s_blue"] - 1) < 0.1  # close to colorimetric
    assert sigma["s_red"] < 0.5 and sigma["rms_gains"] > 5 * sigma["rms_two"]  # the Foveon: red far less saturated
    a4 = int(np.argmin(abs(sigma["slopes"] - 4.0)))
    assert sigma["relative"][a4, 0] > 1.5  # a clear sky's red/green half again colorimetry's, relative to white
    assert all(r["s_red"] < 0.8 and r["s_blue"] < 0.6 for r in raw.values())  # overlapping sensitivities, no matrix


def test_a_result_camera_fixes_every_response_value_it_has():
    """evaluate and --camera hold what the camera dict gives of the response (gains, saturations, vignetting) and
    nothing else; a file without the saturations leaves them to the parameters' default, 1 (colorimetric)."""
    from skyfit.fit.parameters import _NUISANCE_DEFAULTS
    from skyfit.fit.photo import _fixed_camera_values

    cam = {"projection": "equisolid", "gain_red": 0.9, "gain_blue": 1.1, "saturation_red": 0.35, "saturation_blue": 0.82,
           "vignetting": -0.2, "cx": 100.0}
    assert _fixed_camera_values(cam) == {"gain_red": 0.9, "gain_blue": 1.1, "saturation_red": 0.35,
                                         "saturation_blue": 0.82, "vignetting": -0.2}
    assert _fixed_camera_values({"gain_red": 0.9}) == {"gain_red": 0.9}
    assert _NUISANCE_DEFAULTS["saturation_red"] == 1.0 and _NUISANCE_DEFAULTS["saturation_blue"] == 1.0


def test_aerosol_sigma_adds_the_validation_term_in_quadrature():
    """RESULT.json's aerosol: sigma = hypot(budget sigma, expected error of the photo path); the relative term scales
    with the fitted AOD; a parameter held fixed (a grey photo's Angstrom exponent) gets none; no budget sigma, no sigma."""
    from skyfit.fit.photo import PHOTO_VALIDATION_SIGMA, aerosol_summary

    vals = {"mie_aod_550": 0.2, "mie_angstrom_alpha": 1.3, "mie_g": 0.75, "rayleigh_scale": 1.0}
    sig = {"mie_aod_550": 0.004, "mie_angstrom_alpha": 0.05, "mie_g": None}
    a = aerosol_summary(vals, sig, ["mie_aod_550", "mie_g"])
    rel = PHOTO_VALIDATION_SIGMA["aod_550"][1]
    assert a["aod_550"] == 0.2 and a["sigma_validation"]["aod_550"] == pytest.approx(rel * 0.2, rel=1e-12)
    assert a["sigma"]["aod_550"] == pytest.approx(math.sqrt(0.004**2 + (rel * 0.2) ** 2), rel=1e-12)
    assert "angstrom_alpha" not in a["sigma_validation"] and a["sigma"]["angstrom_alpha"] == 0.05
    assert a["sigma"]["g"] is None and a["sigma_validation"]["g"] == PHOTO_VALIDATION_SIGMA["g"][1]
    assert a["sigma_statistical"]["aod_550"] == 0.004 and a["sigma"]["rayleigh_scale"] is None
