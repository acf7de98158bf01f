"""Two-term Henyey-Greenstein phase and the boundary-layer aerosol profile (docs/aerosol.md).

Expected values come from scipy quad in float64 (normalisation, mean cosine, columns along rays
with the kink at the layer top given as a break point) and from closed forms (f = 1 is HG; the
vertical column of the boundary layer is h_mix + H).
"""
from __future__ import annotations

import math

import pytest
import torch
from scipy.integrate import quad

from skyfit.atmosphere import atmosphere_from_config
from skyfit.fit.parameters import FitError, Parameterisation
from skyfit.scattering.phase import henyey_greenstein_phase, mie_phase, two_term_hg_phase
from skyfit.transmittance import make_integrator, prepare_columns
from skyfit.transmittance.boundary_layer import boundary_layer_columns, layer_interval

D64 = torch.float64
RB, RT = 6_360_000.0, 6_420_000.0


# -- two-term Henyey-Greenstein -------------------------------------------------------------------

@pytest.mark.parametrize("g1,g2,f", [(0.7, -0.3, 0.9), (0.95, -0.8, 0.5), (0.2, -0.05, 0.1), (0.999, -0.999, 0.7)])
def test_two_term_hg_normalised_and_mean_cosine(g1, g2, f):
    def p(c):
        return float(two_term_hg_phase(torch.tensor(c, dtype=D64), torch.tensor(g1, dtype=D64),
                                       torch.tensor(g2, dtype=D64), torch.tensor(f, dtype=D64)))

    # peaks at c = +-1 are narrow for |g| -> 1: give quad the points near them
    pts = [-1 + 1e-4, -0.99, 0.99, 1 - 1e-4]
    norm = 2 * math.pi * quad(p, -1, 1, points=pts, limit=400, epsabs=1e-13, epsrel=1e-11)[0]
    mean = 2 * math.pi * quad(lambda c: c * p(c), -1, 1, points=pts, limit=400, epsabs=1e-13, epsrel=1e-11)[0]
    assert norm == pytest.approx(1.0, rel=1e-8)
    assert mean == pytest.approx(f * g1 + (1 - f) * g2, abs=1e-8)  # Kattawar 1975: <cos> = f g1 + (1 - f) g2


def test_two_term_hg_is_hg_at_weight_one():
    nu = torch.linspace(-1, 1, 101, dtype=D64)
    g1 = torch.tensor(0.73, dtype=D64)
    got = two_term_hg_phase(nu, g1, torch.tensor(-0.4, dtype=D64), torch.tensor(1.0, dtype=D64))
    torch.testing.assert_close(got, henyey_greenstein_phase(nu, g1), rtol=0, atol=0)
    torch.testing.assert_close(mie_phase(nu, g1, "two_term_hg", torch.tensor(-0.4, dtype=D64), torch.tensor(1.0, dtype=D64)),
                               henyey_greenstein_phase(nu, g1))


def test_two_term_hg_gradcheck_at_the_peaks():
    # scattering angle 0 and 180 degrees, and the backward lobe near its singular g2 -> -1
    nu = torch.tensor([-1.0, -0.999, 0.0, 0.999, 1.0], dtype=D64, requires_grad=True)
    for g1, g2, f in ((0.7, -0.3, 0.9), (0.98, -0.97, 0.4)):
        args = [torch.tensor(v, dtype=D64, requires_grad=True) for v in (g1, g2, f)]
        assert torch.autograd.gradcheck(two_term_hg_phase, (nu, *args))


def test_two_term_hg_needs_its_parameters():
    with pytest.raises(ValueError, match="two_term_hg phase needs g2 and weight"):
        mie_phase(torch.zeros(3), torch.tensor(0.7), "two_term_hg")


# -- configs -----------------------------------------------------------------------------------------

def _cfg(**mie):
    return {"name": "t", "mie": {"angstrom_alpha": 1.0, "angstrom_beta": 0.05, "scale_height_m": 1200.0, "g": 0.7,
                                 "phase": "henyey_greenstein", **mie}}


def test_config_keys_and_refusals():
    atm = atmosphere_from_config(_cfg(phase="two_term_hg", g2=-0.25, hg_weight=0.85, profile="boundary_layer",
                                      mixing_height_m=800.0), [550.0, 1000.0])
    assert atm.mie_phase == "two_term_hg" and float(atm.mie_g2) == -0.25 and float(atm.mie_hg_weight) == 0.85
    assert atm.mie_profile == "boundary_layer" and float(atm.mie_mixing_height) == 800.0
    # the Angstrom beta is still the optical depth at 1 um: extinction x (h_mix + H_M)
    assert float(atm.mie_extinction[1]) * (800.0 + 1200.0) == pytest.approx(0.05, rel=1e-12)
    with pytest.raises(ValueError, match="mie.g2 is required"):
        atmosphere_from_config(_cfg(phase="two_term_hg", hg_weight=0.9), [550.0])
    with pytest.raises(ValueError, match="belong to phase: two_term_hg"):
        atmosphere_from_config(_cfg(g2=-0.2), [550.0])
    with pytest.raises(ValueError, match="belongs to profile: boundary_layer"):
        atmosphere_from_config(_cfg(mixing_height_m=500.0), [550.0])
    with pytest.raises(ValueError, match="mie.mixing_height_m must be > 0"):
        atmosphere_from_config(_cfg(profile="boundary_layer", mixing_height_m=0.0), [550.0])
    with pytest.raises(ValueError, match="mie_hg_weight must be in"):
        atmosphere_from_config(_cfg(phase="two_term_hg", g2=-0.2, hg_weight=1.5), [550.0])


# -- boundary-layer columns against scipy quad ----------------------------------------------------------

H_MIX, H_M = 1000.0, 1200.0


def _rho(h):
    return 1.0 if h <= H_MIX else math.exp(-(h - H_MIX) / H_M)


def _reference(r, mu, length):
    """int_0^L rho(h(s)) ds by scipy quad, the kinks at the layer crossings given as break points."""
    def h(s):
        return math.sqrt(r * r + 2 * r * mu * s + s * s) - RB

    rm = RB + H_MIX
    disc = (r * mu) ** 2 - (r * r - rm * rm)
    pts = [s for s in ((-r * mu - math.sqrt(disc), -r * mu + math.sqrt(disc)) if disc > 0 else ()) if 0 < s < length]
    return quad(lambda s: _rho(h(s)), 0.0, length, points=pts or None, limit=500, epsabs=1e-9, epsrel=1e-12)[0]


def _rays():
    """(r, mu, length) of rays up, grazing and down, from inside (h = 100 m) and above (3 km) the layer."""
    out = []
    for h0 in (100.0, 3000.0):
        r = RB + h0
        for mu in (0.6, 0.05, 0.0, -0.02, -0.027, -0.06, -0.5):
            disc_g = (r * mu) ** 2 - (r * r - RB * RB)
            if mu < 0 and disc_g > 0:
                length = -r * mu - math.sqrt(disc_g)  # to the ground
            else:
                length = -r * mu + math.sqrt((r * mu) ** 2 - (r * r - RT * RT))  # to the top
            out.append((r, mu, length))
        # short segments ending in the air: from inside out of the layer, from above into it
        out.append((r, 0.3, 4000.0) if h0 < H_MIX else (r, -0.3, 8000.0))
    return out


RAYS = _rays()


def _columns(fn):
    r, mu, L = (torch.tensor(v, dtype=D64) for v in zip(*RAYS))
    return fn(r, mu, L)


def test_rays_cover_every_case():
    r, mu, L = (torch.tensor(v, dtype=D64) for v in zip(*RAYS))
    a, b = layer_interval(r, mu, L, torch.tensor(RB + H_MIX, dtype=D64))
    inside_start = a == 0
    assert bool((inside_start & (b > 0) & (b < L)).any())  # leaves the layer
    assert bool((inside_start & (b == L)).any())  # stays inside (to the ground)
    assert bool(((a > 0) & (b < L) & (b > a)).any())  # enters and leaves (grazing through from above)
    assert bool(((a > 0) & (b == L)).any())  # enters and reaches the ground
    assert bool(((a == L) & (b == L)).any())  # misses it


def test_exact_split_matches_quad():
    """The split (constant part = length, above = exp(h_mix/H) x exponential column) with an accurate
    exponential column (Gauss 400) reproduces quad to 1e-9: the split itself is exact."""
    H = torch.tensor([8000.0, H_M], dtype=D64)
    exp_fn = make_integrator("gauss", samples=400).prepare(H, RB, RT)
    fn = boundary_layer_columns(exp_fn, H, {1: torch.tensor(H_MIX, dtype=D64)}, RB)
    got = _columns(fn)
    want = torch.tensor([_reference(*ray) for ray in RAYS], dtype=D64)
    torch.testing.assert_close(got[:, 1], want, rtol=1e-9, atol=1e-6)
    torch.testing.assert_close(got[:, 0], _columns(exp_fn)[:, 0], rtol=0, atol=0)  # Rayleigh untouched


# (integrator spec, rtol against quad): the quadrature rules sample the kinked profile directly and converge at
# their low order there; the closed forms keep their own exponential accuracy through the split.
QUADRATURE = [("gauss:samples=512", 2e-3), ("trapezoid:samples=2048", 2e-3), ("simpson:samples=2049", 2e-3),
              ("midpoint:samples=2048", 2e-3)]


@pytest.mark.parametrize("spec,rtol", QUADRATURE)
def test_quadrature_boundary_layer_columns(spec, rtol):
    from skyfit.transmittance import parse_integrator

    H = torch.tensor([8000.0, H_M], dtype=D64)
    fn = parse_integrator(spec).prepare_layers(H, RB, RT, {1: torch.tensor(H_MIX, dtype=D64)})
    want = torch.tensor([_reference(*ray) for ray in RAYS], dtype=D64)
    torch.testing.assert_close(_columns(fn)[:, 1], want, rtol=rtol, atol=1e-3)


def _reference_exponential(r, mu, length):
    """int_0^L exp(-h(s) / H_M) ds by scipy quad."""
    return quad(lambda s: math.exp(-(math.sqrt(r * r + 2 * r * mu * s + s * s) - RB) / H_M), 0.0, length,
                limit=500, epsabs=1e-12, epsrel=1e-12)[0]


@pytest.mark.parametrize("spec", ["chapman", "taylor", "spline", "bruneton_lut", "height_fog"])
def test_closed_forms_keep_their_accuracy(spec):
    """Through the split, a closed form's boundary-layer column is as accurate as its exponential column on the
    same rays (largest relative error at most 1.1 x, + 1e-7): the split adds no error of its own. (Taylor's own error on
    long grazing rays is large at H = 1.2 km; the split inherits it, neither more nor less.) Height fog refuses
    curved rays exactly as for exponentials."""
    integ = make_integrator(spec)
    H = torch.tensor([8000.0, H_M], dtype=D64)
    rays = RAYS if spec != "height_fog" else [x for x in RAYS if x[2] <= 10_000.0]
    r, mu, L = (torch.tensor(v, dtype=D64) for v in zip(*rays))
    bl = integ.prepare_layers(H, RB, RT, {1: torch.tensor(H_MIX, dtype=D64)})(r, mu, L)[:, 1]
    ex = integ.prepare(H, RB, RT)(r, mu, L)[:, 1]
    want_bl = torch.tensor([_reference(*x) for x in rays], dtype=D64)
    want_ex = torch.tensor([_reference_exponential(*x) for x in rays], dtype=D64)
    err_bl = (bl - want_bl).abs() / want_bl
    err_ex = (ex - want_ex).abs() / want_ex
    assert float(err_bl.max()) <= 1.1 * float(err_ex.max()) + 1e-7, (err_bl.tolist(), err_ex.tolist())


def test_quadrature_converges_at_the_kink():
    H = torch.tensor([8000.0, H_M], dtype=D64)
    want = torch.tensor([_reference(*ray) for ray in RAYS], dtype=D64)
    errs = []
    for n in (64, 256, 1024):
        fn = make_integrator("trapezoid", samples=n).prepare_layers(H, RB, RT, {1: torch.tensor(H_MIX, dtype=D64)})
        errs.append(float(((_columns(fn)[:, 1] - want).abs() / want).max()))
    assert errs[2] < errs[1] < errs[0]
    assert errs[2] < 1e-3


def test_boundary_layer_vertical_column_is_hmix_plus_h():
    """AOD consistency: a vertical ray from the ground has column h_mix + H_M (curvature does not act on a
    vertical ray; the tail above the top, exp(-(top - h_mix) / H), is < 1e-20)."""
    H = torch.tensor([8000.0, H_M], dtype=D64)
    for spec, kw, rel in (("gauss", {"samples": 2048}, 5e-4), ("chapman", {}, 3e-4), ("spline", {}, 1e-4)):  # Chapman: 1.9e-4 of its own at mu = 1
        fn = make_integrator(spec, **kw).prepare_layers(H, RB, RT, {1: torch.tensor(H_MIX, dtype=D64)})
        col = fn(torch.tensor([RB], dtype=D64), torch.tensor([1.0], dtype=D64), torch.tensor([RT - RB], dtype=D64))
        assert float(col[0, 1]) == pytest.approx(H_MIX + H_M, rel=rel), spec


@pytest.mark.parametrize("spec", ["gauss:samples=64", "chapman"])
def test_boundary_layer_column_gradcheck(spec):
    integ = make_integrator(*spec.split(":")[:1], **({"samples": 64} if "samples" in spec else {}))
    r, mu, L = (torch.tensor(v, dtype=D64) for v in zip(*RAYS))

    def col(h_mix, h_m):
        H = torch.stack([torch.tensor(8000.0, dtype=D64), h_m])
        return integ.prepare_layers(H, RB, RT, {1: h_mix})(r, mu, L)[:, 1]

    h_mix = torch.tensor(H_MIX, dtype=D64, requires_grad=True)
    h_m = torch.tensor(H_M, dtype=D64, requires_grad=True)
    assert torch.autograd.gradcheck(col, (h_mix, h_m), eps=1e-3, atol=1e-6, rtol=1e-5)


def test_split_refuses_an_unrepresentable_ratio():
    H = torch.tensor([8000.0, 20.0], dtype=torch.float32)
    with pytest.raises(ValueError, match="h_mix / H = 100 exceeds 44.*use a quadrature integrator"):
        make_integrator("chapman").prepare_layers(H, RB, RT, {1: torch.tensor(2000.0)})


# -- fit parameters -------------------------------------------------------------------------------------

def _kider_like(**mie):
    cfg = _cfg(**mie)
    return atmosphere_from_config(cfg, [450.0, 550.0, 650.0])


def test_parameters_switch_phase_and_profile_and_keep_aod():
    base = _kider_like()
    p = Parameterisation(base, ["mie_aod_550", "mie_g2", "mie_hg_weight", "mie_mixing_height"],
                         values={"mie_aod_550": 0.2, "mie_mixing_height": 700.0, "mie_g2": -0.4, "mie_hg_weight": 0.8})
    x = p.initial_vector().requires_grad_(True)
    atm = p.atmosphere(p.to_physical(x))
    assert atm.mie_phase == "two_term_hg" and atm.mie_profile == "boundary_layer"
    # AOD = beta_550 (h_mix + H_M): the 550 nm extinction times the boundary-layer column
    assert float(atm.mie_extinction[1]) * (700.0 + 1200.0) == pytest.approx(0.2, rel=1e-12)
    d = p.physical_dict(x.detach())
    assert d["mie_aod_550"] == pytest.approx(0.2, rel=1e-12)
    assert d["mie_beta_550"] == pytest.approx(0.2 / 1900.0, rel=1e-12)
    # every new parameter carries a gradient into the atmosphere
    loss = (atm.mie_g2 + atm.mie_hg_weight + atm.mie_mixing_height / 1000 + atm.mie_extinction.sum() * 1e4)
    loss.backward()
    assert bool(torch.isfinite(x.grad).all()) and bool((x.grad != 0).all())


def test_two_term_needs_a_hg_config():
    base = atmosphere_from_config({**_cfg(), "mie": {**_cfg()["mie"], "phase": "cornette_shanks"}}, [550.0])
    with pytest.raises(FitError, match="Cornette-Shanks phase; set mie.phase to henyey_greenstein or two_term_hg"):
        Parameterisation(base, ["mie_g2"])


def test_render_gradcheck_new_parameters():
    """Single-scattering radiance of a few directions is differentiable in mie_g2, mie_hg_weight and
    mie_mixing_height (float64 gradcheck through Parameterisation.atmosphere, the split Chapman columns and
    the boundary-layer density of the view-ray samples)."""
    from skyfit.scattering import single_scattering

    base = _kider_like()
    p = Parameterisation(base, ["mie_g2", "mie_hg_weight", "mie_mixing_height"])
    integ = make_integrator("chapman")
    r = torch.full((4,), RB + 50.0, dtype=D64)
    mu = torch.tensor([0.9, 0.3, 0.02, -0.1], dtype=D64)
    mu_s, nu = torch.full((4,), 0.5, dtype=D64), torch.tensor([0.3, -0.9, 0.95, 0.0], dtype=D64)

    def radiance(x):
        atm = p.atmosphere(p.to_physical(x))
        return single_scattering(atm, r, mu, mu_s, nu, integ, view_samples=8, rule="gauss")

    x = p.initial_vector().requires_grad_(True)
    assert torch.autograd.gradcheck(radiance, (x,), eps=1e-6, atol=1e-10, rtol=1e-4)


def test_quadrature_and_split_renders_agree():
    """The same boundary-layer sky through the direct quadrature and through Chapman's split columns."""
    from skyfit.scattering import single_scattering

    atm = _kider_like(profile="boundary_layer", mixing_height_m=900.0, phase="two_term_hg", g2=-0.3, hg_weight=0.9)
    r = torch.full((3,), RB + 10.0, dtype=D64)
    mu, mu_s, nu = (torch.tensor(v, dtype=D64) for v in ([0.8, 0.2, 0.03], [0.6, 0.6, 0.6], [0.5, -0.4, 0.9]))
    a = single_scattering(atm, r, mu, mu_s, nu, make_integrator("gauss", samples=256), view_samples=64, rule="gauss")
    b = single_scattering(atm, r, mu, mu_s, nu, prep := make_integrator("chapman"), view_samples=64, rule="gauss")
    del prep
    torch.testing.assert_close(a, b, rtol=5e-3, atol=0)
    assert bool(prepare_columns(make_integrator("gauss"), atm) is not None)


def test_batched_refuses():
    from skyfit.fit.batched import BatchedLikelihood

    class _P:  # the fields unsupported_reason reads
        def __init__(self, param):
            self.param = param
            self.model = type("M", (), {"orders": 1, "integrator": make_integrator("chapman")})()
            self.observations = []

    base = _kider_like()
    assert "two-term" in BatchedLikelihood.unsupported_reason(_P(Parameterisation(base, ["mie_g2"])))
    assert "boundary-layer" in BatchedLikelihood.unsupported_reason(_P(Parameterisation(base, ["mie_mixing_height"])))
    assert BatchedLikelihood.unsupported_reason(_P(Parameterisation(base, ["mie_g"]))) == ""


def test_shipped_configs_unchanged():
    """The shipped configs keep the exponential profile and their phase (regression pin of the defaults)."""
    from skyfit.atmosphere import read_config

    cfg, _ = read_config("kider")
    atm = atmosphere_from_config({k: v for k, v in cfg.items() if k != "fit"}, [550.0])
    assert atm.mie_profile == "exponential" and atm.mie_phase == "henyey_greenstein" and atm.mixing_heights is None
