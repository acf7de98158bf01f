"""Phase functions, normalised to 1 over the sphere [1/sr]."""
from __future__ import annotations

import math

import torch
from torch import Tensor

from ..atmosphere.mie import lognormal_mie_optics

PHASE_FUNCTIONS = ("rayleigh", "cornette_shanks", "henyey_greenstein", "two_term_hg", "lognormal_mie")

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


def tabulated_phase(nu: Tensor, cosines: Tensor, table: Tensor) -> Tensor:
    """A phase tabulated per wavelength, linear in nu between its nodes, shape (..., W). [1/sr]

    Linear in nu (not in the angle) so that d p / d nu stays finite at nu = +-1; beyond the end
    nodes (round-off) the end segments extend. The interpolation runs in float64 (nodes 0.01 deg
    from the forward direction differ from 1 by 1.5e-8, below float32's resolution) and the result
    is cast to ``nu``'s dtype.

    Args:
        nu: cosine of the scattering angle, shape (...). [1]
        cosines: ascending nodes from -1 to 1, shape (A,). [1]
        table: the phase at the nodes, shape (W, A). [1/sr]
    """
    c = cosines.to(dtype=torch.float64, device=nu.device)
    tab = table.to(dtype=torch.float64).transpose(0, 1)  # (A, W)
    x = nu.to(torch.float64)
    i = torch.searchsorted(c, x.detach().contiguous()).clamp_(1, c.numel() - 1)
    c0, c1 = c[i - 1], c[i]
    f = ((x - c0) / (c1 - c0)).unsqueeze(-1)
    return (tab[i - 1] * (1.0 - f) + tab[i] * f).to(nu.dtype)


def lognormal_mie_phase(nu: Tensor, wavelengths: Tensor, median_radius: Tensor, geometric_sigma: Tensor,
                        refractive_index, coarse: tuple[Tensor, Tensor, Tensor] | None = None) -> Tensor:
    """Mie phase of a log-normal size distribution of spheres, per wavelength, shape (..., W). [1/sr]

    The distribution average of the spheres' S11 / (pi x^2 Q_sca) weighted by their scattering
    cross-sections (Bohren & Huffman 1983 eqs. 4.74, 4.77; :func:`skyfit.atmosphere.mie.lognormal_mie_optics`),
    linear in nu between :data:`skyfit.atmosphere.mie.PHASE_COSINES` (:func:`tabulated_phase`);
    it integrates to 1 over the sphere to round-off and is differentiable in r_g and sigma_g.

    Args:
        nu: cosine of the scattering angle, shape (...). [1]
        wavelengths: shape (W,). [nm]
        median_radius: r_g, shape (). [m]
        geometric_sigma: sigma_g in (1, 4], shape (). [1]
        refractive_index: (n, k) of m = n + ik. [1]
        coarse: optional coarse mode (r_c [m], sigma_c [1], fine-mode fraction eta of the 550 nm extinction [1]),
            mixed in by its scattering cross-section (:func:`skyfit.atmosphere.mie.lognormal_mie_optics`).
    """
    optics = lognormal_mie_optics(wavelengths, median_radius, geometric_sigma, refractive_index, coarse)
    return tabulated_phase(nu, optics.cosines, optics.phase)


def mie_phase(nu: Tensor, g: Tensor, name: str = "cornette_shanks", g2: Tensor | None = None,
              weight: Tensor | None = None) -> Tensor:
    """The aerosol phase function by name: ``cornette_shanks``, ``henyey_greenstein`` or ``two_term_hg``
    (which needs ``g2`` and ``weight``; ``g`` is its forward g1) [1/sr]. ``lognormal_mie`` depends on the
    wavelength and has no g form: :func:`lognormal_mie_phase`, or :func:`spectral_mie_phase` of an atmosphere."""
    if name == "cornette_shanks":
        return cornette_shanks_phase(nu, g)
    if name == "henyey_greenstein":
        return henyey_greenstein_phase(nu, g)
    if name == "two_term_hg":
        if g2 is None or weight is None:
            raise ValueError("the two_term_hg phase needs g2 and weight (mie.g2, mie.hg_weight)")
        return two_term_hg_phase(nu, g, g2, weight)
    if name == "lognormal_mie":
        raise ValueError("the lognormal_mie phase depends on the wavelength: use lognormal_mie_phase or spectral_mie_phase")
    raise ValueError(f"unknown Mie phase function {name!r}; valid: cornette_shanks, henyey_greenstein, two_term_hg, "
                     "lognormal_mie")


def atmosphere_mie_phase(nu: Tensor, atm) -> Tensor:
    """The aerosol phase of an :class:`~skyfit.atmosphere.Atmosphere` (its ``mie_phase`` with ``mie_g``,
    and ``mie_g2`` / ``mie_hg_weight`` for ``two_term_hg``) at ``nu``, shape (...). [1/sr]"""
    return mie_phase(nu, atm.mie_g, atm.mie_phase, atm.mie_g2, atm.mie_hg_weight)


def spectral_mie_phase(nu: Tensor, atm) -> Tensor:
    """The aerosol phase of an atmosphere with a trailing wavelength axis, ready to multiply (..., W) spectra:
    (..., W) for ``lognormal_mie`` (:func:`lognormal_mie_phase` on ``atm.wavelengths``), (..., 1) for the
    phases of one shape at every wavelength (:func:`atmosphere_mie_phase`). [1/sr]"""
    if atm.mie_phase == "lognormal_mie":
        return lognormal_mie_phase(nu, atm.wavelengths, atm.mie_median_radius, atm.mie_geometric_sigma,
                                   atm.mie_refractive_index, atm.mie_coarse_mode)
    return atmosphere_mie_phase(nu, atm).unsqueeze(-1)
