"""The lognormal_mie aerosol (skyfit/atmosphere/mie.py, docs/aerosol.md): Mie optics of a log-normal size
distribution, tabulated with miepython and averaged in torch.

Expected values come from closed forms (Bohren & Huffman 1983: the Rayleigh limit eqs. 5.7-5.8, the
extinction paradox Q_ext -> 2 of Sec. 4.4), from miepython's own S1_S2 path (``i_unpolarized``, not the
table's recurrence) and from scipy ``quad``/``quad_vec`` of the size-distribution integrals with miepython's
efficiencies at every radius quad asks for (not the table's nodes), all in float64. Synthetic skies are
rendered from config dicts (``atmosphere_from_config``), not through the fit's parameterisation.
"""
from __future__ import annotations

import math

import miepython
import numpy as np
import pytest
import torch
from scipy.integrate import quad

from skyfit.atmosphere import atmosphere_from_config
from skyfit.tools.reference import lognormal_mie_quad
from skyfit.atmosphere.mie import (
    LN_X_STEP, PHASE_COSINES, effective_radius, effective_variance, lognormal_mie_optics,
    mie_size_table,
)
from skyfit.fit import Parameterisation
from skyfit.fit.parameters import PARAMETERS, FitError
from skyfit.scattering import lognormal_mie_phase, mie_phase, single_scattering, tabulated_phase
from skyfit.transmittance import make_integrator
from test_select import _cfg

D64, F32 = torch.float64, torch.float32
M = (1.45, 0.005)
M_MIE = complex(M[0], -M[1])  # miepython's sign: m = n - ik absorbs
RB = 6_360_000.0


def _t(v, dtype=D64):
    return torch.tensor(v, dtype=dtype)


def _node(x: float) -> int:
    return round(math.log(x) / LN_X_STEP)


# -- single spheres -------------------------------------------------------------------------------------

def test_rayleigh_limit_of_the_table():
    """x << 1: Q_sca = 8/3 x^4 |K|^2 and Q_abs = 4 x Im K, K = (m^2 - 1) / (m^2 + 2) (Bohren & Huffman eqs. 5.7,
    5.8 with m = n + ik); corrections are O(x^2), 1e-4 at x = 0.01."""
    k = _node(0.01)
    tab = mie_size_table(M, k - 2, k + 2)
    x = np.exp(tab.ln_x)
    m = complex(*M)
    K = (m * m - 1) / (m * m + 2)
    np.testing.assert_allclose(tab.q_sca, 8 / 3 * x**4 * abs(K) ** 2, rtol=1e-3)
    np.testing.assert_allclose(tab.q_ext - tab.q_sca, 4 * x * K.imag, rtol=1e-3)
    # the dipole phase: 3 / (16 pi) (1 + cos^2) (Rayleigh), on the nodes
    np.testing.assert_allclose(tab.phase[2], 3 / (16 * math.pi) * (1 + PHASE_COSINES**2), rtol=1e-3)


def test_extinction_paradox_and_phase_against_miepython_s1_s2():
    """Large spheres extinguish twice their area (Bohren & Huffman Sec. 4.4.5): Q_ext -> 2 + O(x^-2/3); the
    table's phase rows (own pi_n / tau_n recurrence, eq. 4.47) equal miepython's i_unpolarized (norm 'one')."""
    k = _node(480.0)
    big = mie_size_table(M, k, k)
    assert abs(float(big.q_ext[0]) - 2.0) < 0.05
    assert float(big.q_ext[0]) > float(big.q_sca[0]) > 1.0  # absorbing: about half of the area's light absorbed
    for x0, rtol in ((1.0, 1e-4), (20.0, 2e-3)):
        kk = _node(x0)
        tab = mie_size_table(M, kk, kk)
        x = float(np.exp(tab.ln_x[0]))
        ref = miepython.i_unpolarized(M_MIE, x, PHASE_COSINES, norm="one")
        np.testing.assert_allclose(tab.phase[0], ref, rtol=rtol)  # rows renormalised on the nodes: raw - 1 = rtol
        qe, qs, _, g = miepython.efficiencies_mx(M_MIE, x)
        assert tab.q_ext[0] == pytest.approx(qe, rel=1e-12) and tab.g[0] == pytest.approx(g, rel=1e-12)


# -- the size distribution ---------------------------------------------------------------------------------

def _reference_averages(r_g, sigma_g, lam_nm):
    """C_ext, C_sca, <g> of the truncated log-normal by scipy quad_vec over ln r with miepython at each radius."""
    return lognormal_mie_quad(r_g, sigma_g, lam_nm, M)


def test_distribution_averages_against_quad():
    """r_g 0.1 um, sigma_g 1.8, 450 nm: cross-sections, albedo and asymmetry against quad_vec of miepython's
    efficiencies (the node interpolation errs by ~(h p)^2 / 8: 1e-3 at most); the averaged phase integrates to 1
    (quad over its linear pieces) and its first moment is the asymmetry to the angle grid's 2e-3."""
    lam = [450.0]
    o = lognormal_mie_optics(_t(lam), _t(0.1e-6), _t(1.8), M)
    for i, wl in enumerate(lam):
        ce, cs, g = _reference_averages(0.1e-6, 1.8, wl)
        assert float(o.extinction[i]) == pytest.approx(ce, rel=1e-3)
        assert float(o.scattering[i]) == pytest.approx(cs, rel=1e-3)
        assert float(o.ssa[i]) == pytest.approx(cs / ce, abs=1e-4)
        assert float(o.asymmetry[i]) == pytest.approx(g, abs=1e-3)
        # the renderers' phase is np.interp of the nodes (checked at random nu), which quad integrates below
        table = o.phase[i].numpy()
        c = torch.rand(1000, generator=torch.Generator().manual_seed(0), dtype=D64) * 2 - 1
        torch.testing.assert_close(tabulated_phase(c, o.cosines, o.phase[i : i + 1])[:, 0],
                                   torch.from_numpy(np.interp(c.numpy(), PHASE_COSINES, table)), rtol=1e-12, atol=0)

        def p(c):
            return float(np.interp(c, PHASE_COSINES, table))

        pts = PHASE_COSINES[1:-1]
        norm = 2 * math.pi * quad(p, -1, 1, points=pts, limit=2000, epsabs=1e-12)[0]
        mean = 2 * math.pi * quad(lambda c: c * p(c), -1, 1, points=pts, limit=2000, epsabs=1e-12)[0]
        assert norm == pytest.approx(1.0, abs=1e-9)
        assert mean == pytest.approx(g, abs=2e-3)


@pytest.mark.parametrize("on_node,tol", [(True, (2e-5, 5e-6, 5e-5, 3e-3)), (False, (1e-3, 5e-5, 5e-4, 1.5e-2))])
def test_narrow_distribution_is_the_single_sphere(on_node, tol):
    """sigma_g = 1.001: the averages are the sphere of radius r_g (miepython at that x ~ 3.4, 550 nm). With x on a
    node of the table they are its values; half-way between nodes, the table's linear interpolation in ln x
    (2 % steps) errs by 6e-4 in C_ext and 0.9 % in the phase at 180 deg (tolerances: C_ext, albedo, g, phase)."""
    lam, sg = 550.0, 1.001
    k = _node(3.4)
    x = math.exp((k + (0.0 if on_node else 0.5)) * LN_X_STEP)
    # the area-weighted median sits e^{2 ln^2 sigma_g} above r_g: put it on x
    r_g = x * lam * 1e-9 / (2 * math.pi) * math.exp(-2 * math.log(sg) ** 2)
    o = lognormal_mie_optics(_t([lam]), _t(r_g), _t(sg), M)
    qe, qs, _, g = miepython.efficiencies_mx(M_MIE, x)
    area = math.pi * (x * lam * 1e-9 / (2 * math.pi)) ** 2
    assert float(o.extinction[0]) == pytest.approx(area * qe, rel=tol[0])
    assert float(o.ssa[0]) == pytest.approx(qs / qe, abs=tol[1])
    assert float(o.asymmetry[0]) == pytest.approx(g, abs=tol[2])
    mu = np.array([-1.0, -0.5, 0.0, 0.5, 0.9, 1.0])
    got = lognormal_mie_phase(_t(mu), _t([lam]), _t(r_g), _t(sg), M)[:, 0].numpy()
    np.testing.assert_allclose(got, miepython.i_unpolarized(M_MIE, x, mu, norm="one"), rtol=tol[3])


def test_effective_radius_and_variance_against_quad():
    """Hansen & Travis 1974 eqs. 2.53-2.54 for the log-normal: r_eff = r_g exp(5/2 ln^2 sg), v_eff = exp(ln^2 sg) - 1."""
    r_g, sg = 0.1e-6, 1.8
    s = math.log(sg)

    def moment(p, c=0.0):
        return quad(lambda t: (math.exp(t) - c) ** (p - 2) * math.exp(2 * t) * math.exp(-0.5 * ((t - math.log(r_g)) / s) ** 2),
                    math.log(r_g) - 12 * s, math.log(r_g) + 14 * s, epsrel=1e-12)[0]

    r_eff = moment(3) / moment(2)
    assert effective_radius(r_g, sg) == pytest.approx(r_eff, rel=1e-9)
    assert effective_variance(sg) == pytest.approx(moment(4, r_eff) / (r_eff**2 * moment(2)), rel=1e-7)


# -- gradients -----------------------------------------------------------------------------------------------

@pytest.mark.parametrize("r_um,sg", [(0.1, 1.8), (0.02, 1.05), (1.5, 2.8)])
def test_gradcheck_phase_and_spectrum(r_um, sg):
    """Phase at nu = -1, 0.3, 0.9999, 1 and the extinction spectrum, albedo and asymmetry in (ln r_g, sigma_g)."""
    nu = _t([-1.0, -0.77, 0.3, 0.9999, 1.0])
    lam = _t([420.0, 550.0, 680.0])

    def f(log_r, sigma):
        o = lognormal_mie_optics(lam, torch.exp(log_r), sigma, M)
        p = tabulated_phase(nu, o.cosines, o.phase).reshape(-1)
        return torch.cat([p, o.extinction / o.extinction[1], o.ssa, o.asymmetry])

    args = (_t(math.log(r_um * 1e-6)).requires_grad_(True), _t(sg).requires_grad_(True))
    assert torch.autograd.gradcheck(f, args, eps=1e-6, atol=1e-8, rtol=1e-4)


def test_gradcheck_in_nu_at_the_ends():
    o = lognormal_mie_optics(_t([550.0]), _t(0.2e-6), _t(1.6), M)
    nu = _t([-1.0, -0.3, 0.42, 1.0]).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda c: tabulated_phase(c, o.cosines, o.phase), (nu,), eps=1e-7, atol=1e-6)


def _lcfg(r_um=0.12, sigma=1.7, index=M, beta_550=6e-5, **mie):
    cfg = _cfg(beta_550=beta_550)
    m = cfg["mie"]
    for k in ("angstrom_alpha", "single_scattering_albedo", "g"):
        m.pop(k, None)
    m.update(phase="lognormal_mie", median_radius_um=r_um, geometric_sigma=sigma, refractive_index=list(index), **mie)
    return cfg


def _hg(**mie):
    cfg = _cfg(beta_550=6e-5)
    cfg["mie"].update({"phase": "henyey_greenstein", "g": 0.75, **mie})
    return cfg


def _rays(dtype=D64):
    r = torch.full((5,), RB + 50.0, dtype=dtype)
    mu = torch.tensor([0.9, 0.3, 0.0, -0.1, 0.5], dtype=dtype)
    mu_s = torch.tensor([0.5, 0.5, 0.5, 0.5, 0.5], dtype=dtype)
    nu = torch.tensor([0.3, -0.9, 0.95, 0.0, 1.0], dtype=dtype)
    return r, mu, mu_s, nu


def test_render_gradcheck_through_the_parameterisation():
    """Single-scattering radiance (Chapman, 8 Gauss nodes) is differentiable in mie_median_radius,
    mie_geometric_sigma and mie_aod_550 from a Henyey-Greenstein config (float64 gradcheck)."""
    base = atmosphere_from_config(_hg(), [450.0, 550.0, 650.0])
    p = Parameterisation(base, ["mie_median_radius", "mie_geometric_sigma", "mie_aod_550"])
    integ = make_integrator("chapman")
    r, mu, mu_s, nu = _rays()

    def radiance(x):
        return single_scattering(p.atmosphere(p.to_physical(x)), r, mu, mu_s, nu, integ, view_samples=8, rule="gauss")

    x = p.initial_vector().requires_grad_(True)
    assert torch.autograd.gradcheck(radiance, (x,), eps=1e-6, atol=1e-10, rtol=1e-4)


# -- the stability grid ----------------------------------------------------------------------------------------

@pytest.mark.parametrize("dtype", [F32, D64])
def test_stability_at_the_ends_of_the_ranges(dtype):
    """The corners of mie_median_radius x mie_geometric_sigma (their fit ranges, just inside) and sigma_g -> 1:
    phase, albedo and radiance finite and positive at nu = +-1, gradients finite, float32 and float64."""
    rs, ss = PARAMETERS["mie_median_radius"], PARAMETERS["mie_geometric_sigma"]
    base = atmosphere_from_config(_hg(), [380.0, 550.0, 780.0]).to(dtype)
    integ = make_integrator("chapman")
    r, mu, mu_s, nu = _rays(dtype)
    nu_grid = torch.tensor([-1.0, -0.5, 0.0, 0.5, 0.999999, 1.0], dtype=dtype)
    corners = [(rv, sv) for rv in (rs.lo * 1.0001, rs.hi * 0.9999) for sv in (ss.lo * 1.0001, ss.hi * 0.9999)]
    for rv, sv in corners + [(0.2e-6, 1.0001)]:
        lr = torch.tensor(math.log(rv), dtype=dtype, requires_grad=True)
        sg = torch.tensor(sv, dtype=dtype, requires_grad=True)
        o = lognormal_mie_optics(base.wavelengths, torch.exp(lr), sg, M)
        ph = tabulated_phase(nu_grid, o.cosines, o.phase)
        assert ph.dtype == dtype and bool(torch.isfinite(ph).all()) and bool((ph > 0).all()), (rv, sv)
        assert bool(((o.ssa > 0) & (o.ssa <= 1)).all()) and bool(((o.asymmetry > -1) & (o.asymmetry < 1)).all())
        (ph.sum() + o.ssa.sum() + (o.extinction / o.extinction[1]).sum()).backward()
        assert math.isfinite(float(lr.grad)) and math.isfinite(float(sg.grad)), (rv, sv)
        if sv > 1.01:
            p = Parameterisation(base, ["mie_median_radius", "mie_geometric_sigma"],
                                 values={"mie_median_radius": rv, "mie_geometric_sigma": sv})
            x = p.initial_vector(dtype).requires_grad_(True)
            L = single_scattering(p.atmosphere(p.to_physical(x)), r, mu, mu_s, nu, integ, view_samples=8, rule="gauss")
            assert bool(torch.isfinite(L).all()) and bool((L >= 0).all()), (rv, sv)
            L.sum().backward()
            assert bool(torch.isfinite(x.grad).all()), (rv, sv)


def _grid_rays(atm, dtype):
    """Rays of the coarse stability grid (skyfit.tools.stability.COARSE): ground, top, space x sun zenith 0, 90.27,
    108 deg x views mu = 1, 0.3, 0, -0.1, -1 towards and away from the sun (nu = +-1 among them)."""
    top = atm.top_radius - atm.bottom_radius
    rows = []
    for h in (0.0, top, 2 * top):
        for sz in (0.0, 90.27, 108.0):
            ms = math.cos(math.radians(sz))
            for m in (1.0, 0.3, 0.0, -0.1, -1.0):
                for sign in (1.0, -1.0):
                    rows.append((atm.bottom_radius + h, m, ms, m * ms + sign * math.sqrt((1 - m * m) * (1 - ms * ms))))
    return (torch.tensor(c, dtype=dtype) for c in zip(*rows))


@pytest.mark.parametrize("dtype", [F32, D64])
def test_stability_on_the_extreme_grid(dtype):
    """docs/stability.md's coarse grid (aerosol scale heights 10 m and 100 km, beta_550 0 and 1e-2 /m, observer on
    the ground, at the top and in space, sun at 0, 90.27 and 108 deg) with the lognormal_mie phase at the corners of
    its fit ranges: single-scattering radiance (Chapman) finite and >= 0, its gradient in (ln r_g, sigma_g) finite."""
    rs, ss = PARAMETERS["mie_median_radius"], PARAMETERS["mie_geometric_sigma"]
    base = atmosphere_from_config(_lcfg(), [380.0, 550.0, 780.0]).to(dtype)
    r, mu, mu_s, nu = _grid_rays(base, dtype)
    integ = make_integrator("chapman")
    lam = torch.cat([base.wavelengths, base.wavelengths.new_tensor([550.0])])
    for rv in (rs.lo * 1.0001, rs.hi * 0.9999):
        for sv in (ss.lo * 1.0001, ss.hi * 0.9999):
            for h_m in (10.0, 100_000.0):
                for beta in (0.0, 1e-2):
                    lr = torch.tensor(math.log(rv), dtype=dtype, requires_grad=True)
                    sg = torch.tensor(sv, dtype=dtype, requires_grad=True)
                    o = lognormal_mie_optics(lam, torch.exp(lr), sg, M)
                    ext = beta * o.extinction[:-1] / o.extinction[-1]
                    atm = base.replace(mie_median_radius=torch.exp(lr), mie_geometric_sigma=sg, mie_extinction=ext,
                                       mie_scattering=ext * o.ssa[:-1], mie_scale_height=torch.tensor(h_m, dtype=dtype))
                    L = single_scattering(atm, r, mu, mu_s, nu, integ, view_samples=8, rule="gauss")
                    case = (rv, sv, h_m, beta)
                    assert bool(torch.isfinite(L).all()) and bool((L >= 0).all()), case
                    if beta > 0:
                        gl, gs = torch.autograd.grad(L.sum(), (lr, sg))
                        assert math.isfinite(float(gl)) and math.isfinite(float(gs)), case


# -- configs and parameters --------------------------------------------------------------------------------------

def test_config_keys_and_refusals():
    atm = atmosphere_from_config(_lcfg(), [440.0, 550.0, 800.0])
    assert atm.mie_phase == "lognormal_mie" and atm.mie_refractive_index == M
    assert float(atm.mie_median_radius) == pytest.approx(0.12e-6) and float(atm.mie_geometric_sigma) == 1.7
    assert float(atm.mie_extinction[1]) == pytest.approx(6e-5, rel=1e-12)  # extinction_550 sets the amount
    o = lognormal_mie_optics(_t([440.0, 550.0, 800.0]), _t(0.12e-6), _t(1.7), M)
    torch.testing.assert_close(atm.mie_extinction, 6e-5 * o.extinction / o.extinction[1])
    torch.testing.assert_close(atm.mie_scattering / atm.mie_extinction, o.ssa)
    assert float(atm.mie_g) == pytest.approx(float(o.asymmetry[1]), abs=1e-12)
    # angstrom_beta is the optical depth at 1 um
    cfg = _lcfg()
    cfg["mie"].pop("extinction_550")
    cfg["mie"]["angstrom_beta"] = 0.05
    cfg.pop("ozone")
    atm = atmosphere_from_config(cfg, [550.0, 1000.0])
    assert float(atm.mie_extinction[1]) * float(atm.mie_scale_height) == pytest.approx(0.05, rel=1e-12)
    for bad, match in ((_lcfg(angstrom_alpha=1.0), "derives the Angstrom exponent"),
                       (_lcfg(g=0.7), "mie.g: phase lognormal_mie derives"),
                       (_hg(median_radius_um=0.1), "belong to phase: lognormal_mie"),
                       (_lcfg(index=(1.5,)), "refractive_index must be"),
                       (_lcfg(index=(1.5, -0.01)), "imaginary part >= 0"),
                       (_lcfg(r_um=50.0), "median radius must be in"),
                       (_lcfg(sigma=1.0), "geometric_sigma must be in")):
        with pytest.raises(ValueError, match=match):
            atmosphere_from_config(bad, [550.0])
    with pytest.raises(ValueError, match="covers 250-5000 nm"):
        atmosphere_from_config(_lcfg(), [200.0, 550.0])
    with pytest.raises(ValueError, match="depends on the wavelength"):
        mie_phase(_t([0.0]), _t(0.7), "lognormal_mie")


def test_cli_refuses_a_derived_key_in_one_line(tmp_path, capsys):
    import yaml
    from _cli import run

    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump(_lcfg(angstrom_alpha=1.3)))
    rc, _, err = run(["render", path, "--out", tmp_path / "x.exr", "--size", "4", "--sun-zenith", "30"], capsys)
    assert rc == 2 and "lognormal_mie" in err and len(err.strip().splitlines()) == 1, err


def test_parameters_switch_phase_refuse_derived_and_report():
    base = atmosphere_from_config(_hg(), [450.0, 550.0, 650.0])
    p = Parameterisation(base, ["mie_median_radius", "mie_geometric_sigma", "mie_aod_550"],
                         values={"mie_median_radius": 0.2e-6, "mie_geometric_sigma": 1.5, "mie_aod_550": 0.2})
    x = p.initial_vector()
    atm = p.atmosphere(p.to_physical(x))
    assert atm.mie_phase == "lognormal_mie" and atm.mie_refractive_index == (1.45, 0.005)
    assert float(atm.mie_extinction[1]) * 1200.0 == pytest.approx(0.2, rel=1e-12)  # AOD = beta_550 H_M
    o = lognormal_mie_optics(_t([440.0, 550.0, 870.0]), _t(0.2e-6), _t(1.5), M)
    d = p.derived(p.to_physical(x))
    alpha = -math.log(float(o.extinction[0] / o.extinction[2])) / math.log(440 / 870)
    assert d["mie_angstrom_alpha"] == pytest.approx(alpha, rel=1e-12)
    assert d["mie_g"] == pytest.approx(float(o.asymmetry[1]), rel=1e-12)
    assert d["mie_ssa"] == pytest.approx(float(o.ssa[1]), rel=1e-12)
    assert d["mie_effective_radius"] == pytest.approx(effective_radius(0.2e-6, 1.5))
    phys = p.physical_dict(x)
    assert phys["mie_g"] == d["mie_g"] and "mie_effective_radius" not in phys  # only parameter names there
    for free in (["mie_median_radius", "mie_g"], ["mie_geometric_sigma", "mie_angstrom_alpha"]):
        with pytest.raises(FitError, match="lognormal_mie phase derives the asymmetry"):
            Parameterisation(base, free)
    lbase = atmosphere_from_config(_lcfg(), [450.0, 550.0, 650.0])
    with pytest.raises(FitError, match="free mie_median_radius, mie_geometric_sigma instead"):
        Parameterisation(lbase, ["mie_ssa"])
    # the config's distribution with only the amount fitted keeps its spectral shape; mie_beta_550 is the 550 nm value
    q = Parameterisation(lbase, ["mie_beta_550"])
    assert q.values["mie_beta_550"] == pytest.approx(6e-5, rel=1e-12)
    a2 = q.atmosphere(q.to_physical(q.to_unconstrained({"mie_beta_550": 3e-5})))
    torch.testing.assert_close(a2.mie_extinction, lbase.mie_extinction / 2)
    torch.testing.assert_close(a2.mie_scattering, lbase.mie_scattering / 2)


def test_batched_sampler_and_bruneton2017_refuse():
    from skyfit.fit.batched import BatchedLikelihood

    class _P:  # the fields unsupported_reason reads
        def __init__(self, param):
            self.param = param
            self.model = type("M", (), {"orders": 1, "integrator": make_integrator("chapman")})()
            self.observations = []

    base = atmosphere_from_config(_hg(), [450.0, 550.0])
    assert "lognormal_mie" in BatchedLikelihood.unsupported_reason(_P(Parameterisation(base, ["mie_median_radius"])))
    assert BatchedLikelihood.unsupported_reason(_P(Parameterisation(base, ["mie_g"]))) == ""


def test_lut_summary_round_trip():
    from skyfit.export.lut import _atmosphere_from_summary

    atm = atmosphere_from_config(_lcfg(), [450.0, 550.0])
    back = _atmosphere_from_summary(atm.summary(), D64, "cpu")
    assert back.mie_refractive_index == M and back.mie_phase == "lognormal_mie"
    nu = _t([-0.5, 0.5])
    from skyfit.scattering import spectral_mie_phase

    torch.testing.assert_close(spectral_mie_phase(nu, back), spectral_mie_phase(nu, atm))


# -- multiple scattering: Bruneton's tables take the phase per wavelength -------------------------------------

def test_bruneton_tables_keep_wavelengths_apart():
    """Every wavelength of the tables is independent: orders 1-3 of a two-wavelength lognormal_mie atmosphere equal
    those of each wavelength alone (so the per-wavelength phase is applied to its own wavelength, in the density
    integral's einsum too), and the rewrite equals the reference implementation."""
    from skyfit.scattering.bruneton_reference import precompute_reference
    from skyfit.scattering.multiple import precompute, sky_radiance
    from test_multiple import TINY, TINY_QUAD

    lam = [450.0, 700.0]
    both = atmosphere_from_config(_lcfg(r_um=0.3, sigma=1.5), lam)
    tab = precompute(both, orders=3, sizes=TINY, quadrature=TINY_QUAD)
    r = torch.full((3,), RB + 10.0, dtype=D64)
    mu, mu_s, nu = _t([0.8, 0.2, 0.5]), _t([0.6, 0.6, 0.3]), _t([0.9, -0.4, 0.2])
    got = sky_radiance(tab, None, r, mu, mu_s, nu, ground=False)
    for i, wl in enumerate(lam):
        one = precompute(atmosphere_from_config(_lcfg(r_um=0.3, sigma=1.5), [wl]), orders=3, sizes=TINY, quadrature=TINY_QUAD)
        torch.testing.assert_close(got[:, i], sky_radiance(one, None, r, mu, mu_s, nu, ground=False)[:, 0], rtol=1e-12, atol=0)
    ref = precompute_reference(both, orders=3, sizes=TINY, quadrature=TINY_QUAD)
    torch.testing.assert_close(sky_radiance(ref, None, r, mu, mu_s, nu, ground=False), got, rtol=1e-10, atol=0)
    # the phase differs between the two wavelengths, so this is not a one-phase case in disguise
    p = lognormal_mie_phase(_t([0.9]), _t(lam), both.mie_median_radius, both.mie_geometric_sigma, M)
    assert abs(float(p[0, 0] / p[0, 1]) - 1) > 0.15


def test_hillaire_multiple_scattering_takes_it():
    """Hillaire's LUT (orders >= 2 isotropic, Hillaire 2020 Sec. 5.5) on top of the per-wavelength single scattering:
    finite, and above single scattering at every view and wavelength."""
    from skyfit.camera.fisheye import zenith_azimuth_to_enu
    from skyfit.fit import SkyModel
    from skyfit.render.sky import render_vectors

    atm = atmosphere_from_config(_lcfg(), [450.0, 550.0, 650.0])
    dirs = zenith_azimuth_to_enu(_t([0.1, 0.8, 1.4, 1.55]), _t([0.0, 1.0, 2.0, 3.0]))
    sun = zenith_azimuth_to_enu(_t(0.9), _t(2.0))
    m = SkyModel(make_integrator("chapman"), orders=2, view_samples=8, rule="gauss")
    two = render_vectors(atm, dirs, sun, m.integrator, 0.0, 2, tables=m.tables(atm), multiple="hillaire", view_samples=8,
                         rule="gauss")
    one = render_vectors(atm, dirs, sun, m.integrator, 0.0, 1, view_samples=8, rule="gauss")
    assert bool(torch.isfinite(two).all()) and bool((two > one).all())
