"""The fast fit paths (issue 15, "Fits in seconds") against the paths they replace.

* Levenberg-Marquardt (``FitOptions.method = "lm"``) reaches the optimum that L-BFGS reaches,
  on a small synthetic problem with multiple scattering, atmospheric and instrument parameters;
* its convergence flag and reason are right (3 iterations from a far start: not converged);
* the cached, batched Hillaire LUT equals the original row loop to 1e-12, values and gradients,
  and its memo returns what a rebuild would.
"""
from __future__ import annotations

import math

import pytest
import torch

from skyfit.atmosphere import load_atmosphere
from skyfit.camera.fisheye import zenith_azimuth_to_enu
from skyfit.fit import FitError, FitOptions, FitProblem, Observation, Parameterisation, SkyModel, fit, make_loss
from skyfit.fit.optimise import least_squares_applies, residual_vector
from skyfit.scattering import hillaire
from skyfit.scattering.bruneton_tables import TableSizes
from skyfit.scattering.hillaire import hillaire_lut
from skyfit.transmittance import make_integrator

F64 = torch.float64
LAM = [400.0, 480.0, 560.0, 680.0]
T_SIZES = TableSizes(transmittance_mu=64, transmittance_r=16)
FREE = ["rayleigh_scale", "mie_beta_550", "mie_g", "exposure", "sun_azimuth_offset"]
TRUTH = {"rayleigh_scale": 1.1, "mie_beta_550": 3.0e-5, "mie_g": 0.72, "exposure": 1.3, "sun_azimuth_offset": math.radians(4.0)}


def _model(**kw) -> SkyModel:
    kw = {"orders": 2, "view_samples": 8, "rule": "gauss", "lut_size": (4, 4), "lut_directions": 8, "lut_samples": 4, **kw}
    return SkyModel(make_integrator("gauss", samples=8), **kw)


@pytest.fixture(scope="module")
def base():
    return load_atmosphere("earth", LAM)


def _observation(base, noise=0.01, seed=0) -> Observation:
    """Model radiance at TRUTH on a ring-and-spoke scan with 1 % seeded noise (the sun at zenith 40, azimuth 120 deg)."""
    zen, az = torch.meshgrid(torch.deg2rad(torch.tensor([10.0, 30.0, 50.0, 70.0, 85.0], dtype=F64)),
                             torch.deg2rad(torch.arange(0.0, 360.0, 30.0, dtype=F64)), indexing="ij")
    dirs = zenith_azimuth_to_enu(zen.reshape(-1), az.reshape(-1))
    sz, sa = torch.tensor(math.radians(40.0), dtype=F64), torch.tensor(math.radians(120.0), dtype=F64)
    n = dirs.shape[0]
    ones = torch.ones(n, len(LAM), dtype=F64)
    chans = tuple(f"L{x:g}" for x in LAM)
    obs = Observation("syn", "synthetic", "spectral", dirs, sz, sa, ones, ones, torch.ones(n, dtype=torch.bool), chans,
                      torch.tensor(LAM, dtype=F64))
    truth = Parameterisation(base, [], values=TRUTH)
    clean = FitProblem(truth, _model(), [obs], make_loss("squared")).predict(truth.initial_vector())[0].detach()
    gen = torch.Generator().manual_seed(seed)
    noisy = clean * (1 + noise * torch.randn(clean.shape, generator=gen, dtype=F64))
    return Observation("syn", "synthetic", "spectral", dirs, sz, sa, noisy, noise * clean, obs.mask, chans, obs.wavelengths)


def _problem(base, obs, loss="squared", **model) -> FitProblem:
    param = Parameterisation(base, FREE, values={"mie_g": 0.6})  # beta and g away from the truth
    return FitProblem(param, _model(**model), [obs], make_loss(loss))


# -- Levenberg-Marquardt against L-BFGS --------------------------------------------------------
def test_lm_reaches_the_lbfgs_optimum(base):
    obs = _observation(base)
    lm = fit(_problem(base, obs), FitOptions(starts=1, method="lm"))
    lb = fit(_problem(base, obs), FitOptions(starts=1, method="lbfgs", max_iter=300, grad_tol=1e-10, rel_tol=1e-14))
    assert lm.convergence["method"] == "lm" and lb.convergence["method"] == "lbfgs"
    assert lm.convergence["converged"], lm.convergence
    assert lm.convergence["reason"] in ("relative loss change", "gradient norm")
    # same minimum: the loss to 1e-9 (LM's may only be lower), the parameters to 1e-4 in x (~1e-4 relative)
    assert lm.loss <= lb.loss * (1 + 1e-9)
    assert lm.loss == pytest.approx(lb.loss, rel=1e-9)
    torch.testing.assert_close(lm.x, lb.x, atol=1e-4, rtol=0)
    # and it is the truth within the noise (an independent check that both found the right basin)
    assert lm.parameters["mie_g"] == pytest.approx(TRUTH["mie_g"], abs=0.02)
    assert math.degrees(lm.parameters["sun_azimuth_offset"]) == pytest.approx(4.0, abs=0.3)
    # far fewer model evaluations than L-BFGS's gradient evaluations would cost
    assert lm.convergence["iterations"] < lb.convergence["iterations"]


def test_auto_is_lm_for_squared_losses_and_lbfgs_otherwise(base):
    obs = _observation(base)
    assert least_squares_applies(_problem(base, obs)) is None
    assert least_squares_applies(_problem(base, obs, loss="huber")) is not None
    auto = fit(_problem(base, obs), FitOptions(starts=1, max_iter=2))
    assert auto.convergence["method"] == "lm"
    hub = fit(_problem(base, obs, loss="huber"), FitOptions(starts=1, max_iter=2, adam_steps=0))
    assert hub.convergence["method"] == "lbfgs"
    with pytest.raises(FitError, match="lm optimiser minimises squared residuals, but the loss rho is 'huber'"):
        fit(_problem(base, obs, loss="huber"), FitOptions(starts=1, method="lm"))
    with pytest.raises(FitError, match="unknown optimiser 'newton'; valid: auto, lm, lbfgs"):
        FitOptions(method="newton")


@pytest.mark.parametrize("method", ["lm", "lbfgs"])
def test_three_iterations_from_afar_do_not_converge(base, method):
    obs = _observation(base)
    res = fit(_problem(base, obs), FitOptions(starts=1, method=method, max_iter=3, adam_steps=0))
    assert res.convergence["converged"] is False
    assert res.convergence["reason"] == "max iterations"
    assert res.convergence["iterations"] == 3
    full = fit(_problem(base, obs), FitOptions(starts=1, method="lm"))
    assert full.convergence["converged"] and full.loss < res.loss


@pytest.mark.parametrize("loss", ["squared", "log"])
def test_residual_vector_is_the_objective(base, loss):
    obs = _observation(base)
    problem = _problem(base, obs, loss=loss)
    x = problem.param.initial_vector() + 0.1
    r = residual_vector(problem, x)
    assert r.shape == (obs.values.numel(),)
    torch.testing.assert_close(0.5 * (r @ r) / problem.n_elements, problem.objective(x), rtol=1e-12, atol=0)


def test_lm_respects_tables_frozen_by_the_caller(base, monkeypatch):
    """A lagged fit (fit.photo.lagged_fit) freezes the LUT: LM's Jacobian must not rebuild it."""
    obs = _observation(base)
    problem = _problem(base, obs)
    problem.frozen_tables = problem.model.tables(problem.param.atmosphere(problem.param.to_physical(problem.param.initial_vector())))
    calls = []
    monkeypatch.setattr(hillaire, "hillaire_lut", lambda *a, **k: calls.append(1))
    res = fit(problem, FitOptions(starts=1, method="lm", max_iter=3))
    assert res.convergence["iterations"] >= 1 and calls == []


def test_lm_rejects_a_trial_step_that_rounds_onto_a_bound(base, monkeypatch):
    """The clamp before the sigmoid (SIGMOID_EDGE) keeps mie_g2 inside (-1, 1) however far a step goes; without it a
    sigmoid rounded onto a bound (mie_g2 = -1 exactly, which the atmosphere refuses) rejects LM's trial step instead
    of ending the fit, and at the fit's own start it is still an error."""
    import skyfit.fit.parameters as parameters
    from skyfit.fit.optimise import _evaluate

    obs = _observation(base)
    hg = base.replace(mie_phase="henyey_greenstein")
    param = Parameterisation(hg, FREE + ["mie_g2", "mie_hg_weight"], values={"mie_g2": -0.3, "mie_hg_weight": 0.9})
    problem = FitProblem(param, _model(), [obs], make_loss("squared"))
    x = param.initial_vector().clone()
    r, tables = _evaluate(problem, x, trial=True)
    assert r is not None and bool(torch.isfinite(r).all())
    x[param.names.index("mie_g2")] = -60.0  # sigmoid 9e-27: -1 + 9e-27 would round to -1.0
    assert -1.0 < float(param.to_physical(x)["mie_g2"]) < -1.0 + 1e-12  # clamped at -30 first
    r, _ = _evaluate(problem, x, trial=True)
    assert r is not None and bool(torch.isfinite(r).all())
    monkeypatch.setitem(parameters.SIGMOID_EDGE, torch.float64, 1e3)  # the clamp off: the old rounding
    assert float(param.to_physical(x)["mie_g2"]) == -1.0
    assert _evaluate(problem, x, trial=True) == (None, None)
    with pytest.raises(FitError, match="invalid atmosphere"):
        _evaluate(problem, x)


# -- the cached LUT against the row loop -------------------------------------------------------
@pytest.mark.parametrize("size, directions, samples", [((4, 5), 8, 4), ((16, 16), 32, 12)])
def test_cached_lut_equals_the_row_loop(base, size, directions, samples):
    kw = dict(size=size, directions=directions, samples=samples, transmittance_sizes=T_SIZES)
    rows = hillaire_lut(base, method="rows", **kw)
    hillaire._GEOMETRY_CACHE.clear()
    hillaire._LAST_LUTS.clear()
    fresh = hillaire_lut(base, method="cached", **kw)  # geometry built now
    hillaire._LAST_LUTS.clear()
    again = hillaire_lut(base, method="cached", **kw)  # geometry from the cache
    for name in ("psi", "l_2nd", "f_ms"):
        torch.testing.assert_close(getattr(fresh, name), getattr(rows, name), rtol=1e-12, atol=0)
        assert torch.equal(getattr(again, name), getattr(fresh, name))


def test_model_forward_is_the_same_with_either_lut(base):
    obs = _observation(base)
    x = _problem(base, obs).param.initial_vector() + 0.05
    old = _problem(base, obs, lut_method="rows").predict(x)[0]
    new = _problem(base, obs).predict(x)[0]
    torch.testing.assert_close(new, old, rtol=1e-12, atol=0)


def test_lut_memo_ignores_only_the_phase(base):
    kw = dict(size=(4, 4), directions=8, samples=4, transmittance_sizes=T_SIZES)
    a = hillaire_lut(base, **kw)
    assert hillaire_lut(base.replace(mie_g=base.mie_g * 0.5), **kw) is a  # the LUT's phase is isotropic
    other = hillaire_lut(base.replace(rayleigh_scattering=base.rayleigh_scattering * 1.01), **kw)
    assert other is not a and not torch.equal(other.psi, a.psi)
    graph = hillaire_lut(base.replace(rayleigh_scattering=base.rayleigh_scattering.clone().requires_grad_(True)), **kw)
    assert graph.psi.grad_fn is not None  # never a memo without the graph


@pytest.mark.parametrize("chunks", [False, True])
def test_cached_lut_gradients(base, monkeypatch, chunks):
    """gradcheck of the cached path (one chunk, and several checkpointed chunks); equal to the row loop's gradient."""
    if chunks:
        monkeypatch.setattr(hillaire, "_CHUNK_ELEMENTS", 3 * 4 * 2)  # 3 texels per chunk of 4 directions x 2 steps
        monkeypatch.setattr(hillaire, "_CHECKPOINT_ELEMENTS", 0)  # and each chunk checkpointed
    atm = load_atmosphere("earth", [550.0])
    names = ["rayleigh_scattering", "mie_scattering", "mie_extinction", "mie_scale_height", "ground_albedo"]
    base_v = [getattr(atm, n).clone() for n in names]
    scale = [b.abs().clamp_min(1e-30) for b in base_v]

    def lut(method, *xs):
        a = atm.replace(**{n: x * s for n, x, s in zip(names, xs, scale)})
        return hillaire_lut(a, size=(3, 3), directions=4, samples=2, transmittance_sizes=T_SIZES,
                            transmittance_samples=20, method=method).psi

    inputs = tuple((b / s).requires_grad_(True) for b, s in zip(base_v, scale))
    assert torch.autograd.gradcheck(lambda *xs: lut("cached", *xs), inputs, eps=1e-6, atol=1e-8, rtol=1e-5)
    w = torch.linspace(0.5, 1.5, 9, dtype=F64).reshape(3, 3, 1)
    g_new = torch.autograd.grad((lut("cached", *inputs) * w).sum(), inputs)
    g_old = torch.autograd.grad((lut("rows", *inputs) * w).sum(), inputs)
    for a, b in zip(g_new, g_old):
        torch.testing.assert_close(a, b, rtol=1e-10, atol=0)


def test_unknown_lut_method_is_refused(base):
    with pytest.raises(ValueError, match="unknown Hillaire LUT method 'fast'; valid: cached, rows"):
        hillaire_lut(base, size=(2, 2), directions=2, samples=2, method="fast")


def test_optimiser_setting_reaches_the_options():
    from skyfit.fit.problem import fit_settings

    assert fit_settings(None).options().method == "auto"
    assert fit_settings({"optimiser": "lbfgs"}).options().method == "lbfgs"
    assert fit_settings({"optimiser": "lm"}, {"optimiser": "lbfgs"}).options().method == "lbfgs"  # a flag wins
    with pytest.raises(FitError, match="fit.optimiser must be one of auto, lm, lbfgs, got 'newton'"):
        fit_settings({"optimiser": "newton"}, where="config k.yaml")
