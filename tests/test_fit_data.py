"""Observations: masks and subsampling of fisheye EXRs, Kider captures as observations, DATA expansion."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch
from torch.testing import assert_close

from skyfit.camera import FisheyeCamera
from skyfit.fit import DataError, expand_data_paths, observation_from_exr, observation_from_kider
from skyfit.io import write_exr

KIDER_DAY = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "kider2014" / "2013-05-27"
SIZE = 16


def _exr(path, sun=(30.0, 200.0), values=None, extra=None, meta_extra=None):
    cam = FisheyeCamera(SIZE)
    img = np.full((SIZE, SIZE), 0.02, np.float32) if values is None else values
    chans = {"L450": img, "L550": 0.5 * img, **(extra or {})}
    meta = {"camera": cam.to_metadata(), "sun": {"zenith_deg": sun[0], "azimuth_deg": sun[1]}, **(meta_extra or {})}
    write_exr(path, chans, meta)
    return cam


def _angles_deg(cam, sun):
    """Independent numpy geometry: angle of each valid pixel's direction from the sun."""
    v, valid = cam.pixel_vectors(torch.float64)
    v = v.numpy()[valid.numpy()]
    z, a = np.radians(sun[0]), np.radians(sun[1])
    s = np.array([np.sin(z) * np.sin(a), np.sin(z) * np.cos(a), np.cos(z)])
    return np.degrees(np.arccos(np.clip(v @ s, -1, 1))), v


def test_exr_masks_sun_disc_horizon_obstacles(tmp_path):
    sun = (60.0, 200.0)
    obstacle = np.ones((SIZE, SIZE), np.float32)
    obstacle[:4, :] = 0.0  # the northern rows are a wall
    cam = _exr(tmp_path / "a.exr", sun, extra={"mask": obstacle})
    ang, v = _angles_deg(cam, sun)
    north_rows = np.zeros((SIZE, SIZE), bool)
    north_rows[:4, :] = True
    wall = north_rows[cam.valid_mask().numpy()]
    elev = np.degrees(np.arcsin(v[:, 2]))
    for disc, min_el in ((0.0, 0.0), (20.0, 0.0), (20.0, 15.0)):
        obs = observation_from_exr(tmp_path / "a.exr", sun_disc_deg=disc, min_elevation_deg=min_el)
        expect = (~wall) & (ang >= disc if disc > 0 else True) & (elev > min_el)
        assert obs.n_samples == int(expect.sum()), (disc, min_el)
        assert obs.kind == "spectral" and obs.channels == ("L450", "L550")
        assert_close(obs.wavelengths, torch.tensor([450.0, 550.0], dtype=torch.float64))
    # default noise: 1 % relative plus 1e-3 of the median
    obs = observation_from_exr(tmp_path / "a.exr")
    assert_close(obs.sigma[:, 0], torch.full_like(obs.sigma[:, 0], math.hypot(0.01 * 0.02, 1e-3 * 0.01)), rtol=1e-6, atol=0)


def test_exr_subsampling_and_pixel_index(tmp_path):
    cam = _exr(tmp_path / "a.exr")
    full = observation_from_exr(tmp_path / "a.exr", sun_disc_deg=0.0)
    sub = observation_from_exr(tmp_path / "a.exr", sun_disc_deg=0.0, max_samples=50)
    step = math.ceil(full.n_samples / 50)
    assert sub.metadata["subsample_step"] == step
    assert sub.n_samples == len(range(0, full.n_samples, step))
    assert_close(sub.directions, full.directions[::step], rtol=0, atol=0)
    # the pixel index points back at the pixel each direction came from
    v, _ = cam.pixel_vectors(torch.float64)
    assert_close(v.reshape(-1, 3)[sub.metadata["pixel_index"]], sub.directions, rtol=0, atol=0)


def test_exr_errors_name_the_file(tmp_path):
    _exr(tmp_path / "night.exr", sun=(95.0, 10.0))
    with pytest.raises(DataError, match=r"night.exr: the sun is below the horizon"):
        observation_from_exr(tmp_path / "night.exr")
    write_exr(tmp_path / "nosun.exr", {"L450": np.ones((SIZE, SIZE), np.float32)}, {"camera": FisheyeCamera(SIZE).to_metadata()})
    with pytest.raises(DataError, match=r"nosun.exr: no sun position"):
        observation_from_exr(tmp_path / "nosun.exr")
    write_exr(tmp_path / "grey.exr", {"Y": np.ones((SIZE, SIZE), np.float32)},
              {"camera": FisheyeCamera(SIZE).to_metadata(), "sun": {"zenith_deg": 30, "azimuth_deg": 0}})
    with pytest.raises(DataError, match=r"grey.exr: neither spectral L<nm> channels nor R, G, B"):
        observation_from_exr(tmp_path / "grey.exr")
    (tmp_path / "text.exr").write_text("hello")
    with pytest.raises(ValueError, match=r"not an OpenEXR file: .*text.exr"):
        observation_from_exr(tmp_path / "text.exr")


def test_expand_data_paths(tmp_path):
    _exr(tmp_path / "b.exr")
    _exr(tmp_path / "a.exr")
    assert [p.name for _, p in expand_data_paths([tmp_path])] == ["a.exr", "b.exr"]
    (tmp_path / "empty").mkdir()
    with pytest.raises(DataError, match="neither Kider captures .* nor .exr files"):
        expand_data_paths([tmp_path / "empty"])
    with pytest.raises(DataError, match="data not found: .*nothing"):
        expand_data_paths([tmp_path / "nothing"])


@pytest.mark.skipif(not KIDER_DAY.is_dir(), reason="shared Kider data (../shared/data/kider2014) not present")
def test_kider_capture_as_observation():
    from skyfit.io import load_kider_capture

    folder = KIDER_DAY / "2013-05-27___12.00.00"
    obs = observation_from_kider(folder)
    cap = load_kider_capture(folder)
    centres, rad, sig = cap.band_average(10, 360, 720)
    assert obs.values.shape == (81, 36) and obs.channels[0] == "L365" and obs.band_nm == 10.0
    assert_close(obs.values, torch.tensor(rad), rtol=0, atol=0)
    assert_close(obs.sigma, torch.tensor(sig), rtol=0, atol=0)
    assert obs.sun_zenith.shape == (81,)  # the sun at each sample's own time
    # docs/data.md: at 12:00 the rings' symmetry axes are 15.3 and 16.0 deg before the SPA sun
    assert -16.5 < math.degrees(obs.metadata["azimuth_offset_guess_rad"]) < -14.8
    # views: ring 4 is the zenith
    assert_close(obs.directions[80], torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64), rtol=0, atol=1e-12)
    one_sun = observation_from_kider(folder, per_sample_sun=False)
    assert one_sun.sun_zenith.shape == ()
    assert float(one_sun.sun_zenith) == pytest.approx(cap.sun_zenith)
    with pytest.raises(ValueError, match="Kider capture folder not found"):
        observation_from_kider(KIDER_DAY / "2013-05-27___23.59.00")
    assert len(expand_data_paths([KIDER_DAY])) == 15
