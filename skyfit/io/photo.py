"""Any photo a user has -> one linear HDR image with per-pixel variance and censoring.

:func:`read_photo` reads a JPEG/PNG/TIFF (8 or 16 bit), a camera RAW file, a
Radiance ``.hdr``, an EXR without skyfit metadata, or a folder holding one
scene's exposure bracket, and returns a :class:`LinearPhoto`: linear values
per unit relative exposure, their variance, and which channels are censored
(clipped in every frame, or black in every frame). A grey image (a monochrome camera's; grey + alpha too, and an
EXR of luminance Y alone) is read as three equal channels with ``meta["monochrome"]`` True: the rest of the path
reads three channels, and a photo fit then counts them as one. Pixels are kept as stored
in the file (EXIF orientation is not applied, as rawpy's ``user_flip=0``), so
a camera calibration refers to the sensor's layout.

Readers: imageio (Pillow) for JPEG/PNG, tifffile for TIFF (first page),
rawpy (LibRaw) for RAW, exifread for EXIF, :func:`skyfit.io.hdr.read_hdr` and
:func:`skyfit.io.exr.read_exr` for the HDR formats.

**Units.** An LDR or RAW frame gives linear values ``X`` in [0, 1] of its own
full scale (decoded code, or (DN - black) / (white - black) through LibRaw).
``rgb = X / e`` with ``e`` the frame's *relative exposure*: ``t ISO / N^2``
(exposure time [s], ISO, f-number N) when EXIF has all three, ``t`` when it
has only the time, the given value (``exposures=``), a ratio estimated from
the frames (the shortest frame is 1), or 1 when nothing says.

**Noise model** (the variance of ``X`` of one frame, in full-scale units²)::

    var_X = X / SHOT_COUNT_FULL_SCALE                      shot-like: Poisson in a nominal count
          + (dX/dc)^2 (1/12 + code_noise^2) / levels^2     quantisation (+ JPEG error) through the response's slope
          + NOISE_FLOOR^2                                   read/dark noise floor

with ``levels`` the number of code steps of full scale (255, 65535, or the
RAW file's white - black), ``code_noise`` :data:`JPEG_CODE_NOISE` for JPEG and
0 otherwise; ``var(rgb) = var_X / e^2``. The constants are nominal (a typical
small-sensor camera at base ISO), not calibrated for a given camera: they set
the *relative* weights of frames and pixels. A bracket merges frames by the
inverse-variance weighted mean (Robertson et al. 2003 weight the same way),
and its variance is ``1 / sum(weights)``. Clipped and black channels carry no
weight; ``variance`` is inf where no frame measured the channel. Radiance
``.hdr`` and EXR images are already linear: ``sd = HDR_RELATIVE_NOISE * x +
HDR_FLOOR_FRACTION * (99th percentile of the image)`` (added in quadrature),
no censoring.

**Camera response.** A single LDR file is decoded with the sRGB transfer
function unless ``linear=True`` or ``response=`` says otherwise (one frame
cannot tell). For a bracket the response is estimated by default (CONTRACT:
"estimated from the frames themselves ... unless --linear or --response"):
the right inverse response ``g`` makes the ratio ``g(c_long) / g(c_short)``
of two frames the same at every brightness (Mitsunaga & Nayar 1999's
criterion). For each pair of frames adjacent in exposure, pixels well
exposed in both are binned by brightness (quantiles of the mean log value,
which is uncorrelated with the log ratio's noise when both frames are
equally noisy); the score of a candidate ``g`` is the RMS over bins of
``median(log ratio in bin) / M - 1`` with ``M`` the known log exposure ratio,
or the pair's median log ratio when the exposures are unknown, each bin weighted
by its samples (a pair of dark frames sharing a few hundred values counts for
that, not for as much as a pair sharing 10^5). Candidates:
linear, sRGB, and ``gamma:G`` (``X = c^G``) with ``G`` fitted in closed form
(least squares of the same relative residuals); sRGB is kept unless another
candidate scores below :data:`RESPONSE_MARGIN` (0.8) of the best simpler one.
``meta["response_scores"]`` records the scores.
Without exposure times the exponent of a response cannot be known from the
images (``g`` and ``g^k`` explain them equally with ratios ``r^k``: Grossberg &
Nayar 2003, "the exponential ambiguity"): then only the *class* is chosen,
sRGB against a power law, and a power law is taken as gamma 2.2 for 8-bit
frames and linear for 16-bit ones, with a note. RAW files are linear.

**Calibrated responses.** ``response="debevec"`` or ``"robertson"`` calibrates a bracket's response per
channel from its own frames (:mod:`skyfit.camera.response`: Debevec & Malik 1997, Robertson et al. 2003) on
the subsampled frames without their clipped, black and invalid values, with the relative exposures from EXIF,
``exposures=``, or (neither) the ratios estimated from the frames' overlap through the best parametric
response, with a note (the ratios and a response are known only together). ``response="file:TABLE.csv"``
(or a path ending ``.csv``) reads a calibrated inverse response: rows ``code, X`` or ``code, R, G, B``, codes
from 0 to 1 strictly increasing, values finite, >= 0 and non-decreasing (any scale: divided by the value at
code 1); it applies to single files too. Both are tabulated curves, interpolated linearly, whose slope
feeds the noise model; ``meta["response_curve"]`` holds 17 points per channel and
:attr:`LinearPhoto.response_table` the whole table (:func:`write_response_table` writes it as such a CSV).
"""
from __future__ import annotations

import dataclasses
import datetime as _dt
import functools
import logging
import math
import os
import re
from pathlib import Path
from typing import Sequence

import numpy as np
import torch

from ..camera.photo_io import DEFAULT_BLACK_LEVEL, DEFAULT_CLIP_LEVEL, png_bit_depth, read_png16
from ..camera.response import (
    ResponseError,
    TabulatedResponse,
    debevec_response,
    robertson_response,
    table_response,
)
from ..camera.icc import SRGB_TOLERANCE as ICC_SRGB_TOLERANCE, IccError, IccProfile, parse_icc
from ..camera.srgb import srgb_decode, srgb_encode_slope
from .atomic import write_text_atomic
from .exr import ExrError, read_exr
from .hdr import HdrError, read_hdr
from .kider import is_kider_capture_name

LDR_EXTENSIONS: tuple[str, ...] = (".jpg", ".jpeg", ".png", ".tif", ".tiff", ".heic", ".heif", ".hif")
"""8/16-bit image files read through imageio/Pillow (JPEG, PNG; pypng for 16-bit PNG), tifffile (TIFF) and
pillow-heif (HEIF/HEIC of phones and cameras, 8 to 12 bits; an optional dependency, ``pip install skyfit[heic]``)."""
HEIF_EXTENSIONS: tuple[str, ...] = (".heic", ".heif", ".hif")
RAW_EXTENSIONS: tuple[str, ...] = (
    ".dng", ".cr2", ".cr3", ".crw", ".nef", ".nrw", ".arw", ".srf", ".sr2", ".orf", ".rw2", ".raf",
    ".pef", ".srw", ".x3f", ".3fr", ".fff", ".iiq", ".mos", ".mrw", ".erf", ".kdc", ".dcr", ".rwl", ".raw",
)
"""Camera RAW files read through rawpy (LibRaw)."""
HDR_EXTENSIONS: tuple[str, ...] = (".hdr",)
"""Radiance RGBE files (:mod:`skyfit.io.hdr`)."""
EXR_EXTENSIONS: tuple[str, ...] = (".exr",)
"""OpenEXR files; only those without skyfit's metadata are photos (:func:`is_photo_path`)."""
PHOTO_EXTENSIONS: tuple[str, ...] = LDR_EXTENSIONS + RAW_EXTENSIONS + HDR_EXTENSIONS + EXR_EXTENSIONS
"""Every file extension :func:`read_photo` reads (lower case, with the dot)."""

SHOT_COUNT_FULL_SCALE: float = 4000.0
"""Nominal photon count at full scale of a frame [1]: shot-like variance ``X / 4000`` (1.6 % at full
scale, 5 % at 10 %), typical of a small-sensor camera at base ISO; sets relative weights, not calibrated."""
JPEG_CODE_NOISE: float = 1.0
"""RMS error of a JPEG's codes from its lossy compression [code steps]; ~1 code at quality 85-95."""
NOISE_FLOOR: float = 2e-4
"""Read/dark noise floor of a frame [full scale]; ~1 DN of a 12-bit raw file."""
HDR_RELATIVE_NOISE: float = 0.01
"""Relative standard deviation assumed for a Radiance .hdr or EXR pixel [1] (RGBE's 8-bit mantissa alone gives 0.1-0.4 %)."""
HDR_FLOOR_FRACTION: float = 1e-4
"""Absolute noise floor of a .hdr/EXR image as a fraction of its 99th percentile [1]."""

WELL_EXPOSED: tuple[float, float] = (0.05, 0.92)
"""Encoded values [1] that count as well exposed for exposure ratios and the response."""
SCENE_CHECK_RANGE: tuple[float, float] = (0.1, 0.9)
"""Encoded values [1] over which two frames of a bracket must agree (quantisation < 5 % per code)."""
SCENE_SPREAD_MAX: float = 0.25
"""Largest robust spread (1.4826 MAD) of the log ratio of two exposure-normalised frames over pixels
well exposed in both [1]: 0.25 is a 28 % typical disagreement. Noise alone gives sd(log) ~ 1-5 % at
these codes; the tests' 8-bit JPEG bracket with 1 % noise and a cloud moved over 13 % of the pixels gives
0.04 (a median is not moved by under half the pixels); the same sky mirrored gives 1.0-2.0."""
EXPOSURE_MISMATCH_NOTE: float = 0.1
"""Relative disagreement of EXIF exposure ratios with the pixels' above which a note is added [1]."""
MIN_OVERLAP: int = 50
"""Fewest pixel channels well exposed in two frames to estimate their exposure ratio."""
MIN_RESPONSE_SAMPLES: int = 300
"""Fewest pixel channels in a frame pair for the response estimate to use it."""
RESPONSE_MARGIN: float = 0.8
"""sRGB, the standard of LDR files, is kept unless linear scores below this fraction of it; a fitted gamma is
chosen only when it scores below this fraction of the better of linear and sRGB [1]."""
MAX_SAMPLES: int = 250_000
"""Pixels (per frame) used for the bracket's statistics; larger frames are subsampled on a regular grid."""


class PhotoError(ValueError):
    """A photo that cannot be read as asked; the message is one line, ``photo PATH: problem``."""


@dataclasses.dataclass
class LinearPhoto:
    """One linear HDR image of a photo, with variance and censoring.

    Attributes:
        rgb: linear values per unit relative exposure, shape (H, W, 3), float64. For a bracket the
            merged value; for one frame its decoded value / relative exposure (1 when unknown).
            Where censored high, the lower bound (clip level / shortest exposure); where censored
            low, the upper bound (black level / longest exposure). [relative]
        variance: variance of ``rgb``, shape (H, W, 3), float64; inf where no frame measured the
            channel (see the module's noise model). [relative²]
        censored_high: clipped in every frame, shape (H, W, 3), bool.
        censored_low: black in every frame, shape (H, W, 3), bool.
        valid: pixels to use (alpha channel at its maximum in every frame, or all True), shape (H, W), bool.
        darkest: linear values of the darkest (shortest) frame / its relative exposure, shape
            (H, W, 3), float64, same units as ``rgb``; clipped channels at their clipped value. [relative]
        darkest_saturated: any channel clipped in that darkest frame, shape (H, W), bool.
        source: the path read.
        meta: JSON-ready facts: ``format`` ("jpeg", "png", "tiff", "heif", "raw", "hdr", "exr", "bracket"),
            ``bit_depth``, ``response`` ("srgb", "linear", "gamma:G", "debevec", "robertson", "table:PATH"),
            ``response_source`` ("default", "--linear", "given", "estimated", "calibrated"), ``response_curve``
            (a tabulated response at 17 codes per channel, :meth:`TabulatedResponse.curve`), ``response_calibration``
            (Debevec/Robertson: pixels, residuals, constant exposure ratio), ``frames`` (list of ``path``, ``exposure_s``,
            ``f_number``, ``iso``, ``relative_exposure``, ``exposure_source``: "exif", "given",
            "estimated" or "unknown"), ``notes`` (warnings), ``noise`` (the model's constants),
            the first frame's EXIF (``exposure_s``, ``f_number``, ``iso``, ``datetime_original``,
            ``camera_make``, ``camera_model``; None when absent) and per format: ``clip_level``,
            ``black_level`` (encoded), ``white_balance`` (RAW), ``response_scores`` (estimated).
    """

    rgb: np.ndarray
    variance: np.ndarray
    censored_high: np.ndarray
    censored_low: np.ndarray
    valid: np.ndarray
    darkest: np.ndarray
    darkest_saturated: np.ndarray
    source: str
    meta: dict
    response_table: TabulatedResponse | None = None
    """The calibrated or given response table (for :func:`write_response_table`); None for a parametric response."""


# --------------------------------------------------------------------------
# Responses: inverse camera response, codes in [0, 1] -> linear X in [0, 1]
# --------------------------------------------------------------------------

CALIBRATIONS: tuple[str, ...] = ("debevec", "robertson")
"""Responses calibrated from a bracket's frames (:mod:`skyfit.camera.response`)."""
_RGB = np.arange(3)


@dataclasses.dataclass(frozen=True)
class _Response:
    name: str  # "linear", "srgb", "gamma:G", "debevec", "robertson", "table:PATH"
    gamma: float | None = None
    table: TabulatedResponse | None = dataclasses.field(default=None, compare=False, repr=False)

    @property
    def per_channel(self) -> bool:
        """Whether the channels have different curves (a three-channel table)."""
        return self.table is not None and self.table.channels == 3

    def decode(self, c: np.ndarray, channel: np.ndarray | None = None) -> np.ndarray:
        """Linear values from encoded values c in [0, 1], same shape; a per-channel response reads ``channel``
        (0, 1, 2 per value) or, when None, c's last axis as R, G, B (c broadcast to (..., 3))."""
        if self.table is not None:
            return self.table.decode(c, channel)
        if self.name == "linear":
            return np.asarray(c, np.float64)
        if self.name == "srgb":
            return srgb_decode(torch.from_numpy(np.asarray(c, np.float64))).numpy()
        return np.asarray(c, np.float64) ** self.gamma

    def slope(self, c: np.ndarray, channel: np.ndarray | None = None) -> np.ndarray:
        """dX/dc at encoded values c, shape as :meth:`decode`."""
        if self.table is not None:
            return self.table.slope(c, channel)
        c = np.asarray(c, np.float64)
        if self.name == "linear":
            return np.ones_like(c)
        if self.name == "srgb":
            x = srgb_decode(torch.from_numpy(c))
            return 1.0 / srgb_encode_slope(x).numpy()
        return self.gamma * np.maximum(c, 1e-12) ** (self.gamma - 1.0)


def _gamma_name(g: float) -> str:
    return f"gamma:{round(g, 2):g}"


def _read_response_table(path: str, table_path: str) -> _Response:
    """A CSV inverse response (rows ``code, X`` or ``code, R, G, B``; codes in [0, 1]) -> _Response; PhotoError (one line
    naming the photo and the table) for a missing, unreadable or malformed table (:func:`skyfit.camera.response.check_table`)."""
    where = f"photo {path}: response table {table_path}"
    if not os.path.isfile(table_path):
        raise PhotoError(f"{where}: no such file")
    try:
        text = Path(table_path).read_text()
    except (OSError, UnicodeDecodeError) as e:
        raise PhotoError(f"{where}: cannot read it ({_one_line(e)})") from None
    rows, lines = [], []
    for n, line in enumerate(text.splitlines(), 1):
        cells = line.split("#")[0].strip()
        if not cells:
            continue
        try:
            vals = [float(v) for v in cells.split(",")]
        except ValueError:
            if not rows:
                continue  # a header line before the numbers
            raise PhotoError(f"{where}: line {n} is not comma-separated numbers: {cells[:40]!r}") from None
        if rows and len(vals) != len(rows[0]):
            raise PhotoError(f"{where}: line {n} has {len(vals)} column(s), the first row {len(rows[0])}")
        rows.append(vals)
        lines.append(n)
    if not rows:
        raise PhotoError(f"{where}: no rows of numbers (expected code, X or code, R, G, B)")
    if len(rows[0]) not in (2, 4):
        raise PhotoError(f"{where}: {len(rows[0])} column(s); a table has 2 (code, X) or 4 (code, R, G, B)")
    arr = np.array(rows)
    try:
        tab = table_response(arr[:, 0], arr[:, 1:], info={"path": table_path, "rows": len(rows)})
    except ResponseError as e:
        raise PhotoError(f"{where}: {e}") from None
    return _Response(f"table:{table_path}", table=tab)


def _parse_response(path: str, spec: str) -> _Response | str:
    """A response spec -> _Response, or the string "estimate", "debevec" or "robertson"; PhotoError for anything else."""
    raw = spec.strip()
    s = raw.lower()
    if s in ("linear", "srgb"):
        return _Response(s)
    if s == "estimate" or s in CALIBRATIONS:
        return s
    if s.startswith("file:"):
        return _read_response_table(path, raw[5:].strip())
    if s.endswith(".csv"):
        return _read_response_table(path, raw)
    if s.startswith("gamma:"):
        try:
            g = float(s[6:])
        except ValueError:
            g = float("nan")
        if not 0.2 <= g <= 5.0:
            raise PhotoError(f"photo {path}: response {spec!r} needs a gamma in [0.2, 5], e.g. gamma:2.2")
        return _Response(_gamma_name(g), g)
    raise PhotoError(f"photo {path}: unknown response {spec!r}; use srgb, linear, gamma:G, estimate, debevec, robertson "
                     "or file:TABLE.csv")


def _response_request(path: str, linear: bool, response: str | None) -> tuple[_Response | str | None, str]:
    """(requested response, "estimate", "debevec", "robertson", or None for the format's default; response_source)."""
    if response is not None and not isinstance(response, str):
        raise PhotoError(f"photo {path}: response must be a string, got {type(response).__name__}")
    if linear:
        if response is not None and response.strip().lower() != "linear":
            raise PhotoError(f"photo {path}: linear=True contradicts response={response!r}; give one of them")
        return _Response("linear"), "--linear"
    if response is None:
        return None, "default"
    return _parse_response(path, response), "given"


# --------------------------------------------------------------------------
# EXIF
# --------------------------------------------------------------------------

def _exif_number(tag) -> float | None:
    if tag is None:
        return None
    try:
        v = tag.values[0] if isinstance(tag.values, (list, tuple)) else tag.values
        x = float(v)
    except (TypeError, ValueError, ZeroDivisionError, IndexError):
        return None
    return x if math.isfinite(x) and x > 0 else None


def exif_tags(path: str | Path) -> dict:
    """The EXIF tags of an image file as exifread reads them ({} when it has none or exifread cannot parse it)."""
    import exifread  # here: only photos need it

    xlog = logging.getLogger("exifread")
    level = xlog.level
    xlog.setLevel(logging.ERROR)  # exifread warns "file does not have exif data" for every plain PNG
    try:
        if os.path.splitext(str(path))[1].lower() in HEIF_EXTENSIONS:
            import io  # exifread does not find the EXIF item of a HEIF file; pillow-heif hands it over

            exif = _heif_extras(str(path))[0]
            return exifread.process_file(io.BytesIO(exif), details=False) if exif else {}
        with open(path, "rb") as f:
            return exifread.process_file(f, details=False)
    except Exception:  # noqa: BLE001 - EXIF is optional: a file exifread cannot parse simply has none
        return {}
    finally:
        xlog.setLevel(level)


EXIF_FORMAT = "%Y:%m:%d %H:%M:%S"
EXIF_OFFSET = re.compile(r"^([+-])(\d{2}):?(\d{2})$")
"""An EXIF OffsetTime value (``+02:00``; ``+0200`` accepted)."""


def _exif_text(tags: dict, *names) -> str | None:
    for n in names:
        if n in tags:
            v = str(getattr(tags[n], "printable", tags[n])).strip().strip("\x00").strip()
            if v:
                return v
    return None


def exif_time(path: str | Path) -> tuple[_dt.datetime | None, str | None]:
    """(EXIF DateTimeOriginal as a naive local datetime, OffsetTimeOriginal as ``+HH:MM``) of an image file.

    DateTimeOriginal (tag 36867; else DateTimeDigitized, else the IFD0 DateTime) with SubSecTimeOriginal when
    present; the offset from OffsetTimeOriginal (tag 36881; EXIF 2.31), else OffsetTime. (None, None) when the
    file has no EXIF or no readable time (``0000:00:00 00:00:00`` and blanks count as none)."""
    tags = exif_tags(path)
    stamp = _exif_text(tags, "EXIF DateTimeOriginal", "EXIF DateTimeDigitized", "Image DateTime")
    when = None
    if stamp is not None:
        try:
            when = _dt.datetime.strptime(stamp[:19], EXIF_FORMAT)
        except ValueError:
            when = None
        sub = _exif_text(tags, "EXIF SubSecTimeOriginal")
        if when is not None and sub and sub.isdigit():
            when = when + _dt.timedelta(seconds=float("0." + sub))
    offset = _exif_text(tags, "EXIF OffsetTimeOriginal", "EXIF OffsetTime")
    m = EXIF_OFFSET.match(offset or "")
    return when, (f"{m.group(1)}{m.group(2)}:{m.group(3)}" if m else None)


def _frame_files(path: str | Path) -> list[Path]:
    """A photo file, or a bracket folder's frames (sorted; hidden files left out)."""
    p = Path(path)
    return [p] if p.is_file() else sorted(q for q in p.iterdir() if q.is_file() and not q.name.startswith("."))


def exif_stamps(path: str | Path) -> list[tuple[_dt.datetime, str | None]]:
    """:func:`exif_time` of a photo, or of every frame of a bracket folder that has one."""
    return [s for s in (exif_time(q) for q in _frame_files(path)) if s[0] is not None]


def _gps_degrees(tag) -> float | None:
    try:
        d, m, sec = (float(v) for v in tag.values[:3])
    except (TypeError, ValueError, ZeroDivisionError, AttributeError):
        return None
    return d + m / 60.0 + sec / 3600.0


def exif_location(path: str | Path) -> tuple[float, float, float | None] | None:
    """(latitude [deg N], longitude [deg E], altitude [m] or None) from a photo's EXIF GPS tags (GPSLatitude and
    its Ref, GPSLongitude and its Ref, GPSAltitude and GPSAltitudeRef 1 = below sea level), or from a bracket's first
    frame that has them; None without them (or with a position of exactly 0, 0: an unset receiver)."""
    for q in _frame_files(path):
        tags = exif_tags(q)
        if "GPS GPSLatitude" not in tags or "GPS GPSLongitude" not in tags:
            continue
        lat, lon = _gps_degrees(tags["GPS GPSLatitude"]), _gps_degrees(tags["GPS GPSLongitude"])
        if lat is None or lon is None or (lat == 0 and lon == 0) or lat > 90 or lon > 180:
            continue
        if (_exif_text(tags, "GPS GPSLatitudeRef") or "N").upper().startswith("S"):
            lat = -lat
        if (_exif_text(tags, "GPS GPSLongitudeRef") or "E").upper().startswith("W"):
            lon = -lon
        alt = None
        try:
            alt = float(tags["GPS GPSAltitude"].values[0])
            ref = tags.get("GPS GPSAltitudeRef")
            if ref is not None and int(np.ravel(ref.values)[0]) == 1:
                alt = -alt
        except (KeyError, TypeError, ValueError, ZeroDivisionError, AttributeError, IndexError):
            pass
        return lat, lon, (alt if alt is not None and math.isfinite(alt) else None)
    return None


def _read_exif(path: str) -> dict:
    """EXIF facts of a file (None where absent): exposure_s, f_number, iso, datetime_original, camera_make/model;
    orientation (1 where absent)."""
    out = {"exposure_s": None, "f_number": None, "iso": None, "datetime_original": None,
           "camera_make": None, "camera_model": None, "color_space": None, "interop_index": None, "orientation": 1}
    tags = exif_tags(path)

    def first(*names):
        for n in names:
            if n in tags:
                return tags[n]
        return None

    out["exposure_s"] = _exif_number(first("EXIF ExposureTime", "Image ExposureTime"))
    out["f_number"] = _exif_number(first("EXIF FNumber", "Image FNumber"))
    out["iso"] = _exif_number(first("EXIF ISOSpeedRatings", "Image ISOSpeedRatings",
                                    "EXIF PhotographicSensitivity", "Image PhotographicSensitivity"))
    for key, names in (("datetime_original", ("EXIF DateTimeOriginal", "Image DateTimeOriginal", "Image DateTime")),
                       ("camera_make", ("Image Make",)), ("camera_model", ("Image Model",))):
        t = first(*names)
        if t is not None:
            s = str(t.printable if hasattr(t, "printable") else t).strip().strip("\x00").strip()
            out[key] = s or None
    cs = first("EXIF ColorSpace")
    if cs is not None and getattr(cs, "values", None):
        out["color_space"] = int(cs.values[0])
    out["interop_index"] = _exif_text(tags, "Interoperability InteroperabilityIndex")
    out["orientation"] = exif_orientation(tags)
    return out


def _exif_relative_exposure(ex: dict, use_iso_n: bool) -> float:
    e = ex["exposure_s"]
    if use_iso_n:
        e = e * ex["iso"] / ex["f_number"] ** 2
    return float(e)


# --------------------------------------------------------------------------
# Frames
# --------------------------------------------------------------------------

@dataclasses.dataclass
class _Frame:
    """One LDR or RAW frame: integer codes and what they mean."""

    path: str
    kind: str                  # "jpeg", "png", "tiff", "heif", "raw"
    codes: np.ndarray          # (H, W, 3) uint8/uint16
    max_code: int              # code of full scale
    levels: float              # quantisation steps per full scale
    code_noise: float          # extra code noise [steps]
    bit_depth: int
    high: np.ndarray           # (H, W, 3) bool
    low: np.ndarray            # (H, W, 3) bool
    valid: np.ndarray          # (H, W) bool
    exif: dict
    fixed_response: _Response | None = None   # RAW: linear, whatever is asked
    clip_code: float | None = None            # encoded clip threshold (LDR); None: the pixel's own value bounds it
    black_code: float | None = None
    info: dict = dataclasses.field(default_factory=dict)
    mono: bool = False                        # a grey image: its one channel in all three of ``codes``
    icc: IccProfile | None = None             # the embedded matrix/TRC profile, if any
    icc_problem: str | None = None            # why an embedded profile is not used
    icc_declared: str | None = None           # no profile: what in EXIF declares Adobe RGB (_exif_colour_space)

    @property
    def shape(self) -> tuple[int, int]:
        return self.codes.shape[:2]


def _one_line(e: BaseException) -> str:
    s = str(e).strip().splitlines()
    return f"{type(e).__name__}: {s[0]}" if s else type(e).__name__


def _kind(ext: str) -> str:
    if ext in (".jpg", ".jpeg"):
        return "jpeg"
    if ext == ".png":
        return "png"
    if ext in (".tif", ".tiff"):
        return "tiff"
    if ext in HEIF_EXTENSIONS:
        return "heif"
    if ext in RAW_EXTENSIONS:
        return "raw"
    if ext in HDR_EXTENSIONS:
        return "hdr"
    return "exr"


def _open_heif(path: str, **kw):
    try:
        import pillow_heif
    except ImportError:  # optional: its wheels bundle an HEVC decoder
        raise PhotoError(f"photo {path}: reading HEIF/HEIC needs the 'pillow-heif' package "
                         "(pip install 'skyfit[heic]'), or save the photo as JPEG or 16-bit TIFF") from None
    try:
        return pillow_heif.open_heif(path, **kw)
    except Exception as e:  # noqa: BLE001 - libheif's errors vary
        raise PhotoError(f"photo {path}: cannot read the image ({_one_line(e)})") from None


def _read_heif(path: str) -> tuple[np.ndarray, int]:
    """A HEIF/HEIC image's codes and bit depth: 8-bit as uint8; 10 or 12 bits (phones' HDR, Fuji's .hif) as uint16
    codes on their own scale (pillow-heif shifts them to the top bits; shifted back here)."""
    f = _open_heif(path, convert_hdr_to_8bit=False)
    bits = int(f.info.get("bit_depth") or 8)
    arr = np.asarray(f)
    if arr.dtype == np.uint16 and 8 < bits < 16:
        arr = arr >> (16 - bits)
    return arr, bits


def _heif_extras(path: str) -> tuple[bytes | None, bytes | None]:
    """(EXIF bytes (TIFF-structured), ICC profile bytes) of a HEIF file's primary image, as pillow-heif gives them."""
    f = _open_heif(path)
    exif = f.info.get("exif")
    if exif and exif[:6] == b"Exif\0\0":
        exif = exif[6:]
    return exif or None, f.info.get("icc_profile") or None


def _read_ldr_array(path: str, kind: str) -> np.ndarray:
    if kind == "png" and png_bit_depth(path) == 16:
        try:
            return read_png16(path)  # Pillow would give 8 bits of a 16-bit RGB PNG
        except ValueError as e:  # its message names the file already
            raise PhotoError(str(e)) from None
    try:
        if kind == "tiff":
            import tifffile  # imageio's TIFF plugin returns every page stacked: read the first page only

            with tifffile.TiffFile(path) as tf:
                cmyk = int(tf.pages[0].photometric) == 5  # SEPARATED (TIFF 6.0, PhotometricInterpretation)
                arr = tf.pages[0].asarray()
        else:
            import imageio.v3 as iio
            from PIL import Image

            with Image.open(path) as im:  # the header only: imageio's arrays do not say CMYK from RGBA
                cmyk = im.mode == "CMYK"
            arr = iio.imread(path, index=0, plugin="pillow")  # not the legacy plugins imageio would also try
    except Exception as e:  # noqa: BLE001 - reader errors vary by plugin
        raise PhotoError(f"photo {path}: cannot read the image ({_one_line(e)})") from None
    if cmyk:  # four channels that are not RGB + alpha: read as such, the ink channel became a mask of nothing valid
        raise PhotoError(f"photo {path}: a CMYK image (print separations) is not a camera's RGB; "
                         "give the camera's own file (JPEG/PNG/TIFF in RGB, RAW)")
    return np.asarray(arr)


def _check_channels(path: str, arr: np.ndarray) -> bool:
    """Whether ``arr`` is a grey image (H, W), (H, W, 1) or grey + alpha (H, W, 2); RGB or RGBA else; PhotoError
    for anything else."""
    if arr.ndim == 2 or (arr.ndim == 3 and arr.shape[-1] in (1, 2)):
        return True
    if arr.ndim != 3 or arr.shape[-1] not in (3, 4):
        what = f"{arr.shape[-1]} channels" if arr.ndim == 3 else f"shape {arr.shape}"
        raise PhotoError(f"photo {path}: expected a grey, grey + alpha, RGB or RGBA image, got {what}")
    return False


def _as_rgba(arr: np.ndarray) -> np.ndarray:
    """A grey (+ alpha) image as RGB(A) of three equal channels: the rest of the path reads three channels, and
    a monochrome photo's fit counts them as one (:func:`skyfit.fit.photo.block_observation`)."""
    g = arr if arr.ndim == 3 else arr[..., None]
    return np.concatenate([np.repeat(g[..., :1], 3, -1), g[..., 1:]], -1)


def _ldr_frame(path: str, kind: str, arr: np.ndarray, exif: dict, bits: int | None = None) -> _Frame:
    """A frame of integer codes; ``bits``: their depth where the type's is wider (10- or 12-bit HEIF in uint16)."""
    mono = _check_channels(path, arr)
    if mono:
        arr = _as_rgba(arr)
    if arr.dtype == np.uint8:
        bits = 8
    elif arr.dtype == np.uint16:
        bits = bits if bits is not None and 8 < bits <= 16 else 16
    else:
        raise PhotoError(f"photo {path}: unsupported bit depth ({arr.dtype}); expected 8- or 16-bit integer channels")
    max_code = 2**bits - 1
    codes = np.ascontiguousarray(arr[..., :3])
    valid = arr[..., 3] == max_code if arr.shape[-1] == 4 else np.ones(arr.shape[:2], bool)
    # Compare codes, not floats, as photo_io does: code 254 of 255 is >= 254/255 whatever the rounding.
    high = codes >= DEFAULT_CLIP_LEVEL * max_code - 1e-6
    low = codes <= DEFAULT_BLACK_LEVEL * max_code + 1e-6
    return _Frame(path=path, kind=kind, codes=codes, max_code=max_code, levels=float(max_code),
                  code_noise=JPEG_CODE_NOISE if kind in ("jpeg", "heif") else 0.0, bit_depth=bits,
                  high=high, low=low, valid=valid, exif=exif,
                  clip_code=DEFAULT_CLIP_LEVEL, black_code=DEFAULT_BLACK_LEVEL, mono=mono)


def _raw_frame(path: str, exif: dict) -> _Frame:
    try:
        import rawpy
    except ImportError:  # optional heavy dependency: fail at the point of use
        raise PhotoError(f"photo {path}: reading RAW files needs the 'rawpy' package (pip install rawpy)") from None
    from scipy import ndimage

    try:
        with rawpy.imread(path) as raw:
            black = np.asarray(raw.black_level_per_channel, np.float64)
            white = float(raw.white_level)
            sites = raw.raw_image_visible
            colours = raw.raw_colors_visible
            # raw_image_visible is a view into LibRaw's memory: use it before the file is closed.
            dark_sites = int((sites <= black[np.clip(colours, 0, len(black) - 1)]).sum())
            clipped_sites = sites >= white
            cam_wb = [float(v) for v in raw.camera_whitebalance]
            day_wb = [float(v) for v in raw.daylight_whitebalance]
            out = raw.postprocess(gamma=(1, 1), no_auto_bright=True, output_bps=16, use_camera_wb=True, user_flip=0)
            bits = int(np.ceil(np.log2(max(white, 2.0))))
            desc = raw.color_desc.decode("ascii", "replace") if isinstance(raw.color_desc, bytes) else str(raw.color_desc)
    except PhotoError:
        raise
    except Exception as e:  # noqa: BLE001 - LibRaw raises its own error classes for every failure
        raise PhotoError(f"photo {path}: cannot read the RAW file ({_one_line(e)})") from None
    out = np.asarray(out)
    if out.ndim != 3 or out.shape[-1] != 3 or out.dtype != np.uint16:
        raise PhotoError(f"photo {path}: LibRaw gave an image of shape {out.shape} and type {out.dtype}, not RGB 16-bit")
    span = float(np.max(white - black))
    if not span > 0:
        raise PhotoError(f"photo {path}: white level {white:g} is not above the black level {black.max():g}")
    # Demosaicing spreads a clipped photosite into its neighbours (AHD reads a 5x5 window): censor those
    # pixels in every channel, as the colour matrix mixes channels too.
    near_clip = ndimage.maximum_filter(clipped_sites.astype(np.uint8), size=5).astype(bool)
    notes = []
    if near_clip.shape != out.shape[:2]:
        rows = (np.arange(out.shape[0]) * near_clip.shape[0]) // out.shape[0]
        cols = (np.arange(out.shape[1]) * near_clip.shape[1]) // out.shape[1]
        near_clip = near_clip[np.ix_(rows, cols)]
        notes.append(f"{os.path.basename(path)}: LibRaw's image ({out.shape[1]}x{out.shape[0]}) differs in size from "
                     "the sensor's; the clipping mask was resampled to it")
    high = near_clip[..., None] | (out >= 65535)
    # At or below the black level (or below zero after the colour matrix); not beside a clipped photosite,
    # where a zero is a demosaicing artefact of the clipped neighbour, already censored high.
    low = (out == 0) & ~near_clip[..., None]
    if any(v > 0 for v in cam_wb[:3]):
        wb = {"source": "camera (as shot)", "multipliers": cam_wb}
    else:
        wb = {"source": "daylight (the file has no as-shot white balance)", "multipliers": day_wb}
    info = {"white_balance": wb, "black_level": [float(b) for b in black], "white_level": white,
            "raw_bit_depth": bits, "raw_colors": desc, "clipped_photosites": int(clipped_sites.sum()),
            "dark_photosites": dark_sites, "output": "linear sRGB primaries (LibRaw), 16 bit"}
    f = _Frame(path=path, kind="raw", codes=out, max_code=65535, levels=span, code_noise=0.0, bit_depth=bits,
               high=high, low=low, valid=np.ones(out.shape[:2], bool), exif=exif,
               fixed_response=_Response("linear"), clip_code=None, black_code=1.0 / span, info=info)
    f.info["notes"] = notes
    return f


EXIF_ORIENTATION_NAMES = {2: "mirrored left-right", 3: "turned 180 deg", 4: "mirrored top-bottom",
                           5: "mirrored about the main diagonal", 6: "turned 90 deg clockwise",
                           7: "mirrored about the anti-diagonal", 8: "turned 90 deg counter-clockwise"}
"""EXIF Orientation values (TIFF 6.0 tag 274; CIPA DC-008 EXIF 2.32, 4.6.4 A) other than 1, by what displaying the
stored image takes."""


def exif_orientation(exif: dict) -> int:
    """The EXIF Orientation (1-8) of a file's tags (:func:`exif_tags`); 1 where absent or out of range."""
    tag = exif.get("Image Orientation")
    try:
        v = int(tag.values[0] if isinstance(tag.values, (list, tuple)) else tag.values)
    except (AttributeError, TypeError, ValueError, IndexError):
        return 1
    return v if 1 <= v <= 8 else 1


def oriented(a: np.ndarray, orientation: int) -> np.ndarray:
    """``a`` (H, W, ...) as displayed under EXIF ``orientation``: what Pillow's ``ImageOps.exif_transpose`` does to an
    image, on an array. By hand because a frame is numpy arrays (codes, censoring masks, validity) and 16-bit PNGs
    and TIFFs do not pass through Pillow; tests/test_photo_read.py checks all eight against Pillow."""
    if orientation == 2:
        a = a[:, ::-1]
    elif orientation == 3:
        a = a[::-1, ::-1]
    elif orientation == 4:
        a = a[::-1]
    elif orientation == 5:
        a = a.swapaxes(0, 1)
    elif orientation == 6:
        a = a.swapaxes(0, 1)[:, ::-1]
    elif orientation == 7:
        a = a.swapaxes(0, 1)[::-1, ::-1]
    elif orientation == 8:
        a = a.swapaxes(0, 1)[::-1]
    return np.ascontiguousarray(a)


def _display_orientation(frame: _Frame) -> int:
    """The EXIF Orientation that reading ``frame`` applies (:func:`_displayed`): the file's, 1 for HEIF (libheif turned
    it in decoding)."""
    return 1 if frame.kind == "heif" else frame.exif.get("orientation", 1)


def _displayed(frame: _Frame) -> _Frame:
    """``frame`` turned as its EXIF Orientation says it is displayed, so that the fit, ``--mask``, RESULT.png and
    every pixel position in RESULT.json read the photo as its owner sees it in a viewer (a phone held up writes
    6 or 8). Not for HEIF: libheif applies the file's own transforms (irot/imir) in decoding, and its EXIF keeps
    the original value."""
    o = _display_orientation(frame)
    if o != 1:
        for name in ("codes", "high", "low", "valid"):
            setattr(frame, name, oriented(getattr(frame, name), o))
        frame.info.setdefault("notes", []).append(
            f"{os.path.basename(frame.path)}: read as displayed, {EXIF_ORIENTATION_NAMES[o]} (EXIF Orientation {o}); "
            "pixel positions, --mask and RESULT.png are of the image so turned")
    return frame


def _read_frame(path: str, kind: str) -> _Frame:
    exif = _read_exif(path)
    if kind == "raw":
        return _displayed(_raw_frame(path, exif))
    arr, bits = _read_heif(path) if kind == "heif" else (_read_ldr_array(path, kind), None)
    if kind == "tiff" and arr.dtype.kind == "f":
        raise PhotoError(f"photo {path}: a floating-point TIFF is not read as a photo frame; "
                         "save linear HDR data as EXR or Radiance .hdr")
    frame = _displayed(_ldr_frame(path, kind, arr, exif, bits))
    frame.icc, frame.icc_problem = _embedded_icc(path, kind, frame.mono)
    if frame.icc is None and frame.icc_problem is None and not frame.mono:
        frame.icc_declared, frame.icc_problem = _exif_colour_space(path, exif)
        if frame.icc_declared is not None:
            frame.icc = _adobe_rgb_profile()
    return frame


ADOBE_RGB = "Adobe RGB (1998)"
EXIF_UNCALIBRATED = 0xFFFF


@functools.lru_cache(maxsize=1)
def _adobe_rgb_profile() -> IccProfile:
    """Adobe RGB (1998)'s profile (:func:`skyfit.camera.icc.profile_for`), built once for every frame that declares it."""
    from ..camera.icc import profile_for

    return parse_icc(profile_for(ADOBE_RGB))


def _exif_colour_space(path: str, exif: dict) -> tuple[str | None, str | None]:
    """(what declares Adobe RGB, why the space is unknown) of a frame without a profile, from EXIF alone, as Canon's
    and other cameras' JPEGs in Adobe RGB mode declare it: ColorSpace "uncalibrated" (0xFFFF) with the
    interoperability index "R03" (DCF 2.0's option colour space), or a DCF option file name ("_" first, e.g.
    ``_MG_1234.JPG``); ColorSpace 2 (Adobe RGB, written by some software though not in the EXIF standard).
    Uncalibrated with neither: not sRGB, space unknown; read as sRGB and say so."""
    cs = exif.get("color_space")
    if cs == 2:
        return "ColorSpace 2", None
    if cs != EXIF_UNCALIBRATED:
        return None, None
    if (exif.get("interop_index") or "").upper() == "R03":
        return "interoperability index R03", None
    if os.path.basename(path).startswith("_"):
        return "a DCF option file name", None
    return None, ("its EXIF colour space is 'uncalibrated' (not sRGB) with no ICC profile and no interoperability "
                  "index R03 (Adobe RGB): the space is unknown; read as sRGB (embed the profile, or convert to sRGB)")


def _embedded_icc(path: str, kind: str, mono: bool) -> tuple[IccProfile | None, str | None]:
    """The photo's embedded ICC profile (Pillow's ``icc_profile`` of a JPEG or PNG, a TIFF's InterColorProfile tag
    34675), and why it is not used where it cannot be: (None, None) without one."""
    try:
        if kind == "tiff":
            import tifffile

            with tifffile.TiffFile(path) as tf:
                tag = tf.pages[0].tags.get(34675)
                data = None if tag is None else bytes(tag.value)
        elif kind == "heif":
            data = _heif_extras(path)[1]
        else:
            from PIL import Image

            with Image.open(path) as im:
                data = im.info.get("icc_profile")
    except Exception:  # noqa: BLE001 - the pixels were read; a profile the reader cannot reach is as none
        return None, None
    if not data:
        return None, None
    try:
        prof = parse_icc(bytes(data))
    except IccError as e:
        return None, f"its ICC profile cannot be read ({e}); read as sRGB"
    if prof is None:
        return None, "its ICC profile is not a matrix/TRC profile (lookup tables are not read); read as sRGB"
    if prof.grey != mono:
        return None, (f"its ICC profile {prof.description!r} is for {'grey' if prof.grey else 'colour'} images, the "
                      f"image is {'grey' if mono else 'colour'}; read as sRGB")
    return prof, None


def _icc_response(prof: IccProfile) -> _Response:
    """The decoding of a profile's tone curves: sRGB's, a power law, linear, or a table of 4097 codes."""
    c = np.linspace(0.0, 1.0, 4097)
    curves = prof.curves if not prof.same_curves() else prof.curves[:1]
    values = np.stack([k(c) for k in curves], 1)
    if values.shape[1] == 1:
        if curves[0].is_srgb():
            return _Response("srgb")
        if np.max(np.abs(values[:, 0] - c)) < ICC_SRGB_TOLERANCE:
            return _Response("linear")
        g = curves[0].gamma
        if g is not None:
            return _Response(_gamma_name(g), g)
    top = values[-1]
    if not (top > 0).all():
        return _Response("srgb")
    tab = table_response(c, np.maximum.accumulate(np.maximum(values, 0.0), axis=0) / top,
                         info={"icc_profile": prof.description})
    return _Response(f"icc:{prof.description or 'embedded'}", table=tab)


def _icc_meta(frame: _Frame, resp: _Response, source: str, notes: list[str]) -> dict:
    """RESULT.json's ``photo.icc`` and a note, for a frame with an embedded profile (empty without one); ``resp`` and
    ``source``: how the codes were decoded."""
    if frame.icc_problem:
        notes.append(frame.icc_problem)
    prof = frame.icc
    if prof is None:
        return {}
    srgb = prof.is_srgb()
    out = {"description": prof.description, "srgb": srgb, "source": "embedded" if frame.icc_declared is None else "exif",
           "rgb_from_xyz": None if prof.grey or srgb else prof.rgb_from_xyz().tolist()}
    if not srgb:
        how = "its tone curves decode the codes" if source == "icc" else f"the codes are decoded as {resp.name} ({source})"
        colour = "" if prof.grey else "; its primaries give the channels' colour (the fit's default camera)"
        if frame.icc_declared is not None:
            how = "its power law 563/256 decodes the codes" if source == "icc" else how
            notes.append(f"the photo has no ICC profile and its EXIF declares Adobe RGB (1998) ({frame.icc_declared}): "
                         f"{how}{colour}")
        else:
            notes.append(f"the photo carries the ICC profile {prof.description or '(unnamed)'!r}, not sRGB: {how}{colour}")
    return {"icc": out}


# --------------------------------------------------------------------------
# Per-frame linear values and variance (lookup tables over the integer codes)
# --------------------------------------------------------------------------

def _tables(frame: _Frame, response: _Response) -> tuple[np.ndarray, np.ndarray]:
    """(X, var_X) for every code 0..max_code of the frame under the response (module noise model), shape
    (max_code + 1,), or (max_code + 1, 3) for a per-channel response (read them with :func:`_lookup`)."""
    c = np.arange(frame.max_code + 1, dtype=np.float64) / frame.max_code
    if response.per_channel:
        c = c[:, None]
    x = response.decode(c)
    slope = response.slope(c)
    # quantisation: one code step of the frame is 1/levels of full scale in c for LDR; for RAW (linear) one DN.
    step = 1.0 / frame.levels
    var = x / SHOT_COUNT_FULL_SCALE + slope**2 * step**2 * (1.0 / 12.0 + frame.code_noise**2) + NOISE_FLOOR**2
    return x, var


def _lookup(table: np.ndarray, codes: np.ndarray) -> np.ndarray:
    """Values of a :func:`_tables` table at integer codes of shape (..., 3)."""
    return table[codes] if table.ndim == 1 else table[codes, _RGB]


def _subsample_step(shape: tuple[int, int]) -> int:
    return max(1, int(math.ceil(math.sqrt(shape[0] * shape[1] / MAX_SAMPLES))))


# --------------------------------------------------------------------------
# Bracket statistics: response, exposure ratios, scene check
# --------------------------------------------------------------------------

def _pair_grid(a: _Frame, b: _Frame, step: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Encoded values of both frames on the subsampled grid, (h, w, 3) each, and where neither is clipped, black or
    invalid (h, w, 3)."""
    ca = a.codes[::step, ::step].astype(np.float64) / a.max_code
    cb = b.codes[::step, ::step].astype(np.float64) / b.max_code
    ok = (~a.high[::step, ::step] & ~b.high[::step, ::step] & ~a.low[::step, ::step] & ~b.low[::step, ::step]
          & (a.valid & b.valid)[::step, ::step, None])
    return ca, cb, ok


def _pair_samples(a: _Frame, b: _Frame, step: int, lo: float, hi: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Encoded values (n,) of channels well exposed in both frames (subsampled grid), and their channel (n,)."""
    ca, cb, ok = _pair_grid(a, b, step)
    ok &= (ca >= lo) & (ca <= hi) & (cb >= lo) & (cb <= hi)
    return ca[ok], cb[ok], np.broadcast_to(_RGB, ok.shape)[ok]


def _bin_medians(s: np.ndarray, d: np.ndarray, n_bins: int) -> np.ndarray:
    """Median of d in n_bins equal-count bins of s."""
    order = np.argsort(s, kind="stable")
    return np.array([np.median(chunk) for chunk in np.array_split(d[order], n_bins)])


def _response_score(pairs, response: _Response, log_k) -> tuple[float, list]:
    """RMS relative deviation of the bin medians of the log ratio from the pair's log ratio (module docstring), each
    pair's bins weighted by the pair's samples: a pair of the darkest frames shares a few hundred noisy, quantised
    values where the next shares 10^5, and unweighted its bins (deviations of -100 % to +200 %) outvoted the well
    exposed pairs' and chose a power law for an sRGB bracket (held-out synthetic case 5, docs/photos.md)."""
    resid, weights, medians = [], [], []
    for (ca, cb), lk in zip(pairs, log_k):
        la = np.log(np.maximum(response.decode(ca), 1e-300))
        lb = np.log(np.maximum(response.decode(cb), 1e-300))
        d = lb - la
        n_bins = int(min(16, max(4, d.size // 100)))
        med = _bin_medians(0.5 * (la + lb), d, n_bins)
        m = lk if lk is not None else float(np.median(d))
        medians.append((med, m))
        if abs(m) < 0.05:  # equal exposures: the pair says nothing about the response
            continue
        resid.append(med / m - 1.0)
        weights.append(np.full(med.size, d.size / med.size))
    if not resid:
        return float("nan"), medians
    r, w = np.concatenate(resid), np.concatenate(weights)
    return float(np.sqrt(np.sum(w * r**2) / np.sum(w))), medians


def _estimate_response(frames: list[_Frame], order: list[int], rel_exp, step: int, notes: list) -> tuple[_Response, dict]:
    """Choose the response of a bracket's frames (module docstring); returns it and its scores."""
    pairs, log_k = [], []
    for i, j in zip(order[:-1], order[1:]):
        ca, cb, _ = _pair_samples(frames[i], frames[j], step, 0.02, 0.94)
        if ca.size < MIN_RESPONSE_SAMPLES:
            continue
        pairs.append((ca, cb))
        log_k.append(None if rel_exp is None else math.log(rel_exp[j] / rel_exp[i]))
    if not pairs or all(lk is not None and abs(lk) < 0.05 for lk in log_k):
        notes.append("the camera response could not be estimated (too few pixels well exposed in two frames "
                     "of different exposure); assumed sRGB")
        return _Response("srgb"), {"method": "fallback"}
    lin, _ = _response_score(pairs, _Response("linear"), log_k)
    srgb, _ = _response_score(pairs, _Response("srgb"), log_k)
    scores = {"linear": lin, "srgb": srgb}
    info = {"method": "ratio constancy" + (" with known exposure ratios" if rel_exp is not None else "")}
    if math.isnan(lin) or math.isnan(srgb):
        notes.append("the camera response could not be estimated (no pair of frames differs in exposure); assumed sRGB")
        return _Response("srgb"), {"method": "fallback"}
    best_fixed = _Response("linear") if lin < RESPONSE_MARGIN * srgb else _Response("srgb")
    if rel_exp is None:
        info["scores"] = scores
        if best_fixed.name == "srgb":
            return best_fixed, info
        # A power law fits best; its exponent is not identifiable without exposure times.
        bits = max(f.bit_depth for f in frames)
        chosen = _Response(_gamma_name(2.2), 2.2) if bits <= 8 else _Response("linear")
        notes.append(f"the frames fit a power-law response better than sRGB, but without exposure times its "
                     f"exponent cannot be known (Grossberg & Nayar 2003); assumed {chosen.name} for {bits}-bit frames: "
                     "give exposures or a response to be sure")
        return chosen, info
    # Known ratios: fit X = c^G in closed form, minimising sum (G m_i / L_i - 1)^2 over bins.
    num = den = 0.0
    for (ca, cb), lk in zip(pairs, log_k):
        if abs(lk) < 0.05:
            continue
        la, lb = np.log(ca), np.log(cb)
        n_bins = int(min(16, max(4, la.size // 100)))
        q = _bin_medians(0.5 * (la + lb), lb - la, n_bins) / lk
        num += float(np.sum(q))
        den += float(np.sum(q**2))
    g = num / den if den > 0 else float("nan")
    if math.isfinite(g) and 0.2 <= g <= 5.0:
        gam = _Response(_gamma_name(g), round(g, 2))
        scores[gam.name] = _response_score(pairs, gam, log_k)[0]
        info["gamma_fit"] = g
        info["scores"] = scores
        if abs(g - 1.0) >= 0.03 and scores[gam.name] < RESPONSE_MARGIN * min(lin, srgb):
            return gam, info
    info["scores"] = scores
    return best_fixed, info


def _log_ratio_samples(a: _Frame, b: _Frame, ra: _Response, rb: _Response, step: int, lo: float, hi: float) -> np.ndarray:
    ca, cb, ch = _pair_samples(a, b, step, lo, hi)
    return np.log(np.maximum(rb.decode(cb, ch), 1e-300)) - np.log(np.maximum(ra.decode(ca, ch), 1e-300))


RATIO_ITERATIONS: int = 3
"""Passes of :func:`_exposure_log_ratio`'s selection by the pair's mean log value."""


def _exposure_log_ratio(a: _Frame, b: _Frame, ra: _Response, rb: _Response, step: int) -> tuple[float, int]:
    """(ln of frame b's exposure over frame a's, the number of values well exposed in both frames), starting from the
    median log ratio over those values.

    Selecting the values well exposed in *each* frame biases the ratio: in the darker frame the values just above the
    floor are there because their noise lifted them, so b / a comes out low. In a realistic camera's dark frames
    (15-50 % noise per value) the synthetic suites' pairs of the two darkest frames came out 10-45 % low (held-out case
    5: 2.57 for a true 4.08, 3.23 for 3.77), and the aureole they measure was read too faint. Here the values are
    selected by their pair's mean log value on a's scale, (ln a + ln b - ln k) / 2, within the well-exposed range
    (k the ratio so far; a few passes, :data:`RATIO_ITERATIONS`): for equal noise in ln a and ln b that mean is
    uncorrelated with ln b - ln a, the same argument as the response's binning (module docstring). On the six
    brackets of the suites without exposure times the pairs' median |error| went 0.87 -> 0.52 % and the worst 58 -> 24 %
    (docs/photos.md, "The factor follows g"). Written here: no library estimates exposure ratios from two frames."""
    ca, cb, base = _pair_grid(a, b, step)
    ch = np.broadcast_to(_RGB, ca.shape)

    def log_decoded(r: _Response, c: np.ndarray, channel: np.ndarray) -> np.ndarray:
        return np.log(np.maximum(r.decode(c, channel), 1e-300))

    la, lb = log_decoded(ra, ca, ch), log_decoded(rb, cb, ch)
    lo_c, hi_c = WELL_EXPOSED
    # the well-exposed range in linear values, per channel (a three-curve table decodes each with its own), (3,)
    lo, hi = log_decoded(ra, np.full(3, lo_c), _RGB), log_decoded(rb, np.full(3, hi_c), _RGB)
    both = base & (ca >= lo_c) & (ca <= hi_c) & (cb >= lo_c) & (cb <= hi_c)
    n = int(both.sum())
    if n == 0:
        return math.nan, 0
    k = float(np.median((lb - la)[both]))
    for _ in range(RATIO_ITERATIONS):
        m = 0.5 * (la + lb - k)
        ok = base & (m >= lo) & (m + k <= hi)
        if int(ok.sum()) < MIN_OVERLAP:
            break
        k = float(np.median((lb - la)[ok]))
    return k, n


SCENE_BLOCK: int = 8
"""Side of the blocks whose median log ratio the scene check compares [px]: a different scene differs over
large areas, noise (shot, JPEG, demosaicing, a colour matrix: 15-25 % per pixel in dark frames of a realistic
camera) averages out over a block."""
SCENE_MIN_BLOCKS: int = 12
"""Fewest blocks well exposed in both frames for the scene check to judge a pair by blocks."""
SCENE_PIXEL_MIN: int = 2000
"""Fewest channel values well exposed in both frames for the per-pixel check (a few dozen near the sun's glare
scatter widely in any bracket)."""
SCENE_PIXEL_SPREAD_MAX: float = 0.7
"""Largest robust spread of the per-pixel log ratio [1] (a factor 2): a realistic camera's dark frames scatter
by 15-50 % per pixel (docs/photos.md), unrelated pixels (a shuffled or another scene) by a factor 3 or more."""


def _block_log_ratios(a: _Frame, b: _Frame, ra: _Response, rb: _Response, lo: float, hi: float) -> np.ndarray:
    """Median log ratio b/a of each SCENE_BLOCK x SCENE_BLOCK block with at least a quarter of its channel values
    well exposed in both frames and away from clipping (the glare of a clipped pixel spreads by a few px through
    demosaicing and JPEG), shape (n_blocks,)."""
    from scipy.ndimage import binary_dilation  # here: scipy loads in ~0.5 s, only brackets need it

    def per_code(f: _Frame, r: _Response) -> tuple[np.ndarray, np.ndarray]:
        # ln X and "well exposed" for every code (the values code / max_code would give), read by code: a 16 MP frame
        # is decoded 256 (or 65536) times instead of 48 million
        c = np.arange(f.max_code + 1, dtype=np.float64) / f.max_code
        x = r.decode(c[:, None] if r.per_channel else c)
        return np.log(np.maximum(x, 1e-300)), (c >= lo) & (c <= hi)

    (la, wa), (lb, wb) = per_code(a, ra), per_code(b, rb)
    clipped = binary_dilation((a.high | b.high).any(-1), iterations=3)
    ok = wa[a.codes] & wb[b.codes] & ~a.low & ~b.low & (a.valid & b.valid & ~clipped)[..., None]
    d = np.where(ok, _lookup(lb, b.codes) - _lookup(la, a.codes), np.nan)
    k = SCENE_BLOCK
    nh, nw = d.shape[0] // k, d.shape[1] // k
    if nh == 0 or nw == 0:  # a frame smaller than one block: the per-pixel check alone judges it
        return np.empty(0)
    blocks = block_view(d, k, nh, nw).reshape(nh, nw, -1)
    enough = np.isfinite(blocks).sum(-1) >= (k * k * 3) // 4
    if not enough.any():
        return np.empty(0)
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN blocks are left out just below
        med = np.nanmedian(blocks[enough], axis=-1)
    return med[np.isfinite(med)]


# --------------------------------------------------------------------------
# Merging
# --------------------------------------------------------------------------

MERGE_ROWS: int = 256
"""Rows merged at a time, which bounds the temporaries of a large photo to a few row blocks."""


def _merge(frames: list[_Frame], responses: list[_Response], rel_exp: list[float]):
    """Inverse-variance merge of the frames (module docstring).

    Returns rgb, variance, censored_high, censored_low (H, W, 3), valid (H, W), darkest (H, W, 3),
    darkest_saturated (H, W), as in :class:`LinearPhoto`.
    """
    h, w = frames[0].shape
    rgb = np.empty((h, w, 3))
    variance = np.empty((h, w, 3))
    high = np.empty((h, w, 3), bool)
    low = np.empty((h, w, 3), bool)
    valid = np.ones((h, w), bool)
    for f in frames:
        valid &= f.valid
    dark = int(np.argmin(rel_exp))
    darkest = np.empty((h, w, 3))
    darkest_sat = frames[dark].high.any(-1)
    tables = [_tables(f, r) for f, r in zip(frames, responses)]
    # Bounds of a censored channel: the decoded clip / black threshold (LDR); for RAW the pixel's own value
    # (after LibRaw's scaling) bounds it from below and one DN from above.
    # (3,) per frame: a per-channel response has a threshold per channel.
    hi_thr = [None if f.clip_code is None else r.decode(np.full(3, f.clip_code)) for f, r in zip(frames, responses)]
    lo_thr = [f.black_code if f.kind == "raw" else r.decode(np.full(3, f.black_code)) for f, r in zip(frames, responses)]
    for r0 in range(0, h, MERGE_ROWS):
        rows = slice(r0, min(h, r0 + MERGE_ROWS))
        num = np.zeros((rows.stop - r0, w, 3))
        den = np.zeros_like(num)
        all_high = np.ones(num.shape, bool)
        all_low = np.ones(num.shape, bool)
        any_high = np.zeros(num.shape, bool)
        hi_bound = np.zeros_like(num)
        lo_bound = np.full_like(num, np.inf)
        for k, (f, (xt, vt), e) in enumerate(zip(frames, tables, rel_exp)):
            codes, fh, fl = f.codes[rows], f.high[rows], f.low[rows]
            x = _lookup(xt, codes) / e
            wgt = np.where(fh | fl, 0.0, e * e / _lookup(vt, codes))
            num += wgt * x
            den += wgt
            all_high &= fh
            all_low &= fl
            any_high |= fh
            hb = x if hi_thr[k] is None else hi_thr[k] / e
            hi_bound = np.where(fh, np.maximum(hi_bound, hb), hi_bound)
            lo_bound = np.where(fl, np.minimum(lo_bound, lo_thr[k] / e), lo_bound)
            if k == dark:
                darkest[rows] = x
        measured = den > 0
        safe = np.where(measured, den, 1.0)
        out = np.where(measured, num / safe, 0.0)
        hi_c = all_high & ~measured
        lo_c = all_low & ~measured
        # Neither measured nor censored (clipped in one frame, black in another): the lower bound, no weight.
        mixed = ~measured & ~hi_c & ~lo_c
        out = np.where(hi_c | (mixed & any_high), hi_bound, out)
        out = np.where(lo_c | (mixed & ~any_high), np.where(np.isfinite(lo_bound), lo_bound, 0.0), out)
        rgb[rows] = out
        variance[rows] = np.where(measured, 1.0 / safe, np.inf)
        high[rows] = hi_c
        low[rows] = lo_c
    return rgb, variance, high, low, valid, darkest, darkest_sat


# --------------------------------------------------------------------------
# Public API
# --------------------------------------------------------------------------

def _check_exposures(path: str, exposures, n: int) -> list[float] | None:
    if exposures is None:
        return None
    try:
        vals = [float(v) for v in exposures]
    except (TypeError, ValueError):
        raise PhotoError(f"photo {path}: exposures must be numbers, got {exposures!r}") from None
    if len(vals) != n:
        raise PhotoError(f"photo {path}: {len(vals)} exposure(s) given for {n} frame(s); give one per frame "
                         "in the folder's sorted file order")
    if not all(math.isfinite(v) and v > 0 for v in vals):
        raise PhotoError(f"photo {path}: exposures must be positive and finite, got {vals}")
    return vals


def _base_meta(fmt: str, bit_depth: int, exif: dict, monochrome: bool = False) -> dict:
    meta = {"format": fmt, "bit_depth": int(bit_depth), "monochrome": bool(monochrome), "notes": []}
    meta.update({k: exif.get(k) for k in ("exposure_s", "f_number", "iso", "datetime_original", "camera_make", "camera_model")})
    return meta


def _noise_meta(frames: list[_Frame]) -> dict:
    return {"model": "var_X = X/shot_count + (dX/dc)^2 (1/12 + code_noise^2)/levels^2 + floor^2; var(rgb) = var_X/e^2",
            "shot_count": SHOT_COUNT_FULL_SCALE, "code_noise": sorted({f.code_noise for f in frames}),
            "levels": sorted({f.levels for f in frames}), "floor": NOISE_FLOOR}


def _read_linear_image(path: str, kind: str, exposures, linear: bool, response) -> LinearPhoto:
    """A Radiance .hdr or an EXR without skyfit metadata: linear, relative noise, no censoring."""
    req, _ = _response_request(path, linear, response)
    notes = []
    if isinstance(req, _Response) and req.name != "linear":
        raise PhotoError(f"photo {path}: a {kind.upper()} image is linear; response {response!r} applies to JPEG/PNG/TIFF")
    if req in CALIBRATIONS:
        raise PhotoError(f"photo {path}: a {kind.upper()} image is linear; response {req!r} calibrates a bracket of "
                         "JPEG/PNG/TIFF frames")
    if req == "estimate":
        notes.append(f"a {kind.upper()} image is linear: the response is not estimated")
    exps = _check_exposures(path, exposures, 1)
    valid = None
    info: dict = {}
    mono = False
    if kind == "hdr":
        try:
            img, header = read_hdr(path)
        except HdrError as e:
            raise PhotoError(f"photo {path}: cannot read the Radiance file ({_one_line(e)})") from None
        img = img.astype(np.float64)
        if str(header.get("format", "")).endswith("xyze"):
            # CIE XYZ -> linear sRGB (IEC 61966-2-1 matrix, D65).
            m = np.array([[3.2406, -1.5372, -0.4986], [-0.9689, 1.8758, 0.0415], [0.0557, -0.2040, 1.0570]])
            img = img @ m.T
            notes.append("the Radiance file holds CIE XYZ; converted to linear sRGB primaries")
        info["hdr_exposure"] = float(header.get("exposure", 1.0))
        bits = 32
    else:
        try:
            chans, meta = read_exr(path)
        except ExrError as e:
            raise PhotoError(f"photo {path}: cannot read the EXR file ({_one_line(e)})") from None
        if meta:
            raise PhotoError(f"photo {path}: an EXR with skyfit metadata is a skyfit image, not a photo; "
                             "read it with skyfit's EXR observation reader")
        if all(c in chans for c in "RGB"):
            img = np.stack([chans[c] for c in "RGB"], -1).astype(np.float64)
        elif "Y" in chans:
            img = np.repeat(chans["Y"][..., None].astype(np.float64), 3, -1)
            mono = True
            notes.append("the EXR holds luminance Y only: a monochrome photo")
        else:
            raise PhotoError(f"photo {path}: an EXR needs R, G, B or Y channels, has {sorted(chans)}")
        if "A" in chans:
            valid = np.asarray(chans["A"]) >= 0.999
        bits = 32
    if img.ndim != 3 or img.shape[-1] != 3 or img.size == 0:
        raise PhotoError(f"photo {path}: expected an RGB image, got shape {img.shape}")
    bad = ~np.isfinite(img)
    if bad.any():
        raise PhotoError(f"photo {path}: {int(bad.sum())} value(s) are NaN or infinite")
    if (img < 0).any():
        raise PhotoError(f"photo {path}: {int((img < 0).sum())} negative value(s) (min {img.min():.3g}); "
                         "a photo's linear values must be >= 0")
    e = exps[0] if exps else 1.0
    rgb = img / e
    pos = rgb[rgb > 0]
    scale = float(np.percentile(pos, 99)) if pos.size else 1.0
    floor = HDR_FLOOR_FRACTION * scale
    variance = (HDR_RELATIVE_NOISE * rgb) ** 2 + floor**2
    h, w = rgb.shape[:2]
    meta = _base_meta(kind, bits, {}, mono)
    meta.update({"response": "linear", "response_source": "--linear" if linear else "default",
                 "frames": [{"path": path, "exposure_s": None, "f_number": None, "iso": None, "relative_exposure": e,
                             "exposure_source": "given" if exps else "unknown"}],
                 "noise": {"model": "sd = relative * x (+) floor", "relative": HDR_RELATIVE_NOISE, "floor": floor},
                 **info})
    meta["notes"] = notes
    return LinearPhoto(rgb=rgb, variance=variance, censored_high=np.zeros((h, w, 3), bool),
                       censored_low=np.zeros((h, w, 3), bool),
                       valid=np.ones((h, w), bool) if valid is None else valid,
                       darkest=rgb.copy(), darkest_saturated=np.zeros((h, w), bool), source=path, meta=meta)


def _frame_list_meta(frames, rel_exp, sources) -> list[dict]:
    return [{"path": f.path, "exposure_s": f.exif.get("exposure_s"), "f_number": f.exif.get("f_number"),
             "iso": f.exif.get("iso"), "relative_exposure": float(e), "exposure_source": s,
             "orientation": _display_orientation(f)}
            for f, e, s in zip(frames, rel_exp, sources)]


def _read_single(path: str, kind: str, linear: bool, exposures, response) -> LinearPhoto:
    req, source = _response_request(path, linear, response)
    if req in CALIBRATIONS:
        raise PhotoError(f"photo {path}: response {req!r} needs a bracket (a folder of one scene's frames at different "
                         "exposures); one file cannot calibrate it: pass the folder, or a table (file:TABLE.csv)")
    exps = _check_exposures(path, exposures, 1)
    frame = _read_frame(path, kind)
    notes = list(frame.info.pop("notes", []))
    if frame.fixed_response is not None:
        if isinstance(req, _Response) and req.name != "linear":
            raise PhotoError(f"photo {path}: a RAW file is linear; response {response!r} applies to JPEG/PNG/TIFF")
        resp = frame.fixed_response
        if req == "estimate":
            notes.append("a RAW file is linear: the response is not estimated")
        source = "--linear" if linear else "default"
    elif req is None:
        resp = _Response("srgb")
        if frame.icc is not None and not frame.icc.is_srgb():
            resp, source = _icc_response(frame.icc), "icc"
    elif req == "estimate":
        resp, source = _Response("srgb"), "default"
        notes.append("one frame cannot tell its camera response; assumed sRGB")
    else:
        resp = req
    ex = frame.exif
    if ex["exposure_s"] is not None:
        use = ex["iso"] is not None and ex["f_number"] is not None
        e, esrc = _exif_relative_exposure(ex, use), "exif"
        if exps is not None:
            notes.append("the given exposure was not used: EXIF has the exposure time")
    elif exps is not None:
        e, esrc = exps[0], "given"
    else:
        e, esrc = 1.0, "unknown"
    rgb, var, high, low, valid, darkest, dsat = _merge([frame], [resp], [e])
    meta = _base_meta(kind, frame.bit_depth, ex, frame.mono)
    meta.update({"response": resp.name, "response_source": source,
                 "frames": _frame_list_meta([frame], [e], [esrc]), "noise": _noise_meta([frame])})
    meta.update(_icc_meta(frame, resp, source, notes))
    if resp.table is not None:
        meta["response_curve"] = resp.table.curve()
    if frame.kind == "raw":
        meta.update({k: v for k, v in frame.info.items()})
    else:
        meta.update({"clip_level": DEFAULT_CLIP_LEVEL, "black_level": DEFAULT_BLACK_LEVEL})
    meta["notes"] = notes
    return LinearPhoto(rgb=rgb, variance=var, censored_high=high, censored_low=low, valid=valid,
                       darkest=darkest, darkest_saturated=dsat, source=path, meta=meta, response_table=resp.table)


def _bracket_files(folder: str) -> list[str]:
    entries = sorted(e for e in os.listdir(folder) if not e.startswith("."))
    files = []
    for name in entries:
        p = os.path.join(folder, name)
        if not os.path.isfile(p):
            raise PhotoError(f"photo {folder}: a bracket folder holds only image frames, but {name!r} is not a file")
        if os.path.splitext(name)[1].lower() not in PHOTO_EXTENSIONS:
            raise PhotoError(f"photo {folder}: {name!r} is not an image frame (extensions: {' '.join(PHOTO_EXTENSIONS)})")
        files.append(p)
    return files


def _calibrate(folder: str, method: str, frames: list[_Frame], rel_exp: list[float], step: int):
    """The bracket's response by Debevec & Malik 1997 or Robertson et al. 2003 (:mod:`skyfit.camera.response`) on the
    subsampled frames, clipped, black and invalid values left out -> (_Response, TabulatedResponse); PhotoError
    (one line) when the frames cannot constrain it."""
    codes = np.stack([f.codes[::step, ::step] / float(f.max_code) for f in frames])
    usable = np.stack([~f.high[::step, ::step] & ~f.low[::step, ::step] & f.valid[::step, ::step, None] for f in frames])
    fn = debevec_response if method == "debevec" else robertson_response
    try:
        tab = fn(codes, rel_exp, max_code=1.0, usable=usable)
    except ResponseError as e:
        raise PhotoError(f"photo {folder}: response {method!r} cannot be calibrated: {e}") from None
    return _Response(method, table=tab), tab


def write_response_table(path, table: TabulatedResponse) -> Path:
    """Write an inverse response as the CSV that ``response="file:PATH"`` reads: a header, then rows ``code, R, G, B``
    (or ``code, X``) at every node of the table, codes in [0, 1]. Returns the path.

    Args:
        path: the CSV to write.
        table: e.g. ``read_photo(folder, response="debevec").response_table``.
    """
    names = ("R", "G", "B") if table.channels == 3 else ("X",)
    lines = ["code," + ",".join(names)]
    lines += [",".join(f"{v:.9g}" for v in (c, *row)) for c, row in zip(table.codes, table.values)]
    p = Path(os.fspath(path))
    write_text_atomic(p, "\n".join(lines) + "\n")
    return p


def _read_bracket(folder: str, linear: bool, exposures, response) -> LinearPhoto:
    if is_kider_capture_name(os.path.basename(os.path.normpath(folder))):
        raise PhotoError(f"photo {folder}: a Kider capture folder, not a photo bracket; read it with load_kider_capture")
    req, source = _response_request(folder, linear, response)
    files = _bracket_files(folder)
    if len(files) < 2:
        raise PhotoError(f"photo {folder}: a bracket needs at least 2 frames, the folder has {len(files)}")
    kinds = sorted({_kind(os.path.splitext(p)[1].lower()) for p in files})
    if len(kinds) > 1:
        raise PhotoError(f"photo {folder}: the frames mix formats ({', '.join(kinds)}); a bracket is one format")
    if kinds[0] in ("hdr", "exr"):
        raise PhotoError(f"photo {folder}: a bracket of {kinds[0].upper()} files is not read; they are already linear "
                         "HDR images, pass one file")
    exps = _check_exposures(folder, exposures, len(files))
    frames = [_read_frame(p, kinds[0]) for p in files]
    notes: list[str] = []
    for f in frames:
        notes.extend(f.info.pop("notes", []))
    h, w = frames[0].shape
    if len({f.mono for f in frames}) > 1:
        raise PhotoError(f"photo {folder}: the frames mix grey and colour images ("
                         + ", ".join(f"{os.path.basename(f.path)} {'grey' if f.mono else 'colour'}" for f in frames)
                         + "); a bracket is one camera's")
    for f in frames[1:]:
        if f.shape != (h, w):
            raise PhotoError(f"photo {folder}: the frames differ in size: {os.path.basename(files[0])} is {w}x{h}, "
                             f"{os.path.basename(f.path)} is {f.shape[1]}x{f.shape[0]}")
    n = len(frames)
    step = _subsample_step((h, w))
    name = [os.path.basename(p) for p in files]

    # Exposures: EXIF for every frame, else given, else estimated below.
    exif_t = [f.exif["exposure_s"] for f in frames]
    if all(t is not None for t in exif_t):
        use = all(f.exif["iso"] is not None and f.exif["f_number"] is not None for f in frames)
        rel_exp = [_exif_relative_exposure(f.exif, use) for f in frames]
        esrc = ["exif"] * n
        if not use:
            notes.append("EXIF lacks ISO or f-number in some frames: relative exposures are exposure times alone")
        if exps is not None:
            notes.append("the given exposures were not used: EXIF has every frame's exposure time")
    elif exps is not None:
        rel_exp, esrc = list(exps), ["given"] * n
        if any(t is not None for t in exif_t):
            notes.append("EXIF has exposure times for some frames only; used the given exposures")
    else:
        rel_exp, esrc = None, ["estimated"] * n

    # Order by exposure (known) or by brightness (unknown: clipping is monotone, so the mean code is too).
    if rel_exp is not None:
        order = sorted(range(n), key=lambda i: (rel_exp[i], i))
    else:
        means = [float(np.mean(f.codes[::step, ::step][f.valid[::step, ::step]])) / f.max_code for f in frames]
        order = sorted(range(n), key=lambda i: (means[i], i))

    # Response.
    info = None
    calibrate = req in CALIBRATIONS
    if frames[0].fixed_response is not None:
        if (isinstance(req, _Response) and req.name != "linear") or calibrate:
            raise PhotoError(f"photo {folder}: RAW frames are linear; response {response!r} applies to JPEG/PNG/TIFF")
        resp, source = frames[0].fixed_response, ("--linear" if linear else "default")
    elif calibrate:
        # The calibration needs the exposures; without them their ratios come from the frames' overlap, read
        # through the best parametric response (its notes are replaced by the one below).
        resp = _Response("srgb")
        if rel_exp is None:
            resp, _ = _estimate_response(frames, order, None, step, [])
            notes.append(f"response {req!r} without exposure times: the frames' exposure ratios were estimated through "
                         f"the parametric response {resp.name} and the calibrated curve is consistent with them; a "
                         "response and the ratios are known only together (Grossberg & Nayar 2003), so give exposures "
                         "(or EXIF) for an absolute calibration")
    elif req is None and frames[0].icc is not None and not frames[0].icc.is_srgb():
        # the frames declare their encoding (Adobe RGB's power law 563/256): the ratio-constancy estimate put it at
        # 2.26-2.48 on the suite's Adobe RGB brackets (docs/photos.md); --response estimate still estimates
        resp, source = _icc_response(frames[0].icc), "icc"
    elif req is None or req == "estimate":
        resp, info = _estimate_response(frames, order, rel_exp, step, notes)
        source = "estimated" if info.get("method") != "fallback" else "default"
    else:
        resp = req
    responses = [f.fixed_response or resp for f in frames]

    # Exposure ratios from the overlap, chained from the darkest frame.
    if rel_exp is None:
        rel = {order[0]: 1.0}
        for i, j in zip(order[:-1], order[1:]):
            k, shared = _exposure_log_ratio(frames[i], frames[j], responses[i], responses[j], step)
            if shared < MIN_OVERLAP:
                raise PhotoError(f"photo {folder}: frames {name[i]} and {name[j]} share no well-exposed pixels "
                                 f"({shared} channel values) so their exposure ratio cannot be estimated; "
                                 "give the exposures")
            rel[j] = rel[i] * math.exp(k)
        rel_exp = [rel[i] for i in range(n)]
        notes.append("exposures were estimated from the frames' overlap (no EXIF exposure times, none given): "
                     "the relative exposures are ratios to the darkest frame")

    calibration = None
    if calibrate:
        resp, calibration = _calibrate(folder, req, frames, rel_exp, step)
        responses = [resp] * n
        source = "calibrated"
        ratio = calibration.info.get("constant_ratio")
        if req == "robertson" and ratio is not None:
            notes.append(f"the exposures step by one factor ({ratio:.3g}): a response is then known only up to a ripple of "
                         "that period in log radiance (Grossberg & Nayar 2003), which Robertson's method cannot choose "
                         "(about 30 % on a test bracket, docs/photos.md); response 'debevec' smooths it out")

    # One scene? After exposure normalisation the frames must agree over the pixels well exposed in both.
    for i, j in zip(order[:-1], order[1:]):
        shift = math.log(rel_exp[j] / rel_exp[i])
        px = _log_ratio_samples(frames[i], frames[j], responses[i], responses[j], step, *SCENE_CHECK_RANGE) - shift
        blocks = _block_log_ratios(frames[i], frames[j], responses[i], responses[j], *SCENE_CHECK_RANGE) - shift
        checks = [(d, lim, what) for d, lim, what, least in (
            (blocks, SCENE_SPREAD_MAX, f"well-exposed {SCENE_BLOCK}x{SCENE_BLOCK} px blocks", SCENE_MIN_BLOCKS),
            (px, SCENE_PIXEL_SPREAD_MAX, "well-exposed values", SCENE_PIXEL_MIN)) if d.size >= least]
        if not checks:
            notes.append(f"frames {name[i]} and {name[j]} share too few well-exposed areas to check they show one scene")
            continue
        for d, lim, what in checks:
            centre = float(np.median(d))
            spread = 1.4826 * float(np.median(np.abs(d - centre)))
            if spread > lim:
                raise PhotoError(f"photo {folder}: frames {name[i]} and {name[j]} disagree by {100 * math.expm1(spread):.0f} % "
                                 f"(robust spread over {d.size} {what}) after exposure normalisation; not one scene's bracket")
        centre = float(np.median(checks[0][0]))
        if abs(math.expm1(centre)) > EXPOSURE_MISMATCH_NOTE:
            notes.append(f"the pixels put {name[j]} at {math.exp(centre):.3f} times the {esrc[j]} exposure ratio to "
                         f"{name[i]}")

    rgb, var, high, low, valid, darkest, dsat = _merge(frames, responses, rel_exp)
    first = frames[0]
    meta = _base_meta("bracket", max(f.bit_depth for f in frames), first.exif, first.mono)
    meta.update({"frame_format": kinds[0], "response": resp.name, "response_source": source,
                 "frames": _frame_list_meta(frames, rel_exp, esrc), "noise": _noise_meta(frames),
                 "darkest_frame": files[order[0]]})
    meta.update(_icc_meta(first, resp, source, notes))
    if info is not None:
        meta["response_estimate"] = {k: v for k, v in info.items() if k != "scores"}
        if "scores" in info:
            meta["response_scores"] = {k: float(v) for k, v in info["scores"].items()}
    if resp.table is not None:
        meta["response_curve"] = resp.table.curve()
    if calibration is not None:
        meta["response_calibration"] = calibration.info
    if first.kind == "raw":
        meta["white_balance"] = [f.info["white_balance"] for f in frames]
    else:
        meta.update({"clip_level": DEFAULT_CLIP_LEVEL, "black_level": DEFAULT_BLACK_LEVEL})
    meta["notes"] = notes
    return LinearPhoto(rgb=rgb, variance=var, censored_high=high, censored_low=low, valid=valid,
                       darkest=darkest, darkest_saturated=dsat, source=folder, meta=meta, response_table=resp.table)


def read_photo(path, *, linear: bool = False, exposures: Sequence[float] | None = None,
               response: str | None = None) -> LinearPhoto:
    """Read a photo file or a bracket folder as one linear HDR image (module docstring for the models).

    Args:
        path: a JPEG/PNG/TIFF (8 or 16 bit, RGB or RGBA, or grey (+ alpha): read as three equal channels,
            ``meta['monochrome']`` True), a camera RAW file, a Radiance ``.hdr``, an
            EXR without skyfit metadata, or a folder holding only the frames of one scene's exposure
            bracket (one format, >= 2 frames; hidden files ignored).
        linear: the LDR codes are linear (same as ``response="linear"``).
        exposures: relative exposure of each frame (e.g. exposure times [s]), in the folder's sorted
            file order; one value for a file. Used when EXIF lacks exposure times.
        response: "srgb", "linear", "gamma:G", "estimate", "debevec" or "robertson" (a bracket's response
            calibrated from its frames), or "file:TABLE.csv" (a calibrated inverse response; module
            docstring). Default: sRGB for one LDR file, estimated for a bracket; RAW, .hdr and EXR are linear.

    Returns:
        A :class:`LinearPhoto` of shape (H, W, 3) in relative units.

    Raises:
        PhotoError: (a ValueError, one line naming the path) no such file; unreadable or corrupt
            image; unsupported bit depth or channel count; a 16-bit RGB PNG read as 8 bits; a
            bracket of fewer than 2 frames, mixed formats, frames of different sizes, different
            scenes, or (without exposures) frames with no well-exposed overlap; a wrong number of
            exposures; NaN, infinite or negative values in a .hdr/EXR; contradictory options; a
            calibration asked of one file, or of frames too few or too alike to constrain it; a missing
            or malformed response table.
    """
    p = os.fspath(path)
    if os.path.isdir(p):
        return _read_bracket(p, linear, exposures, response)
    if not os.path.exists(p):
        raise PhotoError(f"photo {p}: no such file or folder")
    ext = os.path.splitext(p)[1].lower()
    if ext not in PHOTO_EXTENSIONS:
        raise PhotoError(f"photo {p}: not a photo file (extension {ext or 'none'!r}; expected one of {' '.join(PHOTO_EXTENSIONS)})")
    kind = _kind(ext)
    if kind in ("hdr", "exr"):
        return _read_linear_image(p, kind, exposures, linear, response)
    return _read_single(p, kind, linear, exposures, response)


def block_view(a: np.ndarray, step: int, h: int, w: int) -> np.ndarray:
    """(h, w, step * step, ...) view of the top-left h step x w step pixels of ``a`` (H, W, ...) grouped in blocks of
    step x step pixels: block sums, means and flags by reducing axis 2."""
    a = a[: h * step, : w * step]
    return a.reshape(h, step, w, step, *a.shape[2:]).swapaxes(1, 2).reshape(h, w, step * step, *a.shape[2:])


def reduced_photo(photo: LinearPhoto, factor: int) -> LinearPhoto:
    """``photo`` at 1 / ``factor`` of its resolution: block means of ``factor`` x ``factor`` pixels (the ragged right
    and bottom edges dropped), each a pixel of the result (pixel (i, j) of it centred at pixel (i f + (f - 1) / 2,
    j f + (f - 1) / 2) of the original). The censoring keeps its meaning as bounds on the mean: a channel with a
    clipped pixel is a lower bound (its clipped pixels hold their clip level, below their truth), one with a black
    pixel an upper bound; a block with both is flagged both ways, which no fit takes as a bound. The variance is
    the mean's (sum / f^4: independent pixels); a pixel is valid where its whole block is. ``meta["reduced"]``
    records the factor and the original shape. ``factor`` 1 returns ``photo`` itself. Block sums by reshaping: a
    few lines of numpy that keep each field's dtype and meaning, where ``skimage.transform.downscale_local_mean``
    would pad the edges and average the flags."""
    f = int(factor)
    if f < 1:
        raise PhotoError(f"{photo.source}: reduction factor must be >= 1, got {factor}")
    if f == 1:
        return photo
    H, W = photo.rgb.shape[:2]
    h, w = H // f, W // f
    if h < 1 or w < 1:
        raise PhotoError(f"{photo.source}: {H}x{W} px cannot be reduced by {f}")
    blocks = lambda a: block_view(a, f, h, w)  # noqa: E731

    with np.errstate(invalid="ignore"):
        finite = np.isfinite(photo.rgb)
        n = blocks(finite).sum(2)
        rgb = np.where(n > 0, blocks(np.where(finite, photo.rgb, 0.0)).sum(2) / np.maximum(n, 1), np.nan)
        darkest = blocks(np.nan_to_num(photo.darkest)).mean(2)
    meta = {**photo.meta, "reduced": {"factor": f, "original_shape": [H, W]}}
    return dataclasses.replace(
        photo, rgb=rgb, variance=blocks(photo.variance).sum(2) / float(f) ** 4,
        censored_high=blocks(photo.censored_high).any(2), censored_low=blocks(photo.censored_low).any(2),
        valid=blocks(photo.valid).all(2), darkest=darkest, darkest_saturated=blocks(photo.darkest_saturated).any(2),
        meta=meta)


def _exr_has_skyfit_metadata(path: Path) -> bool | None:
    """True/False from the EXR header alone; None when the header cannot be read."""
    from .exr import METADATA_KEY

    try:
        import OpenEXR  # heavy optional dependency, as in skyfit.io.exr

        return METADATA_KEY in OpenEXR.File(str(path), header_only=True).header()
    except Exception:  # noqa: BLE001 - any failure: let the EXR reader report it
        return None


def is_photo_path(path) -> bool:
    """Whether :func:`read_photo` is the reader for ``path``.

    True for a file with an image, RAW or ``.hdr`` extension (also when it does not exist, so that
    :func:`read_photo` reports it), for an EXR without skyfit's metadata, and for a folder whose
    entries (hidden files aside) are all files with image/RAW/.hdr extensions (a bracket). False
    for Kider capture folders (:func:`skyfit.io.kider.is_kider_capture_name`), EXRs carrying skyfit
    metadata (or unreadable ones: their reader reports the problem), folders holding folders or EXRs,
    and anything else.
    """
    p = Path(os.fspath(path))
    if p.is_dir():
        if is_kider_capture_name(p.name):
            return False
        try:
            entries = [e for e in p.iterdir() if not e.name.startswith(".")]
        except OSError:
            return False
        frame_ext = LDR_EXTENSIONS + RAW_EXTENSIONS + HDR_EXTENSIONS
        return bool(entries) and all(e.is_file() and e.suffix.lower() in frame_ext for e in entries)
    ext = p.suffix.lower()
    if ext in EXR_EXTENSIONS:
        return p.is_file() and _exr_has_skyfit_metadata(p) is False
    return ext in PHOTO_EXTENSIONS


__all__ = [
    "EXR_EXTENSIONS",
    "HDR_EXTENSIONS",
    "LDR_EXTENSIONS",
    "PHOTO_EXTENSIONS",
    "RAW_EXTENSIONS",
    "LinearPhoto",
    "PhotoError",
    "block_view",
    "is_photo_path",
    "read_photo",
    "reduced_photo",
    "write_response_table",
]
