"""OpenEXR read/write: round trips, atomic writes, one-line errors naming the file."""
from __future__ import annotations

import numpy as np
import OpenEXR
import pytest

import skyfit.io.exr as exr_mod
from skyfit.io import ExrError, read_exr, write_exr

SHAPE = (7, 11)  # non-square, so a transposed read would fail


def _channels(seed=0):
    rng = np.random.default_rng(seed)
    names = ["R", "G", "B", "Y", "L360", "L412.5", "L550", "L830", "mask"]
    chans = {n: rng.uniform(0.0, 2000.0, SHAPE).astype(np.float32) for n in names}
    chans["L550"][0, 0] = 0.0
    chans["L550"][0, 1] = np.float32(1e-30)  # float32 subnormal range must survive too
    chans["L550"][0, 2] = np.float32(3.4e38)
    return chans


META = {
    "camera": {"projection": "equidistant", "size": 11, "cx": 5.0, "cy": 3.0, "radius_px": 5.5, "up_azimuth_deg": 0.0},
    "sun": {"zenith_deg": 42.5, "azimuth_deg": 181.25},
    "wavelengths_nm": [360.0, 412.5, 550.0, 830.0],
    "note": "unicode ° and µm",
    "nested": {"list": [1, 2.5, None, True]},
}


def _listing(folder):
    return sorted(p.name for p in folder.iterdir())


def test_round_trip_channels_and_metadata(tmp_path):
    chans = _channels()
    out = write_exr(tmp_path / "img.exr", chans, META)
    assert out == tmp_path / "img.exr"
    got, meta = read_exr(out)
    assert set(got) == set(chans)  # R, G, B come back as three channels, not one "RGB"
    for name, arr in chans.items():
        assert got[name].dtype == np.float32 and got[name].shape == SHAPE
        np.testing.assert_array_equal(got[name], arr, err_msg=name)
    assert meta == META
    assert _listing(tmp_path) == ["img.exr"]  # no temporary left behind


def test_float64_input_is_stored_as_float32(tmp_path):
    x = np.linspace(0, 1, 77, dtype=np.float64).reshape(SHAPE)
    got, meta = read_exr(write_exr(tmp_path / "a.exr", {"Y": x}))
    np.testing.assert_array_equal(got["Y"], x.astype(np.float32))
    assert meta == {}


def test_rgb_grouping_is_split_on_read(tmp_path):
    """The binding groups R, G, B (and A) into one (H, W, 3|4) channel when reading a file
    written by another program; read_exr returns them as separate channels."""
    rng = np.random.default_rng(5)
    rgba = {k: rng.random(SHAPE).astype(np.float32) for k in "RGBA"}
    layer = {f"diffuse.{k}": rng.random(SHAPE).astype(np.float32) for k in "RGB"}
    path = tmp_path / "grouped.exr"
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    OpenEXR.File(header, {"RGBA": np.stack([rgba[k] for k in "RGBA"], -1), **layer}).write(str(path))
    # the binding's default reader really does group them (else this test tests nothing)
    assert any(np.asarray(c.pixels).ndim == 3 for c in OpenEXR.File(str(path)).channels().values())
    got, meta = read_exr(path)
    assert set(got) == set(rgba) | set(layer) and meta == {}
    for k, v in {**rgba, **layer}.items():
        np.testing.assert_array_equal(got[k], v, err_msg=k)


def test_half_channels_are_read_as_float32(tmp_path):
    path = tmp_path / "half.exr"
    y = np.array([[0.5, 1.0], [2.0, 65504.0]], dtype=np.float16)
    OpenEXR.File({"compression": OpenEXR.NO_COMPRESSION, "type": OpenEXR.scanlineimage}, {"Y": y}).write(str(path))
    got, _ = read_exr(path)
    assert got["Y"].dtype == np.float32
    np.testing.assert_array_equal(got["Y"], y.astype(np.float32))


@pytest.mark.parametrize(
    "chans, match",
    [
        ({"R": np.zeros((4, 4)), "G": np.zeros((4, 5))}, "one 2-D shape"),
        ({"R": np.zeros((4, 4, 3))}, "one 2-D shape"),
        ({}, "no channels"),
    ],
)
def test_bad_channels_raise_and_write_nothing(tmp_path, chans, match):
    with pytest.raises(ExrError, match=match):
        write_exr(tmp_path / "bad.exr", chans)
    assert _listing(tmp_path) == []


def test_unserialisable_metadata_raises_and_writes_nothing(tmp_path):
    with pytest.raises(ExrError, match="JSON"):
        write_exr(tmp_path / "bad.exr", {"Y": np.zeros((2, 2))}, {"x": object()})
    assert _listing(tmp_path) == []


class _FailingFile:
    """Stands in for OpenEXR.File: writes half a file, then fails (disk full, killed ...)."""

    def __init__(self, header, channels):
        pass

    def write(self, path):
        with open(path, "wb") as f:
            f.write(b"\x76\x2f\x31\x01partial")
        raise RuntimeError("simulated failure mid-write")


def test_failure_mid_write_leaves_no_file_and_keeps_the_old_one(tmp_path, monkeypatch):
    target = tmp_path / "img.exr"
    write_exr(target, _channels(1), {"version": "old"})
    before = target.read_bytes()
    monkeypatch.setattr(OpenEXR, "File", _FailingFile)
    with pytest.raises(ExrError, match="simulated failure") as e:
        write_exr(target, _channels(2), {"version": "new"})
    assert str(target) in str(e.value)
    monkeypatch.undo()
    assert _listing(tmp_path) == ["img.exr"]  # no partial temporary
    assert target.read_bytes() == before  # the previous image is untouched
    assert read_exr(target)[1] == {"version": "old"}

    monkeypatch.setattr(OpenEXR, "File", _FailingFile)
    with pytest.raises(ExrError):
        write_exr(tmp_path / "fresh.exr", _channels(3))
    assert _listing(tmp_path) == ["img.exr"]


def test_missing_file(tmp_path):
    p = tmp_path / "nope.exr"
    with pytest.raises(ExrError, match="not found") as e:
        read_exr(p)
    assert str(p) in str(e.value) and "\n" not in str(e.value)


@pytest.mark.parametrize("content", [b"", b"P6\n2 2\n255\n" + bytes(12), b"not an image at all"])
def test_non_exr_file(tmp_path, content):
    p = tmp_path / "fake.exr"
    p.write_bytes(content)
    with pytest.raises(ExrError, match="not an OpenEXR file") as e:
        read_exr(p)
    assert str(p) in str(e.value)


def test_truncated_exr(tmp_path):
    good = write_exr(tmp_path / "good.exr", _channels())
    bad = tmp_path / "truncated.exr"
    bad.write_bytes(good.read_bytes()[:200])
    with pytest.raises(ExrError, match="cannot read EXR") as e:
        read_exr(bad)
    assert str(bad) in str(e.value) and "\n" not in str(e.value)


def test_directory_is_not_a_file(tmp_path):
    with pytest.raises(ExrError, match="not found") as e:
        read_exr(tmp_path)
    assert str(tmp_path) in str(e.value)


def test_bad_metadata_json(tmp_path):
    p = tmp_path / "meta.exr"
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage, exr_mod.METADATA_KEY: "{oops"}
    OpenEXR.File(header, {"Y": np.zeros((2, 2), np.float32)}).write(str(p))
    with pytest.raises(ExrError, match="not valid JSON") as e:
        read_exr(p)
    assert str(p) in str(e.value)
