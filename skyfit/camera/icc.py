"""Embedded ICC profiles of photos: the tone curves and primaries of matrix/TRC profiles.

A phone's JPEG is Display P3, a camera set to Adobe RGB writes Adobe RGB; read as sRGB, their codes decode
through the wrong tone curve and their channels stand for the wrong primaries. A matrix/TRC RGB profile (what
cameras and phones embed) says both: three tone reproduction curves (``rTRC``, ``gTRC``, ``bTRC``) from code to
linear value, and the colorants (``rXYZ``, ``gXYZ``, ``bXYZ``), the PCS XYZ (D50) of each primary at full scale.
A grey profile has one curve, ``kTRC``.

Why by hand: Pillow's ImageCms (LittleCMS) converts 8-bit pixels between profiles, which would requantise and
clip the codes the likelihood reads, and exposes no tone curve; colour-science reads no ICC file. The tags used
here are the few of ICC.1:2022 (v4.4) that a matrix/TRC profile needs: the header (section 7.2), the tag table
(7.3), ``curveType`` (10.6), ``parametricCurveType`` (10.18, Table 68), ``XYZType`` (10.31), and the
description (``textDescriptionType`` of v2, ``multiLocalizedUnicodeType`` 10.15 of v4). A profile built on lookup
tables (``A2B0`` without colorants) is not read: :func:`parse_icc` returns None and the photo is read as sRGB.
"""
from __future__ import annotations

import dataclasses
import functools
import struct

import numpy as np

D50_XYZ = np.array([0.9642, 1.0, 0.8249])
"""The ICC profile connection space's white (ICC.1:2022 section 7.2.16, s15Fixed16 rounding)."""

SRGB_TOLERANCE = 2e-3
"""A profile is sRGB's when its curves are within this of the sRGB curve at every code and its colorants within
this of the sRGB profile's (whose 4-digit tags differ from the derived ones by < 1e-4)."""


class IccError(ValueError):
    """A malformed ICC profile."""


@dataclasses.dataclass(frozen=True)
class Curve:
    """One tone reproduction curve: code c in [0, 1] -> linear value."""

    kind: str                      # "identity", "gamma", "parametric", "table"
    params: tuple = ()             # gamma: (g,); parametric: (function type, g, a, b, c, d, e, f)
    table: tuple = ()              # table: values at equally spaced codes

    def __call__(self, c: np.ndarray) -> np.ndarray:
        c = np.clip(np.asarray(c, np.float64), 0.0, 1.0)
        if self.kind == "identity":
            return c
        if self.kind == "gamma":
            return c ** self.params[0]
        if self.kind == "table":
            t = np.asarray(self.table)
            return np.interp(c, np.linspace(0.0, 1.0, t.size), t)
        ftype, g, a, b, cc, d, e, f = self.params
        base = np.maximum(a * c + b, 0.0)
        if ftype == 0:
            return c ** g
        if ftype == 1:
            return np.where(c >= -b / a, base ** g, 0.0)
        if ftype == 2:
            return np.where(c >= -b / a, base ** g + cc, cc)
        if ftype == 3:
            return np.where(c >= d, base ** g, cc * c)
        return np.where(c >= d, base ** g + e, cc * c + f)  # type 4

    def is_srgb(self) -> bool:
        """Whether this is the sRGB curve (IEC 61966-2-1) to :data:`SRGB_TOLERANCE` at 1025 codes."""
        c = np.linspace(0.0, 1.0, 1025)
        return bool(np.max(np.abs(self(c) - _srgb_curve(c))) <= SRGB_TOLERANCE)

    @property
    def gamma(self) -> float | None:
        """The exponent of a pure power law (curv with one entry, or parametric type 0), else None."""
        if self.kind == "gamma" or (self.kind == "parametric" and self.params[0] == 0):
            return float(self.params[0] if self.kind == "gamma" else self.params[1])
        return None


@dataclasses.dataclass(frozen=True)
class IccProfile:
    """What a matrix/TRC profile says of a photo's codes.

    Attributes:
        description: the profile's name (``desc`` tag), e.g. "Display P3".
        curves: one :class:`Curve` per channel (three for RGB, one for grey).
        colorants: (3, 3) with columns the PCS XYZ (D50) of R, G, B at full scale; None for a grey profile.
    """

    description: str
    curves: tuple
    colorants: np.ndarray | None

    @property
    def grey(self) -> bool:
        return self.colorants is None

    def decode(self, c: np.ndarray) -> np.ndarray:
        """Linear values of codes c in [0, 1] of shape (..., 3) (each channel its curve) or (...,) (grey, or every
        channel's curve when all three are one)."""
        c = np.asarray(c, np.float64)
        if len(self.curves) == 1 or (c.ndim and c.shape[-1] != 3) or c.ndim == 0:
            return self.curves[0](c)
        return np.stack([k(c[..., i]) for i, k in enumerate(self.curves)], -1)

    def same_curves(self) -> bool:
        """Whether every channel has one curve (to 1e-6 at 1025 codes)."""
        c = np.linspace(0.0, 1.0, 1025)
        ref = self.curves[0](c)
        return all(np.max(np.abs(k(c) - ref)) < 1e-6 for k in self.curves[1:])

    def rgb_from_xyz(self) -> np.ndarray:
        """(3, 3) matrix from CIE XYZ (relative to D65, as :func:`skyfit.render.colour.xyz_to_srgb_matrix` reads
        it) to the profile's linear RGB: Bradford D65 -> D50 (the PCS's adaptation, ICC.1:2022 Annex E), then the
        inverse of the colorants."""
        if self.colorants is None:
            raise IccError("a grey profile has no primaries")
        return np.linalg.inv(self.colorants) @ _bradford_d65_to_d50()

    def is_srgb(self) -> bool:
        """Whether the profile is sRGB's (IEC 61966-2-1): its curves and colorants to :data:`SRGB_TOLERANCE`."""
        if not all(k.is_srgb() for k in self.curves):
            return False
        if self.colorants is None:
            return True
        return bool(np.max(np.abs(self.colorants - srgb_colorants())) < SRGB_TOLERANCE)


def _srgb_curve(c: np.ndarray) -> np.ndarray:
    from .srgb import srgb_decode
    import torch

    return srgb_decode(torch.from_numpy(np.asarray(c, np.float64))).numpy()


@functools.lru_cache(maxsize=1)
def _bradford_d65_to_d50() -> np.ndarray:
    import colour

    d65 = colour.xy_to_XYZ(colour.CCS_ILLUMINANTS["CIE 1931 2 Degree Standard Observer"]["D65"])
    return np.asarray(colour.adaptation.matrix_chromatic_adaptation_VonKries(d65, D50_XYZ, "Bradford"))


@functools.lru_cache(maxsize=1)
def srgb_colorants() -> np.ndarray:
    """The colorants an sRGB profile carries: sRGB's primaries adapted to D50 by Bradford (ICC.1:2022 Annex E)."""
    from ..render.colour import xyz_to_srgb_matrix

    return _bradford_d65_to_d50() @ np.linalg.inv(xyz_to_srgb_matrix())


# -- parsing ---------------------------------------------------------------------------------------

def _s15(b: bytes) -> float:
    return struct.unpack(">i", b)[0] / 65536.0


def _tags(data: bytes) -> dict[bytes, bytes]:
    (count,) = struct.unpack(">I", data[128:132])
    if 132 + 12 * count > len(data):
        raise IccError("tag table runs past the end of the profile")
    out = {}
    for i in range(count):
        sig, off, size = struct.unpack(">4sII", data[132 + 12 * i: 144 + 12 * i])
        if off + size > len(data):
            raise IccError(f"tag {sig.decode('latin-1')!r} runs past the end of the profile")
        out[sig] = data[off: off + size]
    return out


def _curve(t: bytes, name: str) -> Curve:
    kind = t[:4]
    if kind == b"curv":
        (n,) = struct.unpack(">I", t[8:12])
        if n == 0:
            return Curve("identity")
        if n == 1:
            (g,) = struct.unpack(">H", t[12:14])
            return Curve("gamma", (g / 256.0,))  # u8Fixed8Number
        if len(t) < 12 + 2 * n:
            raise IccError(f"{name}: curve table shorter than its {n} entries")
        vals = np.frombuffer(t[12: 12 + 2 * n], ">u2").astype(np.float64) / 65535.0
        return Curve("table", table=tuple(vals.tolist()))
    if kind == b"para":
        (ftype,) = struct.unpack(">H", t[8:10])
        nparams = {0: 1, 1: 3, 2: 4, 3: 5, 4: 7}.get(ftype)
        if nparams is None or len(t) < 12 + 4 * nparams:
            raise IccError(f"{name}: unknown or short parametric curve (type {ftype})")
        p = [_s15(t[12 + 4 * i: 16 + 4 * i]) for i in range(nparams)]
        g, a, b, c, d, e, f = (p + [0.0] * 6)[:7]  # Table 68's parameters in order; those a type lacks unused
        if ftype in (1, 2) and a == 0:
            raise IccError(f"{name}: parametric curve with a = 0")
        return Curve("parametric", (ftype, g, a, b, c, d, e, f))
    raise IccError(f"{name}: curve of type {kind.decode('latin-1')!r}, expected 'curv' or 'para'")


def _xyz(t: bytes, name: str) -> np.ndarray:
    if t[:4] != b"XYZ " or len(t) < 20:
        raise IccError(f"{name}: expected an XYZType")
    return np.array([_s15(t[8 + 4 * i: 12 + 4 * i]) for i in range(3)])


def _description(t: bytes | None) -> str:
    if not t:
        return ""
    try:
        if t[:4] == b"desc":
            (n,) = struct.unpack(">I", t[8:12])
            return t[12: 12 + n].split(b"\0")[0].decode("latin-1").strip()
        if t[:4] == b"mluc":
            n, size = struct.unpack(">II", t[8:16])
            if n:
                length, off = struct.unpack(">II", t[20:28])
                return t[off: off + length].decode("utf-16-be", "replace").strip("\0 ")
    except (struct.error, UnicodeDecodeError):
        pass
    return ""


def parse_icc(data: bytes) -> IccProfile | None:
    """An :class:`IccProfile` of a matrix/TRC RGB or grey-TRC profile; None for any other kind (lookup-table,
    CMYK, Lab); :class:`IccError` for bytes that are not a well-formed profile."""
    if len(data) < 132 or data[36:40] != b"acsp":
        raise IccError("not an ICC profile (no 'acsp' signature)")
    space, pcs = data[16:20], data[20:24]
    tags = _tags(data)
    desc = _description(tags.get(b"desc"))
    if space == b"GRAY" and b"kTRC" in tags:
        return IccProfile(desc, (_curve(tags[b"kTRC"], "kTRC"),), None)
    need = (b"rTRC", b"gTRC", b"bTRC", b"rXYZ", b"gXYZ", b"bXYZ")
    if space != b"RGB " or pcs != b"XYZ " or not all(k in tags for k in need):
        return None
    curves = tuple(_curve(tags[k], k.decode()) for k in need[:3])
    colorants = np.stack([_xyz(tags[k], k.decode()) for k in need[3:]], 1)
    if not np.isfinite(colorants).all() or abs(np.linalg.det(colorants)) < 1e-6:
        raise IccError("colorants do not span a colour space")
    return IccProfile(desc, curves, colorants)


def icc_sensitivities(rgb_from_xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Spectral sensitivities (wavelengths [nm] (K,), curves (K, 3)) of a profile's linear RGB: 683 lm/W times the
    CIE 1931 colour-matching functions through its :meth:`IccProfile.rgb_from_xyz`, as the default camera is the CIE
    observer through sRGB's matrix (:func:`skyfit.fit.model.channel_matrix`)."""
    from ..atmosphere.constants import LUMINOUS_EFFICACY_LM_PER_W
    from ..render.colour import _cmfs

    wl, cmf = _cmfs()
    return wl, LUMINOUS_EFFICACY_LM_PER_W * cmf @ np.asarray(rgb_from_xyz, np.float64).T





# -- writing (the synthetic generator's P3 and Adobe RGB photos, and the tests) ------------------

def _s15_bytes(v: float) -> bytes:
    return struct.pack(">i", int(round(v * 65536.0)))


def _curve_bytes(curve: Curve) -> bytes:
    if curve.kind == "identity":
        return b"curv" + bytes(4) + struct.pack(">I", 0)
    if curve.kind == "gamma":
        return b"curv" + bytes(4) + struct.pack(">IH", 1, int(round(curve.params[0] * 256))) + bytes(2)
    if curve.kind == "table":
        t = np.round(np.asarray(curve.table) * 65535).astype(">u2").tobytes()
        return b"curv" + bytes(4) + struct.pack(">I", len(curve.table)) + t + bytes((-len(t)) % 4)
    ftype, *p = curve.params
    n = {0: 1, 1: 3, 2: 4, 3: 5, 4: 7}[ftype]
    return b"para" + bytes(4) + struct.pack(">HH", ftype, 0) + b"".join(_s15_bytes(v) for v in p[:n])


def build_icc(description: str, curves, colorants: np.ndarray | None) -> bytes:
    """Bytes of a v4 matrix/TRC RGB (colorants (3, 3), columns R, G, B in PCS XYZ) or grey-TRC (colorants None)
    display profile with the given :class:`Curve` (one, shared, or one per channel); read back by :func:`parse_icc`
    and by LittleCMS (the tests check both)."""
    curves = tuple(curves) if isinstance(curves, (list, tuple)) else (curves,)
    text = description.encode("utf-16-be")
    desc = b"mluc" + bytes(4) + struct.pack(">II", 1, 12) + b"enUS" + struct.pack(">II", len(text), 28) + text
    tags = [(b"desc", desc), (b"wtpt", b"XYZ " + bytes(4) + b"".join(_s15_bytes(v) for v in D50_XYZ))]
    if colorants is None:
        tags.append((b"kTRC", _curve_bytes(curves[0])))
    else:
        col = np.asarray(colorants, np.float64)
        for i, k in enumerate((b"rXYZ", b"gXYZ", b"bXYZ")):
            tags.append((k, b"XYZ " + bytes(4) + b"".join(_s15_bytes(v) for v in col[:, i])))
        for i, k in enumerate((b"rTRC", b"gTRC", b"bTRC")):
            tags.append((k, _curve_bytes(curves[min(i, len(curves) - 1)])))
    table_end = 132 + 12 * len(tags)
    body, entries, off = b"", b"", table_end
    for sig, data in tags:
        data = data + bytes((-len(data)) % 4)
        entries += struct.pack(">4sII", sig, off, len(data))
        body += data
        off += len(data)
    size = table_end + len(body)
    header = (struct.pack(">I4sI4s4s4s", size, b"lcms", 0x04300000, b"mntr", b"GRAY" if colorants is None else b"RGB ",
                          b"XYZ ") + bytes(12) + b"acsp" + bytes(4 * 4 + 8 + 4)
              + b"".join(_s15_bytes(v) for v in D50_XYZ) + bytes(4 + 16 + 28))
    assert len(header) == 128
    return header + struct.pack(">I", len(tags)) + entries + body


def profile_for(name: str) -> bytes:
    """ICC bytes of a standard RGB space of colour-science (``"Display P3"``, ``"Adobe RGB (1998)"``, ``"sRGB"``...)
    with its primaries adapted to D50 by Bradford and its tone curve as the profile of that space writes it (the sRGB
    piecewise curve as parametric type 3; Adobe RGB's power 563/256)."""
    import colour

    cs = colour.RGB_COLOURSPACES[name]
    npm = colour.normalised_primary_matrix(cs.primaries, cs.whitepoint)
    white = colour.xy_to_XYZ(cs.whitepoint)
    adapt = colour.adaptation.matrix_chromatic_adaptation_VonKries(white, D50_XYZ, "Bradford")
    if name.startswith("Adobe RGB"):
        curve = Curve("gamma", (563.0 / 256.0,))
    else:
        curve = Curve("parametric", (3, 2.4, 1 / 1.055, 0.055 / 1.055, 1 / 12.92, 0.04045, 0.0, 0.0))
    return build_icc(name, curve, adapt @ npm)

__all__ = ["Curve", "IccError", "IccProfile", "build_icc", "icc_sensitivities", "parse_icc", "profile_for", "srgb_colorants"]
