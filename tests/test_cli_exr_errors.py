"""Bad EXR input to the CLI (issue 4): non-EXR, truncated, metadata-less -> one line, exit 2, nothing written."""
import subprocess
import sys

import numpy as np
import pytest

from skyfit.camera import FisheyeCamera
from skyfit.cli import main
from skyfit.io import write_exr


def _good(path):
    write_exr(path, {"L450": np.ones((8, 8), np.float32), "L650": np.ones((8, 8), np.float32)},
              {"camera": FisheyeCamera(8).to_metadata(), "sun": {"zenith_deg": 30.0, "azimuth_deg": 180.0}})


def _cases(tmp_path):
    text = tmp_path / "text.exr"
    text.write_text("not an image\n")
    good = tmp_path / "good.exr"
    _good(good)
    trunc = tmp_path / "truncated.exr"
    trunc.write_bytes(good.read_bytes()[: len(good.read_bytes()) // 2])
    bare = tmp_path / "bare.exr"
    write_exr(bare, {"L450": np.ones((8, 8), np.float32)})  # no skyfit metadata at all
    return {"text": (text, "not an OpenEXR file"), "truncated": (trunc, "truncated.exr"), "bare": (bare, "bare.exr")}


@pytest.mark.parametrize("case", ["text", "truncated", "bare"])
def test_fit_refuses_bad_exr(case, tmp_path, capsys):
    path, needle = _cases(tmp_path)[case]
    out = tmp_path / "out" / "RESULT.json"
    rc = main(["fit", str(path), "--config", "earth", "--out", str(out), "--no-plots"])
    err = capsys.readouterr().err.strip()
    assert rc == 2
    assert needle in err and "\n" not in err and "Traceback" not in err
    assert not out.parent.exists() or not any(out.parent.iterdir())


def test_truncated_exr_subprocess_exit_status(tmp_path):
    path, _ = _cases(tmp_path)["truncated"]
    p = subprocess.run([sys.executable, "-m", "skyfit.cli", "fit", str(path), "--config", "earth", "--out", str(tmp_path / "R.json")],
                       capture_output=True, text=True, timeout=120)
    assert p.returncode == 2 and len(p.stderr.strip().splitlines()) == 1 and "Traceback" not in p.stderr
    assert not (tmp_path / "R.json").exists()
