"""`skyfit fit` / `skyfit evaluate` on tiny synthetic EXRs (and a Kider capture when the shared data is there).

Contract (CONTRACT.md): RESULT.json holds parameters (SI, named), free, integrator,
metrics (rmse, delta_e, loss) and data (sun position); evaluate prints rmse,
rmse_units, delta_e, n_samples; bad input -> one line naming the problem and the
file, exit status 2, no output file.
"""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from skyfit.cli import main
from skyfit.io import read_exr, write_exr
from _cli import run as _run

KIDER = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "kider2014" / "2013-05-27" / "2013-05-27___09.30.00"
FAST = ["--integrator", "gauss:samples=8", "--view-samples", "4", "--rule", "trapezoid", "--starts", "1", "--max-iter", "30"]
TRUE_G = 0.7




def _files(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir()) if folder.exists() else []


@pytest.fixture(scope="module")
def sky(tmp_path_factory):
    """A 12 x 12 spectral and an RGB fisheye rendered from the earth config with g = 0.7 (float64 render)."""
    d = tmp_path_factory.mktemp("sky")
    cfg = Path(__file__).resolve().parents[1] / "skyfit" / "configs" / "earth.yaml"
    text = cfg.read_text().replace("g: 0.8  ", f"g: {TRUE_G}  ")
    assert f"g: {TRUE_G}" in text
    (d / "truth.yaml").write_text(text)
    common = ["render", d / "truth.yaml", "--size", "12", "--sun-zenith", "40", "--sun-azimuth", "120",
              "--wavelengths", "450:650:100", "--integrator", "gauss:samples=8", "--view-samples", "4", "--rule", "trapezoid", "--spacing", "uniform",
              "--dtype", "float64"]  # the fit's renderer (FAST), so noise-free data are fitted to rounding
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        assert main([str(a) for a in common + ["--out", d / "sky.exr", "--spectral"]]) == 0
        assert main([str(a) for a in common + ["--out", d / "rgb.exr"]]) == 0
    finally:
        torch.set_num_threads(n)
    return d


def test_fit_and_evaluate_a_spectral_exr(sky, tmp_path, capsys):
    out = tmp_path / "res" / "RESULT.json"
    rc, so, se = _run(["fit", sky / "sky.exr", "--config", "earth", "--out", out, "--free", "mie_g,exposure", "--json", *FAST],
                      capsys)
    assert rc == 0, se
    summary = json.loads(so)
    res = json.loads(out.read_text())
    assert res["free"] == ["mie_g", "exposure"]
    assert abs(res["parameters"]["mie_g"] - TRUE_G) < 1e-3  # noise-free data: float32 rounding only
    assert res["parameters"]["exposure"] == pytest.approx(1.0, abs=1e-3)
    assert res["parameters"]["mie_scale_height"] == pytest.approx(1200.0)  # fixed, from the config
    assert res["units"]["mie_beta_550"] == "1/m"
    assert res["integrator"]["name"] == "gauss" and res["integrator"]["samples"] == 8
    assert res["integrator"]["view_samples"] == 4 and res["integrator"]["orders"] == 1
    for k in ("rmse", "delta_e", "loss"):
        assert math.isfinite(res["metrics"][k])
    assert res["metrics"]["rmse_units"] == "mW/(m^2 sr nm)"
    assert res["metrics"]["rmse"] < 1e-2 * 1e3 * 0.02  # < 1 % of a typical 0.02 W/(m^2 sr nm) radiance
    assert res["data"][0]["sun_zenith_deg"] == pytest.approx(40.0)
    assert res["data"][0]["sun_azimuth_deg"] == pytest.approx(120.0)
    assert res["convergence"]["reason"] in ("gradient norm", "relative loss change")
    assert summary["rmse"] == pytest.approx(res["metrics"]["rmse"])
    pngs = [Path(p) for p in res["plots"]]
    assert pngs and all(p.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" for p in pngs)
    assert all(p.parent == out.parent for p in pngs)
    assert not [f for f in _files(out.parent) if f.startswith(".")]  # no temporary files left

    rc, so, se = _run(["evaluate", out, sky / "sky.exr", "--json"], capsys)
    assert rc == 0, se
    ev = json.loads(so)
    assert {"rmse", "rmse_units", "delta_e", "n_samples"} <= set(ev)
    assert ev["rmse"] == pytest.approx(res["metrics"]["rmse"], rel=1e-6)
    assert ev["n_samples"] == res["metrics"]["n_samples"]

    rc, so, se = _run(["evaluate", out, sky / "sky.exr", "--json", "--refit-nuisance"], capsys)
    assert rc == 0, se
    ev2 = json.loads(so)
    assert ev2["refit_nuisance"] and ev2["convergence"] is not None
    assert ev2["rmse"] <= ev["rmse"] * 1.01


def test_camera_tilts_are_fitted_and_refitted(sky, tmp_path, capsys):
    """An untilted render: the fitted tilts stay at zero; --refit-nuisance re-estimates the orientation the fit modelled."""
    out = tmp_path / "RESULT.json"
    rc, so, se = _run(["fit", sky / "sky.exr", "--config", "earth", "--out", out, "--no-plots",
                       "--free", "mie_g,exposure,camera_tilt_north,camera_tilt_east", *FAST], capsys)
    assert rc == 0, se
    res = json.loads(out.read_text())
    for n in ("camera_tilt_north", "camera_tilt_east"):
        assert abs(math.degrees(res["parameters"][n])) < 0.05, (n, res["parameters"][n])
    assert abs(res["parameters"]["mie_g"] - TRUE_G) < 1e-3
    rc, so, se = _run(["evaluate", out, sky / "sky.exr", "--json", "--refit-nuisance"], capsys)
    assert rc == 0, se
    ev = json.loads(so)
    assert ev["refitted"] == ["exposure", "camera_tilt_north", "camera_tilt_east"]
    assert abs(math.degrees(ev["nuisance"]["camera_tilt_north"])) < 0.05
    assert ev["rmse"] <= res["metrics"]["rmse"] * 1.01


def test_fit_section_of_the_config_and_rgb_data(sky, tmp_path, capsys):
    cfg = tmp_path / "fit.yaml"
    text = (Path(__file__).resolve().parents[1] / "skyfit" / "configs" / "earth.yaml").read_text()
    cfg.write_text(text + "\nfit:\n  free: [mie_g, exposure]\n  integrator: gauss:samples=8\n  view_samples: 4\n"
                   "  rule: trapezoid\n  starts: 1\n  max_iter: 30\n")
    out = tmp_path / "RESULT.json"
    rc, so, se = _run(["fit", sky / "rgb.exr", "--config", cfg, "--out", out, "--json", "--no-plots"], capsys)
    assert rc == 0, se
    res = json.loads(out.read_text())
    assert res["data"][0]["kind"] == "rgb"
    assert res["model"]["wavelengths_nm"] == [450.0, 550.0, 650.0]  # the grid the EXR says it was rendered on
    assert abs(res["parameters"]["mie_g"] - TRUE_G) < 5e-3
    assert res["metrics"]["rmse_units"].startswith("linear sRGB")
    assert _files(tmp_path) == ["RESULT.json", "fit.yaml"]


@pytest.mark.parametrize("argv, match", [
    (["fit", "{d}/missing.exr", "--config", "earth", "--out", "{o}"], "data not found: .*missing.exr"),
    (["fit", "{sky}", "--config", "earth", "--out", "{o}", "--free", "mie_g,bogus"], "unknown free parameter 'bogus'"),
    (["fit", "{sky}", "--config", "earth", "--out", "{d}/result.txt"], "--out must name a .json file"),
    (["fit", "{sky}", "--config", "earth", "--out", "{o}", "--loss", "l1"], "unknown loss 'l1'"),
    (["fit", "{sky}", "--config", "{d}/nope.yaml", "--out", "{o}"], "config file not found: .*nope.yaml"),
    (["fit", "{sky}", "--config", "earth", "--out", "{o}", "--orders", "0"], "orders must be >= 1"),
    (["fit", "{sky}", "--config", "earth", "--out", "{o}", "--free", "ozone_column,mie_g", "--orders", "2",
      "--multiple", "bruneton", "--integrator", "gauss:samples=0"], "samples"),
    (["evaluate", "{d}/missing.json", "{sky}", "--json"], "result file not found: .*missing.json"),
    (["fit", "{sky}", "--config", "earth", "--out", "{o}", "--min-elevation", "89.9"], "no usable pixel"),
    (["fit", "{sky}", "--config", "{d}/g_out.yaml", "--out", "{o}"], "mie_g must lie in the open interval \\(-1, 1\\)"),
])
def test_bad_input_exits_2_with_one_line_and_no_file(argv, match, sky, tmp_path, capsys):
    out_dir = tmp_path / "out"
    out_dir.mkdir()
    (tmp_path / "g_out.yaml").write_text("fit:\n  free: [mie_g]\n  initial: {mie_g: 1.5}\n" +
                                         (sky / "truth.yaml").read_text())
    argv = [a.format(d=tmp_path, o=out_dir / "RESULT.json", sky=sky / "sky.exr") for a in argv]
    rc, so, se = _run(argv, capsys)
    assert rc == 2
    assert len(se.strip().splitlines()) == 1 and "Traceback" not in se
    import re

    assert re.search(match, se), se
    assert _files(out_dir) == []


def test_malformed_result_json(sky, tmp_path, capsys):
    bad = tmp_path / "RESULT.json"
    bad.write_text("{not json")
    rc, _, se = _run(["evaluate", bad, sky / "sky.exr", "--json"], capsys)
    assert rc == 2 and str(bad) in se and len(se.strip().splitlines()) == 1
    bad.write_text(json.dumps({"parameters": {}, "free": []}))
    rc, _, se = _run(["evaluate", bad, sky / "sky.exr", "--json"], capsys)
    assert rc == 2 and "not a skyfit fit result (missing integrator, config, model)" in se
    bad.write_text(json.dumps({"parameters": {"mie_colour": 1}, "free": [], "integrator": {}, "config": {}, "model": {}}))
    rc, _, se = _run(["evaluate", bad, sky / "sky.exr", "--json"], capsys)
    assert rc == 2 and "unknown parameter(s) ['mie_colour']" in se


def test_bad_exr_data(sky, tmp_path, capsys):
    chans, meta = read_exr(sky / "sky.exr")
    nan = {k: v.copy() for k, v in chans.items()}
    nan["L550"][6, 6] = np.nan
    write_exr(tmp_path / "nan.exr", nan, meta)
    neg = {k: v.copy() for k, v in chans.items()}
    neg["L450"][5, 6] = -1.0
    write_exr(tmp_path / "neg.exr", neg, meta)
    write_exr(tmp_path / "nocam.exr", chans, {k: v for k, v in meta.items() if k != "camera"})
    out_dir = tmp_path / "out"
    for name, match in (("nan", "NaN or Inf pixels in channel\\(s\\) \\['L550'\\]"), ("neg", "negative pixels in channel\\(s\\) \\['L450'\\]"),
                        ("nocam", "no camera metadata")):
        rc, _, se = _run(["fit", tmp_path / f"{name}.exr", "--config", "earth", "--out", out_dir / "R.json"], capsys)
        assert rc == 2, se
        import re

        assert re.search(match, se) and f"{name}.exr" in se, se
    assert _files(out_dir) == []


@pytest.mark.skipif(not KIDER.is_dir(), reason="shared Kider data (../shared/data/kider2014) not present")
def test_kider_capture_fit_writes_spectra_and_ring_plots(tmp_path, capsys):
    out = tmp_path / "RESULT.json"
    rc, so, se = _run(["fit", KIDER, "--config", "earth_clear_sky_eval", "--out", out, "--free", "exposure,sun_azimuth_offset",
                       "--integrator", "taylor", "--view-samples", "8", "--starts", "1", "--max-iter", "20", "--json"], capsys)
    assert rc == 0, se
    res = json.loads(out.read_text())
    d = res["data"][0]
    assert d["n_samples"] == 81 and d["sun_per_sample"]
    assert d["wavelengths_nm"][0] == 365.0 and d["wavelengths_nm"][-1] == 715.0
    assert res["metrics"]["rmse_units"] == "mW/(m^2 sr nm)"
    # the offset starts at the rings' symmetry axis: docs/data.md measured 6.8-7.2 deg before the SPA sun at 09:30
    start = res["convergence"]["starts"][0]
    assert -7.5 < math.degrees(start["initial"]["sun_azimuth_offset"]) < -6.5
    assert start["loss"] == pytest.approx(res["metrics"]["loss"], rel=1e-9)
    assert math.isfinite(res["parameters"]["sun_azimuth_offset"])
    names = sorted(Path(p).name for p in res["plots"])
    assert names == ["RESULT_2013-05-27___09.30.00_rings.png", "RESULT_2013-05-27___09.30.00_spectra.png"]
    rc, so, se = _run(["evaluate", out, KIDER, "--json"], capsys)
    assert rc == 0, se
    ev = json.loads(so)
    assert ev["n_samples"] == 81 and ev["rmse"] == pytest.approx(res["metrics"]["rmse"], rel=1e-9)


def test_a_diverging_fit_names_the_parameter_and_writes_nothing(sky, tmp_path, capsys, monkeypatch):
    """A NaN gradient w.r.t. mie_g from the 4th evaluation on: exit 2, one line naming mie_g, no RESULT.json."""
    from skyfit.fit.model import FitProblem

    orig = FitProblem.objective

    def poisoned(self, x):
        loss = orig(self, x)
        if self.n_evaluations > 3:
            i = self.param.names.index("mie_g")
            loss = loss + torch.sqrt(x[i] * 0.0)  # value + 0, gradient 0 * inf = NaN
        return loss

    monkeypatch.setattr(FitProblem, "objective", poisoned)
    out = tmp_path / "r.json"
    rc, _, err = _run(["fit", sky / "sky.exr", "--config", "earth", "--out", out, "--free", "mie_g,exposure",
                       "--adam-steps", "0", "--no-plots", *FAST], capsys)
    assert rc == 2
    assert len(err.strip().splitlines()) == 1 and "diverged" in err and "mie_g" in err, err
    assert _files(tmp_path) == []
