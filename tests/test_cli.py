"""The command line's outer contract (CONTRACT.md): bad input -> one line naming the problem
and the file, exit status 2, no traceback, no output file; good input -> a fisheye EXR whose
channels and metadata are what the contract promises."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import colour
import numpy as np
import pytest

from skyfit.cli import main
from skyfit.io import read_exr
from _cli import run as _run

REPO = Path(__file__).resolve().parents[1]
FAST = ["--size", "8", "--view-samples", "4", "--wavelengths", "450:650:100"]




def _all_files(folder: Path) -> list[str]:
    return sorted(str(p.relative_to(folder)) for p in folder.rglob("*")) if folder.exists() else []


def _config(tmp_path: Path, text: str) -> Path:
    p = tmp_path / "cfg" / "atm.yaml"
    p.parent.mkdir(exist_ok=True)
    p.write_text(text)
    return p


# (config text or shipped name, extra args, keywords that must appear in the message)
BAD = {
    "missing config": (None, [], ["not found", "no_such.yaml"]),
    "bad yaml": ("planet: {bottom_radius_m: 6360000\n  top: [\n", [], ["bad YAML", "atm.yaml", "line"]),
    "not a mapping": ("- just\n- a list\n", [], ["mapping", "atm.yaml"]),
    "g = 1.5": ("mie: {g: 1.5}\n", [], ["mie_g", "atm.yaml"]),
    "negative scale height": ("rayleigh: {scale_height_m: -8000}\n", [], ["scale_height", "atm.yaml"]),
    "negative beta": ("mie: {angstrom_beta: -0.1}\n", [], ["angstrom_beta", ">= 0", "atm.yaml"]),
    "top below bottom": ("planet: {bottom_radius_m: 6420000, top_radius_m: 6360000}\n", [], ["top_radius", "atm.yaml"]),
    "top equals bottom": ("planet: {bottom_radius_m: 6360000, top_radius_m: 6360000}\n", [], ["top_radius"]),
    "unknown section": ("atmosfere: {g: 0.7}\n", [], ["unknown config section", "atmosfere", "atm.yaml"]),
    "unknown key": ("mie: {gg: 0.7}\n", [], ["unknown key", "gg", "atm.yaml"]),
    "section not a mapping": ("planet: 5\n", [], ["planet", "mapping"]),
    "unknown integrator": ("earth", ["--integrator", "rk45"], ["unknown integrator", "rk45"]),
    "unknown integrator option": ("earth", ["--integrator", "taylor:zzz=3"], ["taylor", "zzz"]),
    "integrator option without value": ("earth", ["--integrator", "trapezoid:samples"], ["key=value", "samples"]),
    "wavelengths reversed": ("earth", ["--wavelengths", "700:400:10"], ["--wavelengths", "700:400:10"]),
    "wavelengths not numbers": ("earth", ["--wavelengths", "blue"], ["--wavelengths", "blue"]),
    "wavelengths zero step": ("earth", ["--wavelengths", "400:700:0"], ["--wavelengths"]),
    "wavelengths out of range": ("earth", ["--wavelengths", "100:200:10"], ["--wavelengths", "200-3000"]),
    "wavelengths duplicate": ("earth", ["--wavelengths", "550,550"], ["duplicates"]),
    "wavelengths outside a table": ("earth_clear_sky_eval", ["--wavelengths", "550,900"], ["penndorf", "900"]),
    "orders 0": ("earth", ["--orders", "0"], ["--orders"]),
    "bad table sizes": ("earth", ["--orders", "2", "--table-sizes", "8,31,8"], ["--table-sizes"]),
    "odd table mu": ("earth", ["--orders", "2", "--table-sizes", "8,31,8,4"], ["scattering_mu"]),
    "sun zenith too large": ("earth", ["--sun-zenith", "200"], ["--sun-zenith", "200"]),
    "sun zenith negative": ("earth", ["--sun-zenith", "-5"], ["--sun-zenith"]),
    "sun zenith nan": ("earth", ["--sun-zenith", "nan"], ["--sun-zenith"]),
    "sun azimuth nan": ("earth", ["--sun-azimuth", "nan"], ["--sun-azimuth"]),
    "altitude below ground": ("earth", ["--altitude", "-10"], ["--altitude"]),
    "size too small": ("earth", ["--size", "1"], ["--size"]),
    "size not a number": ("earth", ["--size", "big"], ["--size", "big"]),
    "projection unknown": ("earth", ["--projection", "pinhole"], ["--projection", "pinhole"]),
    "view samples zero": ("earth", ["--view-samples", "0"], ["--view-samples"]),
}


@pytest.mark.parametrize("case", sorted(BAD))
def test_render_bad_input(case, tmp_path, capsys):
    cfg, extra, keywords = BAD[case]
    if cfg is None:
        config = tmp_path / "no_such.yaml"
    elif cfg in ("earth", "earth_clear_sky_eval"):
        config = cfg
    else:
        config = _config(tmp_path, cfg)
    out_dir = tmp_path / "out"
    args = ["render", config, "--out", out_dir / "sky.exr", "--sun-zenith", "30", *FAST, *extra]
    rc, out, err = _run(args, capsys)
    assert rc == 2, (case, err)
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert "Traceback" not in err
    for k in keywords:
        assert k.lower() in err.lower(), (k, err)
    assert _all_files(out_dir) == [], "no output, no temporaries"


def test_render_out_must_be_exr(tmp_path, capsys):
    rc, _, err = _run(["render", "earth", "--out", tmp_path / "sky.png", "--sun-zenith", "30", *FAST], capsys)
    assert rc == 2 and ".exr" in err and "sky.png" in err and len(err.strip().splitlines()) == 1
    assert _all_files(tmp_path) == []


def test_render_needs_the_sun(tmp_path, capsys):
    rc, _, err = _run(["render", "earth", "--out", tmp_path / "sky.exr", *FAST], capsys)
    assert rc == 2 and "--sun-zenith" in err
    assert _all_files(tmp_path) == []


def test_failed_render_keeps_an_existing_output(tmp_path, capsys):
    target = tmp_path / "sky.exr"
    target.write_bytes(b"previous result")
    rc, _, _ = _run(["render", "earth", "--out", target, "--sun-zenith", "30", "--integrator", "nope", *FAST], capsys)
    assert rc == 2 and target.read_bytes() == b"previous result"
    assert _all_files(tmp_path) == ["sky.exr"]


@pytest.mark.parametrize(
    "args, keyword",
    [
        (["render", "{cfg}", "--out", "{out}", "--sun-zenith", "30", "--size", "8"], "mie_g"),
        (["render", "earth", "--out", "{out}", "--sun-zenith", "30", "--size", "abc"], "--size"),
    ],
)
def test_subprocess_exit_status_and_single_line(tmp_path, args, keyword):
    cfg = _config(tmp_path, "mie: {g: 1.5}\n")
    out = tmp_path / "out" / "sky.exr"
    argv = [a.format(cfg=cfg, out=out) for a in args]
    p = subprocess.run([sys.executable, "-m", "skyfit.cli", *argv], capture_output=True, text=True, cwd=tmp_path,
                       timeout=120, env={**os.environ, "PYTHONWARNINGS": "ignore"})
    assert p.returncode == 2, p.stderr
    assert len(p.stderr.strip().splitlines()) == 1, p.stderr
    assert "Traceback" not in p.stderr and keyword in p.stderr
    assert not out.parent.exists()


@pytest.mark.parametrize("command", [[], ["render"], ["demo"], ["bench"]])
def test_help(command, capsys):
    rc, out, _ = _run([*command, "--help"], capsys)
    assert rc == 0 and "usage: skyfit" in out


def test_no_command_is_a_one_line_error(capsys):
    rc, _, err = _run([], capsys)
    assert rc == 2 and len(err.strip().splitlines()) == 1


# -- a good render ------------------------------------------------------------------
SRGB_PRIMARIES = np.array([[0.64, 0.33], [0.30, 0.60], [0.15, 0.06]])  # IEC 61966-2-1
D65 = np.array([0.3127, 0.3290])


def _xyz_to_srgb_matrix():
    """Normalised primary matrix (SMPTE RP 177) written out, inverted."""
    def xyz(xy):
        return np.array([xy[0] / xy[1], 1.0, (1 - xy[0] - xy[1]) / xy[1]])

    p = np.stack([xyz(c) for c in SRGB_PRIMARIES], 1)
    s = np.linalg.solve(p, xyz(D65))
    return np.linalg.inv(p * s)


@pytest.fixture(scope="module")
def rendered(tmp_path_factory):
    out = tmp_path_factory.mktemp("render") / "sub" / "sky.exr"
    rc = main(["render", "earth", "--out", str(out), "--size", "24", "--projection", "equisolid", "--up-azimuth", "30",
               "--sun-zenith", "50", "--sun-azimuth", "120", "--wavelengths", "360:830:10", "--spectral",
               "--view-samples", "8", "--json"])
    assert rc == 0
    return out


def test_render_writes_channels_and_metadata(rendered):
    chans, meta = read_exr(rendered)
    lam = np.arange(360.0, 831.0, 10.0)
    assert set(chans) == {"R", "G", "B", "Y"} | {f"L{int(v)}" for v in lam}
    assert all(c.shape == (24, 24) and c.dtype == np.float32 for c in chans.values())
    assert sorted(os.listdir(rendered.parent)) == ["sky.exr"]
    assert meta["camera"]["projection"] == "equisolid" and meta["camera"]["size"] == 24
    assert meta["camera"]["up_azimuth_deg"] == 30.0 and meta["camera"]["radius_px"] == 12.0
    assert meta["sun"] == {"zenith_deg": 50.0, "azimuth_deg": 120.0}
    assert meta["integrator"] == {"name": "gauss", "samples": 16}  # the render defaults (docs/accuracy.md)
    assert (meta["rule"], meta["spacing"], meta["view_samples"]) == ("gauss", "geometric", 8)
    assert meta["atmosphere"]["name"] == "earth" and meta["atmosphere"]["mie_phase"] == "cornette_shanks"
    np.testing.assert_array_equal(meta["wavelengths_nm"], lam)
    assert meta["units"]["L<nm>"] == "W/(m^2 sr nm)"
    # outside the 90° disc nothing, inside positive radiance
    yy, xx = np.mgrid[0:24, 0:24]
    inside = np.hypot(xx - 11.5, yy - 11.5) <= 12.0
    spec = np.stack([chans[f"L{int(v)}"] for v in lam], -1)
    assert np.all(spec[~inside] == 0) and np.all(spec[inside] > 0)


def test_render_y_is_luminance_of_the_spectral_channels(rendered):
    """Y = 683 lm/W * integral L(λ) ybar(λ) dλ over 360-830 nm, computed here from the
    L<nm> channels resampled linearly to colour's 1 nm CIE 1931 table; RGB = linear sRGB
    of that XYZ with the matrix derived from the sRGB primaries."""
    chans, _ = read_exr(rendered)
    lam = np.arange(360.0, 831.0, 10.0)
    spec = np.stack([chans[f"L{int(v)}"] for v in lam], -1).astype(np.float64)
    cmfs = colour.MSDS_CMFS["CIE 1931 2 Degree Standard Observer"]
    wl, cmf = np.asarray(cmfs.wavelengths), np.asarray(cmfs.values)
    fine = np.stack([np.interp(wl, lam, s) for s in spec.reshape(-1, lam.size)])  # (P, 471)
    xyz = (683.0 * fine @ cmf).reshape(24, 24, 3)  # 1 nm steps
    y = chans["Y"].astype(np.float64)
    assert y.max() > 100.0  # a daylight sky: hundreds to thousands of cd/m^2
    np.testing.assert_allclose(y, xyz[..., 1], rtol=1e-5, atol=1e-3)
    rgb = np.stack([chans[c] for c in "RGB"], -1).astype(np.float64)
    np.testing.assert_allclose(rgb, xyz @ _xyz_to_srgb_matrix().T, rtol=1e-4, atol=1e-2)


def test_render_json_output(tmp_path, capsys):
    out = tmp_path / "a.exr"
    argv = ["render", "mars", "--out", out, "--sun-zenith", "10", *FAST, "--integrator", "trapezoid:samples=16", "--json"]
    rc, stdout, err = _run(argv, capsys)
    assert rc == 0, err
    info = json.loads(stdout)
    assert info["out"] == str(out) and info["channels"] == ["B", "G", "R", "Y"]
    meta = read_exr(out)[1]
    assert meta["atmosphere"]["name"] == "mars"
    assert meta["integrator"] == {"name": "trapezoid", "samples": 16}


# -- demo --------------------------------------------------------------------------------
def test_demo_quick(tmp_path, capsys):
    """The whole main job: the noisy image follows its stated noise model, the fit recovers the truth."""
    from skyfit.tools.demo import NOISE, TRUTH

    out = tmp_path / "demo"
    rc, stdout, err = _run(["demo", "--quick", "--out", out, "--json", "--threads", "1"], capsys)
    assert rc == 0, err
    report = json.loads(stdout)
    files = set(_all_files(out))
    assert {"truth.exr", "observed.exr", "truth.png", "RESULT.json", "report.md", "demo.json"} <= files
    assert (out / "luts" / "lut.json").is_file()
    assert not any(f.startswith(".") or "tmp" in f for f in files)
    truth, _ = read_exr(out / "truth.exr")
    observed, meta = read_exr(out / "observed.exr")
    lam = [k for k in truth if k.startswith("L")]
    t = np.stack([truth[k] for k in lam], -1).astype(float)
    o = np.stack([observed[k] for k in lam], -1).astype(float)
    used = t[..., 0] > 0
    sigma = np.hypot(meta["noise"]["sigma_relative"] * t, meta["noise"]["sigma_absolute"])
    z = ((o - t) / sigma)[used]
    assert meta["noise"]["sigma_relative"] == NOISE[0]
    assert abs(z.mean()) < 0.05 and abs(z.std() - 1) < 0.05  # ~11 000 draws: SE 0.01
    rows = {r["parameter"]: r for r in report["rows"]}
    assert set(rows) == set(TRUTH) | {"mie_aod_550"}
    # The truth is rendered with a finer model than the fit's (docs/fitting.md, "Model error"): beta550 and H_M
    # move along their degenerate valley by a few % (measured 3.8 %), their product within 1 %.
    bounds = {"mie_beta_550": 0.06, "mie_scale_height": 0.06, "mie_aod_550": 0.01, "rayleigh_scale": 0.01,
              "ground_albedo": 0.05}
    for name, r in rows.items():
        if name == "mie_g":
            assert abs(r["recovered"] - r["truth"]) < 0.01, r
        else:
            assert abs(r["relative_error"]) < bounds[name], r
        assert r["sigma_laplace"] is not None and r["sigma_laplace"] > 0, r
    assert 0.4 < report["metrics"]["loss"] < 1.0  # chi^2 / 2 per element ~ 0.5 plus the model error


def test_render_sun_from_time_and_location(tmp_path, capsys):
    """--time/--location place the sun by NREL SPA; the image equals one rendered at that sun direction."""
    from skyfit.camera import sun_position

    when, site = "2013-05-27T12:00:00-04:00", "42.443449,-76.481962,250"
    dated, direct = tmp_path / "dated.exr", tmp_path / "direct.exr"
    code, _, _ = _run(["render", "earth", "--out", str(dated), "--size", "12", "--time", when, "--location", site], capsys)
    assert code == 0
    chans, meta = read_exr(dated)
    sp = sun_position(when, 42.443449, -76.481962, 250.0)
    assert meta["sun"]["zenith_deg"] == pytest.approx(float(sp.zenith_geometric), abs=1e-9)
    assert meta["sun"]["azimuth_deg"] == pytest.approx(float(sp.azimuth), abs=1e-9)
    assert meta["sun"]["distance_au"] == pytest.approx(1.0133, abs=2e-4)  # data README: 1.0133 AU on 2013-05-27
    code, _, _ = _run(["render", "earth", "--out", str(direct), "--size", "12", "--sun-zenith", repr(meta["sun"]["zenith_deg"]),
                    "--sun-azimuth", repr(meta["sun"]["azimuth_deg"])], capsys)
    assert code == 0
    chans2, _ = read_exr(direct)
    # Same geometry; the dated render's sun is 1/1.0133^2 brighter than the config's 1 AU sun.
    scale = 1.0 / meta["sun"]["distance_au"] ** 2
    np.testing.assert_allclose(chans["Y"], chans2["Y"] * scale, rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("args, keyword", [
    (["--time", "2013-05-27T12:00:00-04:00"], "go together"),
    (["--time", "2013-05-27T12:00:00", "--location", "42,-76"], "UTC offset"),
    (["--time", "2013-05-27T12:00:00-04:00", "--location", "142,-76"], "latitude"),
    (["--time", "not-a-time", "--location", "42,-76"], "time"),
])
def test_render_bad_time_or_location(args, keyword, tmp_path, capsys):
    out = tmp_path / "x.exr"
    code, _, err = _run(["render", "earth", "--out", str(out), "--size", "8", *args], capsys)
    assert code == 2 and keyword in err and "\n" not in err.strip()
    assert not out.exists()


def test_render_per_layer_taylor_pairs(tmp_path, capsys):
    """taylor:a=A_R/A_M,b=B_R/B_M gives one (a, b) per layer; the header records both."""
    out = tmp_path / "t.exr"
    code, _, _ = _run(["render", "earth", "--out", str(out), *FAST, "--sun-zenith", "40",
                       "--integrator", "taylor:a=0.367/0.424,b=0.359/0.116"], capsys)
    assert code == 0
    _, meta = read_exr(out)
    assert meta["integrator"]["a"] == [0.367, 0.424] and meta["integrator"]["b"] == [0.359, 0.116]
    code, _, err = _run(["render", "earth", "--out", str(tmp_path / "u.exr"), *FAST, "--sun-zenith", "40",
                         "--integrator", "taylor:a=0.3/0.4/0.5"], capsys)
    assert code == 2 and "one per layer" in err


def test_a_southern_or_western_location_is_taken_as_written():
    """``--location -33.9,151.2`` (Sydney) and ``--location 40.7,-74.0,10`` parse as the place, not as an unknown option
    (argparse alone refuses a value that starts with '-' and is not a plain number)."""
    from skyfit.cli import _join_negative_lists, build_parser

    parser = build_parser()
    for loc in ("-33.9,151.2", "-33.9,-70.6,520", "40.7,-74.0,10"):
        args = parser.parse_args(_join_negative_lists(["fit", "sky.jpg", "--time", "2024-06-01T10:00:00+10:00",
                                                       "--location", loc, "--out", "r.json"]))
        assert args.location == loc
    # a plain negative number and an explicit '=' are left alone
    assert _join_negative_lists(["--sun-azimuth", "-30", "--location=-1,2"]) == ["--sun-azimuth", "-30", "--location=-1,2"]
    assert _join_negative_lists(["--location", "-1,2"]) == ["--location=-1,2"]
    # a malformed southern place reaches the location's own check (not argparse's "expected one argument")
    assert _join_negative_lists(["--location", "-33.9,abc"]) == ["--location=-33.9,abc"]
