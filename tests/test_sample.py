"""emcee sampling (skyfit.fit.sample, skyfit.fit.batched): batched = per-walker log-likelihood, priors,
posterior around the truth, resume after SIGKILL, and bad input at the command line.

Skies here are tiny (10 x 10 fisheye, 3 wavelengths, chapman, 4-node Gauss view integral) and
rendered with the very renderer that is fitted, so that no model error biases the posterior.
"""
from __future__ import annotations

import copy
import json
import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch

import skyfit
from skyfit.atmosphere import atmosphere_from_config, load_yaml
from skyfit.camera import FisheyeCamera
from skyfit.cli import main
from skyfit.fit import FitOptions, FitProblem, Observation, Parameterisation, SkyModel, fit, make_loss
from skyfit.fit.batched import BatchedLikelihood, per_walker_loglike
from skyfit.fit.chain import read_checkpoint
from skyfit.fit.posterior import LogPosterior
from skyfit.fit.priors import DEFAULT_PRIORS, SampleError, make_priors
from skyfit.fit.sample import sample_posterior
from skyfit.transmittance import make_integrator
from _cli import run as _cli

LAM = np.array([450.0, 550.0, 650.0])
TRUTH = {"rayleigh_scale": 1.05, "mie_beta_550": 2e-5, "mie_scale_height": 1500.0, "mie_g": 0.75}
FREE = ["mie_beta_550", "mie_scale_height", "mie_g", "rayleigh_scale", "exposure"]
HERE = Path(__file__).resolve().parent


def _config() -> dict:
    return copy.deepcopy(load_yaml(Path(skyfit.__file__).parent / "configs" / "earth.yaml"))


def _model(integrator="chapman"):
    return SkyModel(make_integrator(integrator), view_samples=4, rule="gauss")


def tiny_observation(noise=0.01, seed=0, exposure=1.3, size=10, sun=(40.0, 120.0), integrator="chapman"):
    """(Observation, truth dict): exposure x the model's own radiance for TRUTH, times (1 + noise N(0, 1))."""
    base = atmosphere_from_config(_config(), LAM)
    view, valid = FisheyeCamera(size).pixel_vectors(torch.float64)
    view = view[valid]
    n = view.shape[0]
    t = lambda d: torch.tensor(math.radians(d), dtype=torch.float64)  # noqa: E731
    ones = torch.ones(n, len(LAM), dtype=torch.float64)
    dummy = Observation("t", "truth", "spectral", view, t(sun[0]), t(sun[1]), ones, ones, torch.ones(n, dtype=torch.bool),
                        tuple(f"L{x:g}" for x in LAM), torch.tensor(LAM))
    truth = {**TRUTH, "exposure": exposure}
    tp = Parameterisation(base, list(truth), values=truth)
    prob = FitProblem(tp, _model(integrator), [dummy], make_loss("squared"))
    with torch.no_grad():
        clean = prob.predict(tp.initial_vector())[0]
    gen = torch.Generator().manual_seed(seed)
    noisy = clean * (1 + noise * torch.randn(clean.shape, generator=gen, dtype=clean.dtype))
    obs = Observation(f"tiny{seed}", f"tiny sky {seed}", "spectral", view, t(sun[0]), t(sun[1]), noisy, noise * clean,
                      torch.ones(n, dtype=torch.bool), tuple(f"L{x:g}" for x in LAM), torch.tensor(LAM))
    return obs, truth


def tiny_problem(free=FREE, integrator="chapman", seed=0, noise=0.01):
    obs, truth = tiny_observation(noise=noise, seed=seed, integrator=integrator)
    base = atmosphere_from_config(_config(), LAM)
    return FitProblem(Parameterisation(base, free), _model(integrator), [obs], make_loss("squared")), truth


@pytest.mark.parametrize("integrator", ["chapman", "gauss"])
@pytest.mark.parametrize("free", [
    FREE,
    ["mie_aod_550", "mie_scale_height", "rayleigh_scale_height", "mie_g", "mie_angstrom_alpha", "exposure"],
    ["mie_beta_550", "mie_ssa", "ground_albedo", "mie_g", "exposure", "noise_scale"],
], ids=["default", "aod_heights", "ssa_albedo_noise"])
def test_batched_log_likelihood_equals_the_per_walker_one(integrator, free):
    """One batched pass over 12 walkers vs 12 calls of FitProblem.objective (the fit's own code)."""
    prob, _ = tiny_problem(free, integrator)
    x0 = prob.param.initial_vector()
    X = x0 + 0.4 * torch.randn(12, x0.numel(), dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    a = BatchedLikelihood(prob)(X)
    b = per_walker_loglike(prob, X)
    torch.testing.assert_close(a, b, rtol=1e-10, atol=0)
    chunked = BatchedLikelihood(prob, chunk_bytes=1)  # 8-ray chunks
    assert len(chunked.geoms) == math.ceil(prob.n_elements / 3 / 8)
    torch.testing.assert_close(chunked(X), b, rtol=1e-10, atol=0)


def test_rays_hitting_the_ground_and_a_tilted_sun_batch_exactly():
    """Directions below the horizon (ground term, 'before' Chapman branch) and the sun near the horizon."""
    base = atmosphere_from_config(_config(), LAM)
    z = torch.linspace(0.05, 3.0, 24, dtype=torch.float64)
    az = torch.linspace(0, 6.0, 24, dtype=torch.float64)
    view = torch.stack([torch.sin(z) * torch.sin(az), torch.sin(z) * torch.cos(az), torch.cos(z)], -1)
    ones = torch.ones(24, 3, dtype=torch.float64)
    obs = Observation("g", "ground", "spectral", view, torch.tensor(1.55, dtype=torch.float64), torch.tensor(0.3, dtype=torch.float64),
                      ones, ones, torch.ones(24, dtype=torch.bool), tuple(f"L{x:g}" for x in LAM), torch.tensor(LAM))
    prob = FitProblem(Parameterisation(base, ["mie_beta_550", "ground_albedo", "mie_scale_height", "exposure"]), _model(),
                      [obs], make_loss("squared"))
    bl = BatchedLikelihood(prob)
    assert bl.geoms[0].ground
    X = prob.param.initial_vector() + 0.3 * torch.randn(6, 4, dtype=torch.float64, generator=torch.Generator().manual_seed(2))
    torch.testing.assert_close(bl(X), per_walker_loglike(prob, X), rtol=1e-10, atol=0)


@pytest.mark.parametrize("name", ["mie_scale_height", "mie_g", "exposure", "mie_ssa", "sun_zenith_offset"])
def test_prior_density_in_x_integrates_to_one(name):
    """exp(log pi(v(x)) + log |dv/dx|) over x must integrate to 1 (the Jacobian is right)."""
    prob, _ = tiny_problem([name] if name != "exposure" else ["exposure"])
    lp = LogPosterior(prob, make_priors(prob), batched=False)
    x = torch.linspace(-40, 40, 400_001, dtype=torch.float64)[:, None]
    dens = torch.exp(lp.log_prior(x))
    assert float(torch.trapezoid(dens, x[:, 0])) == pytest.approx(1.0, abs=2e-4)


def test_prior_overrides_and_bad_prior():
    prob, _ = tiny_problem()
    pr = make_priors(prob, {"mie_g": {"kind": "uniform", "lo": 0.5, "hi": 0.9}})
    assert pr["mie_g"].lo == 0.5 and pr["mie_scale_height"] == DEFAULT_PRIORS["mie_scale_height"]
    lp = LogPosterior(prob, pr)
    x = prob.param.initial_vector()[None].repeat(2, 1)
    x[1, 2] = prob.param.to_unconstrained({"mie_g": 0.95})[2]  # outside the user's prior
    out = lp(x.numpy())
    assert np.isfinite(out[0]) and out[1] == -np.inf
    with pytest.raises(SampleError, match="unknown prior kind"):
        make_priors(prob, {"mie_g": {"kind": "beta"}})


def test_default_priors_come_from_the_parameter_table():
    """DEFAULT_PRIORS is derived from PARAMETERS: a kind alone spans the parameter's range."""
    from skyfit.fit.parameters import PARAMETERS

    assert list(DEFAULT_PRIORS) == [n for n, s in PARAMETERS.items() if s.prior is not None]
    for n, spec in PARAMETERS.items():
        if isinstance(spec.prior, str):
            assert (DEFAULT_PRIORS[n].kind, DEFAULT_PRIORS[n].lo, DEFAULT_PRIORS[n].hi) == (spec.prior, spec.lo, spec.hi)
    for n in ("sun_zenith_offset", "camera_tilt_north", "camera_tilt_east"):
        assert (DEFAULT_PRIORS[n].lo, DEFAULT_PRIORS[n].hi) == (PARAMETERS[n].lo, PARAMETERS[n].hi)


def test_posterior_covers_the_truth_and_agrees_with_laplace(tmp_path):
    from skyfit.fit.laplace import laplace_summary

    prob, truth = tiny_problem(seed=5)
    res = fit(prob, FitOptions(starts=1, adam_steps=5, max_iter=100))
    lap = laplace_summary(prob, res.x)
    s = sample_posterior(prob, res.x, tmp_path / "s", walkers=12, steps=400, laplace=lap, seed=1, plots=True,
                         predictive_draws=16)
    P = s["parameters"]
    for n, v in truth.items():
        key = n
        assert abs(P[key]["median"] - v) < 4 * P[key]["std"], (n, P[key], v)
    for n, r in s["laplace_vs_emcee"].items():  # a near-Gaussian posterior: the two widths agree
        assert 0.6 < r["ratio"] < 1.6, (n, r)
    d = s["diagnostics"]
    assert 0.2 < d["acceptance_fraction"]["mean"] < 0.7
    assert all((tmp_path / "s" / f).is_file() for f in ("summary.json", "corner.png", "trace.png", "chain.h5",
                                                       "predictive_std_tiny5.png"))
    import emcee

    hb = emcee.backends.HDFBackend(str(tmp_path / "s" / "chain.h5"), read_only=True)  # emcee reads our checkpoint
    assert hb.iteration == 400 and hb.get_chain().shape == (400, 12, 5)


def _run_cmd(stop_after_kill_file: Path, out: Path, steps: int):
    code = (
        "import sys, torch; sys.path.insert(0, %r); torch.set_num_threads(1)\n"
        "from test_sample import tiny_problem; from skyfit.fit.sample import sample_posterior\n"
        "prob, _ = tiny_problem()\n"
        "sample_posterior(prob, prob.param.initial_vector(), %r, walkers=10, steps=%d, seed=7, checkpoint_seconds=0.0,"
        " plots=False, predictive_draws=4)\n" % (str(HERE), str(out), steps)
    )
    return subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)


def _iteration(path: Path) -> int:
    try:
        return read_checkpoint(path)[0].iteration
    except Exception:
        return 0


def test_sigkill_mid_run_then_resume_gives_the_uninterrupted_chain(tmp_path):
    steps = 240
    out = tmp_path / "killed"
    proc = _run_cmd(None, out, steps)
    t0 = time.time()
    try:
        while _iteration(out / "chain.h5") < 30:
            assert proc.poll() is None, proc.stderr.read().decode()[-2000:]
            assert time.time() - t0 < 120
            time.sleep(0.05)
        os.kill(proc.pid, signal.SIGKILL)
    finally:
        proc.wait()
    k = _iteration(out / "chain.h5")
    assert 30 <= k < steps, k  # killed mid-way, the last checkpoint is readable
    partial = read_checkpoint(out / "chain.h5")[0].chain[:k].copy()
    prob, _ = tiny_problem()
    x0 = prob.param.initial_vector()
    sample_posterior(prob, x0, out, walkers=10, steps=steps, seed=7, resume=True, plots=False, predictive_draws=4)
    resumed = read_checkpoint(out / "chain.h5")[0]
    assert resumed.iteration == steps
    np.testing.assert_array_equal(resumed.chain[:k], partial)  # the first k steps are kept as they were
    sample_posterior(prob, x0, tmp_path / "whole", walkers=10, steps=steps, seed=7, plots=False, predictive_draws=4)
    whole = read_checkpoint(tmp_path / "whole" / "chain.h5")[0]
    np.testing.assert_array_equal(resumed.chain, whole.chain)  # same chain: nothing lost, nothing duplicated
    np.testing.assert_array_equal(resumed.log_prob, whole.log_prob)
    assert len({tuple(r) for r in resumed.chain.reshape(-1, 5)}) == len({tuple(r) for r in whole.chain.reshape(-1, 5)})


# -- command line --------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def fitted(tmp_path_factory):
    d = tmp_path_factory.mktemp("cli")
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        assert main(["render", "earth", "--out", str(d / "sky.exr"), "--size", "10", "--sun-zenith", "40", "--sun-azimuth", "120",
                     "--wavelengths", "450:650:100", "--integrator", "chapman", "--view-samples", "4", "--spectral",
                     "--dtype", "float64"]) == 0
        common = ["fit", str(d / "sky.exr"), "--config", "earth", "--integrator", "chapman", "--view-samples", "4",
                  "--starts", "1", "--max-iter", "40", "--no-plots"]
        assert main(common + ["--out", str(d / "a.json"), "--free", "mie_g,exposure", "--laplace"]) == 0
        assert main(common + ["--out", str(d / "b.json"), "--free", "mie_g,rayleigh_scale,exposure"]) == 0
    finally:
        torch.set_num_threads(n)
    return d


def test_cli_sample_then_resume_and_bad_inputs(fitted, tmp_path, capsys):
    d = fitted
    res = json.loads((d / "a.json").read_text())
    assert set(res["laplace"]["sigma"]) == {"mie_g", "exposure"} and res["laplace"]["positive_definite"]
    cor, shift = res["laplace"]["corrected"], res["laplace"]["budget"]["numerical_shift"]
    for n in ("mie_g", "exposure"):  # the corrected estimate reaches RESULT.json: the fitted value plus the shift
        assert cor["values"][n] == pytest.approx(res["parameters"][n] + shift[n], rel=1e-9)
    base = ["sample", d / "sky.exr", "--config", "earth", "--init", d / "a.json", "--threads", "1"]
    out = tmp_path / "s"
    rc, so, se = _cli(base + ["--out", out, "--walkers", "8", "--steps", "60", "--json"], capsys)
    assert rc == 0, se
    summ = json.loads((out / "summary.json").read_text())
    assert summ["diagnostics"]["steps"] == 60 and summ["throughput"]["batched"]
    assert "too short" in se  # 60 steps < 50 tau: warned
    rc, so, se = _cli(base + ["--out", out, "--walkers", "8", "--steps", "80", "--resume", "--json"], capsys)
    assert rc == 0, se
    assert json.loads((out / "summary.json").read_text())["diagnostics"]["steps"] == 80
    # bad input: one line, exit 2, nothing written
    cases = [
        (["sample", d / "sky.exr", "--config", "earth", "--init", d / "missing.json", "--out", tmp_path / "m"], "not found"),
        (base + ["--out", tmp_path / "w", "--walkers", "2"], "fewer than 2 x 2"),
        (base[:5] + [d / "b.json", "--out", out, "--walkers", "8", "--steps", "90", "--resume"], "another model"),
        (base + ["--out", out, "--walkers", "8"], "exists"),
    ]
    for argv, msg in cases:
        rc, so, se = _cli(argv, capsys)
        assert rc == 2, (argv, se)
        assert msg in se and len(se.strip().splitlines()) == 1, se
    assert not (tmp_path / "m").exists() and not (tmp_path / "w").exists()
    # --resume with nothing to continue starts a new chain and says so (issue 18: it used to be an error)
    rc, so, se = _cli(base + ["--out", tmp_path / "r", "--resume", "--walkers", "8", "--steps", "5", "--no-plots"], capsys)
    assert rc == 0 and "starting a new chain" in se, se


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_batched_log_likelihood_on_cuda_matches_the_cpu():
    prob, _ = tiny_problem()
    x0 = prob.param.initial_vector()
    X = x0 + 0.3 * torch.randn(8, 5, dtype=torch.float64, generator=torch.Generator().manual_seed(4))
    ref = per_walker_loglike(prob, X)
    obs = prob.observations[0].to(torch.float64, "cuda")
    base = prob.param.base.to(device="cuda")
    cuda = FitProblem(Parameterisation(base, FREE), _model(), [obs], make_loss("squared"))
    got = BatchedLikelihood(cuda)(X.cuda()).cpu()
    torch.testing.assert_close(got, ref, rtol=1e-10, atol=0)


def test_integrator_bias_is_measured_by_reweighting(tmp_path):
    """Sampling with the fit's own renderer as the 'cheap' one gives equal weights: zero shift, ESS = draws;
    a 2-node view integral instead of 4 gives a finite, non-zero measured shift."""
    prob, _ = tiny_problem()
    x0 = prob.param.initial_vector()
    s = sample_posterior(prob, x0, tmp_path / "same", walkers=10, steps=30, final_problem=prob, plots=False,
                         predictive_draws=4)
    b = s["integrator_bias"]
    assert b["max_abs_shift_in_sigma"] == pytest.approx(0.0, abs=1e-12) and b["weights_ess"] == pytest.approx(b["draws"])
    cheap = FitProblem(Parameterisation(prob.param.base, FREE), SkyModel(make_integrator("chapman"), view_samples=2, rule="gauss"),
                       prob.observations, make_loss("squared"))
    s = sample_posterior(cheap, x0, tmp_path / "cheap", walkers=10, steps=30, final_problem=prob, plots=False,
                         predictive_draws=4)
    b = s["integrator_bias"]
    assert s["sampler_integrator"]["view_samples"] == 2 and s["final_integrator"]["view_samples"] == 4
    assert 0 < b["max_abs_shift_in_sigma"] < math.inf and b["log_like_difference"]["std"] > 0


def test_joint_fit_with_per_observation_exposure_and_a_robust_loss_batches_exactly():
    o1, _ = tiny_observation(seed=1)
    o2, _ = tiny_observation(seed=2, sun=(60.0, 200.0))
    base = atmosphere_from_config(_config(), LAM)
    p = Parameterisation(base, FREE + ["noise_scale"], 2)
    prob = FitProblem(p, _model(), [o1, o2], make_loss("huber"))
    assert p.names[4:6] == ["exposure[0]", "exposure[1]"]
    X = p.initial_vector() + 0.3 * torch.randn(6, p.size, dtype=torch.float64, generator=torch.Generator().manual_seed(3))
    torch.testing.assert_close(BatchedLikelihood(prob)(X), per_walker_loglike(prob, X), rtol=1e-10, atol=0)
