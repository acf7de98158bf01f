"""Gałaj 2021 spline optical depth (skyfit/transmittance/spline.py) against independent references.

References: scipy.integrate.quad in float64 (epsrel 1e-10) of the defining
integral int_0^L exp(-(sqrt(r^2 + 2 r mu s + s^2) - R_b)/H) ds, written here
from the definition; closed-form integrals of polynomials and exponentials;
scipy's CubicSpline (natural) and Akima1DInterpolator for the spline kinds;
torch.autograd.gradcheck for gradients. Tolerances are the errors measured at
the stated grid (docs/spline.md, scripts/spline_accuracy.py) times ~1.5.
"""
from __future__ import annotations

import functools
import math

import numpy as np
import pytest
import torch
from scipy.integrate import quad
from torch.autograd import gradcheck

from skyfit.transmittance import make_integrator
from skyfit.transmittance.spline import (
    SPLINE_KINDS,
    SplineOpticalDepth,
    _exp_hermite_right_integral,
    _phi,
    evaluate_uniform_spline,
    integrate_uniform_spline,
)

torch.set_num_threads(2)

F64 = torch.float64
R_B, R_T = 6_360_000.0, 6_420_000.0
SCALE_HEIGHTS = (8000.0, 1200.0)  # Rayleigh and Mie [m]

# Max relative error on the CASES grid at the default 50 x 20 grid (smooth, log space,
# Catmull-Rom rows), per kind and per layer (H = 8000, 1200): measured x ~1.5.
MAX_REL_ERR = {
    "linear": (1.5e-3, 7.0e-3),  # measured 9.6e-4, 4.7e-3
    "natural_cubic": (6.5e-5, 5.0e-4),  # 4.3e-5, 3.2e-4
    "catmull_rom": (9.0e-5, 7.0e-4),  # 6.1e-5, 4.6e-4
    "hermite": (7.0e-6, 3.0e-4),  # 4.5e-6, 2.0e-4
    "akima": (7.0e-6, 3.0e-4),  # 4.5e-6, 2.0e-4
    "monotone_hermite": (9.0e-5, 7.0e-4),  # 6.1e-5, 4.6e-4
}


# --------------------------------------------------------------------------
# Independent reference
# --------------------------------------------------------------------------
def quad_column(r: float, mu: float, length: float, h: float) -> float:
    """The defining integral by scipy quad (float64), with the lowest point as a break point."""
    if length <= 0.0:
        return 0.0

    def f(s: float) -> float:
        rho = math.sqrt(max(r * r + 2.0 * r * mu * s + s * s, 0.0))
        return math.exp(-(rho - R_B) / h)

    pts = [p for p in (-r * mu,) if 0.0 < p < length]
    if pts:
        w = math.sqrt(2.0 * r * h)  # width of the peak about the lowest point
        pts += [p for p in (pts[0] - 3 * w, pts[0] + 3 * w) if 0.0 < p < length]
    val, _ = quad(f, 0.0, length, epsrel=1e-10, epsabs=0.0, limit=1000, points=sorted(pts) or None)
    return val


def length_to_boundary(r: float, mu: float) -> float:
    """Distance to the ground (if the ray meets it) or the top, float64 (Bruneton 2017 eqs.)."""
    disc_b = r * r * (mu * mu - 1.0) + R_B * R_B
    if mu < 0.0 and disc_b >= 0.0:
        return max(-r * mu - math.sqrt(disc_b), 0.0)
    return max(-r * mu + math.sqrt(max(r * r * (mu * mu - 1.0) + R_T * R_T, 0.0)), 0.0)


def _cases() -> list[tuple[float, float, float]]:
    """(r, mu, L): radii at and near both boundaries, mu at the poles, horizon and +-1e-6,
    segments to the ground or the top, half way, and a 1 km segment."""
    radii = (R_B, R_B + 1.0, R_B + 1000.0, R_B + 20_000.0, R_T - 1.0, R_T)
    mus = (1.0, 0.5, 0.1, 1e-6, 0.0, -1e-6, -0.1, -0.5, -1.0)
    out = []
    for r in radii:
        mu_h = -math.sqrt(max(1.0 - (R_B / r) ** 2, 0.0))  # the geometric horizon
        for mu in mus + ((mu_h, mu_h + 1e-6) if mu_h < 0 else ()):
            full = length_to_boundary(r, mu)
            for length in {full, 0.5 * full, min(1000.0, full)}:
                out.append((r, mu, length))
    return out


CASES = _cases()


@functools.lru_cache(maxsize=1)
def _reference() -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    r, mu, length = (torch.tensor(v, dtype=F64) for v in zip(*CASES))
    ref = torch.tensor([[quad_column(*c, h) for h in SCALE_HEIGHTS] for c in CASES], dtype=F64)
    return r, mu, length, ref


def _rel_err(col: torch.Tensor, ref: torch.Tensor) -> torch.Tensor:
    """Relative error per case and layer; zero-length segments must be exactly 0."""
    zero = ref == 0
    assert bool((col[zero] == 0).all()), col[zero]
    return torch.where(zero, torch.zeros_like(ref), (col - ref).abs() / torch.where(zero, torch.ones_like(ref), ref))


def _columns(integ, r, mu, length, dtype=F64):
    h = torch.tensor(SCALE_HEIGHTS, dtype=dtype)
    return integ.prepare(h, R_B, R_T)(r.to(dtype), mu.to(dtype), length.to(dtype))


# --------------------------------------------------------------------------
# Accuracy against quad
# --------------------------------------------------------------------------
@pytest.mark.parametrize("kind", SPLINE_KINDS)
def test_matches_quad_at_default_grid(kind):
    r, mu, length, ref = _reference()
    err = _rel_err(_columns(SplineOpticalDepth(kind=kind), r, mu, length), ref)
    worst = err.amax(0)
    for k, tol in enumerate(MAX_REL_ERR[kind]):
        assert float(worst[k]) < tol, (kind, SCALE_HEIGHTS[k], float(worst[k]), CASES[int(err[:, k].argmax())])


def test_error_decreases_as_grid_refines():
    r, mu, length, ref = _reference()
    worst = []
    for n, m in ((20, 10), (50, 20), (100, 40), (200, 80)):
        worst.append(_rel_err(_columns(SplineOpticalDepth(height_points=n, distance_points=m), r, mu, length), ref).amax(0))
    for coarse, fine in zip(worst, worst[1:]):
        assert bool((fine < coarse).all()), worst
    # measured at 200 x 80: 3.6e-6 (H = 8 km), 2.4e-5 (H = 1.2 km); at 50 x 20: 4.3e-5, 3.2e-4
    assert bool((worst[-1] < torch.tensor([5e-6, 3.5e-5], dtype=F64)).all()), worst[-1]


def test_paper_grid_is_worse_and_smooth_grid_fixes_it():
    """The literal Sec. IV.E layout (values, bilinear) against the default: the deviations pay off."""
    r, mu, length, ref = _reference()
    paper = SplineOpticalDepth(grid="paper", space="values", distance_interp="linear")
    err_paper = _rel_err(_columns(paper, r, mu, length), ref).amax(0)
    err_smooth = _rel_err(_columns(SplineOpticalDepth(), r, mu, length), ref).amax(0)
    assert bool(torch.isfinite(err_paper).all())
    assert bool((err_smooth * 100 < err_paper).all()), (err_smooth, err_paper)


def test_float32_agrees_with_float64():
    r, mu, length, ref = _reference()
    integ = SplineOpticalDepth()
    c64 = _columns(integ, r, mu, length)
    c32 = _columns(integ, r, mu, length, dtype=torch.float32)
    assert c32.dtype == torch.float32
    # F(t1) - F(t0) loses eps_32 * F / column: sub-millimetre segments at r = 6.4e6 m come out 0
    # (t0 + L rounds to t0), a 5 m one to 1.5e-3; above 10 m 3.1e-5 (torch 2.13, this CPU)
    # and 6.6e-5 (torch 2.11 on another x86 CPU): float32 rounding depends on the build.
    rel = (c32.double() - c64).abs() / c64.clamp_min(1e-300)
    assert float(rel[c64 > 1.0].max()) < 2.5e-3, float(rel[c64 > 1.0].max())
    assert float(rel[c64 > 10.0].max()) < 2e-4, float(rel[c64 > 10.0].max())
    assert bool(torch.isfinite(c32).all()) and bool((c32 >= 0).all())


def test_zero_length_is_exactly_zero_and_its_derivative_is_the_density():
    integ = SplineOpticalDepth()
    h = torch.tensor(SCALE_HEIGHTS, dtype=F64)
    r = torch.tensor([R_B, R_B + 3000.0, R_T], dtype=F64)
    mu = torch.tensor([0.3, -0.2, 0.0], dtype=F64)
    length = torch.zeros(3, dtype=F64, requires_grad=True)
    col = integ.prepare(h, R_B, R_T)(r, mu, length)
    assert bool((col == 0).all())
    (grad,) = torch.autograd.grad(col[:, 1].sum(), length)
    torch.testing.assert_close(grad, torch.exp(-(r - R_B) / h[1]), rtol=2e-3, atol=0.0)


# --------------------------------------------------------------------------
# Gradients
# --------------------------------------------------------------------------
def test_values_and_gradients_finite_on_the_case_grid():
    r, mu, length, _ = _reference()
    h = torch.tensor(SCALE_HEIGHTS, dtype=F64, requires_grad=True)
    r, mu, length = (x.clone().requires_grad_(True) for x in (r, mu, length))
    col = SplineOpticalDepth().prepare(h, R_B, R_T)(r, mu, length)
    grads = torch.autograd.grad(col.sum(), (r, mu, length, h))
    assert bool(torch.isfinite(col).all())
    for g in grads:
        assert bool(torch.isfinite(g).all())
    assert bool((grads[3] > 0).all())  # thicker layers hold more air: gradients reach H


@pytest.mark.parametrize("kind", ["natural_cubic", "akima"])
def test_gradcheck_wrt_scale_heights(kind):
    """Through the tables built in prepare(): H in km so that gradcheck's step is relative."""
    r = torch.tensor([R_B, R_B + 2000.0, R_B + 10_000.0, R_T - 5000.0], dtype=F64)
    mu = torch.tensor([0.7, -0.3, 0.02, -0.05], dtype=F64)
    length = torch.tensor([50_000.0, 6000.0, 300_000.0, 100_000.0], dtype=F64)
    h_km = torch.tensor([8.0, 1.2], dtype=F64, requires_grad=True)
    integ = SplineOpticalDepth(kind=kind)

    def f(h_km):
        return integ.prepare(h_km * 1e3, R_B, R_T)(r, mu, length)

    assert gradcheck(f, (h_km,), eps=1e-6, atol=1e-6, rtol=1e-5)


def test_gradcheck_wrt_geometry():
    """r (as altitude in km), view angle, length (km) at comfortable points of both regions and the blend."""
    alt = torch.tensor([1.5, 3.0, 0.2, 30.0], dtype=F64, requires_grad=True)
    theta = torch.tensor([70.0, 95.0, 88.9, 120.0], dtype=F64).deg2rad().requires_grad_(True)
    length = torch.tensor([40.0, 30.0, 200.0, 20.0], dtype=F64, requires_grad=True)
    fn = SplineOpticalDepth().prepare(torch.tensor(SCALE_HEIGHTS, dtype=F64), R_B, R_T)

    def f(alt, theta, length):
        return fn(R_B + alt * 1e3, torch.cos(theta), length * 1e3)

    assert gradcheck(f, (alt, theta, length), eps=1e-6, atol=1e-6, rtol=1e-4)


# --------------------------------------------------------------------------
# What each spline kind reproduces exactly (index units, nodes 0..N-1)
# --------------------------------------------------------------------------
N_NODES = 9
Q = torch.arange(N_NODES, dtype=F64)
A = torch.tensor([0.0, 0.3, 2.5, 1.0, 7.9], dtype=F64)
B = torch.tensor([8.0, 4.4, 2.75, 7.0, 8.0], dtype=F64)


def _poly_integral(c: list[float], a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """∫_a^b sum_k c_k q^k dq, closed form."""
    return sum(ck * (b ** (k + 1) - a ** (k + 1)) / (k + 1) for k, ck in enumerate(c))


@pytest.mark.parametrize("kind", SPLINE_KINDS)
def test_every_kind_integrates_linear_functions_exactly(kind):
    c = [1.5, -0.25]
    y = c[0] + c[1] * Q
    torch.testing.assert_close(integrate_uniform_spline(y, kind, A, B), _poly_integral(c, A, B), rtol=1e-13, atol=1e-13)


@pytest.mark.parametrize("kind", SPLINE_KINDS)
def test_log_space_integrates_exponentials_exactly(kind):
    """space="log": every kind reproduces y = 3 exp(-0.7 q) (as for vertical rays), in closed form."""
    y = 3.0 * torch.exp(-0.7 * Q)
    expected = 3.0 / 0.7 * (torch.exp(-0.7 * A) - torch.exp(-0.7 * B))
    torch.testing.assert_close(integrate_uniform_spline(y, kind, A, B, space="log"), expected, rtol=1e-13, atol=0.0)


def test_hermite_integrates_cubics_exactly():
    """Fourth-order finite-difference tangents are exact for cubics, so is the Hermite cubic."""
    c = [0.5, -1.0, 0.3, -0.04]
    y = sum(ck * Q**k for k, ck in enumerate(c))
    torch.testing.assert_close(integrate_uniform_spline(y, "hermite", A, B), _poly_integral(c, A, B), rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("kind", ["catmull_rom", "akima"])
def test_quadratic_exact_kinds(kind):
    """Central-difference tangents are exact for quadratics: Catmull-Rom between nodes 1 and N-2
    (its end tangents are one-sided), Akima everywhere (his slope extension is exact for them)."""
    c = [2.0, -0.5, 0.125]
    y = sum(ck * Q**k for k, ck in enumerate(c))
    a, b = (A, B) if kind == "akima" else (A.clamp(1, N_NODES - 2), B.clamp(1, N_NODES - 2))
    torch.testing.assert_close(integrate_uniform_spline(y, kind, a, b), _poly_integral(c, a, b), rtol=1e-12, atol=1e-12)


def test_natural_cubic_matches_scipy():
    from scipy.interpolate import CubicSpline

    y = torch.tensor([0.0, 1.0, 0.5, 2.0, 2.5, 1.0, -1.0, 0.0, 3.0], dtype=F64)
    ref = CubicSpline(Q.numpy(), y.numpy(), bc_type="natural")
    expected = torch.tensor([float(ref.integrate(a, b)) for a, b in zip(A.tolist(), B.tolist())], dtype=F64)
    torch.testing.assert_close(integrate_uniform_spline(y, "natural_cubic", A, B), expected, rtol=1e-12, atol=1e-12)
    qs = torch.linspace(0, N_NODES - 1, 101, dtype=F64)
    torch.testing.assert_close(evaluate_uniform_spline(y, "natural_cubic", qs), torch.from_numpy(ref(qs.numpy())), rtol=1e-12, atol=1e-12)


def test_akima_matches_scipy():
    from scipy.interpolate import Akima1DInterpolator

    y = torch.tensor([0.0, 1.0, 0.5, 2.0, 2.5, 1.0, -1.0, 0.0, 3.0], dtype=F64)
    ref = Akima1DInterpolator(Q.numpy(), y.numpy(), method="akima")
    expected = torch.tensor([float(ref.integrate(a, b)) for a, b in zip(A.tolist(), B.tolist())], dtype=F64)
    torch.testing.assert_close(integrate_uniform_spline(y, "akima", A, B), expected, rtol=1e-12, atol=1e-12)
    qs = torch.linspace(0, N_NODES - 1, 101, dtype=F64)
    torch.testing.assert_close(evaluate_uniform_spline(y, "akima", qs), torch.from_numpy(ref(qs.numpy())), rtol=1e-12, atol=1e-12)


def test_monotone_hermite_is_monotone_and_three_point_where_unlimited():
    # A step (Fritsch & Carlson's motivating case): no overshoot, monotone everywhere.
    y = torch.tensor([0.0, 0.0, 0.0, 0.1, 1.0, 1.0, 1.0, 1.0, 1.0], dtype=F64)
    v = evaluate_uniform_spline(y, "monotone_hermite", torch.linspace(0, N_NODES - 1, 801, dtype=F64))
    assert bool((v[1:] - v[:-1] >= -1e-15).all()) and float(v.min()) >= 0.0 and float(v.max()) <= 1.0
    # Gentle monotone data, no limiting: the three-point Hermite cubic, written out here.
    y = torch.exp(0.3 * Q)
    m = np.gradient(y.numpy())  # (y[i+1] - y[i-1]) / 2, one-sided at the ends
    m[0], m[-1] = y[1] - y[0], y[-1] - y[-2]
    qs = torch.tensor([0.25, 3.5, 7.75], dtype=F64)
    i, t = qs.floor().long(), qs - qs.floor()
    h00, h10, h01, h11 = 2 * t**3 - 3 * t**2 + 1, t**3 - 2 * t**2 + t, -2 * t**3 + 3 * t**2, t**3 - t**2
    m = torch.from_numpy(m)
    expected = h00 * y[i] + h10 * m[i] + h01 * y[i + 1] + h11 * m[i + 1]
    torch.testing.assert_close(evaluate_uniform_spline(y, "monotone_hermite", qs), expected, rtol=1e-13, atol=1e-13)


def test_phi_functions_match_quad_across_their_branches():
    """phi_k(z) = ∫_0^1 exp(-z v) v^k dv, on both sides of the series / recursion switch."""
    z = torch.tensor([-3.0, -0.7, -1e-9, 0.0, 1e-7, 0.2, 0.4999, 0.5, 0.9999, 1.0, 2.0, 40.0], dtype=F64)
    got = torch.stack(_phi(z), dim=-1)
    ref = torch.tensor([[quad(lambda v, k=k, zz=zz: math.exp(-zz * v) * v**k, 0.0, 1.0, epsabs=0, epsrel=1e-13)[0] for k in range(4)] for zz in z.tolist()], dtype=F64)
    torch.testing.assert_close(got, ref, rtol=1e-13, atol=0.0)
    got32 = torch.stack(_phi(z.float()), dim=-1)
    torch.testing.assert_close(got32.double(), ref, rtol=3e-6, atol=0.0)


def test_exponential_hermite_piece_matches_quad():
    """∫_τ^1 y0 exp(-lam s) R(s) ds with R(0)=R(1)=1, R'(0)=p, R'(1)=q (one interval, any tau)."""
    for lam, p, q, tau in [(0.0, 0.2, -0.1, 0.3), (1e-4, 0.5, 0.5, 0.0), (0.7, -0.3, 0.2, 0.9), (3.0, 1.0, -2.0, -0.2), (25.0, 0.1, 0.4, 0.6)]:
        R = np.polynomial.Polynomial([1.0, p, -(2 * p + q), p + q])
        ref = quad(lambda s: 2.0 * math.exp(-lam * s) * R(s), tau, 1.0, epsabs=0, epsrel=1e-13)[0]
        got = _exp_hermite_right_integral(*(torch.tensor(v, dtype=F64) for v in (2.0, lam, p, q, tau)))
        torch.testing.assert_close(got, torch.tensor(ref, dtype=F64), rtol=1e-12, atol=0.0)


# --------------------------------------------------------------------------
# Settings and refusals
# --------------------------------------------------------------------------
def test_settings_and_registry():
    integ = make_integrator("spline", kind="akima", height_points=30, distance_points=12)
    assert isinstance(integ, SplineOpticalDepth)
    assert integ.settings() == {
        "name": "spline", "height_points": 30, "distance_points": 12, "kind": "akima",
        "grid": "smooth", "distance_interp": "catmull_rom", "space": "log",
    }


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"kind": "bezier"}, "unknown spline kind 'bezier'; valid: linear, natural_cubic, catmull_rom, hermite, akima, monotone_hermite"),
        ({"grid": "lut"}, "unknown spline grid 'lut'; valid: smooth, paper"),
        ({"space": "sqrt"}, "unknown spline space"),
        ({"distance_interp": "cubic"}, "unknown spline distance_interp"),
        ({"height_points": 4}, "height_points must be >= 5"),
        ({"distance_points": 2}, "distance_points must be >= 3"),
    ],
)
def test_bad_settings_raise(kwargs, match):
    with pytest.raises(ValueError, match=match):
        SplineOpticalDepth(**kwargs)


def test_segments_leaving_the_atmosphere_are_refused():
    fn = SplineOpticalDepth().prepare(torch.tensor(SCALE_HEIGHTS, dtype=F64), R_B, R_T)
    one = torch.ones(1, dtype=F64)
    with pytest.raises(ValueError, match="spline: segment end points must lie in the atmosphere"):
        fn(one * (R_T - 10.0), one, one * 5000.0)  # 5 km past the top
    with pytest.raises(ValueError, match="spline: segments must not pass below the ground"):
        fn(one * (R_B + 10.0), -one, one * 2000.0)  # 2 km into the planet
    # From space, a zero-length segment (a ray that misses the atmosphere) is fine.
    assert float(fn(one * 7e6, one, 0 * one).abs().sum()) == 0.0


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_matches_cpu():
    r, mu, length, ref = _reference()
    integ = SplineOpticalDepth()
    h = torch.tensor(SCALE_HEIGHTS, dtype=F64)
    cpu = integ.prepare(h, R_B, R_T)(r, mu, length)
    gpu = integ.prepare(h.cuda(), R_B, R_T)(r.cuda(), mu.cuda(), length.cuda())
    assert gpu.device.type == "cuda"
    torch.testing.assert_close(gpu.cpu(), cpu, rtol=1e-10, atol=1e-9)
