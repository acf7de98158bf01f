"""Fit parameterisation: round trips, gradients of the reparametrisations, and the atmosphere they build.

Expected values are closed forms written in the tests (Angstrom law, sigmoid and exp
maps), not outputs of the code under test.
"""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from torch.testing import assert_close

from skyfit.atmosphere import load_atmosphere
from skyfit.fit import ATMOSPHERE_PARAMETERS, NUISANCE, PARAMETERS, FitError, Parameterisation

LAM = np.array([380.0, 450.0, 550.0, 650.0, 720.0])
# the two-term HG parameters need a HG config (earth_clear_sky_eval is Cornette-Shanks): tests/test_aerosol.py
ALL_ATM = [n for n in ATMOSPHERE_PARAMETERS if n not in ("ground_albedo_scale", "mie_aod_550", "mie_g2", "mie_hg_weight",
                                                      "mie_median_radius", "mie_geometric_sigma", "mie_coarse_radius",
                                                      "mie_coarse_sigma", "mie_fine_fraction")]  # these switch the phase


@pytest.fixture(scope="module")
def eval_atm():
    return load_atmosphere("earth_clear_sky_eval", LAM)


@pytest.fixture(scope="module")
def earth():
    return load_atmosphere("earth", LAM)


def test_every_transform_round_trips_inside_its_range(earth):
    values = {"rayleigh_scale": 1.3, "rayleigh_scale_height": 7000.0, "mie_beta_550": 3e-5, "mie_angstrom_alpha": 1.2,
              "mie_ssa": 0.93, "mie_scale_height": 900.0, "mie_g": -0.4, "ground_albedo": 0.27, "exposure": [0.5, 2.0],
              "noise_scale": 1.7, "sun_azimuth_offset": [-0.3, 0.1], "sun_zenith_offset": [0.05, -0.12]}
    p = Parameterisation(earth, list(values), n_observations=2, values=values)
    x = p.initial_vector()
    assert x.shape == (15,)  # 8 atmosphere + noise_scale (shared) + 3 nuisance x 2 observations
    back = p.physical_dict(x)
    for n, v in values.items():
        assert_close(torch.tensor(back[n], dtype=torch.float64), torch.tensor(v, dtype=torch.float64), rtol=1e-12, atol=1e-15)
    # and x -> v -> x
    assert_close(p.to_unconstrained(back), x, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("name", list(PARAMETERS))
def test_forward_is_the_closed_form_and_stays_inside_the_range(name):
    spec = PARAMETERS[name]
    x = torch.tensor([-25.0, -3.0, 0.0, 0.7, 25.0], dtype=torch.float64)  # within the clamp (SIGMOID_EDGE)
    v = spec.forward(x)
    if spec.transform == "log":
        expect = spec.ref * torch.exp(x)
        assert bool((v > 0).all())
    elif spec.transform == "interval":
        expect = spec.lo + (spec.hi - spec.lo) / (1 + torch.exp(-x))
        assert bool(((v >= spec.lo) & (v <= spec.hi)).all())
    elif spec.transform == "loginterval":
        expect = torch.exp(math.log(spec.lo) + (math.log(spec.hi) - math.log(spec.lo)) / (1 + torch.exp(-x)))
        assert bool(((v >= spec.lo * (1 - 1e-12)) & (v <= spec.hi * (1 + 1e-12))).all())
    else:
        expect = spec.ref * x
    assert_close(v, expect, rtol=1e-13, atol=0.0)


@pytest.mark.parametrize("name", list(PARAMETERS))
def test_reparametrisation_gradcheck_including_far_from_the_start(name):
    spec = PARAMETERS[name]
    hi = 2.0 if name == "ground_albedo_scale" else None
    # x = +-15 is deep in the sigmoid's tails: the gradient is small but never zero (no clamping).
    x = torch.tensor([-15.0, -1.0, 0.0, 2.5, 15.0], dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda t: spec.forward(t, hi), (x,))
    (g,) = torch.autograd.grad(spec.forward(x, hi).sum(), x)
    assert bool((g.abs() > 0).all())


def test_gradcheck_of_the_atmosphere_built_from_x(eval_atm):
    free = ALL_ATM
    p = Parameterisation(eval_atm, free)

    def fields(x):
        a = p.atmosphere(p.to_physical(x))
        return (a.rayleigh_scattering, a.rayleigh_scale_height, a.mie_extinction, a.mie_scattering, a.mie_scale_height,
                a.mie_g, a.ground_albedo)

    x = (p.initial_vector() + 0.1).requires_grad_(True)
    assert torch.autograd.gradcheck(fields, (x,))


def test_defaults_reproduce_the_config_atmosphere(eval_atm):
    """The defaults read off the base atmosphere give back its exact spectra."""
    p = Parameterisation(eval_atm, ALL_ATM)
    a = p.atmosphere(p.to_physical(p.initial_vector()))
    for f in ("rayleigh_scattering", "mie_extinction", "mie_scattering", "rayleigh_scale_height", "mie_scale_height", "mie_g"):
        assert_close(getattr(a, f), getattr(eval_atm, f), rtol=1e-12, atol=0.0)
    # grey albedo replaces the grass table by its mean
    assert_close(a.ground_albedo, eval_atm.ground_albedo.mean().expand(len(LAM)), rtol=1e-12, atol=0.0)


def test_mie_defaults_are_the_angstrom_law_of_the_config(eval_atm):
    # earth_clear_sky_eval.yaml: Angstrom beta 0.04 (optical depth at 1 um), alpha 0.8, H_M 1200 m
    p = Parameterisation(eval_atm, ["mie_beta_550"])
    assert p.defaults["mie_beta_550"] == pytest.approx(0.04 / 1200.0 * 0.55 ** (-0.8), rel=1e-12)
    assert p.defaults["mie_angstrom_alpha"] == pytest.approx(0.8, rel=1e-12)
    assert p.defaults["mie_ssa"] == pytest.approx(0.8, rel=1e-12)


def test_mie_extinction_follows_beta_and_alpha(eval_atm):
    p = Parameterisation(eval_atm, ["mie_beta_550", "mie_angstrom_alpha", "mie_ssa"],
                         values={"mie_beta_550": 2e-5, "mie_angstrom_alpha": 1.5, "mie_ssa": 0.95})
    a = p.atmosphere(p.to_physical(p.initial_vector()))
    expect = 2e-5 * (torch.tensor(LAM, dtype=torch.float64) / 550.0) ** -1.5
    assert_close(a.mie_extinction, expect, rtol=1e-12, atol=0.0)
    assert_close(a.mie_scattering, 0.95 * expect, rtol=1e-12, atol=0.0)


def test_rayleigh_scale_multiplies_the_spectrum_and_fixed_values_apply(earth):
    p = Parameterisation(earth, ["rayleigh_scale"], values={"rayleigh_scale": 1.2, "mie_g": 0.5})
    a = p.atmosphere(p.to_physical(p.initial_vector()))
    assert_close(a.rayleigh_scattering, 1.2 * earth.rayleigh_scattering, rtol=1e-13, atol=0.0)
    assert float(a.mie_g) == pytest.approx(0.5)  # a fixed override
    assert_close(a.mie_extinction, earth.mie_extinction, rtol=0.0, atol=0.0)  # untouched: the base's own tensor


def test_ground_albedo_scale_upper_bound_keeps_albedo_below_one(eval_atm):
    p = Parameterisation(eval_atm, ["ground_albedo_scale"])
    hi = 1.0 / float(eval_atm.ground_albedo.max())
    a = p.atmosphere(p.to_physical(torch.tensor([30.0], dtype=torch.float64)))
    assert float(a.ground_albedo.max()) <= 1.0
    assert float(a.ground_albedo.max()) == pytest.approx(1.0, abs=1e-9)
    with pytest.raises(FitError, match="ground_albedo_scale must lie in the open interval"):
        Parameterisation(eval_atm, ["ground_albedo_scale"], values={"ground_albedo_scale": hi * 1.01})


def test_errors_name_the_parameter(earth):
    with pytest.raises(FitError, match=r"unknown free parameter 'mie_color'; valid: rayleigh_scale"):
        Parameterisation(earth, ["mie_color"])
    with pytest.raises(FitError, match=r"mie_g must lie in the open interval \(-1, 1\)"):
        Parameterisation(earth, ["mie_g"], values={"mie_g": 1.0})
    with pytest.raises(FitError, match=r"mie_scale_height must lie in the open interval \(10, 20000\) m"):
        Parameterisation(earth, ["mie_scale_height"], values={"mie_scale_height": 30_000.0})
    with pytest.raises(FitError, match="mie_beta_550 must be > 0"):
        Parameterisation(earth, ["mie_beta_550"], values={"mie_beta_550": -1e-6})
    with pytest.raises(FitError, match="not both"):
        Parameterisation(earth, ["ground_albedo", "ground_albedo_scale"])
    with pytest.raises(FitError, match="per-observation parameters must be among"):
        Parameterisation(earth, ["mie_g"], per_observation=["mie_g"])
    with pytest.raises(FitError, match="2 values for 3 observation"):
        Parameterisation(earth, ["exposure"], n_observations=3, values={"exposure": [1.0, 2.0]})


def test_per_observation_layout_and_nuisance_lookup(earth):
    p = Parameterisation(earth, ["mie_g", "exposure", "noise_scale"], n_observations=3,
                         values={"exposure": [0.5, 1.0, 2.0]})
    assert p.names == ["mie_g", "exposure[0]", "exposure[1]", "exposure[2]", "noise_scale"]
    phys = p.to_physical(p.initial_vector())
    assert [float(p.nuisance(phys, i)["exposure"]) for i in range(3)] == pytest.approx([0.5, 1.0, 2.0])
    assert set(p.nuisance(phys, 0)) == set(NUISANCE)


def test_spread_starts_are_seeded_and_inside_the_typical_spans(earth):
    p = Parameterisation(earth, ["mie_beta_550", "mie_g", "exposure"])
    a = p.spread_starts(4, torch.Generator().manual_seed(3))
    b = p.spread_starts(4, torch.Generator().manual_seed(3))
    assert len(a) == 4
    for u, v in zip(a, b):
        assert_close(u, v, rtol=0, atol=0)
    assert_close(a[0], p.initial_vector(), rtol=0, atol=0)
    for x in a[1:]:
        d = p.physical_dict(x)
        lo, hi = PARAMETERS["mie_g"].typical
        assert lo <= d["mie_g"] <= hi
        lo, hi = PARAMETERS["mie_beta_550"].typical
        assert lo <= d["mie_beta_550"] <= hi
        assert d["exposure"] == pytest.approx(1.0)  # exposure starts in closed form, not spread
    # Latin hypercube: the 3 spread points of g fall in 3 different thirds of its span
    lo, hi = PARAMETERS["mie_g"].typical
    thirds = sorted(int((p.physical_dict(x)["mie_g"] - lo) / (hi - lo) * 3) for x in a[1:])
    assert thirds == [0, 1, 2]


def test_aerosol_optical_depth_parameterisation(eval_atm):
    """mie_aod_550 = beta_550 x H_M: fitting it with H_M keeps the optical depth when H_M moves."""
    p = Parameterisation(eval_atm, ["mie_aod_550", "mie_scale_height"], values={"mie_aod_550": 0.12, "mie_scale_height": 1500.0})
    a = p.atmosphere(p.to_physical(p.initial_vector()))
    expect = 0.12 / 1500.0 * (torch.tensor(LAM, dtype=torch.float64) / 550.0) ** -0.8
    assert_close(a.mie_extinction, expect, rtol=1e-12, atol=0.0)
    d = p.physical_dict(p.initial_vector())
    assert d["mie_beta_550"] == pytest.approx(0.12 / 1500.0, rel=1e-12)
    # default: the config's optical depth, 0.04 x 0.55^-0.8 (Angstrom beta is the optical depth at 1 um)
    assert Parameterisation(eval_atm, ["mie_aod_550"]).defaults["mie_aod_550"] == pytest.approx(0.04 * 0.55**-0.8, rel=1e-12)
    with pytest.raises(FitError, match="not both"):
        Parameterisation(eval_atm, ["mie_beta_550", "mie_aod_550"])


def test_a_fitted_value_on_a_bound_rebuilds():
    """A fit that ran into a bound reports the sigmoid's rounded end, exactly the bound: inside_bounds moves it just
    inside (u = BOUND_EDGE), the transform accepts it and maps back to the bound within 1e-11 of the range, interior
    values pass unchanged, and a user's value on a bound is still refused."""
    import torch

    from skyfit.fit.parameters import BOUND_EDGE, PARAMETERS, inside_bounds

    for name, v in (("mie_g2", 0.0), ("mie_g2", -1.0), ("mie_median_radius", PARAMETERS["mie_median_radius"].lo),
                    ("mie_median_radius", PARAMETERS["mie_median_radius"].hi), ("mie_fine_fraction", 1.0)):
        spec = PARAMETERS[name]
        w = inside_bounds(name, v)
        assert w != v and spec.lo < w < spec.hi
        x = spec.inverse(w)
        back = float(spec.forward(torch.tensor(x, dtype=torch.float64)))
        assert abs(back - v) <= 1e-11 * (spec.hi - spec.lo) + BOUND_EDGE * spec.hi * 30
    assert inside_bounds("mie_g2", -0.3) == -0.3 and inside_bounds("mie_g", [0.5, 0.7]) == [0.5, 0.7]
    assert inside_bounds("exposure", 0.0) == 0.0  # unbounded transforms are left to their own checks
    # a range whose upper bound depends on the data: inside values pass unchanged, the lower bound moves inside
    assert inside_bounds("ground_albedo_scale", 1.3) == 1.3
    assert 0.0 < inside_bounds("ground_albedo_scale", 0.0) < 1e-9
    with pytest.raises(FitError, match="open interval"):
        PARAMETERS["mie_g2"].inverse(0.0)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_open_interval_parameters_never_reach_their_bounds(dtype):
    """An unconstrained value far out (an optimiser's wild first step) still gives a value strictly inside an open
    interval: mie_g at +-1 is refused by the atmosphere (the sigmoid is exactly 1 from x ~ 37 in float64, 17 in float32)."""
    from skyfit.fit.parameters import PARAMETERS

    for name in ("mie_g", "saturation_red", "vignetting"):
        spec = PARAMETERS[name]
        v = spec.forward(torch.tensor([1e3, -1e3, 50.0, -50.0], dtype=dtype))
        assert bool((v > spec.lo).all() and (v < spec.hi).all()), (name, v)
