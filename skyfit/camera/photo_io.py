"""Measured LDR photos as data: loading, sRGB decoding and censoring masks.

**Measured LDR photos** (JPEG/PNG, 8 or 16 bit) are read with scikit-image,
decoded to linear values with the sRGB transfer function (IEC 61966-2-1,
:func:`skyfit.camera.srgb.srgb_decode`, differentiable; it equals
``colour.cctf_decoding(..., function='sRGB')``), and pixels at the ends of
the code range are flagged as *censored*: a saturated pixel says only "at
least this bright", a black one "at most this bright". The exposure of an
LDR photo is unknown: it is a scale fitted with
:func:`skyfit.camera.likelihood.fit_exposure_scale` or profiled out, and
:func:`skyfit.camera.likelihood.censored_gaussian_nll` scores a model against
such data. Synthetic photos (:mod:`skyfit.camera.sensor`) give the same
:class:`PhotoObservation`.

Units: LDR photo values linear in [0, 1].
"""
from __future__ import annotations

import dataclasses
import os

import numpy as np
import torch
from torch import Tensor

from .srgb import srgb_decode

DEFAULT_CLIP_LEVEL: float = 254.0 / 255.0
"""Encoded value at and above which an LDR pixel counts as saturated (censored high). [1]"""
DEFAULT_BLACK_LEVEL: float = 1.0 / 255.0
"""Encoded value at and below which an LDR pixel counts as black (censored low). [1]"""


@dataclasses.dataclass
class PhotoObservation:
    """A photo as data for a fit.

    Attributes:
        rgb: linear values, shape (H, W, 3); for an LDR photo the decoded
            sRGB in [0, 1], for a raw photo (DN - black) / (max DN - black). [1]
        valid: pixels to use (alpha channel, fisheye disc), shape (H, W), bool.
        censored_high: channel clipped at the top, shape (H, W, 3), bool.
        censored_low: channel clipped at the bottom, shape (H, W, 3), bool.
        bit_depth: bits per channel of the stored values (8, 16, or the raw depth).
        clip_high: linear value at and above which a channel is censored high. [1]
        clip_low: linear value at and below which a channel is censored low. [1]
        exposure_unknown: True when ``rgb`` relates to radiance by an unknown
            scale (always so for LDR files): fit it with :func:`~skyfit.camera.likelihood.fit_exposure_scale`.
        exposure_scale: the scale ``rgb ~= exposure_scale * camera_signal`` when known.
        path: the file the photo came from, if any.
    """

    rgb: Tensor
    valid: Tensor
    censored_high: Tensor
    censored_low: Tensor
    bit_depth: int
    clip_high: float
    clip_low: float
    exposure_unknown: bool = True
    exposure_scale: float | None = None
    path: str | None = None

    @property
    def censored(self) -> Tensor:
        """Pixels with any channel censored (saturated or black), shape (H, W), bool."""
        return (self.censored_high | self.censored_low).any(-1)

    @property
    def usable(self) -> Tensor:
        """Valid and uncensored pixels, shape (H, W), bool."""
        return self.valid & ~self.censored


def _check_levels(clip_level: float, black_level: float) -> None:
    if not 0.0 <= black_level < clip_level <= 1.0:
        raise ValueError(f"need 0 <= black_level < clip_level <= 1 (encoded values), got black_level={black_level}, clip_level={clip_level}")


def observation_from_encoded(
    codes: Tensor, max_code: int, bit_depth: int, clip_level: float, black_level: float, valid: Tensor, path: str | None
) -> PhotoObservation:
    """A :class:`PhotoObservation` of sRGB codes (H, W, 3) in 0..``max_code``: decoded, censored at the levels."""
    enc = codes / max_code
    # Compare codes, not floats, so that code 254 of 255 is >= 254/255 whatever the rounding.
    high = codes >= clip_level * max_code - 1e-6
    low = codes <= black_level * max_code + 1e-6
    dt = codes.dtype
    return PhotoObservation(
        rgb=srgb_decode(enc),
        valid=valid,
        censored_high=high,
        censored_low=low,
        bit_depth=bit_depth,
        clip_high=float(srgb_decode(torch.tensor(clip_level, dtype=dt))),
        clip_low=float(srgb_decode(torch.tensor(black_level, dtype=dt))),
        exposure_unknown=True,
        path=path,
    )


def png_bit_depth(path: str) -> int | None:
    """Bit depth from a PNG's IHDR chunk, or None for a file that is not PNG."""
    with open(path, "rb") as f:
        head = f.read(25)
    if len(head) < 25 or head[:8] != b"\x89PNG\r\n\x1a\n" or head[12:16] != b"IHDR":
        return None
    return head[24]


def read_png16(path: str) -> np.ndarray:
    """A 16-bit PNG's samples as uint16, shape (H, W) for grey or (H, W, C) with C = 2 (grey + alpha), 3 or 4.

    Pillow (behind imageio and scikit-image) turns 16-bit RGB(A) PNG into 8 bits without a word; pypng decodes
    every PNG colour type at its full depth (``asDirect`` applies a tRNS transparency as alpha). ValueError, one
    line, for a file it cannot decode.
    """
    import png  # pypng: pure Python, 0.3 s for 600x600 RGB, 4.5 s for 6 Mpx

    try:
        w, h, rows, info = png.Reader(filename=path).asDirect()
        arr = np.vstack([np.asarray(r, dtype=np.uint16) for r in rows])
    except (png.Error, OSError, ValueError) as e:  # pypng's messages repeat their class: "FormatError: ..."
        what = (str(e).strip().splitlines() or [type(e).__name__])[0]
        raise ValueError(f"photo {path}: cannot read the 16-bit PNG ({what})") from None
    planes = int(info["planes"])
    arr = arr.reshape(h, w, planes)
    return arr[..., 0] if planes == 1 else arr


def load_ldr_photo(
    path: str | os.PathLike,
    *,
    clip_level: float = DEFAULT_CLIP_LEVEL,
    black_level: float = DEFAULT_BLACK_LEVEL,
    valid: Tensor | None = None,
    dtype: torch.dtype = torch.float64,
    device: torch.device | str = "cpu",
) -> PhotoObservation:
    """Read an 8- or 16-bit sRGB JPEG/PNG/TIFF as linear values with censoring masks.

    The file is read with ``skimage.io.imread`` (a 16-bit PNG with :func:`read_png16`: the
    Pillow reader behind skimage decodes 16-bit RGB PNG to 8 bits); codes are divided by the
    largest code (255 or 65535) and decoded with :func:`srgb_decode`. A
    channel is censored high when its encoded value is >= ``clip_level`` and
    censored low when it is <= ``black_level``. An alpha channel marks the
    pixels with alpha below its maximum as invalid. The exposure is unknown.

    Args:
        path: a JPEG, PNG or TIFF file, RGB or RGBA, 8 or 16 bits per channel.
        clip_level: encoded value in (0, 1] at and above which a channel is saturated. [1]
        black_level: encoded value in [0, 1) at and below which a channel is black. [1]
        valid: optional mask of usable pixels (e.g. the fisheye disc), shape (H, W), bool.
        dtype, device: of the returned tensors.

    Returns:
        A :class:`PhotoObservation` with ``rgb`` of shape (H, W, 3).

    Raises:
        FileNotFoundError: no such file.
        ValueError: unreadable, not RGB(A), not 8/16-bit integer, or a bad mask or level.
    """
    _check_levels(clip_level, black_level)
    p = os.fspath(path)
    if not os.path.isfile(p):
        raise FileNotFoundError(f"photo not found: {p}")
    import skimage.io  # here, not at the top: 1.2 s to import, and only a photo file needs it

    if png_bit_depth(p) == 16:
        arr = read_png16(p)
    else:
        try:
            arr = skimage.io.imread(p)
        except Exception as e:  # noqa: BLE001 - reader errors vary by plugin
            raise ValueError(f"cannot read photo {p}: {e}") from None
        arr = np.asarray(arr)
    if arr.ndim != 3 or arr.shape[-1] not in (3, 4):
        raise ValueError(f"photo {p}: expected an RGB or RGBA image of shape (H, W, 3|4), got shape {arr.shape}")
    if arr.dtype == np.uint8:
        bits = 8
    elif arr.dtype == np.uint16:
        bits = 16
    else:
        raise ValueError(f"photo {p}: expected 8- or 16-bit integer channels, got {arr.dtype}")
    max_code = 2**bits - 1
    mask = torch.ones(arr.shape[:2], dtype=torch.bool, device=device)
    if arr.shape[-1] == 4:
        mask = torch.as_tensor(arr[..., 3] == max_code, device=device)
    if valid is not None:
        if tuple(valid.shape) != arr.shape[:2]:
            raise ValueError(f"photo {p}: valid mask has shape {tuple(valid.shape)}, image is {arr.shape[:2]}")
        mask = mask & valid.to(device=device, dtype=torch.bool)
    codes = torch.as_tensor(arr[..., :3].astype(np.float64), device=device).to(dtype)
    return observation_from_encoded(codes, max_code, bits, clip_level, black_level, mask, p)



__all__ = [
    "DEFAULT_BLACK_LEVEL",
    "DEFAULT_CLIP_LEVEL",
    "PhotoObservation",
    "load_ldr_photo",
    "observation_from_encoded",
    "png_bit_depth",
    "read_png16",
]
