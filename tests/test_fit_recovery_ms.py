"""Synthetic recovery with multiple scattering: the ground albedo becomes observable.

Skies are built from config dicts (:func:`skyfit.atmosphere.atmosphere_from_config`, not the
fit's parameterisation) and rendered by :func:`skyfit.camera.render_fisheye` with Hillaire's
LUT built directly by :func:`skyfit.scattering.hillaire.hillaire_lut`; 1 % seeded noise.
48 x 48 equidistant fisheyes, 6 wavelengths (the 128 x 128 x 16 runs are in
``scripts/fit_recovery.py --orders 2``, docs/fitting.md).
"""
from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from skyfit.atmosphere import atmosphere_from_config
from skyfit.camera import FisheyeCamera, render_fisheye
from skyfit.fit import FitOptions, FitProblem, Observation, Parameterisation, SkyModel, fit, make_loss
from skyfit.scattering.bruneton_tables import TableSizes
from skyfit.scattering.hillaire import hillaire_lut
from skyfit.transmittance import make_integrator
from test_fit_recovery import _config, _truth_config

LAM = np.linspace(420.0, 680.0, 6)
FREE = ["mie_beta_550", "mie_scale_height", "mie_g", "rayleigh_scale", "ground_albedo"]


def _sky(base: str, truth: tuple, albedo: float, sun: tuple[float, float], size: int = 48, seed: int = 0) -> Observation:
    cfg = _truth_config(base, *truth)
    cfg["ground"] = {"albedo": albedo}
    atm = atmosphere_from_config(cfg, LAM)
    d = SkyModel(make_integrator("chapman"))  # the fit's LUT defaults: data and model share the renderer
    lut = hillaire_lut(atm, size=d.lut_size, directions=d.lut_directions, samples=d.lut_samples,
                       transmittance_sizes=TableSizes(transmittance_mu=64, transmittance_r=16))
    img = render_fisheye(atm, FisheyeCamera(size), sun[0], sun[1], make_integrator("chapman"), orders=2,
                         multiple="hillaire", tables=lut, view_samples=16, rule="gauss")
    clean = img.spectral[img.valid]
    gen = torch.Generator().manual_seed(seed)
    noisy = clean * (1 + 0.01 * torch.randn(clean.shape, generator=gen, dtype=clean.dtype))
    view, _ = img.camera.pixel_vectors(torch.float64)
    t = lambda d: torch.tensor(math.radians(d), dtype=torch.float64)  # noqa: E731
    return Observation(f"ms{seed}", "synthetic", "spectral", view[img.valid], t(sun[0]), t(sun[1]), noisy, 0.01 * clean,
                       torch.ones(noisy.shape[0], dtype=torch.bool), tuple(f"L{x:g}" for x in LAM), torch.tensor(LAM))


CASES = [
    # base config, truth (rayleigh scale, beta_550, alpha = the base's, H_M, g), ground albedo, sun (zenith, azimuth)
    ("earth", (1.05, 2.0e-5, 0.0, 1500.0, 0.75), 0.30, (40.0, 120.0)),
    ("earth_hazy", (0.95, 6.0e-5, 1.3, 1000.0, 0.62), 0.20, (65.0, 250.0)),
    ("earth_hazy", (1.02, 4.0e-5, 1.3, 800.0, 0.70), 0.50, (75.0, 30.0)),
]


@pytest.mark.parametrize("base, truth, albedo, sun", CASES, ids=["earth-sun40", "hazy-sun65", "hazy-sun75"])
def test_recovers_aerosol_rayleigh_and_ground_albedo(base, truth, albedo, sun):
    obs = _sky(base, truth, albedo, sun)
    param = Parameterisation(atmosphere_from_config(_config(base), LAM), FREE)  # starts at the config (albedo 0.1/0.15)
    model = SkyModel(make_integrator("chapman"), orders=2, view_samples=16, rule="gauss")
    problem = FitProblem(param, model, [obs], make_loss("squared"))
    res = fit(problem, FitOptions(starts=1))
    expect = {"rayleigh_scale": truth[0], "mie_beta_550": truth[1], "mie_scale_height": truth[3], "ground_albedo": albedo}
    for name, v in expect.items():
        assert abs(res.parameters[name] / v - 1) < 0.02, (name, res.parameters[name], v)
    assert abs(res.parameters["mie_g"] - truth[4]) < 0.01
    n = obs.values.numel()
    assert abs(res.loss - 0.5 * (1 - len(FREE) / n)) < 5 / math.sqrt(2 * n), res.loss  # chi^2/2 at the noise


def test_single_scattering_cannot_see_the_albedo():
    """Without multiple scattering the sky does not depend on the ground albedo (gradient exactly 0)."""
    obs = _sky("earth", (1.0, 2.0e-5, 0.0, 1200.0, 0.75), 0.3, (40.0, 120.0), size=12)
    param = Parameterisation(atmosphere_from_config(_config("earth"), LAM), ["ground_albedo"])
    for orders, nonzero in ((1, False), (2, True)):
        problem = FitProblem(param, SkyModel(make_integrator("chapman"), orders=orders, view_samples=8, rule="gauss"),
                             [obs], make_loss("squared"))
        x = param.initial_vector().requires_grad_(True)
        (g,) = torch.autograd.grad(problem.objective(x), x)
        assert (abs(float(g[0])) > 1e-6) == nonzero, (orders, g)


def test_fit_and_evaluate_round_trip_with_multiple_scattering(tmp_path, capsys):
    """RESULT.json records the multiple-scattering model; evaluate on the same data reproduces the fit's RMSE."""
    from skyfit.cli import main

    exr, res = tmp_path / "sky.exr", tmp_path / "r.json"
    assert main(["render", "earth", "--out", str(exr), "--size", "14", "--orders", "2", "--multiple", "hillaire",
                 "--wavelengths", "450,550,650", "--spectral", "--integrator", "chapman", "--sun-zenith", "45",
                 "--sun-azimuth", "100"]) == 0
    assert main(["fit", str(exr), "--config", "earth", "--out", str(res), "--free", "mie_g,exposure", "--orders", "2",
                 "--starts", "1", "--no-plots", "--json", "--threads", "1"]) == 0
    capsys.readouterr()
    fitted = json.loads(res.read_text())
    assert fitted["model"]["orders"] == 2 and fitted["model"]["multiple"] == "hillaire"
    assert main(["evaluate", str(res), str(exr), "--json"]) == 0
    ev = json.loads(capsys.readouterr().out)
    assert ev["rmse"] == pytest.approx(fitted["metrics"]["rmse"], rel=1e-9)
    # noise-free data rendered with a 32 x 32 LUT and 32 trapezoid samples, fitted with 16 x 16 and Gauss-16: small misfit
    assert fitted["parameters"]["mie_g"] == pytest.approx(0.8, abs=0.02)
