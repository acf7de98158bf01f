"""bruneton_lut, chapman and height_fog against independent references.

References: scipy.integrate.quad in float64 (skyfit.tools.reference.column_quad,
epsrel 1e-10) on the docs/accuracy.md grid plus short segments, closed forms
(the Chapman function at the horizon, X e^X K_1(X); the flat-Earth integral),
and torch.autograd.gradcheck. Bounds are the maxima measured by
scripts/lut_chapman_fog_accuracy.py (docs/lut_chapman_fog.md) times ~1.5.
"""
import math

import numpy as np
import pytest
import torch
from scipy import integrate, special

from skyfit.tools.reference import accuracy_cases, column_quad, relative_column_error, segment_to_boundary
from skyfit.transmittance import integrator_class, make_integrator
from skyfit.transmittance.chapman import chapman_column_up
from skyfit.transmittance.fog import curvature_fraction
from skyfit.transmittance.lut import BrunetonLUTOpticalDepth, r_mu_from_transmittance_uv, transmittance_uv_from_r_mu

BOTTOM, TOP = 6_360_000.0, 6_420_000.0
HS = (8000.0, 1200.0)
F64 = torch.float64


def _t(x, dtype=F64):
    return torch.as_tensor(x, dtype=dtype)


def _gradcheck_each(column, h, mu, L, H, eps=None, **kw):
    """gradcheck of column(r, mu, L, H) in each argument separately, with r = BOTTOM + h.

    The radius enters as an altitude (a finite difference of 1e-6 m on r ~ 6.4e6 m is only
    known to 1e-3), and each argument gets a step suited to its scale: differences of columns
    of up to ~1e5 m need steps well above 1e-16 x 1e5.
    """
    eps = {"h": 1e-3, "mu": 1e-6, "L": 1e-3, "H": 1e-2, **(eps or {})}
    args = {"h": h, "mu": mu, "L": L, "H": H}
    for name in args:
        def f(x, name=name):
            a = {**args, name: x}
            return column(BOTTOM + a["h"], a["mu"], a["L"], a["H"])
        x = args[name].clone().requires_grad_()
        assert torch.autograd.gradcheck(f, (x,), eps=eps[name], **kw), name


@pytest.fixture(scope="module")
def grid():
    """accuracy_cases (to boundary, half way) + 1% segments; quad references for the segment and the full ray."""
    cases = accuracy_cases(BOTTOM, TOP)
    cases = cases + [(r, mu, 0.02 * L, lab.replace("half way", "short")) for r, mu, L, lab in cases if lab.endswith("half way")]
    refs = np.array([[column_quad(r, mu, L, H, BOTTOM) for H in HS] for r, mu, L, _ in cases])
    scale = np.array([[_scale_column(r, mu, H) for H in HS] for r, mu, _, _ in cases])
    r, mu, L = (_t([c[i] for c in cases]) for i in range(3))
    return dict(cases=cases, refs=refs, scale=scale, r=r, mu=mu, L=L, labels=[c[3] for c in cases])


def _hits_ground(r, mu):
    return mu < 0 and r * r * (mu * mu - 1) + BOTTOM**2 >= 0


def _scale_column(r, mu, H):
    """The larger column to the top that a difference method subtracts from: from the start along
    the ray, or, for a ray that hits the ground, from its ground point looking back (quad). [m]"""
    if _hits_ground(r, mu):
        mu_g = -(r * mu + segment_to_boundary(r, mu, BOTTOM, TOP)) / BOTTOM
        return column_quad(BOTTOM, mu_g, segment_to_boundary(BOTTOM, mu_g, BOTTOM, TOP), H, BOTTOM)
    return column_quad(r, mu, segment_to_boundary(r, mu, BOTTOM, TOP), H, BOTTOM)


def _columns(name, grid, dtype=F64, **settings):
    fn = make_integrator(name, **settings).prepare(_t(HS, dtype), BOTTOM, TOP)
    return fn(grid["r"].to(dtype), grid["mu"].to(dtype), grid["L"].to(dtype)).double().numpy()


def test_grid_has_the_required_cases(grid):
    labels = " ".join(grid["labels"])
    for needle in ("r=ground,", "r=ground+1m,", "r=ground+1km,", "r=top-1m,", "r=top,", "mu=up", "mu=0.5", "mu=0.1,", "mu=0,",
                   "mu=+1e-6", "mu=-1e-6", "mu=-0.1", "mu=down", "to boundary", "half way", "short"):
        assert needle in labels, needle


# ----------------------------------------------------------------------------------------------
# bruneton_lut
# ----------------------------------------------------------------------------------------------

# A segment's column is a difference of two interpolated columns to the top; its error scales with the
# larger of them, C_scale (see _scale_column). Measured (docs/lut_chapman_fog.md, 256 x 64):
# max |err| / max(C_scale, 1 m) = 4.3e-4 (H = 8 km) and 2.5e-3 (H = 1.2 km).
LUT_BOUND = (6.5e-4, 3.7e-3)


def _lut_error(col, grid):
    return np.abs(col - grid["refs"]) / np.maximum(grid["scale"], 1.0)


def test_lut_table_entries_match_quad():
    lut = BrunetonLUTOpticalDepth()
    table = lut.table(_t(HS), BOTTOM, TOP)
    assert table.shape == (64, 256, 2)
    for j in (0, 1, 31, 63):
        for i in (0, 1, 128, 254, 255):
            u, v = _t((i + 0.5) / 256), _t((j + 0.5) / 64)
            r, mu, d = (float(x) for x in r_mu_from_transmittance_uv(u, v, BOTTOM, TOP, 256, 64))
            for k, H in enumerate(HS):
                ref = column_quad(r, mu, d, H, BOTTOM, epsrel=1e-12)
                assert abs(float(table[j, i, k]) - ref) <= 1e-9 * max(ref, 1e-3), (j, i, H)


def test_lut_texture_mapping_round_trip():
    g = torch.Generator().manual_seed(1)
    r = BOTTOM + (TOP - BOTTOM) * torch.rand(200, generator=g, dtype=F64)
    mu_h = -torch.sqrt(1 - (BOTTOM / r) ** 2)
    mu = mu_h + (1 - mu_h) * torch.rand(200, generator=g, dtype=F64)  # rays that do not hit the ground
    u, v = transmittance_uv_from_r_mu(r, mu, BOTTOM, TOP, 256, 64)
    assert bool(((u >= 0.5 / 256 - 1e-12) & (u <= 1 - 0.5 / 256 + 1e-12)).all())
    r2, mu2, _ = r_mu_from_transmittance_uv(u, v, BOTTOM, TOP, 256, 64)
    torch.testing.assert_close(r2, r, rtol=0, atol=1e-6)
    torch.testing.assert_close(mu2, mu, rtol=0, atol=1e-9)


def test_lut_lookup_is_exact_at_texel_centres():
    lut = BrunetonLUTOpticalDepth(mu_size=32, r_size=8, samples=64)
    table = lut.table(_t(HS), BOTTOM, TOP)
    jj, ii = torch.meshgrid(torch.arange(8), torch.arange(32), indexing="ij")
    r, mu, _ = r_mu_from_transmittance_uv((ii + 0.5).double() / 32, (jj + 0.5).double() / 8, BOTTOM, TOP, 32, 8)
    got = lut.column_to_top(table, r, mu, BOTTOM, TOP)
    torch.testing.assert_close(got, table, rtol=1e-9, atol=1e-9)


def test_lut_against_quad(grid):
    col = _columns("bruneton_lut", grid)
    err = _lut_error(col, grid)
    for k in range(2):
        assert err[:, k].max() <= LUT_BOUND[k], f"H={HS[k]}: {err[:, k].max():.3e} at {grid['labels'][int(err[:, k].argmax())]}"
    assert (col >= 0).all()


def test_lut_error_decreases_with_resolution(grid):
    worst = []
    for mu_size, r_size in ((64, 16), (128, 32), (256, 64), (512, 128)):
        col = _columns("bruneton_lut", grid, mu_size=mu_size, r_size=r_size, samples=128)
        worst.append(_lut_error(col, grid).max(0))
    worst = np.array(worst)
    # bilinear interpolation is second order (~4x per doubling of both sizes; measured 2.5x-8x); > 2x asserted
    assert (worst[:-1] / worst[1:] > 2).all(), worst


def test_lut_gradcheck():
    """Exact first derivative in H (integrated with the table); in r, mu, L the interpolant is bilinear
    in texture space, smooth inside a texel (the points are away from texel edges)."""
    lut = BrunetonLUTOpticalDepth(mu_size=64, r_size=16, samples=32)
    h = _t([12_345.0, 30_123.0, 777.0, 2000.0])
    mu = _t([0.41, 0.123, -0.3, -0.9])
    L = _t([2345.0, 10_000.0, 321.0, 500.0])
    _gradcheck_each(lambda r, mu, L, H: lut.prepare(H, BOTTOM, TOP)(r, mu, L), h, mu, L, _t(HS), eps={"mu": 1e-6}, atol=1e-6, rtol=1e-5)


def test_lut_refusals():
    fn = BrunetonLUTOpticalDepth(mu_size=8, r_size=4, samples=8).prepare(_t(HS), BOTTOM, TOP)
    with pytest.raises(ValueError, match="outside the table"):
        fn(_t(TOP + 100.0), _t(-0.5), _t(10.0))
    with pytest.raises(ValueError, match="outside the table"):
        fn(_t(BOTTOM + 10.0), _t(-1.0), _t(100.0))  # the segment would end 90 m underground
    with pytest.raises(ValueError, match=r"\|mu\| > 1"):
        fn(_t(BOTTOM + 10.0), _t(1.5), _t(0.0))
    with pytest.raises(ValueError, match="mu_size must be >= 2"):
        BrunetonLUTOpticalDepth(mu_size=1)
    with pytest.raises(ValueError, match="unknown quadrature rule"):
        BrunetonLUTOpticalDepth(rule="romberg")


# ----------------------------------------------------------------------------------------------
# chapman
# ----------------------------------------------------------------------------------------------

# Measured: 1.25e-3 (H = 8 km, X = 795) and 1.89e-4 (H = 1.2 km, X = 5300), uniform over the grid.
CHAPMAN_BOUND = (1.9e-3, 2.9e-4)


def test_chapman_against_quad(grid):
    col = _columns("chapman", grid)
    for k in range(2):
        rel = relative_column_error(col[:, k], grid["refs"][:, k])
        assert rel.max() <= CHAPMAN_BOUND[k], f"H={HS[k]}: {rel.max():.3e} at {grid['labels'][int(rel.argmax())]}"


@pytest.mark.parametrize("X", [50.0, 795.0, 5300.0])
def test_chapman_function_limits(X):
    """Horizon: Ch(X, 90 deg) = X e^X K_1(X) = sqrt(pi X/2)(1 + 3/(8X) + ...); zenith: Ch = 1 (flat, exact).

    Fitzmaurice's form is sqrt(pi X/2) at the horizon and 1 - 1/X + ... at the zenith, so its
    relative errors there are -3/(8X) and -1/X to leading order.
    """
    H = _t([BOTTOM / X])
    ch90 = float(chapman_column_up(_t([[0.0]]), _t([[BOTTOM]]), _t([[0.0]]), H)) / float(H)
    exact90 = X * special.kve(1, X)
    assert ch90 / exact90 - 1 == pytest.approx(-3 / (8 * X), rel=0.25)
    ch0 = float(chapman_column_up(_t([[0.0]]), _t([[BOTTOM]]), _t([[1.0]]), H)) / float(H)
    assert ch0 - 1 == pytest.approx(-1 / X, rel=0.1)


def test_chapman_regime_refusals():
    ch = make_integrator("chapman")
    with pytest.raises(ValueError, match=r"X = r/H = 40 .* below min_x = 50"):
        ch.prepare(_t([BOTTOM / 40.0]), BOTTOM, TOP)
    fn = ch.prepare(_t(HS), BOTTOM, TOP)
    with pytest.raises(ValueError, match="below the ground"):
        fn(_t(BOTTOM + 1000.0), _t(-1.0), _t(5000.0))
    with pytest.raises(ValueError, match="below the ground"):
        fn(_t(TOP), _t(-0.2), _t(1e6))  # passes through the planet
    with pytest.raises(ValueError, match="min_x must be > 0"):
        make_integrator("chapman", min_x=0.0)
    # a larger min_x is honoured
    with pytest.raises(ValueError, match="min_x = 1000"):
        make_integrator("chapman", min_x=1000.0).prepare(_t(HS), BOTTOM, TOP)


def _singular_segments():
    """mu = 0, +-1, +-1e-6, r = ground and top, a segment ending exactly at its tangent point, one through it."""
    r = [BOTTOM, BOTTOM + 1.0, BOTTOM + 3000.0, TOP, TOP - 1.0, BOTTOM + 20_000.0, BOTTOM + 20_000.0, TOP, BOTTOM + 500.0]
    mu = [0.0, 1.0, -1.0, -1e-6, 1e-6, -0.05, -0.05, -1.0, 0.0]
    L = [5000.0, 100.0, 2000.0, 10.0, 5000.0, 0.0, 0.0, 60_000.0, 0.0]
    r_t, mu_t = BOTTOM + 20_000.0, -0.05
    L[5] = -r_t * mu_t  # ends exactly at the tangent point
    L[6] = -r_t * mu_t + 30_000.0  # passes it
    return _t(r), _t(mu), _t(L)


def test_chapman_gradcheck():
    ch = make_integrator("chapman")
    column = lambda r, mu, L, H: ch.column(r, mu, L, H, BOTTOM, TOP)  # noqa: E731
    r, mu, L = _singular_segments()
    assert torch.autograd.gradcheck(lambda H: column(r, mu, L, H), (_t(HS).requires_grad_(),), eps=1e-2, atol=1e-7, rtol=1e-6)
    # r, mu, L inside each branch (finite differences must not straddle a switch: there the
    # approximation's second derivative jumps; continuity of the gradient is tested below):
    # upward, below the horizon before the tangent point, through it, towards the ground, vertical.
    h = _t([3000.0, 20_000.0, 20_000.0, 500.0, 40_000.0, 1.0, 100.0])
    mu2 = _t([0.02, -0.05, -0.05, -0.02, -0.3, -0.5, 0.9999])
    L2 = _t([5000.0, 1000.0, 350_000.0, 2000.0, 20_000.0, 1.5, 100.0])
    _gradcheck_each(column, h, mu2, L2, _t(HS), eps={"mu": 1e-6}, atol=1e-5, rtol=1e-5)


def test_chapman_gradient_is_continuous_across_branches():
    """At mu = 0 (up / through the tangent point) and mu_d = 0 (before / through) the gradient taken
    exactly at the switch equals its limits from both sides (the column is C1 there)."""
    ch = make_integrator("chapman")

    def grad(h, mu, L):
        x = _t([h, mu, L]).requires_grad_()
        col = ch.column(BOTTOM + x[0], x[1], x[2], _t(HS), BOTTOM, TOP).sum()
        return torch.autograd.grad(col, x)[0]

    for h, L in ((0.0, 5000.0), (500.0, 70.0), (20_000.0, 300_000.0)):
        g0, gm, gp = grad(h, 0.0, L), grad(h, -1e-10, L), grad(h, 1e-10, L)
        torch.testing.assert_close(g0, gm, rtol=1e-5, atol=1e-8)
        torch.testing.assert_close(g0, gp, rtol=1e-5, atol=1e-8)
    h, mu = 20_000.0, -0.05
    L_t = -(BOTTOM + h) * mu  # ends exactly at the tangent point: mu_d = 0
    g0, gm, gp = grad(h, mu, L_t), grad(h, mu, L_t - 1e-4), grad(h, mu, L_t + 1e-4)
    torch.testing.assert_close(g0, gm, rtol=1e-5, atol=1e-8)
    torch.testing.assert_close(g0, gp, rtol=1e-5, atol=1e-8)


# ----------------------------------------------------------------------------------------------
# height_fog
# ----------------------------------------------------------------------------------------------

FOG_F = 0.01


def _fog_cap(mu, H, f=FOG_F):
    """Largest L with L^2 (1 - mu^2) <= f H (2R - L), times 0.999 (inside the default regime)."""
    a = (1 - mu) * (1 + mu)
    return math.inf if a <= 0 else 0.999 * (-f * H + math.sqrt((f * H) ** 2 + 8 * BOTTOM * f * H * a)) / (2 * a)


def test_fog_matches_the_flat_integral():
    """Ishiyama 2018 eq. 14 is the exact flat-Earth integral: quad of exp(-(h0 + mu s)/H)."""
    fog = make_integrator("height_fog", max_curvature_fraction=1e9)  # geometry check off: flat integral only
    cases = [(h0, mu, L) for h0 in (0.0, 1.0, 1000.0, 59_999.0) for mu in (1.0, 0.5, 0.1, 1e-3, 0.0, 1e-6, -1e-6, -1e-3, -0.1, -1.0)
             for L in (1.0, 1200.0, 9000.0)]
    # y = L |mu| / H around the series switch at 1e-3
    cases += [(100.0, s * 1e-3 * 1200.0 / 1000.0 * (1 + e), 1000.0) for s in (1, -1) for e in (-1e-9, 0.0, 1e-9)]
    r, mu, L = (_t([c[i] for c in cases]) for i in range(3))
    r = r + BOTTOM
    got = fog.column(r, mu, L, _t(HS), BOTTOM, TOP).numpy()
    for n, (h0, m, l) in enumerate(cases):
        for k, H in enumerate(HS):
            ref = integrate.quad(lambda s: math.exp(-(h0 + m * s) / H), 0.0, l, epsrel=1e-13, epsabs=0)[0]
            assert abs(got[n, k] - ref) <= 1e-11 * ref, (h0, m, l, H)


def test_fog_against_spherical_quad_within_its_bound(grid):
    """Inside the regime the flat column is >= the true one and exceeds it by at most delta."""
    cases = [(r, mu, min(L, _fog_cap(mu, min(HS)))) for r, mu, L, _ in grid["cases"]]
    r, mu, L = (_t([c[i] for c in cases]) for i in range(3))
    col = make_integrator("height_fog").prepare(_t(HS), BOTTOM, TOP)(r, mu, L).numpy()
    worst = 0.0
    for k, H in enumerate(HS):
        ref = np.array([column_quad(a, b, c, H, BOTTOM) for a, b, c in cases])
        delta = curvature_fraction(mu, L, H, BOTTOM).numpy()
        signed = (col[:, k] - ref) / np.maximum(ref, 1e-3)
        assert (signed >= -1e-11).all()
        assert (signed <= delta + 1e-11).all()
        worst = max(worst, signed.max())
    assert worst <= FOG_F  # measured 9.3e-3 at the regime's edge (H = 1.2 km, horizontal)


def test_fog_refuses_long_rays_and_accepts_vertical_ones():
    fog = make_integrator("height_fog")
    fn = fog.prepare(_t(HS), BOTTOM, TOP)
    with pytest.raises(ValueError, match=r"curvature fraction .* = 0\.6\d* exceeds max_curvature_fraction = 0\.01"):
        fn(_t(BOTTOM), _t(0.0), _t(100_000.0))
    with pytest.raises(ValueError, match="length >= 0"):
        fn(_t(BOTTOM), _t(0.5), _t(-1.0))
    with pytest.raises(ValueError, match="max_curvature_fraction must be > 0"):
        make_integrator("height_fog", max_curvature_fraction=0)
    # vertical rays have no curvature error: accepted at any length, and exact
    col = fn(_t(BOTTOM + 100.0), _t(1.0), _t(59_900.0))
    ref = [column_quad(BOTTOM + 100.0, 1.0, 59_900.0, H, BOTTOM) for H in HS]
    torch.testing.assert_close(col, _t(ref), rtol=1e-12, atol=0)


def test_fog_gradcheck():
    fog = make_integrator("height_fog")
    h = _t([0.0, 100.0, 2000.0, 60_000.0, 50.0, 50.0, 50.0])
    mu = _t([0.0, 1.0, -1.0, -1e-6, 1.2e-3, -1.2e-3, 1e-9])  # 1.2e-3: y = L |mu| / H near the series switch
    L = _t([3000.0, 500.0, 1500.0, 2000.0, 1000.0, 1000.0, 1000.0])
    _gradcheck_each(lambda r, mu, L, H: fog.column(r, mu, L, H, BOTTOM, TOP), h, mu, L, _t(HS), eps={"mu": 1e-6}, atol=1e-7, rtol=1e-6)


# ----------------------------------------------------------------------------------------------
# all three
# ----------------------------------------------------------------------------------------------

def _regime_segments(name):
    """Segments each method accepts: the singular set, with the fog's lengths capped to its regime."""
    r, mu, L = _singular_segments()
    if name == "height_fog":
        L = _t([min(float(l), _fog_cap(float(m), min(HS))) for m, l in zip(mu, L)])
    return r, mu, L


# float32 vs float64 on the same (float32-representable) inputs, |c32 - c64| <= tol x scale. For the
# difference methods the scale is max(C_scale, 1 m) (see _scale_column): they lose ~1e-7 of the larger
# column; the LUT also inherits float32's 0.5 m radius steps, which matter where the column changes
# fastest with r (horizontal rays just below the top). For the fog the scale is max(c64, 1 mm).
# Measured (docs/lut_chapman_fog.md): chapman 1.9e-4 / 6.4e-6, bruneton_lut 0.13 / 0.016.
F32_TOL = {"chapman": (3e-4, 1e-5), "bruneton_lut": (0.2, 0.025), "height_fog": (1e-5, 1e-5)}


@pytest.mark.parametrize("name", ["chapman", "bruneton_lut", "height_fog"])
def test_float32_matches_float64(name, grid):
    if name == "height_fog":
        cases = [(r, mu, min(L, _fog_cap(mu, min(HS)))) for r, mu, L, _ in grid["cases"]]
    else:
        cases = grid["cases"]
    r32, mu32, L32 = (_t([c[i] for c in cases], torch.float32) for i in range(3))
    H32 = _t(HS, torch.float32)
    integ = make_integrator(name)
    out32 = integ.prepare(H32, BOTTOM, TOP)(r32, mu32, L32)
    assert out32.dtype == torch.float32 and bool(torch.isfinite(out32).all())
    c32 = out32.double().numpy()
    c64 = integ.prepare(H32.double(), BOTTOM, TOP)(r32.double(), mu32.double(), L32.double()).numpy()
    scale = np.maximum(c64, 1e-3) if name == "height_fog" else np.maximum(grid["scale"], 1.0)
    err = np.abs(c32 - c64) / scale
    for k in range(2):
        assert err[:, k].max() <= F32_TOL[name][k], f"H={HS[k]}: {err[:, k].max():.3e}"


@pytest.mark.parametrize("name", ["chapman", "bruneton_lut", "height_fog"])
def test_no_nan_at_singular_points(name):
    integ = make_integrator(name, **({"mu_size": 32, "r_size": 8, "samples": 32} if name == "bruneton_lut" else {}))
    r, mu, L = _regime_segments(name)
    r, mu, L = r.clone().requires_grad_(), mu.clone().requires_grad_(), L.clone().requires_grad_()
    H = _t(HS).requires_grad_()
    col = integ.prepare(H, BOTTOM, TOP)(r, mu, L)
    assert col.shape == (9, 2)
    assert bool(torch.isfinite(col).all()) and bool((col >= 0).all())
    col.sum().backward()
    for g in (r.grad, mu.grad, L.grad, H.grad):
        assert bool(torch.isfinite(g).all())
    # zero-length segments have zero column
    zero = L.detach() == 0
    assert bool((col.detach()[zero] == 0).all())


@pytest.mark.parametrize("name", ["chapman", "bruneton_lut", "height_fog"])
def test_renderer_shapes(name):
    """The renderer calls fn with (n, 1) starts and (n, N) lengths; results broadcast to (n, N, K)."""
    integ = make_integrator(name, **({"mu_size": 32, "r_size": 8, "samples": 32} if name == "bruneton_lut" else {}))
    fn = integ.prepare(_t(HS), BOTTOM, TOP)
    r = _t([[BOTTOM + 10.0], [BOTTOM + 5000.0]])
    mu = _t([[0.7], [-0.2]])
    s = _t([[0.0, 100.0, 400.0], [0.0, 1000.0, 2000.0]])
    col = fn(r, mu, s)
    assert col.shape == (2, 3, 2)
    single = torch.stack([torch.stack([fn(r[i, 0], mu[i, 0], s[i, j]) for j in range(3)]) for i in range(2)])
    torch.testing.assert_close(col, single, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("name,settings", [("chapman", {"min_x": 100.0}), ("bruneton_lut", {"mu_size": 128, "r_size": 32, "samples": 100, "rule": "simpson"}),
                                           ("height_fog", {"max_curvature_fraction": 0.05})])
def test_registry_and_settings_round_trip(name, settings):
    integ = make_integrator(name, **settings)
    assert type(integ) is integrator_class(name) and integ.name == name
    st = integ.settings()
    assert st["name"] == name
    again = make_integrator(name, **{k: v for k, v in st.items() if k not in ("name", "approximation")})
    assert again.settings() == st


def test_in_the_renderer():
    """Single scattering with chapman and the LUT agrees with Gauss-Legendre; the fog is refused."""
    from skyfit.atmosphere import load_atmosphere
    from skyfit.scattering.single import single_scattering

    atm = load_atmosphere("earth", torch.tensor([440.0, 680.0], dtype=F64))
    zen = torch.deg2rad(_t([0.0, 60.0, 85.0, 89.5]))
    mu, mu_s = torch.cos(zen), torch.full((4,), math.cos(math.radians(70.0)), dtype=F64)
    nu = torch.cos(zen - math.radians(70.0))
    r = torch.full((4,), BOTTOM + 1.0, dtype=F64)
    kw = dict(view_samples=32, ground=False)
    ref = single_scattering(atm, r, mu, mu_s, nu, make_integrator("gauss", samples=128), **kw)
    for name, tol in (("chapman", 6e-3), ("bruneton_lut", 3e-3)):  # measured 1.3e-3 / 7.7e-4 (sun 60 deg), 4.0e-3 / 1.0e-3 (88 deg)
        got = single_scattering(atm, r, mu, mu_s, nu, make_integrator(name), **kw)
        torch.testing.assert_close(got, ref, rtol=tol, atol=0)
    with pytest.raises(ValueError, match="curvature fraction"):
        single_scattering(atm, r, mu, mu_s, nu, make_integrator("height_fog"), **kw)


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
@pytest.mark.parametrize("name", ["chapman", "bruneton_lut", "height_fog"])
def test_cuda_matches_cpu(name):
    r, mu, L = _regime_segments(name)
    integ = make_integrator(name)
    cpu = integ.prepare(_t(HS), BOTTOM, TOP)(r, mu, L)
    H = _t(HS).cuda().requires_grad_()
    gpu = integ.prepare(H, BOTTOM, TOP)(r.cuda(), mu.cuda(), L.cuda())
    assert gpu.device.type == "cuda"
    torch.testing.assert_close(gpu.cpu(), cpu, rtol=1e-9, atol=1e-9)
    gpu.sum().backward()
    assert bool(torch.isfinite(H.grad).all())
