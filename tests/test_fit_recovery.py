"""Synthetic recovery: fit skies rendered from known atmospheres with seeded 1 % noise.

The truth is built from a config dict with :func:`skyfit.atmosphere.atmosphere_from_config`
and rendered by :func:`skyfit.camera.render_fisheye` -- not through the fit's own
parameterisation -- so a wrong mapping from fit parameters to the atmosphere fails here.
Small images (<= 32 x 32), 6 wavelengths, single scattering, Gauss-Legendre optical depth.
"""
from __future__ import annotations

import copy
import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest
import torch

import skyfit
from skyfit.atmosphere import atmosphere_from_config, load_yaml
from skyfit.camera import FisheyeCamera, render_fisheye
from skyfit.fit import FitOptions, FitProblem, Observation, Parameterisation, SkyModel, fit, make_loss
from skyfit.render import spectral_to_xyz, xyz_to_linear_srgb
from skyfit.transmittance import make_integrator

LAM = np.linspace(420.0, 680.0, 6)
VIEW = 16
FREE = ["mie_beta_550", "mie_scale_height", "mie_g", "rayleigh_scale", "exposure"]


def _integrator():
    return make_integrator("gauss", samples=16)


def _config(name: str, **changes) -> dict:
    cfg = load_yaml(Path(skyfit.__file__).parent / "configs" / f"{name}.yaml")
    cfg = copy.deepcopy(cfg)
    for key, value in changes.items():
        section, field = key.split("__")
        cfg[section][field] = value
    return cfg


def _truth_config(name, rayleigh_scale, beta_550, alpha, h_m, g):
    cfg = _config(name, rayleigh__scale=rayleigh_scale, mie__scale_height_m=h_m, mie__g=g)
    cfg["mie"].pop("angstrom_beta", None)
    cfg["mie"]["extinction_550"] = beta_550
    cfg["mie"]["angstrom_alpha"] = alpha
    return cfg


def synthetic(cfg, exposure, sun_deg, size=32, noise=0.01, seed=0, rgb=False, sun_azimuth_seen=None):
    """A noisy observation of the sky of ``cfg`` (exposure x radiance); the sun it reports may differ."""
    atm = atmosphere_from_config(cfg, LAM)
    img = render_fisheye(atm, FisheyeCamera(size), sun_deg[0], sun_deg[1], _integrator(), view_samples=VIEW)
    spec = img.spectral[img.valid]
    clean = exposure * (xyz_to_linear_srgb(spectral_to_xyz(spec, atm.wavelengths)) if rgb else spec)
    gen = torch.Generator().manual_seed(seed)
    noisy = clean * (1 + noise * torch.randn(clean.shape, generator=gen, dtype=clean.dtype))
    view, _ = img.camera.pixel_vectors(torch.float64)
    t = lambda d: torch.tensor(math.radians(d), dtype=torch.float64)  # noqa: E731
    az = sun_deg[1] if sun_azimuth_seen is None else sun_azimuth_seen
    channels = ("R", "G", "B") if rgb else tuple(f"L{x:g}" for x in LAM)
    return Observation(f"syn{seed}", f"synthetic {seed}", "rgb" if rgb else "spectral", view[img.valid], t(sun_deg[0]), t(az),
                       noisy, noise * clean, torch.ones(noisy.shape[0], dtype=torch.bool), channels,
                       None if rgb else torch.tensor(LAM))


def _check(res, truth, rel=0.03, g_abs=0.01):
    for name, v in truth.items():
        got = res.parameters[name]
        if name == "mie_g":
            assert abs(got - v) < g_abs, (name, got, v)
        else:
            got = np.asarray(got, float)
            assert np.all(np.abs(got / np.asarray(v, float) - 1) < rel), (name, got, v)


CASES = [
    # base config, truth (rayleigh scale, beta_550 [1/m], alpha, H_M [m], g), exposure, sun (zenith, azimuth) [deg]
    ("earth", (1.05, 2.0e-5, 0.0, 1500.0, 0.75), 1.3, (40.0, 120.0)),
    ("earth_hazy", (0.95, 6.0e-5, 1.3, 1000.0, 0.62), 0.8, (65.0, 250.0)),
]


@pytest.mark.parametrize("base_name, truth, exposure, sun", CASES, ids=[c[0] for c in CASES])
def test_recovers_atmosphere_and_exposure_from_a_fisheye(base_name, truth, exposure, sun):
    rs, beta, alpha, h_m, g = truth
    obs = synthetic(_truth_config(base_name, *truth), exposure, sun)
    base = atmosphere_from_config(_config(base_name), LAM)
    param = Parameterisation(base, FREE)  # starts at the base config's values: beta off by 3.6-4.5x
    start = param.physical_dict(param.initial_vector())
    assert max(start["mie_beta_550"] / beta, beta / start["mie_beta_550"]) > 3
    problem = FitProblem(param, SkyModel(_integrator(), view_samples=VIEW), [obs], make_loss("squared"))
    res = fit(problem, FitOptions(starts=2, seed=1))
    _check(res, {"rayleigh_scale": rs, "mie_beta_550": beta, "mie_scale_height": h_m, "mie_g": g, "exposure": exposure})
    assert res.convergence["converged"], res.convergence
    # the best of the starts is returned
    assert res.loss == pytest.approx(min(s["loss"] for s in res.starts), rel=1e-12)
    # chi^2 / 2 per element at the optimum: mean 0.5 (1 - P / n), standard deviation 1 / sqrt(2 n) ~ 0.01 here
    n = obs.values.numel()
    assert abs(res.loss - 0.5 * (1 - 5 / n)) < 5 / math.sqrt(2 * n), res.loss


def test_joint_fit_of_two_suns_shares_the_atmosphere():
    truth = (1.05, 2.5e-5, 0.0, 1400.0, 0.72)
    cfg = _truth_config("earth", *truth)
    obs = [synthetic(cfg, 1.3, (30.0, 90.0), size=24, seed=1), synthetic(cfg, 0.7, (70.0, 200.0), size=24, seed=2)]
    base = atmosphere_from_config(_config("earth"), LAM)
    param = Parameterisation(base, FREE, n_observations=2, per_observation=["exposure"])
    assert param.names[-2:] == ["exposure[0]", "exposure[1]"]
    problem = FitProblem(param, SkyModel(_integrator(), view_samples=VIEW), obs, make_loss("squared"))
    res = fit(problem, FitOptions(starts=1))
    _check(res, {"rayleigh_scale": truth[0], "mie_beta_550": truth[1], "mie_scale_height": truth[3], "mie_g": truth[4],
                 "exposure": [1.3, 0.7]})


def test_recovers_the_sun_azimuth_offset():
    """The instrument says 120 deg, the sky was rendered with the sun at 125 deg (Kider-like nuisance)."""
    obs = synthetic(_config("earth"), 1.0, (45.0, 125.0), size=24, sun_azimuth_seen=120.0, seed=3)
    base = atmosphere_from_config(_config("earth"), LAM)
    param = Parameterisation(base, ["mie_g", "exposure", "sun_azimuth_offset"], values={"mie_g": 0.7})
    problem = FitProblem(param, SkyModel(_integrator(), view_samples=VIEW), [obs], make_loss("squared"))
    res = fit(problem, FitOptions(starts=1))
    assert math.degrees(res.parameters["sun_azimuth_offset"]) == pytest.approx(5.0, abs=0.2)
    assert res.parameters["mie_g"] == pytest.approx(0.8, abs=0.01)


def test_recovers_a_camera_tilt():
    """The instrument's zenith axis leans 3 deg North and 2 deg West: it reports the views in its own frame.

    The world <- instrument rotation is built with scipy (R_y(east) R_x(-north)), independently of
    FitProblem.view_directions; the fit must find the tilt, not a sun offset that mimics it.
    """
    from scipy.spatial.transform import Rotation

    north, east = math.radians(3.0), math.radians(-2.0)
    obs = synthetic(_config("earth"), 1.0, (40.0, 200.0), size=24, seed=5)
    rot = Rotation.from_rotvec([0.0, east, 0.0]) * Rotation.from_rotvec([-north, 0.0, 0.0])
    assert np.allclose(rot.apply([0.0, 0.0, 1.0]), [math.sin(east) * math.cos(north), math.sin(north),
                                                     math.cos(east) * math.cos(north)])
    inst = torch.from_numpy(rot.inv().apply(obs.directions.numpy()))
    obs = dataclasses.replace(obs, directions=inst)
    base = atmosphere_from_config(_config("earth"), LAM)
    param = Parameterisation(base, ["mie_g", "exposure", "camera_tilt_north", "camera_tilt_east"], values={"mie_g": 0.7})
    problem = FitProblem(param, SkyModel(_integrator(), view_samples=VIEW), [obs], make_loss("squared"))
    res = fit(problem, FitOptions(starts=1))
    assert math.degrees(res.parameters["camera_tilt_north"]) == pytest.approx(3.0, abs=0.1)
    assert math.degrees(res.parameters["camera_tilt_east"]) == pytest.approx(-2.0, abs=0.1)
    assert res.parameters["mie_g"] == pytest.approx(0.8, abs=0.01)


def test_recovers_from_rgb_data():
    truth = (1.0, 3.0e-5, 0.0, 1200.0, 0.7)
    obs = synthetic(_truth_config("earth", *truth), 2.0, (50.0, 160.0), size=24, rgb=True, seed=4)
    base = atmosphere_from_config(_config("earth"), LAM)
    param = Parameterisation(base, ["mie_beta_550", "mie_g", "exposure"])
    problem = FitProblem(param, SkyModel(_integrator(), view_samples=VIEW), [obs], make_loss("squared"))
    res = fit(problem, FitOptions(starts=1))
    _check(res, {"mie_beta_550": truth[1], "mie_g": truth[4], "exposure": 2.0})
