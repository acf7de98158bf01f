"""Issue 18: every failure found by trying 163 bad inputs, as a named regression test.

Each bad input must end as CONTRACT.md says: one line on stderr naming the problem (and the file),
exit status 2, no traceback, nothing written; valid data with broken parts is used with a
one-line warning saying what was left out and why (docs/reliability.md).
"""
from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import pytest

import skyfit.cli as cli
from skyfit.cli import main
from skyfit.fit.data import DataWarning, observation_from_kider
from skyfit.fit.parameters import PARAMETERS
from skyfit.io import read_exr, write_exr
from skyfit.io.atomic import atomic_path, check_writable, remove_stale
from skyfit.io.kider import NEGATIVE_NOISE_FLOOR, broken_samples, load_kider_capture
from skyfit.resources import Estimate, ResourceError, check
from _cli import run

REPO = Path(__file__).resolve().parents[1]
KIDER = REPO.parent / "shared" / "data" / "kider2014" / "2013-05-27" / "2013-05-27___09.30.00"
needs_kider = pytest.mark.skipif(not KIDER.is_dir(), reason=f"Kider 2014 data not found at {KIDER}")
CHEAP = ["--integrator", "chapman", "--view-samples", "4", "--starts", "1", "--max-iter", "3", "--adam-steps", "0"]
SKYFIT = Path(sys.executable).parent / "skyfit"


@pytest.fixture(scope="module")
def sky(tmp_path_factory):
    """A 10 x 10 spectral fisheye and a RESULT.json fitted to it (cheap settings)."""
    d = tmp_path_factory.mktemp("bad_input")
    assert main(["render", "earth", "--out", str(d / "sky.exr"), "--size", "10", "--sun-zenith", "40", "--sun-azimuth", "120",
                 "--wavelengths", "450:650:100", "--integrator", "chapman", "--view-samples", "4", "--spectral",
                 "--dtype", "float64"]) == 0
    assert main(["fit", str(d / "sky.exr"), "--config", "earth", "--out", str(d / "RESULT.json"), "--free", "mie_g,exposure",
                 "--no-plots", *CHEAP]) == 0
    return d


def listing(folder: Path) -> list[str]:
    return sorted(str(p.relative_to(folder)) for p in folder.rglob("*")) if folder.exists() else []


def refused(argv, capsys, *needles):
    """Run in-process; assert exit 2, one stderr line holding every needle, no traceback; return the line."""
    rc, out, err = run(argv, capsys)
    lines = err.strip().splitlines()
    assert rc == 2, (argv, err)
    assert len(lines) == 1 and "Traceback" not in err, err
    for n in needles:
        assert n in lines[0], (n, lines[0])
    return lines[0]


def result_with(sky: Path, tmp_path: Path, **parameters) -> Path:
    res = json.loads((sky / "RESULT.json").read_text())
    res["parameters"].update(parameters)
    p = tmp_path / "RESULT.json"
    p.write_text(json.dumps(res))  # NaN is written as the non-standard NaN; None as null
    return p


# -- tracebacks ---------------------------------------------------------------------------------
@pytest.mark.parametrize("command", [
    ["sample", "{sky}/sky.exr", "--config", "earth", "--init", "{sky}/RESULT.json", "--walkers", "4", "--steps", "2"],
    ["bench", "--quick"],
    ["demo", "--quick"],
])
def test_out_naming_an_existing_file_where_a_folder_is_expected(command, sky, tmp_path, capsys):
    target = tmp_path / "existing"
    target.write_text("keep me")
    argv = [a.format(sky=sky) for a in command] + ["--out", target]
    refused(argv, capsys, "--out", str(target), "exists and is not a directory")
    assert target.read_text() == "keep me" and listing(tmp_path) == ["existing"]


@pytest.mark.parametrize("command", [["render", "earth", "--sun-zenith", "30", "--out", "{t}/x.exr"], ["bench", "--quick", "--out", "{t}/b"]])
def test_bogus_device_is_one_line_and_leaves_no_folder(command, tmp_path, capsys):
    refused([a.format(t=tmp_path) for a in command] + ["--device", "bogus"], capsys, "--device", "bogus")
    assert listing(tmp_path) == []


def test_sample_with_a_billion_walkers_is_refused_with_the_estimate(sky, tmp_path, capsys):
    line = refused(["sample", sky / "sky.exr", "--config", "earth", "--init", sky / "RESULT.json", "--out", tmp_path / "s",
                    "--walkers", "1000000000"], capsys, "memory", "1000000000 walkers", "--force")
    assert "TiB" in line or "PiB" in line
    assert listing(tmp_path) == []


def test_render_with_a_billion_view_samples_is_refused_with_the_estimate(tmp_path, capsys):
    refused(["render", "earth", "--out", tmp_path / "x.exr", "--sun-zenith", "30", "--view-samples", "1000000000"], capsys,
            "memory", "1000000000 view samples", "--force")
    assert listing(tmp_path) == []


def test_export_lut_with_a_billion_texels_is_refused_with_the_estimate(sky, tmp_path, capsys):
    refused(["export-lut", sky / "RESULT.json", "--out", tmp_path / "lut", "--table-sizes", "1000000000,4,2,2"], capsys,
            "memory", "1000000000x4x2x2 texels", "--force")
    assert listing(tmp_path) == []


def test_ctrl_c_in_the_first_second_is_one_line_and_exit_130(tmp_path):
    """SIGINT while the console script imports torch (and later, while it renders): one line, status 130."""
    if not SKYFIT.is_file():
        pytest.skip("the skyfit console script is not installed beside this Python")
    for delay in (0.8, 6.0):
        # A pytest-xdist worker ignores SIGINT and its children inherit that: give the command the default
        # handler a shell would, and never leave it running if the assertion fails.
        p = subprocess.Popen([str(SKYFIT), "render", "earth", "--out", str(tmp_path / "x.exr"), "--sun-zenith", "30",
                              "--size", "1024", "--view-samples", "128"], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                             text=True, cwd=tmp_path,
                             preexec_fn=lambda: signal.signal(signal.SIGINT, signal.default_int_handler))
        try:
            time.sleep(delay)
            p.send_signal(signal.SIGINT)
            _, err = p.communicate(timeout=120)
        finally:
            p.kill()
            p.wait()
        assert p.returncode == 130 and err == "skyfit: interrupted\n", (delay, p.returncode, err)
    assert listing(tmp_path) == []


def test_keyboard_interrupt_during_the_work_is_one_line_and_exit_130(monkeypatch, tmp_path, capsys):
    def interrupted(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(cli, "render_fisheye", interrupted)
    rc, _, err = run(["render", "earth", "--out", tmp_path / "x.exr", "--sun-zenith", "30", "--size", "8"], capsys)
    assert rc == 130 and err == "skyfit: interrupted\n"
    assert listing(tmp_path) == []


# -- hangs --------------------------------------------------------------------------------------
@pytest.mark.parametrize("argv, needles", [
    (["render", "earth", "--out", "{t}/x.exr", "--sun-zenith", "30", "--orders", "1000"], ["would take", "1000 orders", "--force"]),
    (["export-lut", "{sky}/RESULT.json", "--out", "{t}/lut", "--table-sizes", "1000000000,128,32,8"], ["memory", "texels"]),
    (["render", "earth", "--out", "{t}/x.exr", "--sun-zenith", "30", "--wavelengths", "400:700:0.0001"],
     ["--wavelengths", "3e+06 wavelengths", "10000"]),
])
def test_what_used_to_hang_is_refused_at_once(argv, needles, sky, tmp_path, capsys):
    t0 = time.perf_counter()
    refused([a.format(t=tmp_path, sky=sky) for a in argv], capsys, *needles)
    assert time.perf_counter() - t0 < 30  # refused before any work (it ran > 90 s, unbounded, before)
    assert listing(tmp_path) == []


def test_force_lets_a_refused_job_through_the_estimate():
    big = Estimate("render", 1e18, 1e9, "sizes")
    with pytest.raises(ResourceError, match=r"render would need about .* of memory \(sizes\).*; add --force"):
        check(big, hint="add --force")
    assert check(big, force=True) is big


# -- accepted with exit 0 -----------------------------------------------------------------------
@pytest.mark.parametrize("command", ["fit", "evaluate"])
def test_an_all_zero_image_is_refused(command, sky, tmp_path, capsys):
    chans, meta = read_exr(sky / "sky.exr")
    write_exr(tmp_path / "zero.exr", {k: np.zeros_like(v) for k, v in chans.items()}, meta)
    out = tmp_path / "out" / "R.json"
    argv = (["fit", tmp_path / "zero.exr", "--config", "earth", "--out", out, *CHEAP] if command == "fit"
            else ["evaluate", sky / "RESULT.json", tmp_path / "zero.exr", "--json"])
    refused(argv, capsys, "zero.exr", "every used pixel is 0")
    assert not out.parent.exists()


def _broken_capture(tmp_path: Path, index: int, value: str) -> Path:
    """A copy of the 09:30 capture with every radiance of sample ``index`` replaced by ``value``."""
    folder = tmp_path / "2013-05-27" / KIDER.name
    shutil.copytree(KIDER, folder)
    (f,) = folder.glob(f"{KIDER.name}_-_{index}____*.asd.rad.txt")
    head, *rows = f.read_text().splitlines()
    f.write_text("\n".join([head] + [f"{r.split()[0]}\t{value}" for r in rows if r.strip()]) + "\n")
    return folder


@needs_kider
@pytest.mark.parametrize("value, reason", [("nan", "2151 NaN/Inf value(s)"), ("-5.0", "-5 W/(m^2 sr nm) at 350 nm, below the -0.01 noise floor")])
def test_a_broken_kider_sample_is_dropped_with_a_warning(value, reason, tmp_path, capsys):
    folder = _broken_capture(tmp_path, 17, value)
    with pytest.warns(DataWarning, match="1 of 81 samples left out as broken: sample 17"):
        obs = observation_from_kider(folder)
    assert obs.n_samples == 80 and not bool(obs.mask[17])
    assert obs.summary()["mask"]["broken"] == [f"sample 17 ({next(folder.glob('*_-_17____*')).name}): {reason}"]
    out = tmp_path / "R.json"
    rc, _, err = run(["fit", folder, "--config", "earth", "--out", out, "--no-plots", *CHEAP, "--free", "exposure"], capsys)
    assert rc == 0, err
    warned = [ln for ln in err.splitlines() if ln.startswith("skyfit: warning:")]
    assert len(warned) == 1 and "sample 17" in warned[0] and reason in warned[0]
    assert json.loads(out.read_text())["data"][0]["n_samples"] == 80


@needs_kider
def test_the_real_captures_small_negative_values_are_noise_and_kept():
    c = load_kider_capture(KIDER)
    negative = c.radiance < 0
    assert negative.sum() > 10_000 and c.radiance.min() > -NEGATIVE_NOISE_FLOOR  # many, all small
    assert c.wavelengths[negative.any(0)].min() > 1300  # only where water vapour absorbs the signal
    assert c.dropped == {} and c.valid.all()


def test_broken_sample_policy_on_synthetic_spectra():
    wl = np.arange(350.0, 2501.0)
    good = np.full(wl.shape, 0.05)
    noisy = good.copy()
    noisy[wl > 1800] = -0.004  # detector noise where the sky is dark: kept
    nan, low, dark = good.copy(), good.copy(), good.copy()
    nan[1000] = np.nan
    low[1600] = -0.5  # far below any noise: broken
    dark[wl == 500] = 0.0  # no light in the fitted band: broken
    got = broken_samples(wl, np.stack([good, noisy, nan, low, dark]))
    assert sorted(got) == [2, 3, 4]
    assert "1 NaN/Inf" in got[2] and "-0.5 W/(m^2 sr nm) at 1950 nm" in got[3] and "<= 0 in 360-720 nm" in got[4]


@pytest.mark.parametrize("value, needles", [
    (-8000.0, ["rayleigh_scale_height = -8000 m is out of range (must be > 0 m)"]),
    (None, ["rayleigh_scale_height must be a number, got null (NaN)"]),
    ("abc", ["rayleigh_scale_height must be a number, got 'abc'"]),
])
def test_evaluate_refuses_a_bad_scale_height_in_the_result(value, needles, sky, tmp_path, capsys):
    bad = result_with(sky, tmp_path, rayleigh_scale_height=value)
    refused(["evaluate", bad, sky / "sky.exr", "--json"], capsys, str(bad), *needles)


def test_evaluate_refuses_a_nan_parameter_naming_the_file(sky, tmp_path, capsys):
    bad = result_with(sky, tmp_path, mie_beta_550=float("nan"))  # json.dumps writes NaN
    refused(["evaluate", bad, sky / "sky.exr"], capsys, str(bad), "mie_beta_550 must be finite, got nan")


def test_mie_g_out_of_range_has_no_stray_unit(sky, tmp_path, capsys):
    bad = result_with(sky, tmp_path, mie_g=5.0)
    refused(["evaluate", bad, sky / "sky.exr"], capsys, str(bad), "mie_g = 5 is out of range (must be in [-1, 1])")
    with pytest.raises(ValueError) as e:
        PARAMETERS["mie_g"].inverse(5.0)
    assert str(e.value) == "mie_g must lie in the open interval (-1, 1), got 5.0"  # was "(-1, 1) 1, got 5.0"


def test_fit_refuses_a_negative_sun_mask(sky, tmp_path, capsys):
    refused(["fit", sky / "sky.exr", "--config", "earth", "--out", tmp_path / "R.json", "--sun-mask", "-5"], capsys,
            "--sun-mask must be in [0, 180), got -5")
    assert listing(tmp_path) == []


def test_sample_refuses_negative_checkpoint_seconds(sky, tmp_path, capsys):
    refused(["sample", sky / "sky.exr", "--config", "earth", "--init", sky / "RESULT.json", "--out", tmp_path / "s",
             "--checkpoint-seconds", "-1"], capsys, "--checkpoint-seconds must be > 0, got -1")
    assert listing(tmp_path) == []


def test_config_sections_are_checked_with_the_key_and_the_file(sky, tmp_path, capsys):
    cfg = tmp_path / "cfg.yaml"
    cfg.write_text("fit:\n  sun_disc_deg: -5\n")
    refused(["fit", sky / "sky.exr", "--config", cfg, "--out", tmp_path / "o" / "R.json"], capsys,
            str(cfg), "fit.sun_disc_deg must be in [0, 180), got -5")
    cfg.write_text("sample:\n  checkpoint_seconds: abc\n")
    refused(["sample", sky / "sky.exr", "--config", cfg, "--init", sky / "RESULT.json", "--out", tmp_path / "s"], capsys,
            str(cfg), "sample.checkpoint_seconds must be a number, got 'abc'")
    assert not (tmp_path / "o").exists() and not (tmp_path / "s").exists()


# -- messages that did not name the problem and the file ------------------------------------------
@pytest.mark.parametrize("spec, needles", [
    ("taylor:a=abc", ["--integrator taylor:a=abc", "option a must be a number, got 'abc'"]),
    ("trapezoid:foo=3", ["--integrator trapezoid:foo=3", "no option 'foo'", "its options: samples"]),
])
def test_integrator_option_errors_name_the_option(spec, needles, tmp_path, capsys):
    line = refused(["render", "earth", "--out", tmp_path / "x.exr", "--sun-zenith", "30", "--integrator", spec], capsys, *needles)
    assert "__init__" not in line and "invalid data type" not in line


def test_a_string_where_a_number_belongs_names_the_key(tmp_path, capsys):
    cfg = tmp_path / "c.yaml"
    cfg.write_text("mie: {g: abc}\n")
    refused(["render", cfg, "--out", tmp_path / "x.exr", "--sun-zenith", "30"], capsys, str(cfg), "mie.g must be a number, got 'abc'")


@pytest.mark.parametrize("argv", [
    ["render", "earth", "--sun-zenith", "30", "--size", "8", "--out", "/proc/skyfit_test.exr"],
    ["fit", "{sky}/sky.exr", "--config", "earth", "--out", "/proc/skyfit_test.json"],
    ["calibrate-integrator", "earth", "--quick", "--out", "/proc/skyfit_test.json"],
    ["render", "earth", "--sun-zenith", "30", "--size", "8", "--out", "{sky}/sky.exr/x.exr"],
])
def test_an_unwritable_out_is_refused_before_any_work_naming_it(argv, sky, monkeypatch, capsys):
    def no_work(*a, **k):
        raise AssertionError("the work started before --out was checked")

    for name in ("render_fisheye", "run_fit", "calibrate_integrators"):
        monkeypatch.setattr(cli, name, no_work)
    argv = [a.format(sky=sky) for a in argv]
    out = argv[argv.index("--out") + 1]
    line = refused(argv, capsys, f"--out {out}")
    assert ".tmp" not in line and "Errno" not in line


def test_an_unwritable_place_is_named_by_the_writer_too(tmp_path):
    """The library's atomic writer names the target, not its temporary (a folder where the file goes)."""
    (tmp_path / "sky.exr").write_text("a file where a folder is needed")
    with pytest.raises(ValueError, match=r"cannot write .*sky.exr") as e:
        with atomic_path(tmp_path / "sky.exr" / "sub" / "a.json") as tmp:
            tmp.write_text("x")
    assert ".tmp" not in str(e.value)


@pytest.mark.parametrize("which", ["config", "result", "init"])
def test_a_folder_given_as_config_or_result_is_called_a_folder(which, sky, tmp_path, capsys):
    folder = tmp_path / "afolder"
    folder.mkdir()
    argv = {"config": ["render", folder, "--out", tmp_path / "x.exr", "--sun-zenith", "30"],
            "result": ["evaluate", folder, sky / "sky.exr"],
            "init": ["sample", sky / "sky.exr", "--config", "earth", "--init", folder, "--out", tmp_path / "s"]}[which]
    line = refused(argv, capsys, str(folder), "is a folder")
    assert "not found" not in line


def test_a_huge_rayleigh_coefficient_gives_one_line_without_a_numpy_warning(tmp_path, capsys):
    cfg = tmp_path / "c.yaml"
    cfg.write_text("rayleigh: {coefficient: 1e308}\n")
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a RuntimeWarning would now be an exception, not a second line
        refused(["render", cfg, "--out", tmp_path / "x.exr", "--sun-zenith", "30"], capsys,
                str(cfg), "rayleigh.coefficient", "not a finite")


# -- faults -------------------------------------------------------------------------------------
def test_a_stale_temporary_of_a_killed_run_is_removed_by_the_next_run(tmp_path, capsys):
    target = tmp_path / "sky.exr"
    killed = subprocess.run([sys.executable, "-c", (
        "import os, signal, sys\n"
        "from skyfit.io.atomic import atomic_path\n"
        "with atomic_path(sys.argv[1], '.tmp.exr') as tmp:\n"
        "    tmp.write_bytes(b'half an image')\n"
        "    os.kill(os.getpid(), signal.SIGKILL)\n"), str(target)], capture_output=True, timeout=120)
    assert killed.returncode == -signal.SIGKILL
    stale = [n for n in os.listdir(tmp_path) if n.endswith(".tmp.exr")]
    assert len(stale) == 1 and stale[0].startswith(".sky.exr.skyfit-")
    running = tmp_path / f".other.json.skyfit-{os.getpid()}-abcd1234.tmp"  # a live writer's: kept
    running.write_text("in progress")
    rc, _, err = run(["render", "earth", "--out", target, "--sun-zenith", "30", "--size", "8", "--view-samples", "4",
                      "--wavelengths", "450:650:100"], capsys)
    assert rc == 0, err
    assert sorted(os.listdir(tmp_path)) == [running.name, "sky.exr"]


def test_remove_stale_leaves_other_files_alone(tmp_path):
    for name in ("notes.tmp", ".hidden", "a.skyfit-1-x.tmp"):
        (tmp_path / name).write_text("mine")
    assert remove_stale(tmp_path) == []
    assert sorted(os.listdir(tmp_path)) == [".hidden", "a.skyfit-1-x.tmp", "notes.tmp"]


def test_check_writable_creates_nothing(tmp_path):
    check_writable(tmp_path / "a" / "b" / "c.exr")
    check_writable(tmp_path / "a" / "dir", directory=True)
    assert listing(tmp_path) == []


def test_sample_resume_with_no_chain_starts_fresh_and_says_so(sky, tmp_path, capsys):
    out = tmp_path / "s"
    rc, so, err = run(["sample", sky / "sky.exr", "--config", "earth", "--init", sky / "RESULT.json", "--out", out,
                       "--walkers", "4", "--steps", "3", "--resume", "--no-plots", "--json", "--threads", "1"], capsys)
    assert rc == 0, err
    assert "no chain" in err and "starting a new chain" in err
    summary = json.loads((out / "summary.json").read_text())
    assert summary["diagnostics"]["steps"] == 3 and summary["sampler"]["resumed"] is False


def test_image_value_policy():
    """docs/reliability.md: all zero is an error; a zero channel, a flat image and clipped highlights are warnings."""
    import torch

    from skyfit.fit.data import DataError, check_image_values

    rng = np.random.default_rng(0)
    sky = torch.as_tensor(rng.uniform(0.01, 0.05, (400, 2)))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        check_image_values("sky.exr", sky, ["L450", "L550"])  # a plain sky: silent
    with pytest.raises(DataError, match="sky.exr: every used pixel is 0"):
        check_image_values("sky.exr", torch.zeros(400, 2), ["L450", "L550"])
    dead = sky.clone()
    dead[:, 1] = 0
    with pytest.warns(DataWarning, match=r"\['L550'\] are 0 at every used pixel"):
        check_image_values("sky.exr", dead, ["L450", "L550"])
    with pytest.warns(DataWarning, match="same value in every channel"):
        check_image_values("sky.exr", torch.full((400, 2), 0.02), ["L450", "L550"])
    clipped = sky.clone()
    clipped[:50, 0] = 1.0
    with pytest.warns(DataWarning, match=r"\['L450'\] reach their maximum at 50 of 400 used pixels \(clipped\?\)"):
        check_image_values("sky.exr", clipped, ["L450", "L550"])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        check_image_values("sky.exr", clipped, ["L450", "L550"], saturation=1.0)  # a level given: the mask handles it


def test_numeric_strings_in_a_config_are_numbers(sky, tmp_path):
    """PyYAML reads 1e-7 as a string; a fit setting written so is taken as the number it spells."""
    from skyfit.fit.problem import fit_settings

    s = fit_settings({"grad_tol": "1e-7", "view_samples": "8"}, None)
    assert s.grad_tol == 1e-7 and s.view_samples == 8
    with pytest.raises(ValueError, match="fit.view_samples must be an integer, got '8.5'"):
        fit_settings({"view_samples": "8.5"}, None)
