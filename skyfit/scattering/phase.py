"""Phase functions, normalised to 1 over the sphere [1/sr]."""
from __future__ import annotations

import math

import torch
from torch import Tensor

PHASE_FUNCTIONS = ("rayleigh", "cornette_shanks", "henyey_greenstein")

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


def mie_phase(nu: Tensor, g: Tensor, name: str = "cornette_shanks") -> Tensor:
    """The aerosol phase function by name (``cornette_shanks`` or ``henyey_greenstein``)."""
    if name == "cornette_shanks":
        return cornette_shanks_phase(nu, g)
    if name == "henyey_greenstein":
        return henyey_greenstein_phase(nu, g)
    raise ValueError(f"unknown Mie phase function {name!r}; valid: cornette_shanks, henyey_greenstein")
