"""``skyfit render --preview``: an 8-bit sRGB PNG of the fisheye beside the EXR, brightest where the sun is."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest
import skimage.io
import torch
from scipy import ndimage

from skyfit.camera import FisheyeCamera
from skyfit.cli import main
from skyfit.io import read_exr

FAST = ["--size", "48", "--view-samples", "8", "--wavelengths", "450,550,650", "--integrator", "trapezoid:samples=8"]


@pytest.mark.parametrize("zenith, azimuth", [(50.0, 135.0), (60.0, 290.0)])
def test_preview_brightest_where_the_sun_is(tmp_path, capsys, zenith, azimuth):
    out = tmp_path / "sky.exr"
    # A hazy sky: its aerosol's forward peak makes the sun's surroundings the brightest. (In a converged
    # single-scattering `earth` sky the horizon is brighter; only the old 8-sample trapezoid view integral
    # put a 2.5x too bright sun region there, docs/accuracy.md "Render defaults".)
    rc = main(["render", "earth_hazy", "--out", str(out), "--sun-zenith", str(zenith), "--sun-azimuth", str(azimuth),
               "--preview", "--json", *FAST])
    assert rc == 0
    info = json.loads(capsys.readouterr().out)
    png = tmp_path / "sky.png"
    assert info["preview"] == str(png) and png.is_file()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["sky.exr", "sky.png"]  # no temporaries left
    img = skimage.io.imread(png)
    assert img.dtype == np.uint8 and img.shape[:2] == (48, 48)
    # where the sun is, from the EXR header's camera (North up, East left: CONTRACT.md)
    _, meta = read_exr(out)
    cam = FisheyeCamera.from_metadata(meta["camera"])
    sx, sy = (float(v) for v in cam.angles_to_pixel(torch.tensor(math.radians(zenith), dtype=torch.float64),
                                                      torch.tensor(math.radians(azimuth), dtype=torch.float64)))
    valid = cam.valid_mask().numpy()
    assert not img[~valid].any()  # outside the image circle: black
    y = ndimage.uniform_filter(img[..., :3].astype(float).mean(-1), size=5)  # the brightest 5 x 5 region
    by, bx = np.unravel_index(np.argmax(np.where(valid, y, -1.0)), y.shape)
    assert math.hypot(bx - sx, by - sy) <= 4.0, ((bx, by), (sx, sy))
    # the anti-sun side is darker than the sun's
    ax, ay = 47 - sx, 47 - sy  # opposite azimuth, mirrored through the centre
    assert y[int(round(ay)), int(round(ax))] < y[by, bx] - 20


def test_preview_not_written_without_the_flag(tmp_path, capsys):
    assert main(["render", "earth", "--out", str(tmp_path / "sky.exr"), "--sun-zenith", "30", *FAST]) == 0
    assert [p.name for p in tmp_path.iterdir()] == ["sky.exr"]


def test_preview_target_a_folder_is_one_line_exit_2(tmp_path, capsys):
    (tmp_path / "sky.png").mkdir()
    rc = main(["render", "earth", "--out", str(tmp_path / "sky.exr"), "--sun-zenith", "30", "--preview", *FAST])
    err = capsys.readouterr().err
    assert rc == 2 and err.count("\n") == 1 and "--preview" in err
    assert not (tmp_path / "sky.exr").exists()
