"""The ladder's aerosol rungs (two_term_hg, boundary_layer; docs/selection.md): a synthetic sky made with the
component selects it, a sky made without it does not. Skies as in tests/test_select.py (render_vectors from
config dicts, Chapman, 8 Gauss view nodes, seeded 1 % noise, sigma known)."""
from __future__ import annotations

import pytest

from test_select import _cfg, _rung, _subset, ladder, synthetic


def _hg(**mie):
    cfg = _cfg(beta_550=6e-5)
    cfg["mie"].update({"phase": "henyey_greenstein", "g": 0.75, **mie})
    return cfg


def test_two_term_phase_selected_only_when_in_the_data():
    rungs = _subset("rayleigh", "mie", "two_term_hg")
    two = _hg(phase="two_term_hg", g=0.8, g2=-0.5, hg_weight=0.8)
    rep = ladder(_hg(), synthetic(two, 50.0, seed=11, n=160), rungs).run()
    assert "two_term_hg" in rep["chosen"], rep["why"]
    row = _rung(rep, "two_term_hg")
    assert row["delta_bic_parent"] < -20
    assert row["parameters"]["mie_g2"] == pytest.approx(-0.5, abs=0.15)
    assert row["parameters"]["mie_hg_weight"] == pytest.approx(0.8, abs=0.1)
    rep2 = ladder(_hg(), synthetic(_hg(), 50.0, seed=12, n=160), rungs).run()
    assert rep2["chosen"] == "mie", rep2["why"]


def test_boundary_layer_selected_only_when_in_the_data():
    rungs = _subset("rayleigh", "mie", "boundary_layer")
    bl = _hg(profile="boundary_layer", mixing_height_m=3000.0, scale_height_m=500.0)
    rep = ladder(_hg(scale_height_m=500.0), synthetic(bl, 70.0, seed=13, n=160, min_elevation=2.0), rungs).run()
    assert "boundary_layer" in rep["chosen"], rep["why"]
    row = _rung(rep, "boundary_layer")
    assert row["delta_bic_parent"] < -10
    # h_mix itself is weakly identified from the ground (AOD, g and alpha compensate: 630 m for a 3 km truth at
    # seed 13); the rung moves it well away from its 200 m start (the exponential limit is h_mix -> 0)
    assert row["parameters"]["mie_mixing_height"] > 400.0
    rep2 = ladder(_hg(scale_height_m=500.0), synthetic(_hg(scale_height_m=500.0), 70.0, seed=14, n=160,
                                                     min_elevation=2.0), rungs).run()
    assert rep2["chosen"] == "mie", rep2["why"]
