"""Radiance RGBE reader/writer: round trip, a hand-encoded RLE file, bad input."""
import numpy as np
import pytest
import torch
from torch.testing import assert_close

from skyfit.io.hdr import HdrError, read_hdr, write_hdr


def _image(rng, h, w):
    # Log-uniform over 7 decades, some exact zeros, and constant runs for the RLE.
    img = 10 ** rng.uniform(-3, 4, size=(h, w, 3))
    img[0, : w // 2] = 0.0
    img[1, :] = [1.5, 2.5, 3.5]
    return img


@pytest.mark.parametrize("rle", [True, False])
@pytest.mark.parametrize("shape", [(5, 37), (3, 4)])  # width 4 is always flat
def test_round_trip_within_rgbe_precision(tmp_path, rle, shape):
    rng = np.random.default_rng(1)
    img = _image(rng, *shape)
    p = write_hdr(tmp_path / "a.hdr", img, rle=rle)
    back, header = read_hdr(p)
    assert back.shape == img.shape and back.dtype == np.float32
    assert header["format"] == "32-bit_rle_rgbe" and header["orientation"] == "-Y +X"
    # RGBE: one 8-bit mantissa per channel against the pixel's shared exponent,
    # so each channel is within max(r, g, b) / 256 of the input (Ward 1991).
    bound = img.max(-1, keepdims=True) / 256
    assert np.all(np.abs(back - img) <= bound + 1e-30)
    assert np.all(back[0, : shape[1] // 2] == 0)


def test_exposure_is_divided_out(tmp_path):
    img = _image(np.random.default_rng(2), 4, 16)
    back, header = read_hdr(write_hdr(tmp_path / "e.hdr", img, exposure=0.25))
    assert header["exposure"] == 0.25
    assert np.all(np.abs(back - img) <= img.max(-1, keepdims=True) / 256 + 1e-30)


def test_rle_file_encoded_by_hand(tmp_path):
    """A 2 x 8 file written byte by byte from the format description (not by write_hdr):
    row 0 new-style RLE, row 1 flat with an old-style (1, 1, 1, n) repeat."""
    head = b"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\nEXPOSURE=2\n\n-Y 2 +X 8\n"
    row0 = bytes([2, 2, 0, 8])
    row0 += bytes([128 + 8, 128])  # R: run of eight 128s
    row0 += bytes([8]) + bytes(range(0, 128, 16))  # G: eight literals 0, 16, ..., 112
    row0 += bytes([128 + 4, 64, 4, 1, 2, 3, 4])  # B: run of four 64s, then literals 1..4
    row0 += bytes([128 + 8, 129])  # E: eight times 129
    row1 = bytes([10, 20, 30, 130, 1, 1, 1, 7])  # one pixel, repeated 7 more times
    p = tmp_path / "hand.hdr"
    p.write_bytes(head + row0 + row1)
    img, header = read_hdr(p)
    m0 = np.stack([np.full(8, 128), np.arange(0, 128, 16), [64, 64, 64, 64, 1, 2, 3, 4]], -1)
    # value = (m + 0.5) * 2^(E - 136), divided by EXPOSURE = 2.
    want0 = (m0 + 0.5) * 2.0 ** (129 - 136) / 2
    want1 = np.tile((np.array([10, 20, 30]) + 0.5) * 2.0 ** (130 - 136) / 2, (8, 1))
    assert header["exposure"] == 2.0
    assert_close(torch.from_numpy(img.astype(np.float64)), torch.from_numpy(np.stack([want0, want1])),
                 rtol=1e-7, atol=0)
    # The same bytes with "-Y 2 -X 8": columns run right to left.
    p2 = tmp_path / "flip.hdr"
    p2.write_bytes(head.replace(b"+X 8", b"-X 8") + row0 + row1)
    flipped, header2 = read_hdr(p2)
    assert header2["orientation"] == "-Y -X"
    assert_close(torch.from_numpy(flipped), torch.from_numpy(img[:, ::-1].copy()), rtol=0, atol=0)


def test_not_hdr_and_corrupt_files_fail_clearly(tmp_path):
    png = tmp_path / "x.hdr"
    png.write_bytes(b"\x89PNG\r\n\x1a\n" + b"\0" * 32)
    with pytest.raises(HdrError, match="not a Radiance HDR file"):
        read_hdr(png)
    with pytest.raises(HdrError, match="file not found"):
        read_hdr(tmp_path / "missing.hdr")
    good = write_hdr(tmp_path / "g.hdr", _image(np.random.default_rng(3), 4, 16))
    cut = tmp_path / "cut.hdr"
    cut.write_bytes(good.read_bytes()[:-10])
    with pytest.raises(HdrError, match="truncated"):
        read_hdr(cut)
    bad_res = tmp_path / "res.hdr"
    bad_res.write_bytes(b"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\nY 2 X 8\n")
    with pytest.raises(HdrError, match="resolution"):
        read_hdr(bad_res)
    with pytest.raises(HdrError, match="non-negative"):
        write_hdr(tmp_path / "n.hdr", -np.ones((2, 2, 3)))
    assert not (tmp_path / "n.hdr").exists()
