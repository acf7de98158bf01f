"""The sRGB transfer function (IEC 61966-2-1), written in torch so that it is differentiable.

It equals ``colour.cctf_decoding(..., function='sRGB')`` and ``colour.cctf_encoding``. LDR photos
are decoded with it (:mod:`skyfit.camera.photo_io`) and synthetic 8-bit photos encoded
(:mod:`skyfit.camera.sensor`).
"""
from __future__ import annotations

import torch
from torch import Tensor

SRGB_A: float = 0.055
"""sRGB transfer-function offset a [1]. IEC 61966-2-1:1999, §4.7 (also colour-science's ``eotf_inverse_sRGB``)."""
SRGB_GAMMA: float = 2.4
"""sRGB transfer-function exponent [1]. IEC 61966-2-1:1999."""
SRGB_LINEAR_SLOPE: float = 12.92
"""Slope of the linear toe of the sRGB curve [1]. IEC 61966-2-1:1999."""
SRGB_ENCODED_BREAK: float = 0.04045
"""Encoded value where the toe ends [1]. IEC 61966-2-1:1999."""
SRGB_LINEAR_BREAK: float = 0.0031308
"""Linear value where the toe ends [1]. IEC 61966-2-1:1999."""

def srgb_decode(encoded: Tensor) -> Tensor:
    """Linear values from sRGB-encoded values (the sRGB EOTF), differentiable.

    Same formula as ``colour.cctf_decoding(v, function='sRGB')``
    (IEC 61966-2-1): ``v / 12.92`` for ``v <= 0.04045``, else
    ``((v + 0.055) / 1.055) ** 2.4``. Both branches are evaluated on clamped
    arguments so that neither produces NaN for the values it does not serve.

    Args:
        encoded: shape (...), nominally in [0, 1]. [1]

    Returns:
        Linear values, shape (...). [1]
    """
    low = encoded / SRGB_LINEAR_SLOPE
    high = ((torch.clamp(encoded, min=SRGB_ENCODED_BREAK) + SRGB_A) / (1 + SRGB_A)) ** SRGB_GAMMA
    return torch.where(encoded <= SRGB_ENCODED_BREAK, low, high)


def srgb_encode(linear: Tensor) -> Tensor:
    """sRGB-encoded values from linear values (inverse EOTF), differentiable.

    Same formula as ``colour.cctf_encoding(v, function='sRGB')``.

    Args:
        linear: shape (...), nominally in [0, 1]. [1]

    Returns:
        Encoded values, shape (...). [1]
    """
    low = linear * SRGB_LINEAR_SLOPE
    high = (1 + SRGB_A) * torch.clamp(linear, min=SRGB_LINEAR_BREAK) ** (1 / SRGB_GAMMA) - SRGB_A
    return torch.where(linear <= SRGB_LINEAR_BREAK, low, high)


def srgb_encode_slope(linear: Tensor) -> Tensor:
    """d srgb_encode / d linear, shape (...)."""
    high = (1 + SRGB_A) / SRGB_GAMMA * torch.clamp(linear, min=SRGB_LINEAR_BREAK) ** (1 / SRGB_GAMMA - 1)
    return torch.where(linear <= SRGB_LINEAR_BREAK, torch.full_like(linear, SRGB_LINEAR_SLOPE), high)


__all__ = [
    "SRGB_A",
    "SRGB_ENCODED_BREAK",
    "SRGB_GAMMA",
    "SRGB_LINEAR_BREAK",
    "SRGB_LINEAR_SLOPE",
    "srgb_decode",
    "srgb_encode",
    "srgb_encode_slope",
]
