"""The error budget (skyfit.fit.budget): numerical shift, discrepancy floor, total sigma.

Independent computations: the numerical term's one Newton step is checked against a brute-force
refit of the same data with the reference renderer (L-BFGS to a tight tolerance); the floor
against synthetic data whose extra relative noise is known; the total sigma against a fit whose
truth comes from a finer renderer than the fit's, at a noise so low that the noise-only sigma
misses the truth by many sigmas (a deterministic analogue of the coverage study,
scripts/coverage_model_error.py).
"""
from __future__ import annotations

import math

import pytest
import torch

from skyfit.atmosphere import atmosphere_from_config
from skyfit.fit import FitOptions, FitProblem, Parameterisation, SkyModel, fit, make_loss
from skyfit.fit.budget import (REFERENCE_QUADRATURE, ReferenceModel, error_budget, fit_floor, reference_problem,
                               refit_shift, uncertainty)
from skyfit.fit.laplace import laplace_summary
from skyfit.fit.parameters import FitError
from skyfit.fit.problem import fit_settings
from skyfit.tools.demo import chain_steps
from skyfit.transmittance import make_integrator

from test_sample import LAM, _config, tiny_observation

FREE = ["mie_beta_550", "mie_scale_height", "mie_g", "rayleigh_scale", "exposure"]
TIGHT = FitOptions(starts=1, adam_steps=0, max_iter=300, grad_tol=1e-12, rel_tol=1e-15)


def _coarse():
    """The fit's renderer: Chapman optical depth."""
    return SkyModel(make_integrator("chapman"), view_samples=4, rule="gauss")


def _fine():
    """The truth's (and the reference's) renderer: 16-node Gauss-Legendre optical depth, same view integral."""
    return SkyModel(make_integrator("gauss", samples=16), view_samples=4, rule="gauss")


@pytest.fixture(scope="module")
def biased_fit():
    """A 10 x 10 sky rendered with the fine model, 0.02 % noise, fitted with the coarse one."""
    torch.manual_seed(0)
    obs, truth = tiny_observation(noise=2e-4, seed=5, integrator="gauss")
    base = atmosphere_from_config(_config(), LAM)
    prob = FitProblem(Parameterisation(base, FREE), _coarse(), [obs], make_loss("squared"))
    res = fit(prob, TIGHT)
    lap = laplace_summary(prob, res.x)
    return prob, res, lap, truth


def test_newton_shift_matches_a_brute_force_refit_with_the_reference(biased_fit):
    """dx = -H^-1 g (one Newton step) vs the optimum of the same data under the reference renderer,
    to 5 % of the shift (the Newton step neglects the change of H along the shift and of delta with x);
    the lagged refits (refit_shift) to 1 %."""
    prob, res, lap, _ = biased_fit
    ref = reference_problem(prob, _fine())
    brute = fit(ref, TIGHT, x0=res.x).x
    b = error_budget(prob, res.x, lap, reference=_fine(), floor=False)
    newton = torch.tensor([b["budget"]["numerical_shift"][n] for n in FREE], dtype=torch.float64)
    v0 = torch.tensor([res.parameters[n] for n in FREE], dtype=torch.float64)
    vb = torch.tensor([ref.param.physical_dict(brute)[n] for n in FREE], dtype=torch.float64)
    shift = vb - v0
    sig = torch.tensor([lap["sigma"][n] for n in FREE], dtype=torch.float64)
    assert bool((shift.abs() > 3 * sig).any())  # a shift the noise sigma alone would miss
    torch.testing.assert_close(newton, shift, rtol=0.05, atol=0.05 * float(sig.min()))
    s_x = torch.tensor([lap["sigma_unconstrained"][n] for n in FREE], dtype=torch.float64)
    rs = refit_shift(prob, res.x, ref, res.x, s_x, iterations=3, options=TIGHT, tol=1e-3)
    torch.testing.assert_close(rs["x"], brute, rtol=0, atol=0.01 * float(s_x.min()))
    # each refit from the fit's Laplace covariance (optimise.curved): the same optimum
    cov = torch.as_tensor(lap["covariance_unconstrained"], dtype=torch.float64)
    rc = refit_shift(prob, res.x, ref, res.x, s_x, iterations=3, options=TIGHT, tol=1e-3, cov_x=cov)
    assert rc["solvers"] == ["curved"] * len(rc["steps"])
    torch.testing.assert_close(rc["x"], brute, rtol=0, atol=0.01 * float(s_x.min()))
    # the numerical sigma is the size of the shift
    for n in FREE:
        assert b["budget"]["sigma_numerical"][n] == pytest.approx(abs(b["budget"]["numerical_shift"][n]), rel=1e-3)


def test_total_sigma_covers_a_truth_the_noise_sigma_misses(biased_fit):
    """Truth from the fine renderer: |error| / sigma_noise > 3 somewhere, |error| / sigma_total <= 2 everywhere."""
    prob, res, lap, truth = biased_fit
    tot = error_budget(prob, res.x, lap, reference=ReferenceModel.of(prob.model))  # the default reference family
    z_noise = {n: (res.parameters[n] - truth[n]) / lap["sigma"][n] for n in FREE}
    z_total = {n: (res.parameters[n] - truth[n]) / tot["sigma"][n] for n in FREE}
    assert max(abs(z) for z in z_noise.values()) > 3, z_noise
    assert max(abs(z) for z in z_total.values()) <= 2, z_total
    for n in FREE:  # total >= each part; the parts add in quadrature on the diagonal
        b = tot["budget"]
        parts = b["sigma_noise"][n] ** 2 + b["sigma_numerical"][n] ** 2 + b["sigma_discrepancy"][n] ** 2
        assert tot["sigma"][n] == pytest.approx(math.sqrt(parts), rel=1e-6)
        assert tot["sigma"][n] >= lap["sigma"][n]
        lo, hi = tot["interval95"][n]
        assert lo <= truth[n] <= hi
    assert tot["sigma_mode"] == "total" and tot["sigma_noise"] == lap["sigma"]


def test_corrected_estimate_is_the_reference_fit_with_the_noise_sigma(biased_fit):
    """``corrected``: the value at x + dx (the fitted value plus ``numerical_shift``), its sigma without the shift.
    With the truth's own renderer as the reference, the corrected estimate is the reference's fit of the same data,
    so its error is the noise's: |error| / sigma_corrected <= 2 where the uncorrected value is > 3 noise sigma off,
    and it is nearer the truth than the fitted value on every parameter the bias moved by more than 3 noise sigma."""
    prob, res, lap, truth = biased_fit
    b = error_budget(prob, res.x, lap, reference=_fine(), floor=False)
    c = b["corrected"]
    moved = [n for n in FREE if abs(res.parameters[n] - truth[n]) > 3 * lap["sigma"][n]]
    assert moved, "the fixture's bias should exceed the noise"
    for n in FREE:
        assert c["values"][n] == pytest.approx(res.parameters[n] + b["budget"]["numerical_shift"][n], rel=1e-9, abs=1e-12)
        assert c["sigma"][n] <= b["sigma"][n] * (1 + 1e-9)
        assert abs(c["values"][n] - truth[n]) <= 2 * c["sigma"][n], (n, c["values"][n], truth[n], c["sigma"][n])
    for n in moved:
        assert abs(c["values"][n] - truth[n]) < abs(res.parameters[n] - truth[n])
    assert c["derived"]["mie_aod_550"]["value"] != pytest.approx(b["derived"]["mie_aod_550"]["value"], rel=1e-6)


def test_floor_recovers_a_known_extra_relative_noise():
    """Data = model (1 + 0.02 N) + sigma N with sigma the stated 1 % noise: chi^2/dof = 5; the floor solving
    chi^2 = dof is 0.02 within its 68 % range (chi^2 at dof +- sqrt(2 dof)) and 10 %."""
    f_true = 0.02
    obs, truth = tiny_observation(noise=0.01, seed=7, size=30)
    base = atmosphere_from_config(_config(), LAM)
    prob = FitProblem(Parameterisation(base, list(truth), values=truth), _coarse(), [obs], make_loss("squared"))
    x = prob.param.initial_vector()
    with torch.no_grad():  # the model the data were rendered with (Chapman, the same view integral)
        clean = prob.predict(x)[0]
    gen = torch.Generator().manual_seed(11)
    extra = clean * f_true * torch.randn(clean.shape, generator=gen, dtype=clean.dtype)
    obs.values[obs.mask] = obs.values[obs.mask] + extra
    preds = [clean]
    phys = prob.param.to_physical(x)
    dof = clean.numel()
    f = fit_floor(prob, preds, dof, phys)
    lo = fit_floor(prob, preds, dof, phys, dof + math.sqrt(2 * dof))
    hi = fit_floor(prob, preds, dof, phys, dof - math.sqrt(2 * dof))
    assert lo <= f_true <= hi, (lo, f, hi)
    assert f == pytest.approx(f_true, rel=0.1)
    # no extra noise: chi^2 at about dof, a floor within its own range of 0
    obs0, _ = tiny_observation(noise=0.01, seed=7, size=30)
    prob0 = FitProblem(Parameterisation(base, list(truth), values=truth), _coarse(), [obs0], make_loss("squared"))
    assert fit_floor(prob0, preds, dof, phys, dof + math.sqrt(2 * dof)) == 0.0


def test_noise_mode_is_the_laplace_summary_and_bad_modes_fail(biased_fit):
    prob, res, lap, _ = biased_fit
    noise = uncertainty(prob, res.x, "noise")
    assert noise["sigma_mode"] == "noise" and "budget" not in noise
    torch.testing.assert_close(noise["sigma"]["mie_g"], lap["sigma"]["mie_g"], rtol=1e-10, atol=0)
    with pytest.raises(FitError, match="sigma must be one of total, noise"):
        uncertainty(prob, res.x, "everything")
    with pytest.raises(FitError, match=r"fit.sigma must be one of total, noise, got 'all'"):
        fit_settings({"sigma": "all"})
    with pytest.raises(FitError, match=r"sigma_reference must be \[R, MU, MU_S, NU, ORDERS\]"):
        fit_settings({"sigma_reference": [16, 64, 16]})


def test_reference_model_adds_bruneton_orders_to_converged_single_scattering():
    """orders 1: the reference is converged single scattering (its Gauss-Legendre nodes); orders 2: plus the
    tables' orders >= 2, which brighten every direction."""
    obs, _ = tiny_observation(noise=0.01, seed=1, size=6)
    base = atmosphere_from_config(_config(), LAM)
    p1 = FitProblem(Parameterisation(base, ["exposure"]), _coarse(), [obs], make_loss("squared"))
    r1 = reference_problem(p1)
    assert r1.model.orders == 1 and r1.model.view_samples == 128
    x = p1.param.initial_vector()
    ms = SkyModel(make_integrator("chapman"), orders=2, view_samples=4, rule="gauss")
    p2 = FitProblem(Parameterisation(base, ["exposure"]), ms, [obs], make_loss("squared"))
    small = ReferenceModel.of(ms, tables=(4, 8, 4, 4), orders=3)
    with torch.no_grad():
        single = r1.predict(x)[0]
        multiple = reference_problem(p2, small).predict(x)[0]
        coarse = p1.predict(x)[0]
        p1.model = SkyModel(make_integrator("gauss", samples=32), view_samples=128, rule="gauss")
        direct = p1.predict(x)[0]
    assert bool((multiple > single).all())
    torch.testing.assert_close(single, direct, rtol=1e-12, atol=0)  # the reference's single scattering
    assert float(((coarse - single) / single).abs().max()) > 0.01  # 4 view samples: not converged
    assert small.settings()["table_orders"] == 3


@pytest.mark.parametrize("tau, done, expected", [(16.5, 150, 990), (72.0, 150, 4320), (100.0, 150, 6000), (1.0, 150, 151),
                                                 (float("nan"), 150, 6000)])
def test_demo_chain_steps_follow_the_tau_rule(tau, done, expected):
    """1.2 x 50 tau steps, at least one more than done, at most the cap."""
    assert chain_steps(tau, done) == expected


def test_a_fit_from_a_known_curvature_reaches_the_lbfgs_optimum_in_fewer_gradients(biased_fit):
    """optimise.curved from 3 noise sigma off the optimum, with the Laplace covariance there: the L-BFGS optimum to 0.01
    sigma in under half its evaluations; with the matrix 4x too large or too small, still there. It gives up (None) with
    a matrix that is not positive definite or too few iterations; refit_shift then refits by L-BFGS, to the same
    optimum."""
    from skyfit.fit.optimise import curved

    prob, res, lap, _ = biased_fit
    cov = torch.as_tensor(lap["covariance_unconstrained"], dtype=torch.float64)
    s_x = torch.tensor([lap["sigma_unconstrained"][n] for n in FREE], dtype=torch.float64)
    start = res.x.detach() + 3 * s_x.to(res.x.dtype) * torch.tensor([1.0, -1.0, 1.0, -1.0, 1.0], dtype=res.x.dtype)
    lb = fit(prob, TIGHT, x0=start)
    cv = curved(prob, start, cov)
    assert cv is not None and cv.convergence["method"] == "bfgs (known curvature)"
    torch.testing.assert_close(cv.x, lb.x, rtol=0, atol=0.01 * float(s_x.min()))
    assert cv.convergence["evaluations"] < 0.5 * lb.convergence["evaluations"], (cv.convergence, lb.convergence)
    for wrong in (4.0, 0.25):  # a curvature taken elsewhere: BFGS corrects it (the stopping rule trusts it: 2x)
        cw = curved(prob, start, wrong * cov)
        assert cw is not None
        torch.testing.assert_close(cw.x, lb.x, rtol=0, atol=0.02 * float(s_x.min()))
    assert curved(prob, start, -cov) is None  # not positive definite
    assert curved(prob, start, cov, iterations=1) is None  # not there in one step
    # there on its last allowed iteration (scipy's status 1 with the gradient under tol): it stands, as the same run
    # with iterations to spare; one iteration fewer is not there
    k = cv.convergence["iterations"]
    assert k > 1
    last = curved(prob, start, cov, iterations=k)
    assert last is not None and torch.equal(last.x, cv.x)
    assert curved(prob, start, cov, iterations=k - 1) is None
    ref = reference_problem(prob, _fine())
    rs = refit_shift(prob, res.x, ref, res.x, s_x, iterations=1, options=TIGHT, cov_x=-cov)
    rn = refit_shift(prob, res.x, ref, res.x, s_x, iterations=1, options=TIGHT, cov_x=cov)
    assert rs["solvers"] == ["lbfgs"] and rn["solvers"] == ["curved"]
    torch.testing.assert_close(rs["x"], rn["x"], rtol=0, atol=0.01 * float(s_x.min()))


def test_refits_run_only_where_the_newton_step_is_not_linear(biased_fit, monkeypatch):
    """A linear shift keeps the Newton step (same sigma as refits=0); a forced lagged refit reports its method,
    the Newton step beside it, and a numerical sigma no smaller than its shift (one refit: + the disagreement)."""
    import skyfit.fit.budget as budget

    prob, res, lap, _ = biased_fit
    b0 = error_budget(prob, res.x, lap, reference=_fine(), floor=False)
    b2 = error_budget(prob, res.x, lap, reference=_fine(), floor=False, refits=2)
    assert b2["budget"]["nonlinearity"] < budget.NONLINEAR and b2["budget"]["method"] == "newton"
    assert b2["sigma"] == b0["sigma"]
    monkeypatch.setattr(budget, "NONLINEAR", -1.0)
    b1 = error_budget(prob, res.x, lap, reference=_fine(), floor=False, refits=1, options=TIGHT)
    assert b1["budget"]["method"] == "refit (1 lagged refits)"
    for n in FREE:
        shift, newton = b1["budget"]["numerical_shift"][n], b1["budget"]["numerical_shift_newton"][n]
        assert shift == pytest.approx(newton, rel=0.1, abs=0.1 * lap["sigma"][n])  # a linear case: both agree
        assert b1["budget"]["sigma_numerical"][n] >= 0.99 * abs(shift)  # J dx vs the mapped shift: to 1 %


def test_prediction_jacobian_and_the_floor_covariance():
    """J by Jacobian-vector products vs central differences (h = 1e-6 in x); the Gauss-Newton covariance
    grows with the floor (cov(f) - cov(0) positive semi-definite) and, for a floor far above the noise,
    as (f / noise)^2 with relative noise (sigma = 1 % of the value)."""
    from skyfit.fit.budget import gauss_newton_covariance, prediction_jacobian

    obs, _ = tiny_observation(noise=0.01, seed=3, size=8)
    base = atmosphere_from_config(_config(), LAM)
    prob = FitProblem(Parameterisation(base, ["mie_g", "exposure"]), _coarse(), [obs], make_loss("squared"))
    x = prob.param.initial_vector()
    J = prediction_jacobian(prob, x)[0]
    h = 1e-6
    with torch.no_grad():
        fd = torch.stack([(prob.predict(x + h * e)[0] - prob.predict(x - h * e)[0]) / (2 * h)
                          for e in torch.eye(2, dtype=torch.float64)], -1)
        m = prob.predict(x)
    torch.testing.assert_close(J, fd, rtol=1e-5, atol=1e-9 * float(fd.abs().max()))
    phys = prob.param.to_physical(x)
    c0 = gauss_newton_covariance(prob, [J], m, 0.0, phys)
    c1 = gauss_newton_covariance(prob, [J], m, 0.05, phys)
    assert float(torch.linalg.eigvalsh(c1 - c0).min()) >= -1e-12 * float(c1.abs().max())
    assert bool((torch.diagonal(c1) > torch.diagonal(c0)).all())
    # sigma = 1 % of the model itself: sigma'^2 = (0.01^2 + 0.05^2) m^2 = 26 sigma^2 everywhere, cov x 26
    prob.observations[0].sigma[prob.observations[0].mask] = 0.01 * m[0]
    torch.testing.assert_close(gauss_newton_covariance(prob, [J], m, 0.05, phys),
                               26.0 * gauss_newton_covariance(prob, [J], m, 0.0, phys), rtol=1e-9, atol=0)


def test_cli_sigma_flag_reaches_the_fit_settings():
    """``skyfit fit --sigma noise`` sets FitSettings.sigma; the default is the total."""
    from skyfit.cli import _fit_overrides, build_parser

    args = build_parser().parse_args(["fit", "sky.exr", "--config", "earth", "--out", "r.json", "--sigma", "noise"])
    assert fit_settings(None, _fit_overrides(args)).sigma == "noise"
    args = build_parser().parse_args(["fit", "sky.exr", "--config", "earth", "--out", "r.json"])
    assert fit_settings(None, _fit_overrides(args)).sigma == "total"
    with pytest.raises(SystemExit):
        build_parser().parse_args(["fit", "sky.exr", "--out", "r.json", "--sigma", "all"])


def test_reference_polish_reaches_the_reference_optimum_also_from_a_bound(biased_fit, monkeypatch):
    """Levenberg-Marquardt on the reference (skyfit.fit.budget.reference_polish) from the fit's optimum, and from the
    same point with H_M on its 20 km bound (where the fit's sigmoid coordinates have no slope), ends at the brute-force
    optimum of the reference (L-BFGS to a tight tolerance) within 0.05 noise sigma in every parameter and at its loss;
    the budget with ``polish`` then shifts x to it (kept because it lowers the reference's loss)."""
    from skyfit.fit.budget import numerical_term, reference_polish

    prob, res, lap, _ = biased_fit
    ref = reference_problem(prob, _fine())
    brute = fit(ref, TIGHT, x0=res.x)
    vb = ref.param.physical_dict(brute.x)
    sig = {n: lap["sigma"][n] for n in FREE}
    x_bound = res.x.clone()
    x_bound[FREE.index("mie_scale_height")] = 40.0
    assert prob.param.physical_dict(x_bound)["mie_scale_height"] == pytest.approx(20000.0)
    for start in (res.x, x_bound):
        pol = reference_polish(prob, ref, start, 12)
        vp = prob.param.physical_dict(pol["x"])
        for n in FREE:
            assert abs(vp[n] - vb[n]) < 0.05 * sig[n], (n, vp[n], vb[n])
        assert pol["loss"] == pytest.approx(brute.loss, rel=1e-6) and pol["loss"] <= pol["loss_start"]
    import skyfit.fit.budget as budget_module

    monkeypatch.setattr(budget_module, "NONLINEAR", -1.0)  # the refits run whatever the Newton step's linearity
    term = numerical_term(prob, res.x, lap, reference=_fine(), refits=1, polish=12,
                          options=FitOptions(starts=1, adam_steps=0, max_iter=3))  # one short refit: far from it
    assert "reference LM steps" in term.budget["method"]
    assert term.budget["polish"]["loss"] < term.budget["polish"]["loss_start"]
    vt = prob.param.physical_dict(res.x + term.dx.to(res.x.dtype))
    for n in FREE:
        assert abs(vt[n] - vb[n]) < 0.05 * sig[n], (n, vt[n], vb[n])


def test_the_reference_of_multiple_scattering_builds_its_tables_for_the_fits_suns():
    """The budget's reference (orders >= 2) spans the fit's suns (REFERENCE_SUN_WINDOW): reference_problem gives it the
    observations' sun zenith span, its tables are a precompute over sun_window of that span (equal to them), its
    settings say so; on a hazy sky with the sun at 30 deg the whole axis of the same texel count is > 5 % off at the
    zenith, where the window agrees with a window of twice its texels to 1 %; with a fitted sun zenith offset (the sun
    moves) it keeps the whole axis; fit.sigma_reference_axis takes window or whole."""
    import copy
    import dataclasses

    from skyfit.atmosphere import load_atmosphere
    from skyfit.scattering.bruneton_tables import TableSizes, sun_window
    from skyfit.scattering.multiple import precompute

    obs, _ = tiny_observation(noise=0.01, seed=1, size=6, sun=(30.0, 120.0))
    hazy = load_atmosphere("earth_hazy", LAM, dtype=torch.float64)
    ms = SkyModel(make_integrator("chapman"), orders=2, view_samples=4, rule="gauss")
    p = FitProblem(Parameterisation(hazy, ["exposure"]), ms, [obs], make_loss("squared"))
    small = ReferenceModel.of(ms, tables=(8, 32, 8, 8), orders=4)
    ref = reference_problem(p, small)
    assert ref.model.sun_zenith_deg == pytest.approx((30.0, 30.0), abs=1e-9)
    window, texels = sun_window(30.0, 30.0, 8)
    got_window, got_texels = ref.model.window()
    assert got_window == pytest.approx(window, rel=1e-12) and got_texels == texels
    assert ref.model.settings()["mu_s_range"] == pytest.approx(list(window), rel=1e-12)
    x = p.param.initial_vector()

    def predicted(model):
        q = copy.copy(ref)
        q.model = model
        return q.predict(x)[0]

    with torch.no_grad():
        got = ref.predict(x)[0]
        built = precompute(hazy, orders=4, progress=False, mu_s_range=window, quadrature=REFERENCE_QUADRATURE,
                           sizes=TableSizes(scattering_r=8, scattering_mu=32, scattering_mu_s=texels, scattering_nu=8))
        direct = dataclasses.replace(ref.model, sun_window=False)
        direct.tables = lambda atm: built  # the window's tables, built here
        same = predicted(direct)
        whole = predicted(dataclasses.replace(ref.model, sun_window=False))
        denser = dataclasses.replace(ref.model, sun_window=False)
        denser.tables = lambda atm: precompute(hazy, orders=4, progress=False, mu_s_range=window, quadrature=REFERENCE_QUADRATURE,
                                               sizes=TableSizes(scattering_r=8, scattering_mu=32,
                                                                scattering_mu_s=2 * texels, scattering_nu=8))
        finer = predicted(denser)  # twice the window's sun texels
    torch.testing.assert_close(got, same, rtol=1e-10, atol=0)
    zenith = int(torch.argmax(obs.directions[:, 2]))
    assert abs(float(whole[zenith, 1] / got[zenith, 1]) - 1.0) > 0.05
    assert float(((finer - got) / finer).abs().max()) < 0.01
    p.param = Parameterisation(hazy, ["exposure", "sun_zenith_offset"])
    assert reference_problem(p, small).model.window() == (None, 8)
    p.param = Parameterisation(hazy, ["exposure"])  # an observer in space sees its rays' entry points' suns
    p.observations = [dataclasses.replace(obs, altitude_m=float(hazy.top_radius - hazy.bottom_radius) + 1000.0)]
    assert reference_problem(p, small).model.window() == (None, 8)
    from skyfit.fit.photo import sun_window as lagged_window  # the lagged Bruneton fits' tables: the same span

    assert lagged_window(p, p.param.initial_vector(), 8) == (None, 8)
    assert fit_settings({"sigma_reference_axis": "whole"}).sigma_reference_axis == "whole"
    with pytest.raises(FitError, match="fit.sigma_reference_axis must be window or whole, got 'half'"):
        fit_settings({"sigma_reference_axis": "half"})


def test_the_reference_integrates_the_view_rays_by_gauss_legendre():
    """The budget's reference builds its Bruneton tables with Gauss-Legendre view rays and split zenith bands
    (REFERENCE_QUADRATURE): on a hazy sky (earth_hazy, sun at 40 deg) its radiance agrees with tables of twice the
    density directions in theta and phi (32 x 64, the same rule) to 1.5 % at every direction, where 2017's equal steps
    along the view ray put it > 10 % high somewhere (docs/uncertainty.md, "The reference's view-ray rule")."""
    import copy
    import dataclasses

    from skyfit.atmosphere import load_atmosphere
    from skyfit.scattering.bruneton_tables import TableSizes
    from skyfit.scattering.multiple import Quadrature, precompute

    obs, _ = tiny_observation(noise=0.01, seed=1, size=6, sun=(40.0, 120.0))
    hazy = load_atmosphere("earth_hazy", LAM, dtype=torch.float64)
    ms = SkyModel(make_integrator("chapman"), orders=2, view_samples=4, rule="gauss")
    p = FitProblem(Parameterisation(hazy, ["exposure"]), ms, [obs], make_loss("squared"))
    ref = reference_problem(p, ReferenceModel.of(ms, tables=(8, 32, 8, 8), orders=4))
    assert ref.model.settings()["ray_rule"] == "gauss" == REFERENCE_QUADRATURE.ray_rule
    x = p.param.initial_vector()

    def with_rules(quadrature):
        model = copy.copy(ref.model)
        window, texels = ref.model.window()
        model.tables = lambda atm: precompute(hazy, orders=4, progress=False, mu_s_range=window, quadrature=quadrature,
                                              sizes=TableSizes(scattering_r=8, scattering_mu=32, scattering_mu_s=texels,
                                                               scattering_nu=8))
        q = copy.copy(ref)
        q.model = model
        return q.predict(x)[0]

    with torch.no_grad():
        got = ref.predict(x)[0]
        finer = with_rules(dataclasses.replace(REFERENCE_QUADRATURE, density_theta=32, density_phi=64, density_zenith=0))
        old = with_rules(Quadrature())
    assert float(((got - finer) / finer).abs().max()) < 0.015
    assert float((old / finer).max()) > 1.10


def test_a_hazy_sky_fitted_with_hillaires_multiple_scattering_gets_a_note():
    """results.model_notes: a fit with Hillaire's orders >= 2 whose aerosol optical depth at 550 nm (interpolated in
    log-log between the model's wavelengths) reaches HILLAIRE_HAZE_AOD gets one note naming the AOD and the error
    budget's total sigma; a clear sky, single scattering and Bruneton's orders get none."""
    from skyfit.atmosphere import load_atmosphere
    from skyfit.fit.results import HILLAIRE_HAZE_AOD, model_notes

    obs, _ = tiny_observation(noise=0.01, seed=1, size=6)

    def notes(config, orders=2, multiple="hillaire"):
        atm = load_atmosphere(config, LAM, dtype=torch.float64)
        p = FitProblem(Parameterisation(atm, ["exposure"]), SkyModel(make_integrator("chapman"), orders=orders,
                                                                    multiple=multiple), [obs], make_loss("squared"))
        depth = float(atm.mie_extinction.reshape(-1)[1] * atm.mie_column_height)  # LAM[1] is 550 nm
        return model_notes(p, p.param.initial_vector()), depth

    hazy, depth = notes("earth_hazy")
    assert depth >= HILLAIRE_HAZE_AOD and len(hazy) == 1
    assert f"{depth:.3g}" in hazy[0] and "laplace.sigma" in hazy[0]
    clear, depth = notes("earth")
    assert depth < HILLAIRE_HAZE_AOD and clear == []
    assert notes("earth_hazy", orders=1)[0] == [] and notes("earth_hazy", multiple="bruneton")[0] == []
