"""Ozone in the direct renderer: the exact tent column, its wiring, and the ``ozone_column`` fit parameter.

Expected values are independent of skyfit's code: adaptive ``scipy.integrate.quad`` of the
tent density along the ray in float64 (break points at the shell crossings, computed here
from the quadratic), closed forms of the tent's column along vertical rays, the nested
scipy single-scattering reference of tests/test_single_scattering_reference.py extended
with the ozone transmittance, Bruneton's precomputed tables (which always had ozone), and
recovery of a known column from a synthetic sky rendered from a config dict.
"""
from __future__ import annotations

import copy
import decimal
import math
from pathlib import Path

import numpy as np
import pytest
import torch
from scipy import integrate
from torch.testing import assert_close

import skyfit
from skyfit.atmosphere import atmosphere_from_config, load_atmosphere, load_yaml
from skyfit.camera import FisheyeCamera, render_fisheye
from skyfit.fit import FitError, FitOptions, FitProblem, Observation, Parameterisation, SkyModel, fit, make_loss
from skyfit.scattering import TableSizes, precompute, single_scattering, sky_radiance
from skyfit.scattering.hillaire import hillaire_lut, hillaire_multiple
from skyfit.scattering.single import transmittance_to_sun
from skyfit.transmittance import make_integrator, ozone_column
from skyfit.transmittance.ozone import asinh_minus_identity

from test_single_scattering_reference import SETTINGS, Reference, sphere_roots, unit  # the scipy reference

F64 = torch.float64
R = 6_360_000.0
R_TOP = 6_420_000.0
LAYER = (10_000.0, 25_000.0, 40_000.0)


# ------------------------------------------------------------------------------------------
# The column against scipy quad


def tent(h: float, layer=LAYER) -> float:
    lo, pk, hi = layer
    return max(0.0, min((h - lo) / (pk - lo), (hi - h) / (hi - pk), 1.0))


def column_quad(r: float, mu: float, length: float, layer=LAYER) -> float:
    """int_0^L tent(|x + t v| - R) dt by adaptive quad, break points at the shell crossings. [m]"""
    if length <= 0:
        return 0.0
    b = r * mu
    pts = [-b] if 0.0 < -b < length else []
    for h in layer:
        roots = sphere_roots(r * r, b, R + h)
        pts += [t for t in (roots or ()) if 0.0 < t < length]
    f = lambda t: tent(math.sqrt(max(r * r + 2.0 * b * t + t * t, 0.0)) - R, layer)  # noqa: E731
    val, err = integrate.quad(f, 0.0, length, points=sorted(pts) or None, epsabs=1e-9, epsrel=1e-13, limit=500)
    assert err < 1e-7 + 1e-10 * abs(val)
    return val


def _to_boundary(r: float, mu: float) -> float:
    """Distance to the ground (if the ray hits it) or to the top of the atmosphere. [m]"""
    ground = sphere_roots(r * r, r * mu, R)
    if mu < 0 and ground is not None and ground[0] >= 0:
        return ground[0]
    top = sphere_roots(r * r, r * mu, R_TOP)
    return max(top[1], 0.0)


def _column_cases() -> list[tuple[float, float, float]]:
    cases = []
    # from the ground, inside the layer, on its shells, above it and at the top; every kind of direction
    for alt in (0.0, 5e3, 10e3, 18e3, 25e3, 33e3, 40e3, 52e3, 60e3):
        for mu in (1.0, -1.0, 0.5, -0.5, 0.1, -0.1, 0.01, -0.01, 0.0, 1e-4, -1e-4, 0.999999):
            L = _to_boundary(R + alt, mu)  # to the ground (segments ending on it) or to the top
            cases += [(R + alt, mu, L), (R + alt, mu, 0.37 * L), (R + alt, mu, min(L, 1234.5))]
    # grazing rays tangent to each shell, and rays from space through the limb
    for h in LAYER:
        r = R + h + 3000.0
        cases.append((r, -math.sqrt(1.0 - ((R + h) / r) ** 2), 4e5))
    r_space = R_TOP + 100e3
    for mu in (-1.0, -0.95, -0.9, -0.8):
        cases.append((r_space, mu, 1.5e6 if mu > -0.9 else _to_boundary(r_space, mu)))
    rng = np.random.default_rng(0)
    for _ in range(150):
        r, mu = R + rng.uniform(0.0, 60e3), rng.uniform(-1.0, 1.0)
        cases.append((r, mu, min(rng.uniform(0.0, 8e5), _to_boundary(r, mu))))
    return cases


def test_column_matches_quad_float64():
    cases = _column_cases()
    expected = torch.tensor([column_quad(*c) for c in cases], dtype=F64)
    assert bool((expected > 1e3).sum() > 100) and bool((expected == 0).any())
    T = lambda i: torch.tensor([c[i] for c in cases], dtype=F64)  # noqa: E731
    got = ozone_column(T(0), T(1), T(2), R, LAYER)
    assert_close(got, expected, rtol=1e-10, atol=1e-7)


# float32 tolerance: the inputs are rounded to float32 first (r to ~0.5 m, mu to 6e-8) and the
# reference evaluated at those rounded values; the rest is the closed form's own rounding
# (measured max 4e-5 relative of max(column, 1 m) on these cases).
DTYPE_TOL = {torch.float64: (1e-10, 1e-7), torch.float32: (2e-4, 2e-4)}


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_column_dtypes(dtype):
    cases = [tuple(float(np.float32(x)) if dtype == torch.float32 else x for x in c) for c in _column_cases()[::3]]
    expected = torch.tensor([column_quad(*c) for c in cases], dtype=F64)
    T = lambda i: torch.tensor([c[i] for c in cases], dtype=dtype)  # noqa: E731
    got = ozone_column(T(0), T(1), T(2), R, LAYER)
    assert got.dtype == dtype
    rtol, atol_rel = DTYPE_TOL[dtype]
    err = (got.double() - expected).abs() / expected.clamp_min(1.0)
    assert float(err.max()) < rtol + atol_rel, float(err.max())


def test_bad_layer_is_refused():
    one = torch.ones(1, dtype=F64)
    with pytest.raises(ValueError, match=r"bottom < peak < top, got \(25000.0, 10000.0, 40000.0\)"):
        ozone_column(one * R, one, one, R, (25e3, 10e3, 40e3))


def test_vertical_columns_closed_form():
    """Vertical rays: the tent's integral in altitude, (top - bottom) / 2 through the whole layer."""
    lo, pk, hi = LAYER
    r = torch.tensor([R, R, R + 18e3, R + 30e3, R_TOP, R_TOP], dtype=F64)
    mu = torch.tensor([1.0, 1.0, 1.0, -1.0, -1.0, -1.0], dtype=F64)
    L = torch.tensor([R_TOP - R, 30e3, 2e3, 30e3, R_TOP - R, 35e3], dtype=F64)
    rise = lambda a, b: ((a - lo) + (b - lo)) / 2 * (b - a) / (pk - lo)  # noqa: E731  int_a^b of the rising side
    fall = lambda a, b: ((hi - a) + (hi - b)) / 2 * (b - a) / (hi - pk)  # noqa: E731
    expected = torch.tensor([
        (hi - lo) / 2,
        rise(lo, pk) + fall(pk, 30e3),
        rise(18e3, 20e3),
        rise(lo, pk) + fall(pk, 30e3),
        (hi - lo) / 2,
        fall(pk, hi),  # 60 km down to 25 km: the falling side only
    ], dtype=F64)
    got = ozone_column(r, mu, L, R, LAYER)
    assert_close(got, expected, rtol=1e-12, atol=1e-9)


def test_asinh_minus_identity_series_and_direct_agree():
    z = torch.tensor([-0.5, -0.1, -0.0999999, -1e-3, -1e-8, 0.0, 1e-8, 1e-3, 0.0999999, 0.1, 0.27, 3.0], dtype=F64)
    with decimal.localcontext() as ctx:  # 60-digit asinh(z) - z = ln(z + sqrt(z^2 + 1)) - z
        ctx.prec = 60
        ref = [(lambda d: (d + (d * d + 1).sqrt()).ln() - d)(decimal.Decimal(v)) for v in z.tolist()]
    expected = torch.tensor([float(v) for v in ref], dtype=F64)
    assert_close(asinh_minus_identity(z), expected, rtol=1e-13, atol=1e-300)


def _grad_rows():
    tangent = R + 25e3 + 3000.0
    rows = [
        (R, 1.0, 60e3),  # vertical up from the ground (c = 0)
        (R + 30e3, -1.0, 30e3),  # vertical down to the ground
        (R, 0.0, 8e5),  # horizontal from the ground
        (R + 18e3, 0.0, 5e5),  # horizontal inside the layer (perigee inside: u1 u2 < 0 pieces)
        (tangent, -math.sqrt(1.0 - ((R + 24e3) / tangent) ** 2), 2e5),  # perigee 1 km below the peak shell
        (R + 5e4, -0.3, 1e5),  # from above the layer, down into it
        (R + 20e3, 0.3, 1e5),
        (R + 13e3, -0.05, 3e5),  # ends on the ground side of the layer
        (R_TOP, -0.2, _to_boundary(R_TOP, -0.2)),  # from the top to the ground
        (R + 7e3, 0.999, 2e4),
    ]
    return rows


def test_gradcheck_wrt_r_mu_length_and_layer():
    """float64 gradcheck at the singular points (c = 0, horizontal, perigee inside the layer, ground-ending).

    Variables are scaled to km so that gradcheck's finite-difference step is meaningful."""
    rows = _grad_rows()
    alt = torch.tensor([(a[0] - R) / 1e3 for a in rows], dtype=F64, requires_grad=True)
    mu = torch.tensor([a[1] for a in rows], dtype=F64, requires_grad=True)
    L = torch.tensor([a[2] / 1e3 for a in rows], dtype=F64, requires_grad=True)
    layer = [torch.tensor(v / 1e3, dtype=F64, requires_grad=True) for v in LAYER]

    def f(alt, mu, L, lo, pk, hi):
        return ozone_column(R + alt * 1e3, mu, L * 1e3, R, (lo * 1e3, pk * 1e3, hi * 1e3)) / 1e3

    assert torch.autograd.gradcheck(f, (alt, mu, L, *layer), eps=1e-6, atol=1e-5, rtol=1e-4)


def test_gradient_at_a_tangent_to_the_peak_shell():
    """Tangent to the tent's kink the column's second derivative in r is singular (~ 1/sqrt of the
    perigee's distance to the shell), so central differences converge like sqrt(step); they approach the
    autograd value, which is exact (the detached split points carry no gradient by continuity)."""
    tangent = R + 28e3
    mu = torch.tensor(-math.sqrt(1.0 - ((R + 25e3) / tangent) ** 2), dtype=F64)
    L = torch.tensor(2e5, dtype=F64)
    r = torch.tensor(tangent, dtype=F64, requires_grad=True)
    (g,) = torch.autograd.grad(ozone_column(r, mu, L, R, LAYER), r)
    col = lambda x: float(ozone_column(torch.tensor(x, dtype=F64), mu, L, R, LAYER))  # noqa: E731
    errs = [abs((col(tangent + e) - col(tangent - e)) / (2 * e) - float(g)) for e in (1e-1, 1e-2, 1e-3, 1e-4)]
    assert all(b < a for a, b in zip(errs, errs[1:])), errs  # converging to autograd's value
    assert errs[-1] < 1e-3 * abs(float(g)), errs


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_gradients_finite_everywhere(dtype):
    """No NaN or inf gradients at c = 0, the horizon, tangents, zero-length segments, starts on a shell."""
    r = torch.tensor([R, R, R + 25e3, R + 40e3, R + 10e3, R_TOP, R + 25e3], dtype=dtype, requires_grad=True)
    mu = torch.tensor([1.0, 0.0, 0.0, 1.0, -1.0, -1.0, 0.3], dtype=dtype, requires_grad=True)
    L = torch.tensor([0.0, 8e5, 3e5, 1e4, 1e4, 60e3, 0.0], dtype=dtype, requires_grad=True)
    ozone_column(r, mu, L, R, LAYER).sum().backward()
    for g in (r.grad, mu.grad, L.grad):
        assert bool(torch.isfinite(g).all()), g


# ------------------------------------------------------------------------------------------
# The renderer with ozone against the scipy reference


class OzoneReference(Reference):
    """The independent reference with the ozone transmittance exp(-k_O3 * quad column) on every path."""

    def __init__(self, atm):
        super().__init__(atm)
        self.k = atm.ozone_absorption.detach().cpu().double().numpy()
        self.layer = tuple(float(v) for v in atm.ozone_layer_m)

    def transmittance(self, p, d, length):
        r = math.sqrt(float(p @ p))
        mu = float(p @ d) / r
        return super().transmittance(p, d, length) * np.exp(-self.k * column_quad(r, mu, length, self.layer))


def _reference_cases():
    s = lambda z: unit(z, 0.0)  # noqa: E731
    return {
        "ground": [(R, unit(z, a), s(sz)) for sz, z, a in ((0.0, 0.0, 0.0), (60.0, 45.0, 170.0), (60.0, 89.5, 10.0),
                                                         (85.0, 70.0, 0.0), (85.0, 89.9, 180.0), (85.0, 95.0, 20.0))],
        "5km": [(R + 5000.0, unit(z, a), s(30.0)) for z, a in ((120.0, 180.0), (92.0, 150.0))],
        "space": [(R_TOP + 100e3, unit(z, 0.0), s(sz)) for z, sz in ((170.0, 30.0), (160.0, 85.0))],
        "night": [(R + 1000.0, unit(45.0, 0.0), s(96.0))],
    }


@pytest.fixture(scope="module")
def earth3():
    return load_atmosphere("earth", [440.0, 550.0, 600.0], dtype=F64)


@pytest.mark.parametrize("group", ["ground", "5km", "space", "night"])
def test_single_scattering_with_ozone_matches_scipy_reference(earth3, group):
    cases = _reference_cases()[group]
    expected = torch.tensor(np.array([OzoneReference(earth3).radiance(r, v, s) for r, v, s in cases]))
    T = lambda x: torch.tensor(x, dtype=F64)  # noqa: E731
    r, mu = T([c[0] for c in cases]), T([float(c[1][2]) for c in cases])
    mu_s, nu = T([float(c[2][2]) for c in cases]), T([float(c[1] @ c[2]) for c in cases])
    n_view, n_int = SETTINGS[group]
    got = single_scattering(earth3, r, mu, mu_s, nu, make_integrator("gauss", samples=n_int), view_samples=n_view,
                            rule="gauss", chunk_bytes=8e6)
    assert_close(got, expected, rtol=1e-4, atol=1e-14)
    # and ozone matters here: without it the radiance at 600 nm is off by far more than the tolerance
    no_o3 = single_scattering(earth3.replace(ozone_absorption=None), r, mu, mu_s, nu,
                              make_integrator("gauss", samples=n_int), view_samples=n_view, rule="gauss")
    assert float(((no_o3 - expected).abs() / expected.clamp_min(1e-30))[:, 2].max()) > 1e-2


def test_sun_transmittance_is_exp_of_the_vertical_ozone_column(earth3):
    """Sun at the zenith from the ground: T_sun(ozone) / T_sun(no ozone) = exp(-k (top - bottom) / 2)."""
    gauss = make_integrator("gauss", samples=64).prepare(earth3.scale_heights, R, R_TOP)
    r, mu_s = torch.tensor([R], dtype=F64), torch.tensor([1.0], dtype=F64)
    ratio = transmittance_to_sun(gauss, earth3, r, mu_s) / transmittance_to_sun(gauss, earth3.replace(ozone_absorption=None), r, mu_s)
    assert_close(ratio[0], torch.exp(-earth3.ozone_absorption * 15_000.0), rtol=1e-12, atol=0.0)
    # 300 DU: vertical optical depth ~0.03 at 600 nm (Chappuis band)
    assert 0.02 < float(earth3.ozone_absorption[2] * 15_000.0) < 0.04


# ------------------------------------------------------------------------------------------
# Consistency with the multiple-scattering code (which always had ozone)


def _dirs(vz_deg, az_deg, sun_deg):
    v, a, s = torch.deg2rad(vz_deg), torch.deg2rad(az_deg), math.radians(sun_deg)
    mu = torch.cos(v)
    nu = torch.sin(v) * math.sin(s) * torch.cos(a) + mu * math.cos(s)
    return mu, torch.full_like(mu, math.cos(s)), nu


# max |table - direct| / (per-wavelength peak) at these sizes (440/550/600 nm), measured with ozone
# in both [sun 0, 60, 85, 90]: .0084 .0059 .018 .053 (the tables' resolution error: the same as without
# ozone on both sides, tests/test_multiple.py); with ozone only in the tables (the renderer before
# this change): .045 .083 .36 .58, dominated by 550-600 nm.
BRUNETON_BOUNDS = {0: 0.013, 60: 0.011, 85: 0.028, 90: 0.075}


@pytest.fixture(scope="module")
def bruneton_single(earth3):
    sizes = TableSizes(transmittance_mu=128, transmittance_r=32, irradiance_mu_s=16, irradiance_r=4,
                       scattering_r=8, scattering_mu=32, scattering_mu_s=16, scattering_nu=8)
    return precompute(earth3, orders=1, sizes=sizes)


@pytest.mark.parametrize("sun_zenith", [0, 60, 85, 90])
def test_direct_single_scattering_with_ozone_matches_bruneton_tables(earth3, bruneton_single, sun_zenith):
    vz = torch.tensor([0, 15, 30, 45, 60, 70, 80, 85, 88, 89.5], dtype=F64)
    az = torch.tensor([0, 60, 120, 180.0], dtype=F64)
    V, A = torch.meshgrid(vz, az, indexing="ij")
    mu, mu_s, nu = (t.reshape(-1) for t in _dirs(V, A, sun_zenith))
    r = torch.full_like(mu, R)
    tab = sky_radiance(bruneton_single, None, r, mu, mu_s, nu, ground=False)
    gauss = make_integrator("gauss", samples=64)
    # the tables' own outer rule (2017: 50 trapezoid intervals) isolates their resolution error
    direct = single_scattering(earth3, r, mu, mu_s, nu, gauss, view_samples=51, rule="trapezoid", ground=False)
    no_o3 = single_scattering(earth3.replace(ozone_absorption=None), r, mu, mu_s, nu, gauss, view_samples=51,
                              rule="trapezoid", ground=False)
    peak = direct.max(0).values
    err = float(((tab - direct).abs() / peak).max())
    err_without = float(((tab - no_o3).abs() / peak).max())
    assert err < BRUNETON_BOUNDS[sun_zenith], err
    assert err_without > 3 * err, (err, err_without)


def test_hillaire_multiple_term_sees_ozone_on_the_view_path(earth3):
    """Zenith ray from the ground, one midpoint sample at 30 km, same LUT: the ozone atmosphere's
    multiple term is the ozone-free one times exp(-k column(0-30 km)), closed form 11666.67 m."""
    lut = hillaire_lut(earth3, size=(4, 4), directions=8, samples=4)
    one = torch.ones(1, dtype=F64)
    args = (torch.full((1,), R, dtype=F64), one, one * 0.5, one * 0.5, make_integrator("gauss", samples=32))
    with_o3 = hillaire_multiple(earth3, *args, view_samples=1, rule="midpoint", lut=lut)
    without = hillaire_multiple(earth3.replace(ozone_absorption=None), *args, view_samples=1, rule="midpoint", lut=lut)
    lo, pk, hi = LAYER
    col = (pk - lo) / 2 + (5e3 * ((hi - pk) + (hi - 30e3)) / 2) / (hi - pk)
    assert_close(with_o3 / without, torch.exp(-earth3.ozone_absorption * col).unsqueeze(0), rtol=1e-12, atol=0.0)


# ------------------------------------------------------------------------------------------
# The fit parameter


def _config(**ozone) -> dict:
    cfg = copy.deepcopy(load_yaml(Path(skyfit.__file__).parent / "configs" / "earth.yaml"))
    cfg["ozone"].update(ozone)
    return cfg


FIT_LAM = [450.0, 500.0, 550.0, 600.0, 650.0, 700.0]


def test_parameterisation_scales_ozone_absorption_linearly():
    base = atmosphere_from_config(_config(), FIT_LAM)
    p = Parameterisation(base, ["ozone_column"])
    assert p.defaults["ozone_column"] == pytest.approx(300.0, rel=1e-12)
    truth = atmosphere_from_config(_config(column_du=410.0), FIT_LAM)  # the config's own DU -> absorption
    a = p.atmosphere(p.to_physical(p.to_unconstrained({"ozone_column": 410.0})))
    assert_close(a.ozone_absorption, truth.ozone_absorption, rtol=1e-12, atol=0.0)
    x = p.initial_vector().requires_grad_(True)
    assert torch.autograd.gradcheck(lambda x: p.atmosphere(p.to_physical(x)).ozone_absorption, (x,))


def test_ozone_column_free_without_ozone_is_a_one_line_fit_error():
    base = load_atmosphere("mars", FIT_LAM)
    with pytest.raises(FitError, match=r"ozone_column is free but config 'mars' has no ozone") as e:
        Parameterisation(base, ["ozone_column", "exposure"])
    assert "\n" not in str(e.value)
    # not free: a config without ozone still fits, and the report says 0 DU
    p = Parameterisation(base, ["exposure"])
    assert p.physical_dict(p.initial_vector())["ozone_column"] == 0.0
    assert p.atmosphere(p.to_physical(p.initial_vector())).ozone_absorption is None


def test_recovers_the_ozone_column_from_a_synthetic_spectral_sky():
    """380 DU sky (rendered from the config dict), sun at 75 deg, ~300 directions, 1 % noise;
    the fit starts from the config's 300 DU with the aerosol and exposure free too."""
    integ = make_integrator("gauss", samples=16)
    truth = atmosphere_from_config(_config(column_du=380.0), FIT_LAM)
    img = render_fisheye(truth, FisheyeCamera(20), 75.0, 140.0, integ, view_samples=16)
    clean = 1.2 * img.spectral[img.valid]
    gen = torch.Generator().manual_seed(7)
    noisy = clean * (1 + 0.01 * torch.randn(clean.shape, generator=gen, dtype=clean.dtype))
    view, _ = img.camera.pixel_vectors(F64)
    n = int(img.valid.sum())
    assert 250 <= n <= 400
    obs = Observation("oz", "synthetic ozone", "spectral", view[img.valid], torch.tensor(math.radians(75.0), dtype=F64),
                      torch.tensor(math.radians(140.0), dtype=F64), noisy, 0.01 * clean,
                      torch.ones(n, dtype=torch.bool), tuple(f"L{x:g}" for x in FIT_LAM), torch.tensor(FIT_LAM))
    base = atmosphere_from_config(_config(), FIT_LAM)
    param = Parameterisation(base, ["ozone_column", "mie_beta_550", "exposure"])
    problem = FitProblem(param, SkyModel(integ, view_samples=16), [obs], make_loss("squared"))
    res = fit(problem, FitOptions(starts=1))
    assert res.parameters["ozone_column"] == pytest.approx(380.0, rel=0.05)
    assert res.parameters["exposure"] == pytest.approx(1.2, rel=0.02)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_matches_cpu():
    cases = _column_cases()[::5]
    T = lambda i, dev: torch.tensor([c[i] for c in cases], dtype=F64, device=dev)  # noqa: E731
    cpu = ozone_column(T(0, "cpu"), T(1, "cpu"), T(2, "cpu"), R, LAYER)
    gpu = ozone_column(T(0, "cuda"), T(1, "cuda"), T(2, "cuda"), R, LAYER)
    assert gpu.device.type == "cuda"
    assert_close(gpu.cpu(), cpu, rtol=1e-12, atol=1e-9)
