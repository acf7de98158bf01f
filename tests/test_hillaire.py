"""Hillaire 2020 multiple-scattering LUT (skyfit.scattering.hillaire)."""
from __future__ import annotations

import math

import pytest
import torch

from skyfit.atmosphere import load_atmosphere
from skyfit.scattering import single_scattering
from skyfit.scattering.bruneton_tables import TableSizes
from skyfit.scattering.hillaire import fibonacci_sphere, hillaire_lut, hillaire_multiple, hillaire_sky_radiance
from skyfit.scattering.multiple import precompute, sky_radiance
from skyfit.transmittance import make_integrator

F64 = torch.float64
T_SIZES = TableSizes(transmittance_mu=64, transmittance_r=16)
BRUNETON = TableSizes(scattering_r=8, scattering_mu=32, scattering_mu_s=8, scattering_nu=4, transmittance_mu=64,
                      transmittance_r=16, irradiance_mu_s=16, irradiance_r=8)
GAUSS = make_integrator("gauss", samples=16)


@pytest.fixture(scope="module")
def earth():
    # Without ozone, as measured in docs/hillaire.md (both methods include it consistently: tests/test_ozone.py).
    return load_atmosphere("earth", [440.0, 680.0]).replace(ozone_absorption=None)


@pytest.fixture(scope="module")
def lut(earth):
    return hillaire_lut(earth, size=(16, 16), directions=64, samples=20, transmittance_sizes=T_SIZES)


def _dirs(vz, az, sun_zenith_deg):
    V, A = torch.meshgrid(torch.deg2rad(torch.as_tensor(vz, dtype=F64)), torch.deg2rad(torch.as_tensor(az, dtype=F64)), indexing="ij")
    s = math.radians(sun_zenith_deg)
    mu = torch.cos(V)
    nu = mu * math.cos(s) + torch.sin(V) * math.sin(s) * torch.cos(A)
    return mu, torch.full_like(mu, math.cos(s)), nu


def test_fibonacci_directions_integrate_low_moments():
    d = fibonacci_sphere(64, F64, "cpu")
    torch.testing.assert_close(d.norm(dim=-1), torch.ones(64, dtype=F64))
    assert float(d.mean(0).abs().max()) < 3e-3  # first moments vanish (measured 1.6e-3)
    torch.testing.assert_close((d[:, 2] ** 2).mean(), torch.tensor(1 / 3, dtype=F64), atol=2e-3, rtol=0)


def test_vanishing_scattering_gives_zero_multiple_term(earth):
    z = torch.zeros_like(earth.rayleigh_scattering)
    atm = earth.replace(rayleigh_scattering=z, mie_scattering=z)
    lut = hillaire_lut(atm, size=(4, 4), directions=16, samples=6, transmittance_sizes=T_SIZES)
    assert float(lut.f_ms.abs().max()) == 0.0
    mu, mu_s, nu = _dirs([0.0, 45, 80, 100], [0.0, 90], 30)
    m = hillaire_multiple(atm, earth.bottom_radius + 10.0, mu, mu_s, nu, GAUSS, 16, lut=lut)
    assert float(m.abs().max()) == 0.0


def test_psi_nonnegative_and_grows_with_albedos(earth, lut):
    assert bool((lut.psi >= 0).all()) and bool((lut.f_ms >= 0).all()) and bool((lut.f_ms < 1).all())
    lit = lut.psi[:, -1]  # sun at the zenith
    assert bool((lit > 0).all())
    small = dict(size=(4, 6), directions=32, samples=8, transmittance_sizes=T_SIZES)
    one = torch.ones_like(earth.ground_albedo)
    g0 = hillaire_lut(earth.replace(ground_albedo=0 * one), **small)
    g1 = hillaire_lut(earth.replace(ground_albedo=one), **small)
    day = slice(3, None)  # mu_s = 0.2, 0.6, 1 (the ground is lit)
    assert bool((g1.psi[:, day] > g0.psi[:, day] * 1.05).all())
    # Single-scattering albedo of aerosols 1 vs 0 (same extinction): more scattered light.
    a1 = hillaire_lut(earth.replace(mie_scattering=earth.mie_extinction.clone()), **small)
    a0 = hillaire_lut(earth.replace(mie_scattering=torch.zeros_like(earth.mie_extinction)), **small)
    assert bool((a1.psi[:, day] > a0.psi[:, day]).all()) and bool((a1.f_ms > a0.f_ms).all())


# |Hillaire - Bruneton orders 2-4| / (single + Bruneton orders 2-4), clear Earth without ozone,
# ground observer, 440 and 680 nm, view zenith 0-89 x azimuth 0/90/180, single scattering
# from the direct renderer on both sides (Hillaire LUT 16 x 16, 64 directions, 20 samples;
# Bruneton tables BRUNETON, orders 4). Measured max / mean signed:
#   sun 0: .029 / +.015   30: .024 / +.004   60: .058 / -.016   85: .144 / -.026
BOUNDS = {0: 0.04, 30: 0.035, 60: 0.075, 85: 0.18}


@pytest.fixture(scope="module")
def bruneton(earth):
    return precompute(earth, orders=4, sizes=BRUNETON)


@pytest.mark.parametrize("sun_zenith", [0, 30, 60, 85])
def test_total_radiance_close_to_bruneton_orders(earth, lut, bruneton, sun_zenith):
    mu, mu_s, nu = _dirs([0.0, 30, 60, 80, 89], [0.0, 90, 180], sun_zenith)
    r = torch.full_like(mu, earth.bottom_radius + 1.0)
    m_b = sky_radiance(bruneton, None, r, mu, mu_s, nu, ground=False) - sky_radiance(bruneton, None, r, mu, mu_s, nu, orders=1, ground=False)
    single = single_scattering(earth, r, mu, mu_s, nu, GAUSS, 32, ground=False)
    m_h = hillaire_multiple(earth, r, mu, mu_s, nu, GAUSS, 32, lut=lut)
    err = ((m_h - m_b) / (single + m_b)).abs().max()
    assert float(err) < BOUNDS[sun_zenith], float(err)
    total = hillaire_sky_radiance(earth, r, mu, mu_s, nu, GAUSS, 32, lut=lut, ground=False)
    torch.testing.assert_close(total, single + m_h)


def test_float32_follows_float64(earth):
    kw = dict(size=(4, 4), directions=16, samples=6, transmittance_sizes=T_SIZES)
    mu, mu_s, nu = _dirs([0.0, 60, 120], [0.0, 180], 40)
    r = torch.full_like(mu, earth.bottom_radius + 100.0)
    l64 = hillaire_sky_radiance(earth, r, mu, mu_s, nu, GAUSS, 16, lut=hillaire_lut(earth, **kw))
    a32 = earth.to(dtype=torch.float32)
    l32 = hillaire_sky_radiance(a32, r.float(), mu.float(), mu_s.float(), nu.float(), GAUSS, 16, lut=hillaire_lut(a32, **kw))
    assert l32.dtype == torch.float32
    torch.testing.assert_close(l32.double(), l64, rtol=1e-4, atol=0.0)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA")
def test_cuda_matches_cpu(earth):
    kw = dict(size=(4, 4), directions=16, samples=6, transmittance_sizes=T_SIZES)
    mu, mu_s, nu = _dirs([0.0, 60, 120], [0.0, 180], 40)
    cpu = hillaire_sky_radiance(earth, 6.4e6, mu, mu_s, nu, GAUSS, 16, lut=hillaire_lut(earth, **kw))
    g = earth.to(device="cuda")
    gpu = hillaire_sky_radiance(g, 6.4e6, mu, mu_s, nu, GAUSS, 16, lut=hillaire_lut(g, **kw))
    torch.testing.assert_close(gpu.cpu(), cpu)


def test_gradcheck_wrt_coefficients(earth):
    atm = load_atmosphere("earth", [550.0]).replace(ozone_absorption=None)
    mu, mu_s, nu = _dirs([10.0, 70, 100], [0.0, 120], 50)
    r = torch.full_like(mu, atm.bottom_radius + 500.0)
    names = ["rayleigh_scattering", "mie_scattering", "mie_g", "ground_albedo"]
    base = [getattr(atm, n).clone() for n in names]
    scale = [b.abs().clamp_min(1e-30) for b in base]

    def f(*xs):  # unit-scaled inputs so that finite differences are well conditioned
        a = atm.replace(**{n: x * s for n, x, s in zip(names, xs, scale)})
        lut = hillaire_lut(a, size=(3, 3), directions=8, samples=4, transmittance_sizes=T_SIZES, transmittance_samples=20)
        return hillaire_sky_radiance(a, r, mu, mu_s, nu, GAUSS, 6, lut=lut)

    inputs = tuple((b / s).requires_grad_(True) for b, s in zip(base, scale))
    # mie_g scaled at 0.8: 0.8 * (1 +- eps) stays inside (-1, 1); albedo 0.1 stays in [0, 1].
    assert torch.autograd.gradcheck(f, inputs, eps=1e-6, atol=1e-8, rtol=1e-5)
