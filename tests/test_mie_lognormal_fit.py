"""The lognormal_mie aerosol in fits (docs/aerosol.md): synthetic recovery of r_g and sigma_g within their Laplace
sigma, and the ``lognormal_mie`` rung of ``fit --select``. Skies as in tests/test_select.py (render_vectors from
config dicts, not through the fit's parameterisation; Chapman, 8 Gauss view nodes, seeded 1 % noise, sigma known)."""
from __future__ import annotations

import math

import pytest

from skyfit.atmosphere import atmosphere_from_config
from skyfit.fit import FitOptions, FitProblem, Parameterisation, fit, make_loss
from skyfit.fit.laplace import laplace_summary
from test_mie_lognormal import _hg, _lcfg
from test_select import LAM, _model, _rung, _subset, ladder, synthetic

TRUTH = {"mie_median_radius": 0.12e-6, "mie_geometric_sigma": 1.7}
FREE = ["mie_median_radius", "mie_geometric_sigma", "mie_aod_550", "exposure"]


def test_synthetic_recovery_within_laplace_sigma():
    """Skies of r_g 0.12 um, sigma_g 1.7 (AOD 0.072, sun 50 deg, 160 directions x 6 wavelengths, 1 % noise,
    Chapman) fitted from r_g 0.08 um, sigma_g 1.5: five seeds, each within 3 Laplace sigma and their z-scores'
    RMS within [0.35, 1.8] (the Laplace sigma is neither much too small nor much too large)."""
    base = atmosphere_from_config(_lcfg(r_um=0.08, sigma=1.5), LAM)
    truth = _lcfg(r_um=0.12, sigma=1.7)
    zs = []
    for seed in range(5):
        obs = synthetic(truth, 50.0, seed=20 + seed, n=160)
        prob = FitProblem(Parameterisation(base, FREE), _model(), [obs], make_loss("squared"))
        res = fit(prob, FitOptions(starts=1, adam_steps=0, max_iter=100))
        lap = laplace_summary(prob, res.x)
        assert lap["positive_definite"]
        for name, true in TRUTH.items():
            z = (res.parameters[name] - true) / lap["sigma"][name]
            assert abs(z) < 3.0, (seed, name, res.parameters[name], lap["sigma"][name])
            zs.append(z)
        assert res.parameters["mie_aod_550"] == pytest.approx(6e-5 * 1200.0, rel=0.02)
    rms = math.sqrt(sum(z * z for z in zs) / len(zs))
    assert 0.35 < rms < 1.8, zs


def test_select_chooses_lognormal_mie_only_when_in_the_data():
    """The ladder rayleigh -> mie (g, alpha) -> lognormal_mie (r_g, sigma_g instead of g, alpha) on a Henyey-Greenstein
    config: a lognormal sky (default refractive index) chooses the rung, a Henyey-Greenstein sky does not."""
    rungs = _subset("rayleigh", "mie", "lognormal_mie")
    rep = ladder(_hg(), synthetic(_lcfg(), 50.0, seed=11, n=160), rungs).run()
    assert rep["chosen"] == "lognormal_mie", rep["why"]
    row = _rung(rep, "lognormal_mie")
    assert row["delta_bic_parent"] < -100 and "mie_g" not in row["free"] and "mie_angstrom_alpha" not in row["free"]
    assert row["parameters"]["mie_median_radius"] == pytest.approx(0.12e-6, rel=0.3)
    assert row["parameters"]["mie_geometric_sigma"] == pytest.approx(1.7, rel=0.1)
    rep2 = ladder(_hg(), synthetic(_hg(), 50.0, seed=12, n=160), rungs).run()
    assert rep2["chosen"] == "mie", rep2["why"]
    assert _rung(rep2, "lognormal_mie")["delta_bic_parent"] > 100


def test_select_from_a_lognormal_config():
    """With a lognormal_mie config the lower rungs fit a Henyey-Greenstein phase (g from the distribution at 550 nm)
    instead of being refused, and the rung then frees the config's distribution (start r_g 0.08 um, sigma_g 1.5)."""
    rungs = _subset("rayleigh", "mie", "lognormal_mie")
    rep = ladder(_lcfg(r_um=0.08, sigma=1.5), synthetic(_lcfg(), 50.0, seed=13, n=160), rungs).run()
    assert "bic" in _rung(rep, "mie"), rep["why"]
    assert rep["chosen"] == "lognormal_mie", rep["why"]
    assert _rung(rep, "lognormal_mie")["parameters"]["mie_median_radius"] == pytest.approx(0.12e-6, rel=0.3)
