"""``--device`` on every command and ``device=`` in the Python API (issue: every command on the GPU).

Without a GPU: every command refuses an unknown or absent device with one line and exit 2, before
any work and without output; ``auto`` is the CPU. With a GPU (marker ``cuda``): the API's render
and fit on CUDA agree with the CPU to stated tolerances.
"""
from __future__ import annotations

import pytest
import torch
from _cli import run

import skyfit
from skyfit.api import resolve_device
from skyfit.cli import build_parser

COMMANDS = {
    "render": lambda d: ["render", "earth", "--out", d / "sky.exr", "--sun-zenith", "40", "--size", "8"],
    "fit": lambda d: ["fit", d / "missing.exr", "--config", "earth", "--out", d / "r.json"],
    "evaluate": lambda d: ["evaluate", d / "r.json", d / "missing.exr"],
    "sample": lambda d: ["sample", d / "missing.exr", "--config", "earth", "--init", d / "init.json", "--out", d / "post"],
    "export-lut": lambda d: ["export-lut", d / "r.json", "--out", d / "luts"],
    "calibrate-integrator": lambda d: ["calibrate-integrator", "earth", "--out", d / "cal.json", "--quick"],
    "bench": lambda d: ["bench", "--quick", "--out", d / "bench"],
    "demo": lambda d: ["demo", "--quick", "--out", d / "demo"],
    "envmap": lambda d: ["envmap", "earth", "--out", d / "sky.exr", "--sun-zenith", "40", "--size", "8"],
    "batch": lambda d: ["batch", d / "missing.exr", "--config", "earth", "--out", d / "batch"],
}
BAD = ["bogus", "cuda:x", "tpu"] + ([] if torch.cuda.is_available() else ["cuda", "cuda:7"])


def test_every_command_has_a_device_flag():
    sub = next(a for a in build_parser()._actions if a.__class__.__name__ == "_SubParsersAction")
    missing = [name for name, p in sub.choices.items() if not any("--device" in a.option_strings for a in p._actions)]
    assert missing == []
    assert set(COMMANDS) <= set(sub.choices)


@pytest.mark.parametrize("device", BAD)
@pytest.mark.parametrize("command", sorted(COMMANDS))
def test_a_bad_device_is_one_line_and_exit_2(tmp_path, capsys, command, device):
    (tmp_path / "init.json").write_text("{}")
    before = sorted(p.name for p in tmp_path.iterdir())
    rc, out, err = run([*COMMANDS[command](tmp_path), "--device", device], capsys)
    assert rc == 2, err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "--device" in lines[0] and device in lines[0], err
    assert "Traceback" not in err
    assert sorted(p.name for p in tmp_path.iterdir()) == before  # nothing written


def test_resolve_device():
    assert resolve_device("cpu") == torch.device("cpu")
    assert resolve_device("auto") == torch.device("cuda" if torch.cuda.is_available() else "cpu")
    with pytest.raises(ValueError, match="unknown device 'bogus'"):
        resolve_device("bogus")


def _sky(device, dtype=torch.float64):
    atm = skyfit.load_atmosphere("earth", "450,550,650", dtype=dtype, device=device)
    cam = skyfit.FisheyeCamera(12)
    return atm, cam, skyfit.render(atm, cam, sun=(40, 100))


def test_api_auto_device_is_the_cpu_here_or_cuda():
    atm, _, sky = _sky("auto")
    assert atm.device.type == ("cuda" if torch.cuda.is_available() else "cpu") == sky.radiance.device.type


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_api_render_and_fit_on_cuda_match_the_cpu():
    _, cam, cpu = _sky("cpu")
    _, _, gpu = _sky("cuda")
    # same float64 arithmetic on another device: agreement to rounding (tolerance 1e-10 relative)
    torch.testing.assert_close(gpu.radiance.cpu(), cpu.radiance, rtol=1e-10, atol=1e-12)
    atm = skyfit.load_atmosphere("earth", "450,550,650")
    obs = skyfit.Observation.from_arrays(cpu.radiance, cam, sun=(40, 100), wavelengths=atm.wavelengths)
    kw = dict(free=["mie_beta_550", "exposure"], starts=1)
    a = skyfit.fit(obs, "earth", device="cpu", **kw)
    b = skyfit.fit(obs, "earth", device="cuda", **kw)
    for n in kw["free"]:  # the optimiser's path differs in the last digits: agreement to 1e-6 relative
        assert abs(a.parameters[n] - b.parameters[n]) <= 1e-6 * abs(a.parameters[n])


GPU = "cuda"  # the device compared with the CPU below (a GPU machine; the CPU-only CI skips these)


def _cli_result(tmp_path, capsys, name: str, argv: list) -> dict:
    """Run one CLI command writing ``--out tmp_path/name.json``; its RESULT.json."""
    import json

    out = tmp_path / f"{name}.json"
    rc, _, err = run([*argv, "--out", out], capsys)
    assert rc == 0, err
    return json.loads(out.read_text())


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cli_fit_of_a_fisheye_on_cuda_writes_what_the_cpu_writes(tmp_path, capsys):
    """The whole ``skyfit fit --laplace`` on an EXR (fit, error budget, residual maps) on CUDA: the same free values and
    sigmas as on the CPU to 1e-5 relative (float64; the optimiser's path differs in the last digits), and the plots.
    Before, the report indexed the CPU pixel index with the CUDA mask (found on an H200, 2026-12-04)."""
    sky = tmp_path / "sky.exr"
    assert run(["render", "earth", "--out", sky, "--sun-zenith", "40", "--size", "32"], capsys)[0] == 0
    res = {dev: _cli_result(tmp_path, capsys, dev, ["fit", sky, "--config", "earth", "--free", "mie_beta_550,mie_g,exposure",
                                                    "--laplace", "--no-progress", "--device", dev]) for dev in ("cpu", GPU)}
    for n in res["cpu"]["free"]:
        assert res[GPU]["parameters"][n] == pytest.approx(res["cpu"]["parameters"][n], rel=1e-5)
        assert res[GPU]["laplace"]["sigma"][n] == pytest.approx(res["cpu"]["laplace"]["sigma"][n], rel=1e-3)
    assert (tmp_path / f"{GPU}_sky_maps.png").stat().st_size > 0


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cli_fit_of_a_photo_on_cuda_recovers_what_the_cpu_does(tmp_path, capsys):
    """A synthetic 200x200 photo fitted end to end on CUDA (camera, masks, lagged Bruneton fit, lens from the sun,
    error budget, RESULT.png) gives the CPU's AOD and sigma to 1e-4 relative. Before, the lens step built its rotation
    on the CPU from CUDA tilts and the budget's Newton step multiplied a CPU covariance by a CUDA gradient."""
    from skyfit.tools.photo_synth import make_case

    truth = make_case(3, tmp_path / "case", size=200, projection="equisolid")
    photo = tmp_path / "case" / truth["photo"]
    res = {dev: _cli_result(tmp_path, capsys, dev, ["fit", photo, "--time", truth["time"], "--location=" + truth["location"],
                                                    "--no-progress", "--device", dev]) for dev in ("cpu", GPU)}
    a, b = res["cpu"]["aerosol"], res[GPU]["aerosol"]
    assert b["aod_550"] == pytest.approx(a["aod_550"], rel=1e-4)
    assert b["sigma"]["aod_550"] == pytest.approx(a["sigma"]["aod_550"], rel=1e-3)
    assert res[GPU]["sun"]["separation_deg"] == pytest.approx(res["cpu"]["sun"]["separation_deg"], abs=1e-3)
    assert (tmp_path / f"{GPU}.png").stat().st_size > 0
