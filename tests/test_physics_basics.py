"""Physics basics against closed forms and scipy quad (float64, and float32 where stated).

* Phase functions: normalised over the sphere, mean cosine (HG: g; Cornette-Shanks:
  3g(4 + g^2) / (5 (2 + g^2)), Cornette & Shanks 1992 eq. 9), Cornette-Shanks at g = 0
  is the Rayleigh phase 3 / (16 pi) (1 + nu^2).
* Ray / sphere geometry against the stable quadratic roots computed here.
* Radiance closed forms: no atmosphere (beta = 0); the zenith ray with the sun at the
  zenith, where the view and sun columns add to the whole vertical column; the nadir
  from space with the sun behind the observer, for a one-layer atmosphere.
"""
from __future__ import annotations

import functools
import math
from fractions import Fraction

import numpy as np
import pytest
import torch
from scipy import integrate

from skyfit.atmosphere import load_atmosphere
from skyfit.geometry import atmosphere_segment, distance_to_bottom, distance_to_top, ray_hits_ground
from skyfit.scattering import single_scattering, transmittance_to_sun
from skyfit.scattering.phase import cornette_shanks_phase, henyey_greenstein_phase, rayleigh_phase
from skyfit.transmittance import INTEGRATORS, integrator_class, make_integrator

torch.set_num_threads(2)

F64 = torch.float64
R_BOTTOM, R_TOP = 6_360_000.0, 6_420_000.0
G_VALUES = [-0.9, 0.0, 0.5, 0.999]
# Break points for quad where the forward peak (width ~ 1 - g) sits.
PEAK_POINTS = [1.0 - 10.0**-k for k in range(1, 8)]


# --------------------------------------------------------------------------
# Phase functions
# --------------------------------------------------------------------------
def _sphere_integral(fn, weight=lambda nu: 1.0) -> float:
    """int over the sphere of weight(nu) fn(nu) = 2 pi int_{-1}^{1} ... dnu, by quad on the float64 torch function."""
    f = lambda nu: 2.0 * math.pi * weight(nu) * float(fn(torch.tensor(nu, dtype=F64)))  # noqa: E731
    val, err = integrate.quad(f, -1.0, 1.0, points=PEAK_POINTS, limit=500, epsabs=1e-14, epsrel=1e-12)
    assert err < 1e-9
    return val


@pytest.mark.parametrize("g", G_VALUES)
@pytest.mark.parametrize("phase", [cornette_shanks_phase, henyey_greenstein_phase], ids=["cornette_shanks", "henyey_greenstein"])
def test_phase_normalised(phase, g):
    gt = torch.tensor(g, dtype=F64)
    assert _sphere_integral(lambda nu: phase(nu, gt)) == pytest.approx(1.0, rel=1e-9, abs=0)


def test_rayleigh_phase_normalised():
    assert _sphere_integral(rayleigh_phase) == pytest.approx(1.0, rel=1e-12, abs=0)


@pytest.mark.parametrize("g", G_VALUES)
def test_phase_mean_cosine(g):
    gt = torch.tensor(g, dtype=F64)
    hg = _sphere_integral(lambda nu: henyey_greenstein_phase(nu, gt), weight=lambda nu: nu)
    cs = _sphere_integral(lambda nu: cornette_shanks_phase(nu, gt), weight=lambda nu: nu)
    assert hg == pytest.approx(g, rel=1e-9, abs=1e-12)
    assert cs == pytest.approx(3.0 * g * (4.0 + g * g) / (5.0 * (2.0 + g * g)), rel=1e-9, abs=1e-12)


@pytest.mark.parametrize("dtype", [torch.float32, F64])
def test_cornette_shanks_at_g0_is_rayleigh_shaped(dtype):
    nu = torch.linspace(-1.0, 1.0, 101, dtype=dtype)
    expected = torch.from_numpy(3.0 / (16.0 * np.pi) * (1.0 + np.linspace(-1.0, 1.0, 101) ** 2)).to(dtype)
    torch.testing.assert_close(cornette_shanks_phase(nu, torch.tensor(0.0, dtype=dtype)), expected)
    torch.testing.assert_close(rayleigh_phase(nu), expected)
    torch.testing.assert_close(henyey_greenstein_phase(nu, torch.tensor(0.0, dtype=dtype)), torch.full_like(nu, 1.0 / (4.0 * math.pi)))


_PHASE_TOL = {torch.float32: dict(rtol=2e-5, atol=0.0), F64: dict(rtol=1e-13, atol=0.0)}


@pytest.mark.parametrize("dtype", [torch.float32, F64])
@pytest.mark.parametrize("g", G_VALUES + [0.8, -0.999])
def test_phase_formulas(g, dtype):
    """Against the textbook forms in numpy float64 (HG 1941; Cornette & Shanks 1992 eq. 4), incl. nu = 1 and g -> 1."""
    nu, gt = torch.tensor(np.concatenate([np.linspace(-1.0, 1.0, 41), [1.0 - 1e-6, -1.0 + 1e-6, 1.0]]), dtype=dtype), torch.tensor(g, dtype=dtype)
    # The expectation at the inputs as represented in ``dtype``; 1 + g^2 - 2 g nu exactly (rationals),
    # since in floating point it cancels at the peaks (g -> +-1, nu -> +-1).
    gq = Fraction(float(gt))
    nu_np = nu.double().numpy()
    k = np.array([float(1 + gq * gq - 2 * gq * Fraction(float(x))) for x in nu_np])
    g = float(gt)
    hg = (1 - g * g) / (4 * np.pi * k**1.5)
    cs = 3.0 / (8.0 * np.pi) * (1 - g * g) * (1 + nu_np**2) / ((2 + g * g) * k**1.5)
    torch.testing.assert_close(henyey_greenstein_phase(nu, gt).double(), torch.from_numpy(hg), **_PHASE_TOL[dtype])
    torch.testing.assert_close(cornette_shanks_phase(nu, gt).double(), torch.from_numpy(cs), **_PHASE_TOL[dtype])


# --------------------------------------------------------------------------
# Geometry
# --------------------------------------------------------------------------
def _roots(r: float, mu: float, radius: float):
    """Roots t1 <= t2 of t^2 + 2 r mu t + r^2 - radius^2 = 0 (stable form), or None."""
    b, c = r * mu, (r - radius) * (r + radius)
    disc = b * b - c
    if disc < 0:
        return None
    q = -(b + math.copysign(math.sqrt(disc), b))
    if q == 0.0:
        return (0.0, 0.0)
    return tuple(sorted((q, c / q)))


def _segment_np(r: float, mu: float):
    """(start, end, hits) of the ray inside the shell [R_BOTTOM, R_TOP]."""
    top = _roots(r, mu, R_TOP)
    if r > R_TOP and (top is None or top[0] < 0 or mu >= 0):
        return 0.0, 0.0, False
    start = top[0] if r > R_TOP else 0.0
    ground = _roots(r, mu, R_BOTTOM)
    hits = mu < 0 and ground is not None
    return start, (ground[0] if hits else top[1]), hits


def _geometry_cases():
    rs = [R_BOTTOM, R_BOTTOM + 1.0, R_BOTTOM + 5000.0, R_TOP - 1.0, R_TOP, R_TOP + 1e5, R_TOP + 1e6]
    cases = []
    for r in rs:
        mus = [1.0, 0.5, 0.01, 0.0, -0.01, -0.5, -1.0]
        for rad in (R_BOTTOM, R_TOP):
            if r > rad:  # just above and below the tangent to that sphere
                m = -math.sqrt(1.0 - (rad / r) ** 2)
                mus += [m + 1e-6, m - 1e-6]
        cases += [(r, mu) for mu in mus]
    return cases


GEOMETRY = _geometry_cases()


def test_atmosphere_segment_matches_closed_form():
    r = torch.tensor([c[0] for c in GEOMETRY], dtype=F64)
    mu = torch.tensor([c[1] for c in GEOMETRY], dtype=F64)
    start, end, hits = atmosphere_segment(r, mu, R_BOTTOM, R_TOP)
    exp = [_segment_np(*c) for c in GEOMETRY]
    assert hits.tolist() == [e[2] for e in exp]
    # Distances to 1e-12 relative, or 1e-6 m for the zero ones.
    torch.testing.assert_close(start, torch.tensor([e[0] for e in exp], dtype=F64), rtol=1e-12, atol=1e-6)
    torch.testing.assert_close(end, torch.tensor([e[1] for e in exp], dtype=F64), rtol=1e-12, atol=1e-6)
    assert bool((end > 0).any()) and bool((start > 0).any())


def test_distance_to_top_and_bottom_match_closed_form():
    inside = [(r, mu) for r, mu in GEOMETRY if r <= R_TOP]
    r = torch.tensor([c[0] for c in inside], dtype=F64)
    mu = torch.tensor([c[1] for c in inside], dtype=F64)
    torch.testing.assert_close(distance_to_top(r, mu, R_TOP), torch.tensor([_roots(*c, R_TOP)[1] for c in inside], dtype=F64), rtol=1e-12, atol=1e-6)
    hit = ray_hits_ground(r, mu, R_BOTTOM)
    exp_hit = [mu_ < 0 and _roots(r_, mu_, R_BOTTOM) is not None for r_, mu_ in inside]
    assert hit.tolist() == exp_hit
    d = distance_to_bottom(r, mu, R_BOTTOM)[hit]
    expected = torch.tensor([_roots(r_, mu_, R_BOTTOM)[0] for (r_, mu_), h in zip(inside, exp_hit) if h], dtype=F64)
    torch.testing.assert_close(d, expected, rtol=1e-12, atol=1e-6)


def test_geometry_float32_within_radius_rounding():
    """float32 distances agree with the float64 closed forms to the rounding of a 6.4e6 m radius (ulp 0.5 m)."""
    inside = [(r, mu) for r, mu in GEOMETRY if r <= R_TOP]
    r = torch.tensor([c[0] for c in inside], dtype=torch.float32)
    mu = torch.tensor([c[1] for c in inside], dtype=torch.float32)
    expected = torch.tensor([_roots(*c, R_TOP)[1] for c in inside], dtype=F64)
    # A distance to the top of ~1e5 m rounds to ~1e-2 m; near the horizon an error of
    # 0.5 m in r moves the far root by 0.5 m / |mu|-ish: 20 m bounds every case here.
    torch.testing.assert_close(distance_to_top(r, mu, R_TOP).double(), expected, rtol=1e-5, atol=20.0)


# --------------------------------------------------------------------------
# Radiance closed forms
# --------------------------------------------------------------------------
def _integrator(name: str, **kw):
    try:
        integrator_class(name)
    except (ModuleNotFoundError, AttributeError):
        pytest.skip(f"integrator module for {name!r} not implemented yet")
    return make_integrator(name, **kw)


@functools.lru_cache(maxsize=1)
def _earth():
    return load_atmosphere("earth", [440.0, 550.0, 680.0], dtype=F64)


def _vacuum():
    z = torch.zeros(3, dtype=F64)
    return _earth().replace(rayleigh_scattering=z, mie_scattering=z, mie_extinction=z, ozone_absorption=None)


RENDERED = [n for n in INTEGRATORS if n != "height_fog"]


@pytest.mark.parametrize("name", RENDERED)
def test_no_atmosphere_gives_direct_light_only(name):
    """beta = 0: no sky radiance, transmittance 1, the ground at albedo / pi E mu_s, the disc at E / (pi alpha^2)."""
    integ = _integrator(name)
    atm = _vacuum()
    alpha = atm.sun_angular_radius
    sz = math.radians(40.0)
    # From 5 km: up, horizon, onto the ground (straight down and slanted), and at the sun.
    th = torch.tensor([0.0, math.pi / 2, math.pi, math.radians(120.0), sz], dtype=F64)
    mu, mu_s = torch.cos(th), torch.full((5,), math.cos(sz), dtype=F64)
    dphi = torch.tensor([1.0, 2.0, 0.0, 0.0, 0.0], dtype=F64)
    nu = torch.clamp(mu * mu_s + torch.sin(th) * math.sin(sz) * torch.cos(dphi), -1.0, 1.0)
    r = torch.full((5,), R_BOTTOM + 5000.0, dtype=F64)
    out = single_scattering(atm, r, mu, mu_s, nu, integ, view_samples=16, rule="gauss", sun_disk=True)
    E, A = atm.solar_irradiance, atm.ground_albedo
    # Where a ray from (r, mu) meets the ground: the sun cosine there is (r mu_s + d nu) / R.
    expected = torch.zeros(5, 3, dtype=F64)
    for i in (2, 3):
        rr, m = float(r[i]), float(mu[i])
        d = -rr * m - math.sqrt(rr * rr * m * m - (rr - R_BOTTOM) * (rr + R_BOTTOM))
        mus_g = (rr * float(mu_s[i]) + d * float(nu[i])) / R_BOTTOM
        expected[i] = A / math.pi * E * mus_g
    expected[4] = E / (math.pi * alpha**2)
    torch.testing.assert_close(out, expected, rtol=1e-10, atol=1e-15)
    # And the transmittance to the sun is the visible fraction only: 1 well above the horizon.
    col = integ.prepare(atm.scale_heights, R_BOTTOM, R_TOP)
    t = transmittance_to_sun(col, atm, torch.tensor([R_BOTTOM, R_BOTTOM + 3e4], dtype=F64), torch.tensor([1.0, 0.1], dtype=F64))
    torch.testing.assert_close(t, torch.ones_like(t), rtol=0, atol=1e-15)


# Closed-form radiance accuracy per integrator (view: 64 Gauss nodes; quadrature families at 1024
# samples). Measured worst relative errors (zenith / nadir): trapezoid 1.0e-6 / 1.6e-6, midpoint
# 5.1e-7 / 7.8e-7, simpson 6.8e-11, gauss 1.5e-13, taylor 1.5e-13 (exact for vertical rays, d = 0:
# h is linear in t), spline 1.5e-13, bruneton_lut 1.6e-13 / 3.8e-6, chapman 3.3e-4 / 4.6e-4.
_CLOSED_FORM_SETTINGS = {"trapezoid": {"samples": 1024}, "midpoint": {"samples": 1024}, "simpson": {"samples": 1025}, "gauss": {"samples": 64}}
_CLOSED_FORM_RTOL = {
    "trapezoid": 5e-6,
    "midpoint": 3e-6,
    "simpson": 1e-9,
    "gauss": 1e-10,
    "taylor": 1e-9,
    "spline": 1e-6,
    "bruneton_lut": 2e-5,
    "chapman": 1e-3,
}


def _layer_column(H: float) -> float:
    """int_0^(top - R) exp(-h / H) dh: the vertical column of a layer. [m]"""
    return H * -math.expm1(-(R_TOP - R_BOTTOM) / H)


@pytest.mark.parametrize("name", RENDERED)
def test_zenith_view_with_zenith_sun_closed_form(name):
    """Ground, view and sun at the zenith: T(x,y) T(y,sun) = exp(-tau_vertical) for every y, so

    L = E exp(-tau) sum_i beta_i^s P_i(1) C_i,   C_i = H_i (1 - exp(-(top - R)/H_i)),  tau = sum_i beta_i^e C_i
    + k_O3 (top_O3 - bottom_O3) / 2 (the ozone tent's vertical column; it absorbs only).
    """
    integ = _integrator(name, **_CLOSED_FORM_SETTINGS.get(name, {}))
    atm = _earth()
    one = torch.ones(1, dtype=F64)
    out = single_scattering(atm, torch.full((1,), R_BOTTOM, dtype=F64), one, one, one, integ, view_samples=64, rule="gauss")
    c_r, c_m = _layer_column(float(atm.rayleigh_scale_height)), _layer_column(float(atm.mie_scale_height))
    g = float(atm.mie_g)
    p_r = 3.0 / (16.0 * math.pi) * 2.0
    p_m = 3.0 / (8.0 * math.pi) * (1 - g * g) * 2.0 / ((2 + g * g) * (1 - g) ** 3)
    b_r, b_ms, b_me = (t.numpy() for t in (atm.rayleigh_scattering, atm.mie_scattering, atm.mie_extinction))
    lo, _, hi = atm.ozone_layer_m
    tau = b_r * c_r + b_me * c_m + atm.ozone_absorption.numpy() * (hi - lo) / 2.0
    expected = atm.solar_irradiance.numpy() * np.exp(-tau) * (b_r * p_r * c_r + b_ms * p_m * c_m)
    torch.testing.assert_close(out[0], torch.from_numpy(expected), rtol=_CLOSED_FORM_RTOL[name], atol=0.0)


@pytest.mark.parametrize("name", RENDERED)
def test_nadir_from_space_rayleigh_only_closed_form(name):
    """From space, straight down, sun at the zenith behind the observer (nu = -1), Rayleigh only.

    The view and the sun column from y both equal the column above y, u(h) = exp(-h/H) - exp(-D/H)
    times H, so with tau = beta H (1 - exp(-D/H)) the in-scattering integral is exact:
        L = E P_R(-1) (1 - exp(-2 tau)) / 2  +  albedo / pi E exp(-2 tau).
    """
    integ = _integrator(name, **_CLOSED_FORM_SETTINGS.get(name, {}))
    z = torch.zeros(3, dtype=F64)
    atm = _earth().replace(mie_scattering=z, mie_extinction=z, ozone_absorption=None)
    one = torch.ones(1, dtype=F64)
    out = single_scattering(atm, torch.full((1,), R_TOP + 1e5, dtype=F64), -one, one, -one, integ, view_samples=64, rule="gauss")
    tau = atm.rayleigh_scattering.numpy() * _layer_column(float(atm.rayleigh_scale_height))
    E, A = atm.solar_irradiance.numpy(), atm.ground_albedo.numpy()
    expected = E * (3.0 / (16.0 * math.pi) * 2.0) * -np.expm1(-2.0 * tau) / 2.0 + A / math.pi * E * np.exp(-2.0 * tau)
    torch.testing.assert_close(out[0], torch.from_numpy(expected), rtol=_CLOSED_FORM_RTOL[name], atol=0.0)
