"""A minimal 16-bit PNG writer for the tests (PNG spec, ISO/IEC 15948: filter 0 rows, one IDAT): Pillow cannot
write 16-bit RGB(A), and the reader under test (pypng) must not be the writer of its own test files."""
from __future__ import annotations

import struct
import zlib

import numpy as np

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
