"""Phase functions, normalised to 1 over the sphere [1/sr]."""
from __future__ import annotations

import math

import torch
from torch import Tensor

PHASE_FUNCTIONS = ("rayleigh", "cornette_shanks", "henyey_greenstein", "two_term_hg")

_INV_4PI = 1.0 / (4.0 * math.pi)


def rayleigh_phase(nu: Tensor) -> Tensor:
    """Rayleigh phase ``3 / (16 pi) (1 + nu^2)`` (Bruneton & Neyret 2008, eq. 2; Gałaj 2021 eq. 4).

    Args:
        nu: cosine of the scattering angle, shape (...). [1]
    """
    return 3.0 / (16.0 * math.pi) * (1.0 + nu * nu)


def _one_plus_g2_minus_2gnu(g: Tensor, nu: Tensor) -> Tensor:
    # 1 + g^2 - 2 g nu as a sum of non-negative terms, so that it never cancels:
    # (1 - g)^2 + 2 g (1 - nu) for g >= 0 (forward peak, g -> 1, nu -> 1) and
    # (1 + g)^2 - 2 g (1 + nu) for g < 0 (backward peak, g -> -1, nu -> -1; there the
    # first form lost 23% in float32 and 1e-9 in float64 at g = -0.999, nu = -1).
    g = torch.as_tensor(g, dtype=nu.dtype, device=nu.device)
    return torch.where(g >= 0, (1.0 - g) ** 2 + 2.0 * g * (1.0 - nu), (1.0 + g) ** 2 - 2.0 * g * (1.0 + nu))


def cornette_shanks_phase(nu: Tensor, g: Tensor) -> Tensor:
    """Cornette-Shanks phase (Bruneton & Neyret 2008 eq. 4; Gałaj 2021 eq. 5).

    ``3 / (8 pi) (1 - g^2)(1 + nu^2) / ((2 + g^2)(1 + g^2 - 2 g nu)^{3/2})``.

    Args:
        nu: cosine of the scattering angle, shape (...). [1]
        g: asymmetry in (-1, 1), shape () or broadcastable. [1]
    """
    k = 3.0 / (8.0 * math.pi) * (1.0 - g * g) / (2.0 + g * g)
    return k * (1.0 + nu * nu) / _one_plus_g2_minus_2gnu(g, nu) ** 1.5


def henyey_greenstein_phase(nu: Tensor, g: Tensor) -> Tensor:
    """Henyey-Greenstein phase ``(1 - g^2) / (4 pi (1 + g^2 - 2 g nu)^{3/2})`` (Henyey & Greenstein 1941)."""
    return _INV_4PI * (1.0 - g * g) / _one_plus_g2_minus_2gnu(g, nu) ** 1.5


def two_term_hg_phase(nu: Tensor, g1: Tensor, g2: Tensor, weight: Tensor) -> Tensor:
    """Two-term Henyey-Greenstein phase ``f HG(g1) + (1 - f) HG(g2)`` [1/sr].

    A forward lobe g1 > 0 and a backward lobe g2 < 0 mixed with weight f (Kattawar 1975,
    JQSRT 15, 839, eq. 5; the form of Irvine 1965). Each lobe is normalised, so the mixture
    is for every f in [0, 1]; f = 1 is :func:`henyey_greenstein_phase` (g1). Its asymmetry
    is f g1 + (1 - f) g2.

    Args:
        nu: cosine of the scattering angle, shape (...). [1]
        g1: forward asymmetry in (-1, 1), shape () or broadcastable. [1]
        g2: backward asymmetry in (-1, 1), shape () or broadcastable. [1]
        weight: f in [0, 1], shape () or broadcastable. [1]
    """
    return weight * henyey_greenstein_phase(nu, g1) + (1.0 - weight) * henyey_greenstein_phase(nu, g2)


def mie_phase(nu: Tensor, g: Tensor, name: str = "cornette_shanks", g2: Tensor | None = None,
              weight: Tensor | None = None) -> Tensor:
    """The aerosol phase function by name: ``cornette_shanks``, ``henyey_greenstein`` or ``two_term_hg``
    (which needs ``g2`` and ``weight``; ``g`` is its forward g1) [1/sr]."""
    if name == "cornette_shanks":
        return cornette_shanks_phase(nu, g)
    if name == "henyey_greenstein":
        return henyey_greenstein_phase(nu, g)
    if name == "two_term_hg":
        if g2 is None or weight is None:
            raise ValueError("the two_term_hg phase needs g2 and weight (mie.g2, mie.hg_weight)")
        return two_term_hg_phase(nu, g, g2, weight)
    raise ValueError(f"unknown Mie phase function {name!r}; valid: cornette_shanks, henyey_greenstein, two_term_hg")


def atmosphere_mie_phase(nu: Tensor, atm) -> Tensor:
    """The aerosol phase of an :class:`~skyfit.atmosphere.Atmosphere` (its ``mie_phase`` with ``mie_g``,
    and ``mie_g2`` / ``mie_hg_weight`` for ``two_term_hg``) at ``nu``, shape (...). [1/sr]"""
    return mie_phase(nu, atm.mie_g, atm.mie_phase, atm.mie_g2, atm.mie_hg_weight)
