"""``multiple: bruneton_lagged``: Bruneton's orders >= 2 as a factor on the live single scattering,
frozen per fit and refreshed at its result (skyfit.fit.model.SkyModel.lagged, skyfit.fit.photo.lagged_fit)."""
from __future__ import annotations

import json

import pytest
import torch

from skyfit.cli import main
from skyfit.fit.parameters import FitError
from skyfit.fit.photo import freeze_tables
from skyfit.fit.problem import fit_settings, prepare
from skyfit.scattering.multiple import sky_radiance
from skyfit.scattering.single import ray_parameters

SIZES = [64, 16, 16, 8, 8, 32, 8, 4]
FIT = ["--integrator", "chapman", "--view-samples", "8", "--rule", "gauss", "--starts", "1", "--adam-steps", "0",
       "--orders", "4", "--multiple", "bruneton_lagged"]


@pytest.fixture(scope="module")
def sky(tmp_path_factory):
    """A 14 x 14 spectral sky with 4 Bruneton orders (its tables' single scattering replaced by the live one is
    what the lagged model is: rendered here by the fit's own renderer at the truth, below)."""
    d = tmp_path_factory.mktemp("lagged")
    assert main(["render", "earth_hazy", "--out", str(d / "sky.exr"), "--size", "14", "--sun-zenith", "50",
                 "--wavelengths", "450,550,650", "--integrator", "chapman", "--view-samples", "8", "--rule", "gauss",
                 "--spectral", "--dtype", "float64"]) == 0
    return d


def _problem(sky, free=()):
    from skyfit.atmosphere import load_yaml
    from skyfit.atmosphere.config import SHIPPED_CONFIGS

    cfg = load_yaml(str(SHIPPED_CONFIGS / "earth_hazy.yaml"))
    cfg["fit"] = {"orders": 4, "multiple": "bruneton_lagged", "table_sizes": SIZES, "integrator": "chapman",
                  "view_samples": 8, "rule": "gauss", "free": list(free) or ["exposure"]}
    prep = prepare([sky / "sky.exr"], cfg, fit_settings(cfg["fit"]))
    return prep.fit_problem()


def test_the_factor_must_be_frozen_and_then_adds_the_tables_multiple_scattering(sky):
    problem = _problem(sky)
    assert problem.model.lagged and problem.model.tables(problem.param.atmosphere(
        problem.param.to_physical(problem.param.initial_vector()))) is None
    x = problem.param.initial_vector()
    with pytest.raises(FitError, match="bruneton_lagged needs its multiple-scattering factor"):
        problem.predict(x)
    with torch.no_grad():
        phys = problem.param.to_physical(x)
        atm = problem.param.atmosphere(phys)
        freeze_tables(problem, x, problem.model.factor_model(), wavelength_nodes_count=None)
        factor = problem.frozen_factor
        problem.frozen_factor = [torch.ones_like(f) for f in factor]
        live = problem.spectra(phys, atm)[0] / problem.solar_scale[0]
        problem.frozen_factor = factor
        lagged = problem.spectra(phys, atm)[0] / problem.solar_scale[0]
        tables = problem.bruneton[1]
        r, mu, mu_s, nu = ray_parameters(atm, problem.view_directions(phys, 0), problem.sun_vectors(phys, 0), 0.0)
        every = sky_radiance(tables, atm, r, mu, mu_s, nu, below_mu_s_min="clamp")
        first = sky_radiance(tables, atm, r, mu, mu_s, nu, orders=1, below_mu_s_min="clamp")
    # live single scattering + the tables' orders >= 2 (their own first order taken off)
    torch.testing.assert_close(lagged, live + (every - first), rtol=1e-10, atol=1e-12 * float(live.abs().max()))
    assert float((every - first).min()) > 0.0  # multiple scattering adds light


def test_fit_and_evaluate_with_the_lagged_model(sky, tmp_path):
    """The sky was rendered with single scattering only: a lagged 4-order fit must darken it by the exposure
    (the factor > 1 everywhere), refresh its factor and converge; evaluate rebuilds the factor at the fit."""
    out = tmp_path / "r.json"
    assert main(["fit", str(sky / "sky.exr"), "--config", "earth_hazy", "--out", str(out), "--free", "exposure,mie_g",
                 "--no-plots", *FIT]) == 0
    res = json.loads(out.read_text())
    conv = res["convergence"]
    assert res["model"]["multiple"] == "bruneton_lagged"
    assert conv["ms_refreshes"] >= 2 and conv["ms_table_builds"] >= 2
    assert res["parameters"]["exposure"] < 0.95  # the added multiple scattering is taken back by the exposure
    from skyfit.fit.run import run_evaluate

    e = run_evaluate(out, [sky / "sky.exr"])
    assert e["rmse"] == pytest.approx(res["metrics"]["rmse"], rel=1e-6)
