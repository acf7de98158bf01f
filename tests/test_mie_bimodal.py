"""The coarse mode of the lognormal_mie aerosol (skyfit/atmosphere/mie.py ``lognormal_mie_optics(..., coarse)``,
docs/aerosol.md): a fine and a coarse log-normal mode of the same spheres mixed by the fine mode's share eta of
the 550 nm extinction.

Expected values: scipy ``quad_vec`` over each mode's size distribution with miepython's efficiencies at every radius
(:func:`skyfit.tools.reference.lognormal_mie_quad`, not the table), mixed with particle numbers n_f = eta / C_ext,f(550)
and n_c = (1 - eta) / C_ext,c(550) as the definition of the two-mode distribution says; the limits eta = 1 and 0 (one
mode); gradcheck; synthetic recovery within the Laplace sigma; the extreme grid in float32 and float64.
"""
from __future__ import annotations

import math

import pytest
import torch

from skyfit.atmosphere import atmosphere_from_config
from skyfit.atmosphere.config import ConfigError
from skyfit.atmosphere.mie import lognormal_mie_optics, mode_mie_optics
from skyfit.fit import FitOptions, FitProblem, Parameterisation, fit, make_loss
from skyfit.fit.laplace import laplace_summary
from skyfit.fit.parameters import PARAMETERS
from skyfit.scattering import lognormal_mie_phase, single_scattering
from skyfit.tools.reference import lognormal_mie_quad
from skyfit.transmittance import make_integrator
from test_mie_lognormal import M, _grid_rays, _lcfg, _rays
from test_select import LAM, _model, synthetic

D64, F32 = torch.float64, torch.float32
FINE, COARSE = (0.09e-6, 1.6), (0.7e-6, 1.9)


def _t(v, dtype=D64):
    return torch.tensor(v, dtype=dtype)


def _coarse(r=COARSE[0], s=COARSE[1], eta=0.6, dtype=D64, grad=False):
    return tuple(torch.tensor(v, dtype=dtype, requires_grad=grad) for v in (r, s, eta))


def _bcfg(eta=0.6, r_c_um=0.7, **kw):
    return _lcfg(r_um=0.09, sigma=1.6, coarse_median_radius_um=r_c_um, coarse_geometric_sigma=1.9,
                 fine_fraction=eta, **kw)


def test_mixture_against_quad_of_each_mode():
    """Extinction spectrum (relative to 550 nm), albedo and asymmetry of the two-mode aerosol at 440 / 550 / 870 nm
    against quad_vec of each mode mixed by particle number (table interpolation errs by ~1e-3)."""
    lam = [440.0, 550.0, 870.0]
    eta = 0.6
    o = lognormal_mie_optics(_t(lam), _t(FINE[0]), _t(FINE[1]), M, _coarse(eta=eta))
    f = [lognormal_mie_quad(*FINE, wl, M) for wl in lam]
    c = [lognormal_mie_quad(*COARSE, wl, M) for wl in lam]
    n_f, n_c = eta / f[1][0], (1 - eta) / c[1][0]
    for i in range(3):
        ext = n_f * f[i][0] + n_c * c[i][0]
        sca = n_f * f[i][1] + n_c * c[i][1]
        g = (n_f * f[i][1] * f[i][2] + n_c * c[i][1] * c[i][2]) / sca
        assert float(o.extinction[i] / o.extinction[1]) == pytest.approx(ext / (n_f * f[1][0] + n_c * c[1][0]), rel=2e-3)
        assert float(o.ssa[i]) == pytest.approx(sca / ext, abs=5e-4)
        assert float(o.asymmetry[i]) == pytest.approx(g, abs=2e-3)
    # eta is the fine mode's share of the extinction at 550 nm, by construction of the numbers
    fine_550 = mode_mie_optics(_t([550.0]), _t(FINE[0]), _t(FINE[1]), M).extinction[0]
    n_total = eta / float(fine_550) + (1 - eta) / c[1][0]
    assert (eta / float(fine_550)) * float(fine_550) / (float(o.extinction[1]) * n_total) == pytest.approx(eta, rel=2e-3)


def test_limits_are_one_mode():
    """eta = 1 is the fine mode alone and eta = 0 the coarse mode alone (cross-sections per particle, phase, albedo);
    the mixture's phase integrates to 1 and its forward peak lies between the modes'."""
    lam = _t([450.0, 650.0])
    fine = mode_mie_optics(lam, _t(FINE[0]), _t(FINE[1]), M)
    crs = mode_mie_optics(lam, _t(COARSE[0]), _t(COARSE[1]), M)
    one = lognormal_mie_optics(lam, _t(FINE[0]), _t(FINE[1]), M, _coarse(eta=1.0))
    zero = lognormal_mie_optics(lam, _t(FINE[0]), _t(FINE[1]), M, _coarse(eta=0.0))
    for mixed, mode in ((one, fine), (zero, crs)):
        for name in ("extinction", "scattering", "ssa", "asymmetry", "phase"):
            torch.testing.assert_close(getattr(mixed, name), getattr(mode, name), rtol=1e-12, atol=0)
    mid = lognormal_mie_optics(lam, _t(FINE[0]), _t(FINE[1]), M, _coarse(eta=0.5))
    c = mid.cosines
    norm = 2 * math.pi * torch.trapezoid(mid.phase, c, dim=-1)
    torch.testing.assert_close(norm, torch.ones(2, dtype=D64), rtol=1e-10, atol=0)
    assert bool((fine.phase[:, -1] < mid.phase[:, -1]).all()) and bool((mid.phase[:, -1] < crs.phase[:, -1]).all())


def test_gradcheck_in_all_five_values():
    """The mixture's phase at a few angles and its extinction spectrum are differentiable in r_f, sigma_f, r_c,
    sigma_c and eta (float64 gradcheck)."""
    lam = _t([450.0, 550.0, 700.0])
    nu = _t([-1.0, 0.0, 0.9, 0.999, 1.0])

    def f(rf, sf, rc, sc, eta):
        o = lognormal_mie_optics(lam, rf, sf, M, (rc, sc, eta))
        p = lognormal_mie_phase(nu, lam, rf, sf, M, (rc, sc, eta))
        return torch.cat([o.extinction / o.extinction[1], o.ssa, p.reshape(-1)])

    args = [torch.tensor(v, dtype=D64, requires_grad=True) for v in (0.1e-6, 1.6, 0.8e-6, 1.9, 0.55)]
    # radii enter through ln r; scale them so that gradcheck's eps is relative
    def g(lrf, sf, lrc, sc, eta):
        return f(torch.exp(lrf), sf, torch.exp(lrc), sc, eta)

    x = [torch.log(args[0]).detach().requires_grad_(True), args[1], torch.log(args[2]).detach().requires_grad_(True),
         args[3], args[4]]
    assert torch.autograd.gradcheck(g, tuple(x), eps=1e-6, atol=1e-8, rtol=1e-4)


def test_config_keys():
    """A config's coarse mode loads; eta = 1 renders as the one-mode config; part of the coarse keys is refused."""
    atm = atmosphere_from_config(_bcfg(), [450.0, 550.0, 650.0])
    assert atm.mie_coarse_mode is not None and float(atm.mie_fine_fraction) == 0.6
    one = atmosphere_from_config(_bcfg(eta=1.0), [450.0, 550.0, 650.0])
    plain = atmosphere_from_config(_lcfg(r_um=0.09, sigma=1.6), [450.0, 550.0, 650.0])
    torch.testing.assert_close(one.mie_extinction, plain.mie_extinction, rtol=1e-12, atol=0)
    r, mu, mu_s, nu = _rays()
    integ = make_integrator("chapman")
    torch.testing.assert_close(single_scattering(one, r, mu, mu_s, nu, integ, view_samples=8, rule="gauss"),
                               single_scattering(plain, r, mu, mu_s, nu, integ, view_samples=8, rule="gauss"),
                               rtol=1e-12, atol=0)
    cfg = _bcfg()
    cfg["mie"].pop("fine_fraction")
    with pytest.raises(ConfigError, match="fine_fraction"):
        atmosphere_from_config(cfg, [550.0])
    with pytest.raises(ConfigError, match="coarse"):
        atmosphere_from_config(_bcfg(r_c_um=50.0), [550.0])


def test_synthetic_recovery_within_laplace_sigma():
    """Skies of a fine (0.09 um, 1.6) and a coarse mode (0.7 um, 1.9) with eta 0.6 (sun 50 deg, 160 directions x 6
    wavelengths, 1 % noise, Chapman) fitted from r_c 1.2 um and eta 0.85 with the fine mode, the coarse radius,
    eta, the AOD and the exposure free: three seeds, each within 3 Laplace sigma of the truth."""
    base = atmosphere_from_config(_bcfg(eta=0.85, r_c_um=1.2), LAM)
    truth = _bcfg()
    free = ["mie_median_radius", "mie_geometric_sigma", "mie_coarse_radius", "mie_fine_fraction", "mie_aod_550", "exposure"]
    zs = []
    for seed in range(3):
        obs = synthetic(truth, 50.0, seed=40 + seed, n=160)
        prob = FitProblem(Parameterisation(base, free), _model(), [obs], make_loss("squared"))
        res = fit(prob, FitOptions(starts=1, adam_steps=0, max_iter=150))
        lap = laplace_summary(prob, res.x)
        assert lap["positive_definite"]
        for name, true in (("mie_coarse_radius", 0.7e-6), ("mie_fine_fraction", 0.6), ("mie_median_radius", 0.09e-6)):
            z = (res.parameters[name] - true) / lap["sigma"][name]
            assert abs(z) < 3.0, (seed, name, res.parameters[name], lap["sigma"][name])
            zs.append(z)
    assert max(abs(z) for z in zs) > 0.05  # the fit is not sitting on the truth by construction


@pytest.mark.parametrize("dtype", [F32, D64])
def test_stability_on_the_extreme_grid(dtype):
    """docs/stability.md's coarse grid (aerosol scale heights 10 m and 100 km, beta_550 0 and 1e-2 /m, observer on
    the ground, at the top and in space, sun at 0, 90.27 and 108 deg) with the coarse mode at the corners of its fit
    ranges (r_c, eta at 0 and 1): radiance finite and >= 0, its gradient in (ln r_c, eta) finite."""
    rc_spec = PARAMETERS["mie_coarse_radius"]
    base = atmosphere_from_config(_bcfg(), [380.0, 550.0, 780.0]).to(dtype)
    r, mu, mu_s, nu = _grid_rays(base, dtype)
    integ = make_integrator("chapman")
    lam = torch.cat([base.wavelengths, base.wavelengths.new_tensor([550.0])])
    rf, sf = base.mie_median_radius, base.mie_geometric_sigma
    for rv in (rc_spec.lo * 1.0001, rc_spec.hi * 0.9999):
        for ev in (0.0, 1.0):
            for h_m in (10.0, 100_000.0):
                for beta in (0.0, 1e-2):
                    lr = torch.tensor(math.log(rv), dtype=dtype, requires_grad=True)
                    eta = torch.tensor(ev, dtype=dtype, requires_grad=True)
                    coarse = (torch.exp(lr), base.mie_coarse_sigma, eta)
                    o = lognormal_mie_optics(lam, rf, sf, M, coarse)
                    ext = beta * o.extinction[:-1] / o.extinction[-1]
                    atm = base.replace(mie_coarse_radius=coarse[0], mie_fine_fraction=eta, mie_extinction=ext,
                                       mie_scattering=ext * o.ssa[:-1], mie_scale_height=torch.tensor(h_m, dtype=dtype))
                    L = single_scattering(atm, r, mu, mu_s, nu, integ, view_samples=8, rule="gauss")
                    case = (rv, ev, h_m, beta)
                    assert bool(torch.isfinite(L).all()) and bool((L >= 0).all()), case
                    if beta > 0:
                        gl, ge = torch.autograd.grad(L.sum(), (lr, eta))
                        assert math.isfinite(float(gl)) and math.isfinite(float(ge)), case


def test_float32_agrees_with_float64():
    """The mixture's optics in float32 agree with float64 to 1e-4 relative (phase, albedo, spectrum)."""
    lam = [400.0, 550.0, 700.0]
    o64 = lognormal_mie_optics(_t(lam), _t(FINE[0]), _t(FINE[1]), M, _coarse())
    o32 = lognormal_mie_optics(_t(lam, F32), _t(FINE[0], F32), _t(FINE[1], F32), M, _coarse(dtype=F32))
    for name in ("ssa", "asymmetry", "phase"):
        torch.testing.assert_close(getattr(o32, name).double(), getattr(o64, name), rtol=1e-4, atol=0)
    torch.testing.assert_close((o32.extinction / o32.extinction[1]).double(), o64.extinction / o64.extinction[1],
                               rtol=1e-4, atol=0)


def test_select_takes_the_coarse_mode_only_when_in_the_data():
    """The ladder rayleigh -> mie -> ozone -> lognormal_mie -> coarse_mode: a two-mode sky (eta 0.6) takes the coarse mode
    (strong BIC evidence) and recovers eta within 0.1; a one-mode log-normal sky stops at lognormal_mie."""
    from test_select import _rung, _subset, ladder

    rungs = _subset("rayleigh", "mie", "ozone", "lognormal_mie", "coarse_mode")  # the skies have the config's ozone
    # the config's fine mode (0.07 um, 1.5) is not the truth's (0.09 um, 1.6), so the fine mode must be fitted too
    rep = ladder(_lcfg(r_um=0.07, sigma=1.5), synthetic(_bcfg(), 50.0, seed=31, n=160), rungs).run()
    assert rep["chosen"] == "coarse_mode", rep["why"]
    row = _rung(rep, "coarse_mode")
    assert row["delta_bic_parent"] < -10
    assert row["parameters"]["mie_fine_fraction"] == pytest.approx(0.6, abs=0.1)
    rep2 = ladder(_lcfg(r_um=0.07, sigma=1.5), synthetic(_lcfg(r_um=0.09, sigma=1.6), 50.0, seed=32, n=160), rungs).run()
    assert rep2["chosen"] == "lognormal_mie", rep2["why"]


def test_laplace_sigma_of_the_derived_alpha_g_ssa():
    """RESULT.json's derived alpha (440/870), g and ssa (550 nm) of a two-mode fit carry a delta-method sigma: the
    autograd gradient's sigma equals one from central finite differences of the reported values (1e-4 relative),
    and the values equal the report's."""
    base = atmosphere_from_config(_bcfg(eta=0.85, r_c_um=1.2), LAM)
    free = ["mie_median_radius", "mie_geometric_sigma", "mie_coarse_radius", "mie_fine_fraction", "mie_aod_550", "exposure"]
    obs = synthetic(_bcfg(), 50.0, seed=40, n=160)
    prob = FitProblem(Parameterisation(base, free), _model(), [obs], make_loss("squared"))
    res = fit(prob, FitOptions(starts=1, adam_steps=0, max_iter=150))
    lap = laplace_summary(prob, res.x)
    p = prob.param
    cov = torch.tensor(lap["covariance_unconstrained"], dtype=D64)
    x0 = res.x.detach().to(D64)
    reported = p.lognormal_derived(p.to_physical(x0))
    for name in ("mie_angstrom_alpha", "mie_g", "mie_ssa"):
        d = lap["derived"][name]
        assert d["value"] == pytest.approx(reported[name], rel=1e-12)
        h = 1e-5
        grad = torch.zeros_like(x0)
        for i in range(x0.numel()):
            e = torch.zeros_like(x0)
            e[i] = h
            grad[i] = (p.lognormal_derived(p.to_physical(x0 + e))[name]
                       - p.lognormal_derived(p.to_physical(x0 - e))[name]) / (2 * h)
        assert d["sigma"] == pytest.approx(math.sqrt(float(grad @ cov @ grad)), rel=1e-4)
        assert d["sigma"] > 0


def test_lut_summary_round_trip_keeps_the_coarse_mode():
    """export-lut's lut.json atmosphere summary rebuilds the two-mode aerosol: the same coarse mode and phase."""
    from skyfit.export.lut import _atmosphere_from_summary
    from skyfit.scattering import spectral_mie_phase

    atm = atmosphere_from_config(_bcfg(), [450.0, 550.0])
    back = _atmosphere_from_summary(atm.summary(), D64, "cpu")
    assert back.mie_coarse_mode is not None
    assert float(back.mie_fine_fraction) == pytest.approx(0.6) and float(back.mie_coarse_radius) == pytest.approx(0.7e-6)
    nu = _t([-0.5, 0.5, 0.999])
    torch.testing.assert_close(spectral_mie_phase(nu, back), spectral_mie_phase(nu, atm))
    # and the coarse mode changes the phase (the round trip is not of a one-mode aerosol)
    one = atmosphere_from_config(_lcfg(r_um=0.09, sigma=1.6), [450.0, 550.0])
    assert not torch.allclose(spectral_mie_phase(nu, one), spectral_mie_phase(nu, back), rtol=1e-3)
