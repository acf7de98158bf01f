"""Fit losses against their closed forms (numbers written out here), masks, and the RGB projection."""
from __future__ import annotations

import math

import pytest
import torch
from torch.testing import assert_close

from skyfit.fit import Loss, horizon_mask, make_loss, rho_cauchy, rho_huber, saturation_mask, sun_disc_mask

F64 = torch.float64
M = torch.tensor([[1.0, 2.0], [3.0, 5.0], [0.5, 4.0]], dtype=F64)
O = torch.tensor([[1.5, 1.0], [3.0, 9.0], [0.25, 4.5]], dtype=F64)
S = torch.tensor([[0.5, 0.25], [1.0, 2.0], [0.1, 1.0]], dtype=F64)


def _mean(xs):
    return sum(xs) / len(xs)


def test_squared_is_weighted_least_squares():
    # r = (m - o) / s = -1, 4, 0, -2, 2.5, -0.5 -> mean of r^2 / 2
    r = [-1.0, 4.0, 0.0, -2.0, 2.5, -0.5]
    assert float(make_loss("squared")(M, O, S)) == pytest.approx(_mean([0.5 * v * v for v in r]), rel=1e-14)


def test_log_residual_uses_the_delta_method_sigma():
    r = [math.log(m / o) * o / s for m, o, s in zip(M.flatten().tolist(), O.flatten().tolist(), S.flatten().tolist())]
    assert float(make_loss("log")(M, O, S)) == pytest.approx(_mean([0.5 * v * v for v in r]), rel=1e-14)
    # without sigma it is plain least squares of log ratios
    r = [math.log(m / o) for m, o in zip(M.flatten().tolist(), O.flatten().tolist())]
    assert float(make_loss("log")(M, O)) == pytest.approx(_mean([0.5 * v * v for v in r]), rel=1e-14)


def test_relative_ignores_sigma():
    r = [(m - o) / o for m, o in zip(M.flatten().tolist(), O.flatten().tolist())]
    assert float(make_loss("relative")(M, O, S)) == pytest.approx(_mean([0.5 * v * v for v in r]), rel=1e-14)


def test_huber_both_branches():
    d = 1.345
    r = [-1.0, 4.0, 0.0, -2.0, 2.5, -0.5]
    expect = [0.5 * v * v if abs(v) <= d else d * (abs(v) - d / 2) for v in r]
    assert float(make_loss("huber")(M, O, S)) == pytest.approx(_mean(expect), rel=1e-14)
    # value and slope are continuous at |r| = delta
    x = torch.tensor([d - 1e-9, d + 1e-9], dtype=F64, requires_grad=True)
    y = rho_huber(x, d)
    (g,) = torch.autograd.grad(y.sum(), x)
    assert float((y[1] - y[0]).detach()) == pytest.approx(0.0, abs=1e-8)
    assert float(g[1] - g[0]) == pytest.approx(0.0, abs=1e-8)


def test_cauchy_closed_form_and_custom_delta():
    c = 2.0
    r = [-1.0, 4.0, 0.0, -2.0, 2.5, -0.5]
    expect = [0.5 * c * c * math.log(1 + (v / c) ** 2) for v in r]
    assert float(make_loss("cauchy:delta=2")(M, O, S)) == pytest.approx(_mean(expect), rel=1e-14)
    # near 0 it is r^2 / 2
    assert float(rho_cauchy(torch.tensor(1e-4, dtype=F64))) == pytest.approx(0.5e-8, rel=1e-7)


def test_noise_scale_term_and_its_optimum():
    """rho(r / s) + log s: for the squared loss its minimum over s is s^2 = mean(r^2) (Gaussian ML)."""
    loss = make_loss("squared")
    r2 = _mean([v * v for v in [-1.0, 4.0, 0.0, -2.0, 2.5, -0.5]])
    s = torch.tensor(1.7, dtype=F64)
    assert float(loss(M, O, S, noise_scale=s)) == pytest.approx(r2 / (2 * 1.7**2) + math.log(1.7), rel=1e-14)
    s = torch.tensor(math.sqrt(r2), dtype=F64, requires_grad=True)
    (g,) = torch.autograd.grad(loss(M, O, S, noise_scale=s), s)
    assert float(g) == pytest.approx(0.0, abs=1e-13)


def test_masks_and_weights():
    loss = make_loss("squared")
    r = [-1.0, 4.0, 0.0, -2.0, 2.5, -0.5]
    mask = torch.tensor([True, False, True])
    assert float(loss(M, O, S, mask=mask)) == pytest.approx(_mean([0.5 * v * v for v in r[:2] + r[4:]]), rel=1e-14)
    w = torch.tensor([[1.0, 2.0], [0.0, 1.0], [1.0, 1.0]], dtype=F64)
    expect = sum(wi * 0.5 * v * v for wi, v in zip(w.flatten().tolist(), r)) / 6
    assert float(loss(M, O, S, weights=w)) == pytest.approx(expect, rel=1e-14)
    assert float(loss(M, O, S, reduction="sum")) == pytest.approx(sum(0.5 * v * v for v in r), rel=1e-14)


def test_masked_bad_values_give_no_nan_value_or_gradient():
    """A masked zero or negative observation must not leak NaN through log or division."""
    o = O.clone()
    o[1, 0] = 0.0
    o[2, 1] = -3.0
    mask = torch.tensor([[True, True], [False, True], [True, False]])
    for name in ("log", "relative", "squared", "huber", "cauchy"):
        m = M.clone().requires_grad_(True)
        val = make_loss(name)(m, o, S, mask=mask)
        (g,) = torch.autograd.grad(val, m)
        assert math.isfinite(float(val.detach())), name
        assert bool(torch.isfinite(g).all()), name
        assert float(g[1, 0]) == 0.0 and float(g[2, 1]) == 0.0, name


def test_loss_parsing():
    l = make_loss("huber:residual=log,delta=2")
    assert (l.residual, l.rho, l.delta) == ("log", "huber", 2.0)
    assert make_loss("cauchy").settings() == {"name": "cauchy", "residual": "linear", "rho": "cauchy", "delta": 2.3849}
    with pytest.raises(ValueError, match="unknown loss 'l2'; valid: squared, log, relative, huber, cauchy"):
        make_loss("l2")
    with pytest.raises(ValueError, match="unknown loss residual 'sqrt'"):
        make_loss("huber:residual=sqrt")
    with pytest.raises(ValueError, match="loss delta must be > 0"):
        Loss(rho="huber", delta=-1.0)


def test_horizon_sun_and_saturation_masks():
    el = torch.tensor([-5.0, 0.5, 10.0, 89.0], dtype=F64)
    az = torch.zeros(4, dtype=F64)
    d = torch.stack([torch.cos(torch.deg2rad(el)) * torch.sin(az), torch.cos(torch.deg2rad(el)) * torch.cos(az),
                     torch.sin(torch.deg2rad(el))], -1)
    assert horizon_mask(d).tolist() == [False, True, True, True]
    assert horizon_mask(d, 5.0).tolist() == [False, False, True, True]
    sun = torch.tensor([0.0, math.cos(math.radians(11.0)), math.sin(math.radians(11.0))], dtype=F64)
    # angles to the sun: 16, 10.5, 1, 78 degrees
    assert sun_disc_mask(d, sun, 2.0).tolist() == [True, True, False, True]
    assert sun_disc_mask(d, sun, 12.0).tolist() == [True, False, False, True]
    assert sun_disc_mask(d, sun, 0.0).tolist() == [True] * 4
    v = torch.tensor([[0.1, 0.2], [0.99, 0.5], [0.3, 1.0]], dtype=F64)
    assert saturation_mask(v, 0.99).tolist() == [True, False, False]
    assert saturation_mask(v, None).tolist() == [True] * 3


def test_rgb_channel_matrix_is_cie_then_srgb():
    from skyfit.fit import Observation, channel_matrix
    from skyfit.render import spectral_to_xyz, xyz_to_linear_srgb

    lam = torch.tensor([400.0, 450.0, 500.0, 550.0, 600.0, 650.0, 700.0], dtype=F64)
    spec = torch.rand(5, 7, dtype=F64, generator=torch.Generator().manual_seed(0))
    obs = Observation("x", "x", "rgb", torch.tensor([[0.0, 0.0, 1.0]] * 5, dtype=F64), torch.tensor(0.5, dtype=F64),
                      torch.tensor(0.0, dtype=F64), torch.ones(5, 3, dtype=F64), torch.ones(5, 3, dtype=F64),
                      torch.ones(5, dtype=torch.bool), ("R", "G", "B"))
    assert_close(spec @ channel_matrix(lam, obs), xyz_to_linear_srgb(spectral_to_xyz(spec, lam)), rtol=1e-12, atol=1e-12)
    # spectral data select their wavelengths
    sobs = Observation("x", "x", "spectral", obs.directions, obs.sun_zenith, obs.sun_azimuth, torch.ones(5, 2, dtype=F64),
                       torch.ones(5, 2, dtype=F64), obs.mask, ("L450", "L650"), torch.tensor([450.0, 650.0], dtype=F64))
    assert_close(spec @ channel_matrix(lam, sobs), spec[:, [1, 5]], rtol=0, atol=0)
    bad = Observation("x", "x", "spectral", obs.directions, obs.sun_zenith, obs.sun_azimuth, torch.ones(5, 1, dtype=F64),
                      torch.ones(5, 1, dtype=F64), obs.mask, ("L451",), torch.tensor([451.0], dtype=F64))
    with pytest.raises(ValueError, match="451.0.*not on the model grid"):
        channel_matrix(lam, bad)
