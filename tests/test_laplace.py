"""Laplace approximation (skyfit.fit.laplace): closed forms and an independent finite-difference Hessian.

Closed forms (squared loss, linear residual): with only the exposure k = e^x free, the
negative log-likelihood is sum (k m - o)^2 / (2 sigma^2); at its minimum the residual term
of the second derivative vanishes, so d^2/dx^2 = sum (k m)^2 / sigma^2 and sigma_k = k sigma_x
(delta method). With noise_scale s = e^y free as well, d^2/dy^2 = 2 sum r^2 / s^2 = 2 n at
the optimum (s^2 = mean r^2) and the cross term is 0, so sigma_y = 1 / sqrt(2 n).
"""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from skyfit.atmosphere import atmosphere_from_config
from skyfit.fit import FitOptions, FitProblem, Observation, Parameterisation, SkyModel, fit, make_loss
from skyfit.fit.laplace import hessian_nll, laplace_summary
from skyfit.transmittance import make_integrator

from test_sample import LAM, _config, tiny_observation


def _problem(free, obs, integrator="chapman"):
    base = atmosphere_from_config(_config(), LAM)
    param = Parameterisation(base, free)
    return FitProblem(param, SkyModel(make_integrator(integrator), view_samples=4, rule="gauss"), [obs], make_loss("squared"))


def test_exposure_and_noise_scale_sigmas_match_closed_forms():
    obs, _ = tiny_observation(noise=0.02, seed=3, exposure=1.7)
    prob = _problem(["exposure", "noise_scale"], obs)
    res = fit(prob, FitOptions(starts=1, adam_steps=0, max_iter=200, grad_tol=1e-12))
    lap = laplace_summary(prob, res.x)
    assert lap["positive_definite"]
    k = res.parameters["exposure"]
    s = res.parameters["noise_scale"]
    with torch.no_grad():
        m = prob.predict_unscaled(prob.param.to_physical(res.x))[0]
    sig = obs.sigma[obs.mask]
    n = prob.n_elements
    sx = 1.0 / math.sqrt(float(((k * m) ** 2 / (sig * s) ** 2).sum()))
    torch.testing.assert_close(lap["sigma_unconstrained"]["exposure"], sx, rtol=1e-5, atol=0)
    torch.testing.assert_close(lap["sigma"]["exposure"], k * sx, rtol=1e-5, atol=0)
    torch.testing.assert_close(lap["sigma_unconstrained"]["noise_scale"], 1.0 / math.sqrt(2 * n), rtol=1e-4, atol=0)
    assert abs(lap["correlation"][0][1]) < 1e-4
    # 68 % interval: exp(x +- 0.994 sigma_x) around k
    lo, hi = lap["interval68"]["exposure"]
    torch.testing.assert_close(lo, k * math.exp(-0.9944578832097535 * sx), rtol=1e-6, atol=0)
    torch.testing.assert_close(hi, k * math.exp(0.9944578832097535 * sx), rtol=1e-6, atol=0)


def test_hessian_matches_finite_differences_of_the_gradient():
    """Autograd's second derivatives vs central differences of first derivatives (h = 1e-5 in x)."""
    obs, _ = tiny_observation(noise=0.01, seed=1)
    prob = _problem(["mie_beta_550", "mie_scale_height", "mie_g", "rayleigh_scale", "exposure"], obs)
    x = prob.param.initial_vector() + torch.tensor([0.1, -0.05, 0.2, 0.03, -0.1], dtype=torch.float64)
    H = hessian_nll(prob, x)

    def grad(v):
        v = v.clone().requires_grad_(True)
        (g,) = torch.autograd.grad(prob.objective(v) * prob.n_elements, v)
        return g

    h = 1e-5
    fd = torch.stack([(grad(x + h * e) - grad(x - h * e)) / (2 * h) for e in torch.eye(5, dtype=torch.float64)])
    torch.testing.assert_close(H, 0.5 * (fd + fd.T), rtol=1e-5, atol=1e-6 * float(H.abs().max()))


def test_delta_method_and_derived_aod():
    """Physical covariance = J cov_x J; the derived AOD = beta H_M sigma from its gradient."""
    obs, _ = tiny_observation(noise=0.01, seed=2)
    prob = _problem(["mie_beta_550", "mie_scale_height", "exposure"], obs)
    res = fit(prob, FitOptions(starts=1, adam_steps=0, max_iter=100))
    lap = laplace_summary(prob, res.x)
    cx = np.array(lap["covariance_unconstrained"])
    b, hm = res.parameters["mie_beta_550"], res.parameters["mie_scale_height"]
    # beta = 1e-5 e^x: dbeta/dx = beta; H_M = lo (hi/lo)^sigmoid(x): dH/dx = H log(hi/lo) s (1 - s)
    xs = float(res.x[1])
    sg = 1 / (1 + math.exp(-xs))
    j = np.array([b, hm * math.log(20000 / 10) * sg * (1 - sg), res.parameters["exposure"]])
    np.testing.assert_allclose(np.array(lap["covariance"]), j[:, None] * cx * j[None, :], rtol=1e-9)
    # AOD = beta H: d log AOD = dx_beta + dlogH/dx dx_H
    g = np.array([b * hm, b * hm * math.log(2000) * sg * (1 - sg), 0.0])
    assert lap["derived"]["mie_aod_550"]["sigma"] == pytest.approx(math.sqrt(g @ cx @ g), rel=1e-8)
    assert lap["derived"]["mie_aod_550"]["value"] == pytest.approx(b * hm, rel=1e-12)


def test_a_parameter_on_its_bound_has_no_gaussian_sigma_but_its_interval_reaches_the_bound():
    """H_M's sigmoid saturated at its upper bound (20 km): the delta method's physical sigma would be about 0 m (the
    transform's slope), which a reader takes for a measured value; it is None and the name is in ``at_bound``,
    while the 95 % interval still runs from inside the range to the bound. At the fit's optimum, off the bound, every
    sigma is there."""
    obs, _ = tiny_observation(noise=0.01, seed=2)
    prob = _problem(["mie_beta_550", "mie_scale_height", "exposure"], obs)
    x = fit(prob, FitOptions(starts=1, adam_steps=0, max_iter=100)).x.clone()
    mid = laplace_summary(prob, x)
    assert mid["at_bound"] == [] and mid["sigma"]["mie_scale_height"] is not None
    x[1] = 20.0  # u = sigmoid(20): 2e-9 from the top
    lap = laplace_summary(prob, x)
    assert lap["at_bound"] == ["mie_scale_height"]
    assert lap["sigma"]["mie_scale_height"] is None
    assert lap["values"]["mie_scale_height"] == pytest.approx(20000.0, rel=1e-6)
    lo, hi = lap["interval95"]["mie_scale_height"]
    assert hi == pytest.approx(20000.0, rel=1e-6) and lo < 20000.0


def test_a_parameter_held_on_its_bound_leaves_the_others_their_sigma():
    """H_M past its bound's clamp (x = 40: the sigmoid's slope is 0, so the Hessian has a zero row and is not positive
    definite) at the optimum of the others there: every sigma used to be None. The others' covariance is now that of
    H_M held there, as an active constraint: equal to the Laplace sigma of the same fit with H_M not free and set to
    its bound (an independent problem, fitted on its own), and H_M itself None and listed in ``held_at_bound``."""
    from skyfit.fit.parameters import PARAMETERS

    obs, _ = tiny_observation(noise=0.01, seed=2)
    top = PARAMETERS["mie_scale_height"].hi
    base = atmosphere_from_config(_config(), LAM)
    base = base.replace(mie_scale_height=torch.full_like(base.mie_scale_height, top))
    fixed = FitProblem(Parameterisation(base, ["mie_beta_550", "exposure"]),
                       SkyModel(make_integrator("chapman"), view_samples=4, rule="gauss"), [obs], make_loss("squared"))
    xf = fit(fixed, FitOptions(starts=1, adam_steps=0, max_iter=200, grad_tol=1e-12)).x
    want = laplace_summary(fixed, xf)
    assert want["positive_definite"]

    prob = _problem(["mie_beta_550", "mie_scale_height", "exposure"], obs)
    x = torch.stack([xf[0], torch.tensor(40.0, dtype=xf.dtype), xf[1]])
    assert float(prob.param.physical_dict(x)["mie_scale_height"]) == pytest.approx(top, rel=1e-9)
    assert not bool(torch.linalg.eigvalsh(hessian_nll(prob, x)).min() > 0)  # the case that gave every sigma None
    lap = laplace_summary(prob, x)
    assert lap["positive_definite"] and lap["held_at_bound"] == ["mie_scale_height"]
    assert lap["sigma"]["mie_scale_height"] is None
    for n in ("mie_beta_550", "exposure"):
        assert lap["sigma"][n] == pytest.approx(want["sigma"][n], rel=1e-6)
