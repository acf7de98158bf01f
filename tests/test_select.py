"""Model selection (skyfit.fit.select): the ladder keeps what the data require and drops the rest.

Synthetic skies are rendered from config dicts with :func:`skyfit.render.sky.render_vectors`
(not through the fit's parameterisation) at a few hundred random directions, 6 wavelengths,
Chapman optical depth and an 8-node Gauss view integral, with seeded 1 % noise; sigma is
known (``sigma="known"``) so that BIC is the exact Gaussian criterion.
"""
from __future__ import annotations

import copy
import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

import skyfit
from skyfit.atmosphere import atmosphere_from_config, load_yaml
from skyfit.camera.fisheye import zenith_azimuth_to_enu
from skyfit.fit import FitOptions, Observation, SkyModel, make_loss
from skyfit.fit.parameters import FitError
from skyfit.fit.select import RUNGS, Ladder, gaussian_nll, heldout_split, log_sigma_sum
from skyfit.render.sky import render_vectors
from skyfit.transmittance import make_integrator
from _cli import run as _run

LAM = np.linspace(420.0, 680.0, 6)
VIEW = 8
N_DIRS = 240


def _cfg(mie: bool = True, ozone: bool = True, beta_550: float = 2.0e-5) -> dict:
    cfg = copy.deepcopy(load_yaml(Path(skyfit.__file__).parent / "configs" / "earth.yaml"))
    cfg["mie"].pop("angstrom_beta", None)
    cfg["mie"]["extinction_550"] = beta_550 if mie else 0.0
    if not ozone:
        cfg.pop("ozone")
    return cfg


def _model(orders: int = 1) -> SkyModel:
    return SkyModel(make_integrator("chapman"), orders=orders, view_samples=VIEW, rule="gauss")


def synthetic(cfg: dict, sun_zenith: float, orders: int = 1, seed: int = 0, exposure: float = 1.2,
              noise: float = 0.01, n: int = N_DIRS, min_elevation: float = 5.0) -> Observation:
    """A noisy observation of ``cfg``'s sky at ``n`` random directions ``min_elevation``-90 deg above the horizon."""
    atm = atmosphere_from_config(cfg, LAM)
    gen = torch.Generator().manual_seed(seed)
    lo = math.sin(math.radians(min_elevation))
    mu = lo + (1 - lo) * torch.rand(n, generator=gen, dtype=torch.float64)
    az = 2 * math.pi * torch.rand(n, generator=gen, dtype=torch.float64)
    dirs = zenith_azimuth_to_enu(torch.acos(mu), az)
    sz, sa = torch.tensor(math.radians(sun_zenith), dtype=torch.float64), torch.tensor(2.0, dtype=torch.float64)
    sun = zenith_azimuth_to_enu(sz, sa)
    keep = (dirs @ sun) < math.cos(math.radians(3.0))
    dirs = dirs[keep]
    m = _model(orders)
    clean = exposure * render_vectors(atm, dirs, sun, m.integrator, 0.0, orders, tables=m.tables(atm),
                                      multiple="hillaire", view_samples=VIEW, rule="gauss")
    sigma = noise * clean + 1e-3 * noise * clean.max()  # relative noise and a floor (shadowed twilight views)
    noisy = clean + sigma * torch.randn(clean.shape, generator=gen, dtype=clean.dtype)
    return Observation(f"syn{seed}", f"synthetic {seed}", "spectral", dirs, sz, sa, noisy, sigma,
                       torch.ones(dirs.shape[0], dtype=torch.bool), tuple(f"L{x:g}" for x in LAM), torch.tensor(LAM))


def ladder(cfg: dict, obs, rungs=RUNGS, **kw) -> Ladder:
    atm = atmosphere_from_config(cfg, LAM)
    kw.setdefault("options", FitOptions(starts=1, adam_steps=5, max_iter=40))
    return Ladder(atm, _model(), [obs], make_loss("squared"), sigma=kw.pop("sigma", "known"), rungs=rungs, **kw)


def _rung(report, name):
    return next(r for r in report["rungs"] if r["name"] == name)


def _subset(*names):
    return tuple(r for r in RUNGS if r.name in names)


# -- the likelihood and the split ----------------------------------------------------------
def test_gaussian_nll_matches_the_normal_density():
    """nll of known sigma = -sum log N(o | m, sigma); scaled = the same with sigma s, s^2 = mean r^2."""
    gen = torch.Generator().manual_seed(3)
    m = torch.rand(50, 3, generator=gen, dtype=torch.float64) + 1
    sig = 0.05 * torch.rand(50, 3, generator=gen, dtype=torch.float64) + 0.01
    o = m + 1.7 * sig * torch.randn(50, 3, generator=gen, dtype=torch.float64)
    obs = Observation("a", "a", "spectral", zenith_azimuth_to_enu(torch.full((50,), 0.3, dtype=torch.float64),
                                                                   torch.linspace(0, 6, 50, dtype=torch.float64)),
                      torch.tensor(0.5), torch.tensor(0.0), o, sig, torch.ones(50, dtype=torch.bool), ("L1", "L2", "L3"),
                      torch.tensor([1.0, 2.0, 3.0]))
    loss = make_loss("squared")
    mean_loss = float(loss(m, o, sig))
    ls, n = log_sigma_sum([obs], loss)
    ref = -float(torch.distributions.Normal(m, sig).log_prob(o).sum())
    assert gaussian_nll(mean_loss, n, ls, "known")[0] == pytest.approx(ref, rel=1e-12)
    nll_s, s = gaussian_nll(mean_loss, n, ls, "scaled")
    assert s == pytest.approx(float(((o - m) / sig).pow(2).mean().sqrt()), rel=1e-12)
    assert nll_s == pytest.approx(-float(torch.distributions.Normal(m, s * sig).log_prob(o).sum()), rel=1e-12)
    assert nll_s < ref  # the profiled scale fits at least as well


def test_heldout_split_is_complementary_and_deterministic():
    obs = synthetic(_cfg(), 40.0, n=200)
    tr, he = heldout_split([obs], 0.2, seed=5)
    tr2, he2 = heldout_split([obs], 0.2, seed=5)
    assert torch.equal(tr[0].mask, tr2[0].mask) and torch.equal(he[0].mask, he2[0].mask)
    assert not bool((tr[0].mask & he[0].mask).any()) and torch.equal(tr[0].mask | he[0].mask, obs.mask)
    assert 0.12 < he[0].n_samples / obs.n_samples < 0.28
    assert not torch.equal(heldout_split([obs], 0.2, seed=6)[1][0].mask, he[0].mask)


def test_robust_losses_are_refused():
    obs = synthetic(_cfg(), 40.0, n=40)
    with pytest.raises(FitError, match="Gaussian"):
        Ladder(atmosphere_from_config(_cfg(), LAM), _model(), [obs], make_loss("huber"))


# -- the selection tests -------------------------------------------------------------
def test_no_mie_data_drops_mie():
    """A sky without aerosol (Rayleigh and ozone): aerosol is taken on the way up (it mimics part of the
    ozone band while ozone is off) and dropped again once ozone is in; with aerosol in the data it stays."""
    rungs = _subset("rayleigh", "mie", "ozone", "scale_heights")
    rep = ladder(_cfg(), synthetic(_cfg(mie=False), 40.0, seed=1), rungs).run()
    assert rep["components"] == ["rayleigh", "ozone"], rep["why"]
    drop = _rung(rep, rep["chosen"])
    assert drop["step"] == "remove" and drop["removed"] == ["mie_aod_550", "mie_g", "mie_angstrom_alpha"]
    assert drop["delta_bic_parent"] < 0  # dropping the aerosol lowers BIC
    assert drop["parameters"]["rayleigh_scale"] == pytest.approx(1.0, abs=0.01)
    assert drop["parameters"]["ozone_column"] == pytest.approx(300.0, rel=0.1)
    # the same ladder on a sky with aerosol keeps it, by a wide margin
    rep2 = ladder(_cfg(), synthetic(_cfg(), 40.0, seed=2), rungs).run()
    assert "mie" in rep2["components"], rep2["why"]
    assert _rung(rep2, "mie")["delta_bic_parent"] < -100
    assert "mie" in _rung(rep2, rep2["heldout_choice"])["components"]  # held-out pixels agree that it is needed


def test_ozone_data_keeps_ozone_and_ozone_free_data_drops_it():
    """Sun 60 deg: the Chappuis band (500-700 nm) absorbs a few % of the light, unlike any Rayleigh or Mie change."""
    rungs = _subset("rayleigh", "mie", "ozone")
    rep = ladder(_cfg(), synthetic(_cfg(), 60.0, seed=4), rungs).run()
    assert rep["chosen"] == "ozone" and "ozone" in rep["components"], rep["why"]
    assert _rung(rep, "ozone")["delta_bic_parent"] < -50
    assert _rung(rep, "ozone")["parameters"]["ozone_column"] == pytest.approx(300.0, rel=0.15)
    rep2 = ladder(_cfg(), synthetic(_cfg(ozone=False), 60.0, seed=5), rungs).run()
    assert "ozone" not in rep2["components"], rep2["why"]
    assert _rung(rep2, "ozone")["delta_bic_parent"] > 0


def test_multiple_scattering_dropped_for_single_scattering_noon_data_kept_at_twilight():
    """Noon data rendered without multiple scattering: the 'multiple' rung (orders 2) fits worse and is
    dropped. Twilight data (sun 94 deg) rendered with it (Hillaire 2020): kept, and only then is the fit
    at the noise level (loss ~ 1/2 per element)."""
    rungs = _subset("rayleigh", "mie", "ozone", "multiple")
    rep = ladder(_cfg(), synthetic(_cfg(), 30.0, seed=6, n=120), rungs).run()
    assert "multiple" not in rep["components"], rep["why"]
    assert _rung(rep, "multiple")["delta_bic_parent"] > 0
    rep2 = ladder(_cfg(), synthetic(_cfg(), 94.0, orders=2, seed=7, n=120), rungs).run()
    assert rep2["chosen"] == "multiple", rep2["why"]
    assert _rung(rep2, "multiple")["delta_bic_parent"] < -1000
    assert _rung(rep2, "multiple")["loss"] < 0.6
    assert rep2["heldout_choice"] == "multiple"


# -- skyfit fit --select ------------------------------------------------------------------------


def test_cli_select_writes_the_ladder_and_a_result_that_evaluate_rebuilds(tmp_path, capsys):
    """A 10 x 10 noise-free render of the earth config (sigma 1 %, known): the ladder keeps aerosol and ozone,
    drops multiple scattering, skips the height fog (a sky dome is not short-range), and ``evaluate`` of the
    chosen model reproduces the fit's RMSE."""
    common = ["render", "earth", "--size", "10", "--sun-zenith", "40", "--sun-azimuth", "120", "--wavelengths",
              "450:650:100", "--integrator", "chapman", "--view-samples", "8", "--rule", "gauss", "--dtype", "float64"]
    rc, _, err = _run(common + ["--out", tmp_path / "sky.exr", "--spectral"], capsys)
    assert rc == 0, err
    out = tmp_path / "RESULT.json"
    fast = ["--integrator", "chapman", "--view-samples", "8", "--rule", "gauss", "--starts", "1", "--max-iter", "20",
            "--adam-steps", "3"]
    rc, so, err = _run(["fit", tmp_path / "sky.exr", "--config", "earth", "--out", out, "--select", "--json",
                        "--select-sigma", "known", "--no-plots", *fast], capsys)
    assert rc == 0, err
    res = json.loads(out.read_text())
    sel = res["selection"]
    assert [r["name"] for r in sel["rungs"]][: len(RUNGS)] == [r.name for r in RUNGS]
    assert sel["components"] == ["rayleigh", "mie", "ozone"], sel["why"]
    fog = next(r for r in sel["rungs"] if r["name"] == "height_fog")
    assert "flat-Earth" in fog["skipped"]
    assert json.loads(so)["selection"]["chosen"] == sel["chosen"]
    assert set(res["free"]) == set(next(r for r in sel["rungs"] if r["name"] == sel["chosen"])["free"])
    rc, so, err = _run(["evaluate", out, tmp_path / "sky.exr", "--json"], capsys)
    assert rc == 0, err
    assert json.loads(so)["rmse"] == pytest.approx(res["metrics"]["rmse"], rel=1e-6, abs=1e-9)


def test_cli_select_refuses_a_robust_loss_and_a_bad_heldout_fraction(tmp_path, capsys):
    rc, _, err = _run(["render", "earth", "--size", "8", "--out", tmp_path / "sky.exr", "--spectral", "--sun-zenith", "40",
                       "--wavelengths", "450:650:100"], capsys)
    assert rc == 0, err
    out = tmp_path / "RESULT.json"
    rc, so, err = _run(["fit", tmp_path / "sky.exr", "--config", "earth", "--out", out, "--select", "--loss", "huber"], capsys)
    assert rc == 2 and err.count("\n") == 1 and "Gaussian" in err, err
    assert not out.exists()
    rc, so, err = _run(["fit", tmp_path / "sky.exr", "--config", "earth", "--out", out, "--select", "--heldout", "1.5"], capsys)
    assert rc == 2 and err.count("\n") == 1 and "held-out fraction" in err, err
    assert not out.exists()


def test_height_fog_rung_is_fitted_only_for_a_flat_earth_scene():
    """Views within 8 deg of the zenith and the sun 5 deg from it: every segment's curvature fraction is below
    1 %, so the flat-Earth height-fog rung is fitted; it fits no better than Chapman (both near exact on steep
    rays), so it is not taken. A sky down to 5 deg elevation is refused with the integrator's reason."""
    rungs = _subset("rayleigh", "mie", "height_fog")
    rep = ladder(_cfg(), synthetic(_cfg(ozone=False), 5.0, seed=9, n=100, min_elevation=82.0), rungs).run()
    fog = _rung(rep, "height_fog")
    assert "bic" in fog and fog["integrator"] == "height_fog", fog
    assert abs(fog["delta_bic_parent"]) < 2 and not fog["accepted"]
    assert rep["components"] == ["rayleigh", "mie"]
    rep2 = ladder(_cfg(), synthetic(_cfg(ozone=False), 5.0, seed=9, n=60), rungs).run()
    assert "flat-Earth" in _rung(rep2, "height_fog")["skipped"]
