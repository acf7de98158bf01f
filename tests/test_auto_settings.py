"""Automatic renderer settings (skyfit.render.auto): the choice rule on hand-made measurements, and
on the shipped trade-study measurements the chosen setting meets the tolerance against a converged
reference computed here, on a different pixel set than the bench's."""
from __future__ import annotations

import contextlib
import io
import json
import math
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from skyfit.render import auto
from skyfit.render.auto import Tolerance, bracket_scenes, choose, fit_overrides, noise_tolerance, parse_accuracy


# -- parsing -----------------------------------------------------------------------------------
def test_parse_accuracy_forms():
    assert parse_accuracy("de=1") == Tolerance("de", 1.0)
    assert parse_accuracy(" REL=0.02 ") == Tolerance("rel", 0.02)
    assert parse_accuracy("auto") == Tolerance("de", auto.DEFAULT_DELTA_E)
    # With a noise level (fit/sample), auto and noise are a third of it.
    assert parse_accuracy("auto", noise_rel=0.03) == Tolerance("rel", pytest.approx(0.01))
    assert parse_accuracy("noise", noise_rel=0.03).value == pytest.approx(0.01)


@pytest.mark.parametrize("text, match", [("fast", "must be 'auto'"), ("de", "must be 'auto'"), ("dE=x", "not a number"),
                                         ("de=0", "finite number > 0"), ("rel=-1", "> 0"), ("rel=nan", "> 0"),
                                         ("noise", "needs data")])
def test_parse_accuracy_refuses(text, match):
    with pytest.raises(ValueError, match=match):
        parse_accuracy(text)


def test_noise_tolerance_is_the_median_relative_sigma():
    v = [np.array([1.0, 2.0, 4.0, 0.0]), np.array([[10.0, -10.0]])]
    s = [np.array([0.01, 0.04, 0.4, 1.0]), np.array([[0.2, 0.3]])]
    # relative sigmas of the non-zero values: 0.01, 0.02, 0.1, 0.02, 0.03 -> median 0.02
    assert noise_tolerance(v, s) == pytest.approx(0.02)
    with pytest.raises(ValueError, match="no positive data"):
        noise_tolerance([np.zeros(3)], [np.ones(3)])


# -- the choice rule on hand-made measurements --------------------------------------------------
def _frontier():
    scenes = [{"name": f"z{z}", "sun_zenith_deg": z, "altitude_m": 0.0} for z in (20.0, 60.0, 90.0)]
    settings = [{"id": k, "family": "single", "multiple": None, "orders": 1, "integrator": k, "view_samples": 8,
                 "rule": "gauss", "dtype": "float32", "hillaire_lut": None, "table_sizes": None} for k in ("cheap", "mid", "dear")]
    settings.append({**settings[0], "id": "f64", "integrator": "f64", "dtype": "float64"})
    de = {"cheap": (0.5, 2.0, 3.0), "mid": (0.3, 0.6, 1.2), "dear": (0.1, 0.2, 0.3), "f64": (0.01, 0.01, 0.01)}
    cost = {"cheap": 1.0, "mid": 2.0, "dear": 10.0, "f64": 0.5}
    results = {k: {sc["name"]: {"cpu_s": cost[k], "prepare_cpu_s": 0.1, "mean_delta_e": e, "rel_rmse": e / 100}
                   for sc, e in zip(scenes, de[k])} for k in de}
    return {"scenes": scenes, "settings": settings, "results": results}


def test_bracket_scenes():
    fr = _frontier()
    assert bracket_scenes(fr, [40.0], [0.0]) == ["z20.0", "z60.0"]
    assert bracket_scenes(fr, [60.0], [0.0]) == ["z60.0"]
    assert bracket_scenes(fr, [5.0], [0.0]) == ["z20.0"]  # below the smallest zenith: the high-sun scene
    assert bracket_scenes(fr, [91.5, 30.0], [0.0, 0.0]) == ["z90.0", "z20.0", "z60.0"]
    with pytest.raises(ValueError, match="beyond the measured scenes"):
        bracket_scenes(fr, [95.0], [0.0])
    with pytest.raises(ValueError, match="altitude"):
        bracket_scenes(fr, [30.0], [5000.0])


def test_choose_takes_the_cheapest_setting_meeting_the_tolerance_over_the_bracket():
    fr = _frontier()
    # Sun at 20 deg: cheap has ΔE 0.5 <= 0.7 x 1.
    c = choose(Tolerance("de", 1.0), 20.0, frontier=fr)
    assert c.setting["id"] == "cheap" and c.predicted_error == 0.5 and c.scenes == ("z20.0",)
    assert c.predicted_cpu_s == pytest.approx(1.1) and c.max_cpu_s == pytest.approx(10.1)
    # Sun at 40 deg: bracket z20 + z60, cheap's worst is 2.0, mid's 0.6 <= 0.7.
    c = choose(Tolerance("de", 1.0), 40.0, frontier=fr)
    assert c.setting["id"] == "mid" and c.predicted_error == 0.6
    # Without the margin, the worst error must only be <= the tolerance itself.
    assert choose(Tolerance("de", 0.6), 40.0, frontier=fr, margin=1.0).setting["id"] == "mid"
    assert choose(Tolerance("de", 0.6), 40.0, frontier=fr).setting["id"] == "dear"
    # The relative metric is read from its own column.
    assert choose(Tolerance("rel", 0.01), 40.0, frontier=fr).setting["id"] == "mid"
    # float64 rows are chosen only for float64.
    assert choose(Tolerance("de", 1.0), 85.0, frontier=fr, dtype="float64").setting["id"] == "f64"
    with pytest.raises(ValueError, match=r"no measured setting reaches de=0.01.*dear.*0.3"):
        choose(Tolerance("de", 0.01), 80.0, frontier=fr)
    with pytest.raises(ValueError, match="no multiple-scattering settings"):
        choose(Tolerance("de", 1.0), 40.0, orders=2, frontier=fr)


# -- the shipped measurements ------------------------------------------------------------------------
@pytest.fixture(scope="module")
def shipped():
    return auto.load_frontier()


def test_shipped_frontier_is_a_trade_study_run(shipped):
    assert shipped["command"].startswith("skyfit bench --study trade")
    assert len(shipped["scenes"]) == 8 and {s["altitude_m"] for s in shipped["scenes"]} == {0.0, 10000.0}
    fams = {s["family"] for s in shipped["settings"]}
    assert fams == {"single", "multiple"}
    assert {s["dtype"] for s in shipped["settings"] if s["family"] == "single"} == {"float32", "float64"}


def test_looser_tolerance_is_never_more_expensive(shipped):
    for sc in shipped["scenes"]:
        costs = []
        for de in (0.3, 1.0, 3.0):
            try:
                costs.append(choose(Tolerance("de", de), sc["sun_zenith_deg"], sc["altitude_m"], frontier=shipped).predicted_cpu_s)
            except ValueError:
                costs.append(math.inf)
        assert costs[0] >= costs[1] >= costs[2], (sc, costs)


def _errors(ref: np.ndarray, img: np.ndarray, wavelengths: np.ndarray) -> tuple[float, float]:
    """(mean CIE 1976 ΔE, relative RMS error), written out here with colour-science's Lab (not skyfit's ΔE)."""
    import colour

    from skyfit.render import spectral_to_xyz_matrix

    m = spectral_to_xyz_matrix(torch.as_tensor(wavelengths, dtype=torch.float64)).numpy()
    white = np.percentile(ref @ m[:, 1], 99.0)
    wp = colour.CCS_ILLUMINANTS["CIE 1931 2 Degree Standard Observer"]["D65"]
    lab = [colour.XYZ_to_Lab((x @ m) / white, wp) for x in (img, ref)]
    de = np.sqrt(((lab[0] - lab[1]) ** 2).sum(-1)).mean()
    return float(de), float(np.linalg.norm(img - ref) / np.linalg.norm(ref))


def test_chosen_single_scattering_settings_meet_the_tolerance(shipped):
    """Every fixed scene, ΔE 1 and 1 % relative error, float32: rendered on a 26 x 26 sky (another pixel
    set than the bench's 40 x 40) against Gauss-Legendre 32 x 128 nodes in float64."""
    from skyfit.atmosphere import load_atmosphere
    from skyfit.camera import FisheyeCamera, render_fisheye
    from skyfit.transmittance import parse_integrator
    from skyfit.transmittance import make_integrator

    torch.set_num_threads(1)
    lam = np.asarray(shipped["wavelengths_nm"])
    atm = {d: load_atmosphere("earth", lam, dtype=getattr(torch, d)).replace(ozone_absorption=None) for d in ("float32", "float64")}
    cam = FisheyeCamera(26)
    ref_int = make_integrator("gauss", samples=32)
    checked = 0
    for sc in shipped["scenes"]:
        def sky(a, integ, **kw):
            with torch.no_grad():
                img = render_fisheye(a, cam, sc["sun_zenith_deg"], sc["sun_azimuth_deg"], integ, altitude=sc["altitude_m"], **kw)
            return img.spectral[img.valid].double().numpy()

        ref = sky(atm["float64"], ref_int, view_samples=128, rule="gauss")
        for tol in (Tolerance("de", 1.0), Tolerance("rel", 0.01)):
            c = choose(tol, sc["sun_zenith_deg"], sc["altitude_m"], orders=1, dtype="float32", frontier=shipped)
            st = c.setting
            img = sky(atm["float32"], parse_integrator(st["integrator"]), view_samples=st["view_samples"], rule=st["rule"])
            de, rel = _errors(ref, img, lam)
            got = de if tol.metric == "de" else rel
            assert got <= tol.value, (sc["name"], str(tol), st, de, rel)
            checked += 1
    assert checked == 2 * len(shipped["scenes"])


def test_fit_overrides_from_the_data_noise(shipped):
    """A fit's ``accuracy: auto`` on 1 % noise data asks for rel <= 0.0033 over its observations' scenes."""
    obs = [SimpleNamespace(values=torch.full((5, 3), 2.0), sigma=torch.full((5, 3), 0.02), mask=torch.ones(5, dtype=torch.bool),
                           sun_zenith=torch.tensor(math.radians(30.0)), altitude_m=0.0),
           SimpleNamespace(values=torch.full((4, 3), 1.0), sigma=torch.full((4, 3), 0.01), mask=torch.ones(4, dtype=torch.bool),
                           sun_zenith=torch.deg2rad(torch.tensor([70.0, 72.0, 71.0, 70.5])), altitude_m=0.0)]
    over, c = fit_overrides("auto", obs, orders=1, dtype="float64", frontier=shipped)
    assert c.tolerance == Tolerance("rel", pytest.approx(0.01 / 3))
    assert set(c.scenes) == {"noon", "morning", "sunset"}  # 30 deg -> noon + morning; 70-72 deg -> morning + sunset
    assert c.setting["dtype"] == "float64" and c.predicted_error <= auto.MARGIN * 0.01 / 3
    assert set(over) == {"integrator", "view_samples", "rule"} and over["integrator"] == c.setting["integrator"]


def test_fit_settings_resolve_accuracy():
    from skyfit.fit.problem import fit_settings, resolve_accuracy

    s = fit_settings({"accuracy": "de=1", "integrator": "taylor", "view_samples": 3})
    obs = [SimpleNamespace(values=torch.ones(3, 2), sigma=torch.full((3, 2), 0.01), mask=torch.ones(3, dtype=torch.bool),
                           sun_zenith=torch.tensor(0.5), altitude_m=0.0)]
    s2, model = resolve_accuracy(s, obs)
    c = choose(Tolerance("de", 1.0), math.degrees(0.5), 0.0, dtype="float64")
    assert (s2.integrator, s2.view_samples, s2.rule) == (c.setting["integrator"], c.setting["view_samples"], c.setting["rule"])
    assert model.view_samples == c.setting["view_samples"] and s2.accuracy == "de=1"


# -- the CLI ------------------------------------------------------------------------------------------
def _run(argv):
    from skyfit.cli import main

    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        rc = main(argv)
    return rc, out.getvalue(), err.getvalue()


def test_render_accuracy_flag(tmp_path, shipped):
    from skyfit.io import read_exr

    out = tmp_path / "sky.exr"
    rc, so, se = _run(["render", "earth", "--out", str(out), "--size", "12", "--sun-zenith", "40", "--altitude", "2000",
                       "--accuracy", "de=1", "--wavelengths", "400:700:50", "--json"])
    assert rc == 0, se
    info = json.loads(so)["accuracy"]
    c = choose(Tolerance("de", 1.0), 40.0, 2000.0, frontier=shipped)
    assert info["setting"] == c.setting and set(info["scenes"]) == {"noon", "morning", "noon-10km", "morning-10km"}
    meta = read_exr(out)[1]
    assert json.dumps(meta).count(c.setting["integrator"].split(":")[0]) >= 1


@pytest.mark.parametrize("acc, match", [("fast", "must be 'auto'"), ("de=1e-9", "no measured setting reaches")])
def test_render_accuracy_refusals(tmp_path, acc, match):
    out = tmp_path / "sky.exr"
    rc, so, se = _run(["render", "earth", "--out", str(out), "--size", "8", "--sun-zenith", "40", "--accuracy", acc])
    assert rc == 2 and match in se and len(se.strip().splitlines()) == 1 and "Traceback" not in se
    assert not out.exists()


def test_fit_accuracy_auto_end_to_end(tmp_path, shipped):
    """``skyfit fit --accuracy auto`` on a rendered EXR: the fit runs with the choice for a third of the
    data's noise, records it in RESULT.json's settings, and recovers the exposure."""
    from skyfit.fit import problem as R

    n = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        sky = tmp_path / "sky.exr"
        rc, _, se = _run(["render", "earth", "--out", str(sky), "--size", "8", "--sun-zenith", "50", "--spectral",
                          "--wavelengths", "450:650:100", "--integrator", "gauss:samples=16", "--view-samples", "32",
                          "--rule", "gauss", "--dtype", "float64"])
        assert rc == 0, se
        out = tmp_path / "r" / "RESULT.json"
        rc, so, se = _run(["fit", str(sky), "--config", "earth", "--out", str(out), "--free", "exposure", "--accuracy", "auto",
                           "--starts", "1", "--max-iter", "4", "--adam-steps", "0", "--no-plots", "--json"])
        assert rc == 0, se
    finally:
        torch.set_num_threads(n)
    res = json.loads(out.read_text())
    s = R.fit_settings({"accuracy": "auto"})
    obs = R.load_data([sky], s, None, None)
    over, c = fit_overrides("auto", obs, dtype="float64", frontier=shipped)
    rel_sigma = np.median((obs[0].sigma / obs[0].values)[obs[0].mask].numpy())
    assert c.tolerance.metric == "rel" and c.tolerance.value == pytest.approx(rel_sigma / 3, rel=1e-9)
    assert res["settings"]["accuracy"] == "auto"
    assert {k: res["settings"][k] for k in over} == over
    assert res["parameters"]["exposure"] == pytest.approx(1.0, abs=3 * c.tolerance.value)
