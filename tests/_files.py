"""Writers of test files: a minimal 16-bit PNG (PNG spec, ISO/IEC 15948: filter 0 rows, one IDAT; Pillow cannot
write 16-bit RGB(A), and the reader under test, pypng, must not write its own test files), and EXIF of a time and
a GPS position as cameras and phones write them (through Pillow)."""
from __future__ import annotations

import struct
import zlib

import numpy as np
from PIL import ExifTags, Image, TiffImagePlugin

COLOUR_TYPES = {1: 0, 2: 4, 3: 2, 4: 6}  # channels -> PNG colour type: grey, grey + alpha, RGB, RGBA


def png16(path, arr: np.ndarray, icc: bytes | None = None) -> None:
    """Write ``arr`` (H, W) or (H, W, C), C in 1..4, as a 16-bit PNG; ``icc``: an iCCP chunk of these profile bytes."""
    a = arr[..., None] if arr.ndim == 2 else arr
    h, w, c = a.shape
    raw = b"".join(b"\x00" + a[r].astype(">u2").tobytes() for r in range(h))

    def chunk(tag, data):
        return struct.pack(">I", len(data)) + tag + data + struct.pack(">I", zlib.crc32(tag + data) & 0xFFFFFFFF)

    ihdr = struct.pack(">IIBBBBB", w, h, 16, COLOUR_TYPES[c], 0, 0, 0)
    iccp = chunk(b"iCCP", b"skyfit\x00\x00" + zlib.compress(icc)) if icc is not None else b""
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + iccp + chunk(b"IDAT", zlib.compress(raw))
                     + chunk(b"IEND", b""))


def exif_when_where(when: str | None, offset: str | None, lat: float | None = None, lon: float | None = None,
                    alt: float | None = None) -> Image.Exif:
    """EXIF DateTimeOriginal (36867) and OffsetTimeOriginal (36881); a GPS IFD of degrees, minutes and seconds."""
    R = TiffImagePlugin.IFDRational
    ex = Image.Exif()
    sub = ex.get_ifd(ExifTags.IFD.Exif)
    if when:
        sub[36867] = when
    if offset:
        sub[36881] = offset
    if lat is not None:
        gps = ex.get_ifd(ExifTags.IFD.GPSInfo)

        def dms(v):
            d, m = int(abs(v)), int(abs(v) * 60) % 60
            return (R(d), R(m), R(round((abs(v) * 3600 - d * 3600 - m * 60) * 1000), 1000))

        gps[1], gps[2], gps[3], gps[4] = ("N" if lat >= 0 else "S"), dms(lat), ("E" if lon >= 0 else "W"), dms(lon)
        if alt is not None:
            gps[5], gps[6] = (b"\x01" if alt < 0 else b"\x00"), R(round(abs(alt) * 10), 10)
    return ex


def exif_colour_space(color_space: int, interop: str | None = None) -> Image.Exif:
    """EXIF ColorSpace (40961: 1 sRGB, 0xFFFF uncalibrated) and an interoperability IFD with its index (1: "R98" for
    sRGB, "R03" for DCF's option space, Adobe RGB), as a camera set to Adobe RGB writes them without a profile."""
    ex = Image.Exif()
    sub = ex.get_ifd(ExifTags.IFD.Exif)
    sub[40961] = color_space
    if interop is not None:
        sub[ExifTags.IFD.Interop] = {1: interop, 2: b"0100"}  # a dict: Pillow writes it as the nested IFD
    return ex
