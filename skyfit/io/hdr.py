"""Radiance RGBE (.hdr / .pic) images in and out, in numpy.

Written by hand: on the project's machines imageio 2.38 has no Radiance
reader without the opencv or freeimage plugin (both extra downloads), and its
``imwrite("x.hdr", ...)`` silently writes a TIFF under that name; scikit-image
delegates to imageio. The format is small:

* Header lines up to an empty line: ``#?RADIANCE`` (or ``#?RGBE``) first,
  then ``VAR=value`` lines and ``#`` comments. ``FORMAT=32-bit_rle_rgbe`` (or
  ``32-bit_rle_xyze``); ``EXPOSURE=e`` (cumulative, several multiply) says the
  stored values were multiplied by e; ``COLORCORR=r g b`` likewise per
  channel. Reading divides them out, so values are back in the writer's units.
* A resolution line, ``-Y H +X W`` for the standard top-to-bottom,
  left-to-right order (all 8 orientations are read).
* Scanlines of 4-byte pixels (R, G, B mantissas, shared exponent E):
  value = (m + 0.5) 2^(E - 136), 0 when E = 0. A scanline of width 8..32767
  may be "new-style" run-length encoded: bytes 2, 2, W >> 8, W & 255, then
  the four components one after the other, each as runs (count > 128: one
  byte repeated count - 128 times) and literals (count <= 128 bytes).
  Otherwise it is flat, where a pixel (1, 1, 1, n) repeats the previous one
  (old-style RLE).

Reference: G. Ward, "Real Pixels", Graphics Gems II (1991), and the Radiance
sources (src/common/color.c: fwritecolrs / freadcolrs / setcolr / colr_color).
"""
from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from .atomic import write_bytes_atomic

__all__ = ["HdrError", "read_hdr", "write_hdr", "float_to_rgbe", "rgbe_to_float"]


class HdrError(ValueError):
    """A file that is not a readable Radiance RGBE image."""


def float_to_rgbe(rgb: np.ndarray) -> np.ndarray:
    """Encode non-negative floats (..., 3) to RGBE bytes (..., 4), as Radiance's setcolr.

    Mantissas are floor(c * 256 / 2^e) with 2^(e-1) <= max(r, g, b) < 2^e, so
    decoding with +0.5 is within max(r, g, b) / 256 of the input per channel.
    Values below 1e-32 become 0.
    """
    rgb = np.asarray(rgb, dtype=np.float64)
    if rgb.shape[-1] != 3:
        raise HdrError(f"need (..., 3) values, got shape {rgb.shape}")
    if not np.all(np.isfinite(rgb)) or np.any(rgb < 0):
        raise HdrError("RGBE stores finite non-negative values only")
    mx = rgb.max(-1)
    mant, exp = np.frexp(mx)  # mx = mant * 2^exp, mant in [0.5, 1)
    out = np.zeros(rgb.shape[:-1] + (4,), dtype=np.uint8)
    ok = mx >= 1e-32
    if np.any(exp[ok] + 128 > 255):
        raise HdrError("value too large for RGBE (>= 2^127)")
    scale = np.where(ok, np.ldexp(1.0, 8 - exp), 0.0)  # 256 / 2^exp
    m = np.floor(rgb * scale[..., None])
    out[..., :3] = np.clip(m, 0, 255).astype(np.uint8)
    out[..., 3] = np.where(ok, exp + 128, 0).astype(np.uint8)
    return out


def rgbe_to_float(rgbe: np.ndarray) -> np.ndarray:
    """Decode RGBE bytes (..., 4) to float32 (..., 3), as Radiance's colr_color."""
    rgbe = np.asarray(rgbe, dtype=np.uint8)
    e = rgbe[..., 3].astype(np.int32)
    f = np.where(e > 0, np.ldexp(1.0, e - 136), 0.0)
    return ((rgbe[..., :3].astype(np.float64) + 0.5) * f[..., None]).astype(np.float32)


_RES_RE = re.compile(rb"^([-+])([XY]) (\d+) ([-+])([XY]) (\d+)$")


def _parse_header(data: bytes, path) -> tuple[dict, int]:
    if not data.startswith(b"#?"):
        raise HdrError(f"not a Radiance HDR file (no '#?' signature): {path}")
    pos = 0
    info: dict = {"exposure": 1.0, "colorcorr": (1.0, 1.0, 1.0), "format": None, "program": None}
    extra = {}
    first = True
    while True:
        nl = data.find(b"\n", pos)
        if nl < 0:
            raise HdrError(f"HDR header of {path} has no end (empty line)")
        line = data[pos:nl].rstrip(b"\r")
        pos = nl + 1
        if first:
            info["program"] = line[2:].decode("ascii", "replace")
            first = False
            continue
        if not line:
            break
        if line.startswith(b"#"):
            continue
        key, eq, val = line.decode("ascii", "replace").partition("=")
        if not eq:
            continue
        key, val = key.strip(), val.strip()
        try:
            if key == "FORMAT":
                info["format"] = val
            elif key == "EXPOSURE":
                info["exposure"] *= float(val)
            elif key == "COLORCORR":
                cc = [float(x) for x in val.split()]
                info["colorcorr"] = tuple(a * b for a, b in zip(info["colorcorr"], cc))
            else:
                extra[key] = val
        except ValueError:
            raise HdrError(f"HDR header of {path}: bad value in {line!r}") from None
    if info["format"] not in (None, "32-bit_rle_rgbe", "32-bit_rle_xyze"):
        raise HdrError(f"HDR file {path}: unsupported FORMAT={info['format']}")
    nl = data.find(b"\n", pos)
    if nl < 0:
        raise HdrError(f"HDR file {path} has no resolution line")
    m = _RES_RE.match(data[pos:nl].rstrip(b"\r"))
    if not m or m[2] == m[5]:
        raise HdrError(f"HDR file {path}: bad resolution line {data[pos:nl][:40]!r}")
    info["orientation"] = (m[1] + m[2] + b" " + m[4] + m[5]).decode()
    info["_res"] = (m[1].decode(), m[2].decode(), int(m[3]), m[4].decode(), m[5].decode(), int(m[6]))
    info.update(extra=extra)
    return info, nl + 1


def _decode_scanlines(data: bytes, pos: int, n_lines: int, width: int, path) -> np.ndarray:
    buf = np.frombuffer(data, dtype=np.uint8)
    out = np.empty((n_lines, width, 4), dtype=np.uint8)
    size = len(buf)
    for y in range(n_lines):
        if pos + 4 > size:
            raise HdrError(f"HDR file {path} is truncated at scanline {y}")
        b0, b1, b2, b3 = (int(v) for v in buf[pos:pos + 4])
        if 8 <= width <= 0x7FFF and b0 == 2 and b1 == 2 and not (b2 & 0x80):
            if (b2 << 8 | b3) != width:
                raise HdrError(f"HDR file {path}: scanline {y} length {(b2 << 8) | b3} != width {width}")
            pos += 4
            for c in range(4):
                x = 0
                row = out[y, :, c]
                while x < width:
                    if pos >= size:
                        raise HdrError(f"HDR file {path} is truncated at scanline {y}")
                    count = int(buf[pos])
                    pos += 1
                    if count > 128:
                        count -= 128
                        if pos >= size:
                            raise HdrError(f"HDR file {path} is truncated at scanline {y}")
                        if x + count > width:
                            raise HdrError(f"HDR file {path}: run past the end of scanline {y}")
                        row[x:x + count] = buf[pos]
                        pos += 1
                    else:
                        if count == 0 or x + count > width:
                            raise HdrError(f"HDR file {path}: bad literal count in scanline {y}")
                        if pos + count > size:
                            raise HdrError(f"HDR file {path} is truncated at scanline {y}")
                        row[x:x + count] = buf[pos:pos + count]
                        pos += count
                    x += count
        else:  # flat pixels, with old-style (1, 1, 1, n) repeats
            x, shift = 0, 0
            while x < width:
                if pos + 4 > size:
                    raise HdrError(f"HDR file {path} is truncated at scanline {y}")
                px = buf[pos:pos + 4]
                pos += 4
                if px[0] == 1 and px[1] == 1 and px[2] == 1:
                    if x == 0:
                        raise HdrError(f"HDR file {path}: repeat with no previous pixel at scanline {y}")
                    n = int(px[3]) << shift
                    if x + n > width:
                        raise HdrError(f"HDR file {path}: repeat past the end of scanline {y}")
                    out[y, x:x + n] = out[y, x - 1]
                    x += n
                    shift += 8
                else:
                    out[y, x] = px
                    x += 1
                    shift = 0
    return out


def read_hdr(path) -> tuple[np.ndarray, dict]:
    """Read a Radiance RGBE image.

    Returns:
        image: float32, shape (H, W, 3), row 0 at the top, column 0 at the
            left, in the writer's units (EXPOSURE and COLORCORR divided out);
            CIE XYZ when header["format"] is "32-bit_rle_xyze".
        header: "format", "exposure" (product), "colorcorr", "orientation"
            (as in the file, e.g. "-Y +X"), "program" (after "#?"), "extra"
            (other VAR=value pairs).

    Raises:
        HdrError: not an HDR file, unsupported format, truncated or corrupt data.
    """
    path = Path(path)
    if not path.is_file():
        raise HdrError(f"file not found: {path}")
    data = path.read_bytes()
    info, pos = _parse_header(data, path)
    s1, a1, n1, s2, a2, n2 = info.pop("_res")
    if n1 == 0 or n2 == 0:
        raise HdrError(f"HDR file {path}: empty image")
    raw = _decode_scanlines(data, pos, n1, n2, path)  # (first axis, second axis, 4)
    img = rgbe_to_float(raw)
    # Scanlines run along the second axis; "-Y" means top to bottom, "+X" left to right.
    if a1 == "X":
        img = img.transpose(1, 0, 2)  # -> (Y, X)
        sy, sx = s2, s1
    else:
        sy, sx = s1, s2
    if sy == "+":
        img = img[::-1]
    if sx == "-":
        img = img[:, ::-1]
    corr = np.asarray(info["colorcorr"], np.float64) * info["exposure"]
    if np.any(corr <= 0):
        raise HdrError(f"HDR file {path}: non-positive EXPOSURE or COLORCORR")
    if np.any(corr != 1.0):
        img = (img / corr).astype(np.float32)
    return np.ascontiguousarray(img), info


def _rle_component(row: np.ndarray) -> bytes:
    """New-style RLE of one component of one scanline (runs of >= 4 as runs)."""
    out = bytearray()
    n = len(row)
    # Start of each run of equal bytes.
    starts = np.flatnonzero(np.concatenate([[True], row[1:] != row[:-1]]))
    lengths = np.diff(np.concatenate([starts, [n]]))
    lit_start = 0  # first byte not yet written
    for s, ln in zip(starts.tolist(), lengths.tolist()):
        if ln < 4:
            continue
        for k in range(lit_start, s, 128):  # pending literals
            chunk = row[k:min(k + 128, s)]
            out.append(len(chunk))
            out += chunk.tobytes()
        left = ln
        while left > 0:
            c = min(left, 127)
            out += bytes((128 + c, int(row[s])))
            left -= c
        lit_start = s + ln
    for k in range(lit_start, n, 128):
        chunk = row[k:min(k + 128, n)]
        out.append(len(chunk))
        out += chunk.tobytes()
    return bytes(out)


def write_hdr(path, image, *, rle: bool = True, exposure: float | None = None) -> Path:
    """Write a float (H, W, 3) image as Radiance RGBE, atomically.

    Args:
        path: target file.
        image: finite, non-negative, shape (H, W, 3), row 0 at the top.
        rle: new-style run-length encoding (widths 8..32767; flat otherwise).
        exposure: if given, stored values are image * exposure and the header
            says EXPOSURE=exposure, so read_hdr returns ``image`` again.

    Raises:
        HdrError: bad shape or values.
    """
    path = Path(path)
    img = np.asarray(image, dtype=np.float64)
    if img.ndim != 3 or img.shape[2] != 3 or img.shape[0] == 0 or img.shape[1] == 0:
        raise HdrError(f"write_hdr needs a non-empty (H, W, 3) image, got shape {img.shape}")
    h, w = img.shape[:2]
    header = "#?RADIANCE\n# written by skyfit\nFORMAT=32-bit_rle_rgbe\n"
    if exposure is not None:
        if not (np.isfinite(exposure) and exposure > 0):
            raise HdrError(f"exposure must be finite and positive, got {exposure}")
        img = img * exposure
        header += f"EXPOSURE={exposure:.9g}\n"
    header += f"\n-Y {h} +X {w}\n"
    # float_to_rgbe normalises every non-zero pixel's largest mantissa to >= 128,
    # so no pixel can be mistaken for an RLE marker (2, 2, <128) or an old-style
    # repeat (1, 1, 1, n) in flat mode.
    rgbe = float_to_rgbe(img)
    body = bytearray()
    if rle and 8 <= w <= 0x7FFF:
        for y in range(h):
            body += bytes((2, 2, w >> 8, w & 255))
            for c in range(4):
                body += _rle_component(rgbe[y, :, c])
    else:
        body += rgbe.tobytes()
    return write_bytes_atomic(path, header.encode("ascii") + bytes(body))
