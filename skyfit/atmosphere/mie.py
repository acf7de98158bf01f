"""Aerosol optics of a log-normal size distribution of homogeneous spheres (Mie theory).

One physical description instead of independent Angstrom exponent, single-scattering albedo
and phase asymmetry: a number distribution of radii r

    n(r) dr = N / (sqrt(2 pi) ln(sigma_g) r) exp(-(ln r - ln r_g)^2 / (2 ln^2 sigma_g)) dr

(the log-normal of Hansen & Travis 1974, Space Sci. Rev. 16, 527, eq. 2.60 with r_g the
median radius and sigma_g the geometric standard deviation; truncated here to
:data:`LOGNORMAL_RADIUS_RANGE_M`) and one complex refractive index m = n + ik. For each
sphere, Mie theory (Bohren & Huffman 1983, *Absorption and Scattering of Light by Small
Particles*, Ch. 4) gives the extinction and scattering efficiencies Q_ext, Q_sca (eqs. 4.61,
4.62), the asymmetry g and the amplitudes S1, S2 (eq. 4.74); these come from miepython
(Prahl), computed once in float64 on a fixed grid of size parameters x = 2 pi r / lambda and
scattering angles (:func:`mie_size_table`). The distribution averages are then torch sums over
that grid, differentiable in r_g and sigma_g (:func:`lognormal_mie_optics`):

    C(lambda)  = int pi r^2 Q(2 pi r / lambda) n(r) dr / int n(r) dr              [m^2 per particle]
    p(nu, lambda) = int r^2 Q_sca S11(nu) / (pi x^2 Q_sca) n dr / int r^2 Q_sca n dr  [1/sr]

with S11 = (|S1|^2 + |S2|^2) / 2 (Bohren & Huffman eq. 4.77). In t = ln x the area-weighted
log-normal is again a normal density, r^2 n(r) dln r ~ N(t; ln(2 pi r_g / lambda) + 2 ln^2
sigma_g, ln sigma_g) dt, so with Q (and Q_sca S11 / x^2) linear between the nodes of the
x grid every integral is a sum of node values times exact Gaussian integrals of the
nodes' hat functions (:func:`lognormal_hat_weights`, with ``erfc``): no quadrature error in
the distribution's width, and a narrow distribution (sigma_g -> 1) tends to the single
particle interpolated at x.

Everything lives in the atmosphere layer because the config and the fit build an
:class:`~skyfit.atmosphere.Atmosphere`'s extinction and scattering spectra from it; the phase
that the renderers evaluate is :func:`skyfit.scattering.phase.lognormal_mie_phase`.
"""
from __future__ import annotations

import dataclasses
import functools
import math

import numpy as np
import torch
from torch import Tensor

LOGNORMAL_RADIUS_RANGE_M: tuple[float, float] = (1e-9, 20e-6)
"""Radii between which the log-normal is kept (truncated outside) [m]. Below 1 nm a particle's
scattering (~r^6) is nothing against the distribution's; 20 um bounds the Mie table at
x = 2 pi 20 um / 250 nm = 503 (larger particles are not haze but drops and dust grains, whose
forward peak, narrower than 0.1 deg, the angle grid could not carry)."""

MEDIAN_RADIUS_RANGE_M: tuple[float, float] = (1e-9, 20e-6)
"""Median radii r_g an :class:`~skyfit.atmosphere.Atmosphere` accepts [m] (within the truncation)."""

GEOMETRIC_SIGMA_RANGE: tuple[float, float] = (1.0, 4.0)
"""Open/closed range (1, 4] of the geometric standard deviation sigma_g [1]: 1 is one radius
(the single particle), 4 is broader than any single aerosol mode (AERONET's modes have
1.5-2.5; Dubovik et al. 2002, J. Atmos. Sci. 59, 590, Table 1)."""

LN_X_STEP: float = 0.02
"""Node spacing of the size-parameter table in ln x [1]: 2 % in radius. Linear interpolation
of Q in ln x then errs by (h p)^2 / 8 relative for a power law x^p: 1.3e-3 in the Rayleigh
regime (Q_sca ~ x^4), less where Q is smooth; resonance ripples narrower than 2 % in x are
sampled, not averaged (they average out in any sigma_g >= 1.05 distribution)."""

_BLOCK = 64
"""Nodes of the x table computed together and cached (a fit that moves r_g reuses them)."""

WAVELENGTH_RANGE_NM: tuple[float, float] = (250.0, 5000.0)
"""Wavelengths the table covers with the radius range above [nm]: x from 1.3e-6 to 503."""


def _scattering_angles_deg() -> np.ndarray:
    # dense near the forward peak (width ~ 1/x rad: 0.11 deg at x = 503): 0, 0.01 deg to 10 deg
    # geometrically (5.3 % steps), then every 0.5 deg to 180
    return np.concatenate([[0.0], np.geomspace(0.01, 10.0, 131), np.arange(10.5, 180.0 + 1e-9, 0.5)])


SCATTERING_ANGLES_DEG: np.ndarray = _scattering_angles_deg()
"""Scattering angles of the tabulated phase [deg]: 0; 0.01-10 deg geometric (131); 10.5-180 every 0.5 deg."""

PHASE_COSINES: np.ndarray = np.cos(np.radians(SCATTERING_ANGLES_DEG))[::-1].copy()
"""cos(theta) of :data:`SCATTERING_ANGLES_DEG`, ascending from -1 to 1: the nodes the phase is linear
between (:func:`skyfit.scattering.phase.tabulated_phase`) [1]."""


def check_refractive_index(refractive_index) -> tuple[float, float]:
    """(n, k) of m = n + ik as floats; ValueError unless n > 0 and k >= 0 (absorption) are finite."""
    try:
        n, k = (float(v) for v in refractive_index)
    except (TypeError, ValueError):
        raise ValueError(f"refractive_index must be [real, imaginary] (m = n + ik), got {refractive_index!r}") from None
    if not (math.isfinite(n) and math.isfinite(k) and n > 0 and k >= 0):
        raise ValueError(f"refractive_index must have a real part > 0 and an imaginary part >= 0 (absorption), "
                         f"got [{n}, {k}]")
    return n, k


def _pi_tau(mu: np.ndarray, n_terms: int) -> tuple[np.ndarray, np.ndarray]:
    """Angular functions pi_n, tau_n (n = 1..n_terms) at ``mu``, shape (n_terms, A): Bohren & Huffman eq. 4.47,
    pi_n = (2n - 1)/(n - 1) mu pi_{n-1} - n/(n - 1) pi_{n-2}, tau_n = n mu pi_n - (n + 1) pi_{n-1}."""
    pi = np.zeros((n_terms + 1, mu.size))
    tau = np.zeros((n_terms + 1, mu.size))
    pi[1] = 1.0
    tau[1] = mu
    for n in range(2, n_terms + 1):
        pi[n] = ((2 * n - 1) * mu * pi[n - 1] - n * pi[n - 2]) / (n - 1)
        tau[n] = n * mu * pi[n] - (n + 1) * pi[n - 1]
    return pi[1:], tau[1:]


@functools.lru_cache(maxsize=64)
def _table_block(n: float, k: float, block: int) -> tuple[np.ndarray, ...]:
    """Single-particle table of nodes ``block * _BLOCK ... + _BLOCK - 1`` (t = node * LN_X_STEP): float64
    (ln x, Q_ext, Q_sca, g, phase (K, A) [1/sr] each row normalised on the nodes, raw normalisation)."""
    try:
        # miepython imports scipy.special (0.8 s): loaded only when a lognormal_mie table is first built
        import miepython
    except ImportError:  # pragma: no cover - a dependency of skyfit; fail at the point of use (STYLE.md)
        raise ImportError("you must install 'miepython' (pip install 'miepython>=3.3,<4') to use the lognormal_mie "
                          "aerosol phase") from None
    nodes = np.arange(block * _BLOCK, (block + 1) * _BLOCK)
    t = nodes * LN_X_STEP
    x = np.exp(t)
    m = complex(n, -k)  # miepython's convention: m = n - ik absorbs
    q_ext, q_sca, _, g = miepython.efficiencies_mx(m, x)
    mu = PHASE_COSINES
    phase = np.empty((x.size, mu.size))
    raw = np.empty(x.size)
    coefficients = [miepython.an_bn(m, float(xi), 0) for xi in x]
    pi_all, tau_all = _pi_tau(mu, max(a.size for a, _ in coefficients))  # once per block, sliced per sphere
    for i, (xi, (a, b)) in enumerate(zip(x, coefficients)):
        nt = a.size
        pi, tau = pi_all[:nt], tau_all[:nt]
        nn = np.arange(1, nt + 1)
        c = (2 * nn + 1) / (nn * (nn + 1.0))
        s1 = (c * a) @ pi + (c * b) @ tau  # Bohren & Huffman eq. 4.74
        s2 = (c * a) @ tau + (c * b) @ pi
        s11 = 0.5 * (np.abs(s1) ** 2 + np.abs(s2) ** 2)  # eq. 4.77
        # p = S11 / (pi x^2 Q_sca), normalised to 1 over the sphere; here by the nodes' own trapezoid rule in mu
        # (the exact integral of the piecewise-linear phase the renderers evaluate), so that every row, and every
        # distribution average of rows, integrates to 1; raw: that integral before, against Q_sca (1 when resolved)
        p = s11 / (math.pi * xi * xi * q_sca[i]) if q_sca[i] > 0 else np.full(mu.size, 0.25 / math.pi)
        integral = 2 * math.pi * np.sum(0.5 * (p[1:] + p[:-1]) * np.diff(mu))
        raw[i] = integral
        phase[i] = p / integral
    return t, np.asarray(q_ext, float), np.asarray(q_sca, float), np.asarray(g, float), phase, raw


@dataclasses.dataclass(frozen=True)
class MieSizeTable:
    """Single-sphere Mie quantities on nodes t_k = k LN_X_STEP of t = ln x, float64 numpy arrays.

    Attributes (K nodes, A = len(PHASE_COSINES) angles):
        ln_x: t_k, shape (K,). [1]
        q_ext, q_sca: extinction and scattering efficiencies, shape (K,). [1]
        g: asymmetry parameter <cos theta>, shape (K,). [1]
        phase: single-sphere phase at PHASE_COSINES, each row integrating to 1 over the sphere, shape (K, A). [1/sr]
        raw_normalisation: 2 pi int p dmu of the rows on the nodes before that normalisation, shape (K,) (1 where
            the angle grid resolves the phase). [1]
    """

    ln_x: np.ndarray
    q_ext: np.ndarray
    q_sca: np.ndarray
    g: np.ndarray
    phase: np.ndarray
    raw_normalisation: np.ndarray


def mie_size_table(refractive_index, k_lo: int, k_hi: int) -> MieSizeTable:
    """The single-sphere table of nodes k_lo..k_hi (inclusive; t = k LN_X_STEP = ln x) for m = n + ik.

    Computed block by block with miepython in float64 (Bohren & Huffman 1983 Ch. 4) and cached
    in memory: a full table (x from 1e-3 to 500) takes about a second, once per refractive index.
    """
    n, k = check_refractive_index(refractive_index)
    b_lo, b_hi = k_lo // _BLOCK, k_hi // _BLOCK
    parts = [_table_block(n, k, b) for b in range(b_lo, b_hi + 1)]
    cat = [np.concatenate([p[i] for p in parts]) for i in range(6)]
    s = slice(k_lo - b_lo * _BLOCK, k_hi - b_lo * _BLOCK + 1)
    return MieSizeTable(*(c[s] for c in cat))


@functools.lru_cache(maxsize=32)
def _torch_table(n: float, k: float, k_lo: int, k_hi: int, dtype: torch.dtype, device: str):
    tab = mie_size_table((n, k), k_lo, k_hi)
    T = functools.partial(torch.as_tensor, dtype=dtype, device=device)
    return (T(tab.ln_x), T(tab.q_ext), T(tab.q_sca), T(tab.q_sca * tab.g), T(tab.q_sca[:, None] * tab.phase))


def _normal_mass(za: Tensor, zb: Tensor) -> Tensor:
    """Phi(zb) - Phi(za) for za <= zb without cancellation in either tail (erfc of the far side)."""
    r2 = 1.0 / math.sqrt(2.0)
    upper = 0.5 * (torch.erfc(za * r2) - torch.erfc(zb * r2))
    lower = 0.5 * (torch.erfc(-zb * r2) - torch.erfc(-za * r2))
    return torch.where(za > 0, upper, lower)


def lognormal_hat_weights(nodes: Tensor, mean: Tensor, s: Tensor, lo: Tensor, hi: Tensor) -> Tensor:
    """Integrals of the nodes' hat functions against the normal density N(t; mean, s) on [lo, hi].

    w_k = int_lo^hi phi_k(t) N(t; mean, s) dt with phi_k the piecewise-linear hat of node k on the
    uniform ``nodes``, so that int f N dt = sum_k w_k f(t_k) exactly for f linear between nodes. Per
    segment [a, b] (clipped to [lo, hi]) of length h from node t_k: I0 = Phi(b) - Phi(a) and
    I1 = int (t - t_k) N dt = (mean - t_k) I0 - s (e^{-z_b^2/2} - e^{-z_a^2/2}) / sqrt(2 pi), giving
    I1 / h to node k + 1 and I0 - I1 / h to node k.

    Args:
        nodes: equally spaced t_k, shape (K,), K >= 2. [1]
        mean, s: the normal's mean and standard deviation (> 0), shape (W,) and () or (W,). [1]
        lo, hi: integration limits (the truncation), shape (W,). [1]

    Returns:
        Weights, shape (W, K); their sum is Phi((hi - mean) / s) - Phi((lo - mean) / s).
    """
    h = nodes[1] - nodes[0]
    mean, s = mean.unsqueeze(-1), s.reshape(-1, 1) if s.dim() else s
    a = torch.minimum(torch.maximum(nodes[:-1], lo.unsqueeze(-1)), hi.unsqueeze(-1))  # (W, K - 1)
    b = torch.minimum(torch.maximum(nodes[1:], lo.unsqueeze(-1)), hi.unsqueeze(-1))
    za, zb = (a - mean) / s, (b - mean) / s
    i0 = _normal_mass(za, zb)
    i1 = (mean - nodes[:-1]) * i0 - s * (torch.exp(-0.5 * zb * zb) - torch.exp(-0.5 * za * za)) / math.sqrt(2 * math.pi)
    right = i1 / h
    left = i0 - right
    zero = torch.zeros_like(left[..., :1])
    return torch.cat([left, zero], -1) + torch.cat([zero, right], -1)


@dataclasses.dataclass
class LognormalOptics:
    """Distribution-averaged optics per wavelength (:func:`lognormal_mie_optics`).

    Attributes (W wavelengths, A = len(PHASE_COSINES)):
        extinction, scattering: mean cross-sections per particle of the (truncated) distribution, shape (W,). [m^2]
        ssa: single-scattering albedo scattering / extinction, shape (W,). [1]
        asymmetry: <cos theta> of the averaged phase, from the spheres' Mie g, shape (W,). [1]
        phase: the averaged phase at ``cosines``, integrating to 1 over the sphere, shape (W, A). [1/sr]
        cosines: the nodes of ``phase``, ascending (:data:`PHASE_COSINES`), float64, shape (A,). [1]
    """

    extinction: Tensor
    scattering: Tensor
    ssa: Tensor
    asymmetry: Tensor
    phase: Tensor
    cosines: Tensor


WINDOW_SIGMAS: float = 8.0
"""Nodes farther than this many ln(sigma_g) from the area-weighted mean carry weights below 1e-15 and are
left out of the sums [1]."""


COARSE_RADIUS_RANGE_M: tuple[float, float] = (0.1e-6, 10e-6)
"""Median radii of the number distribution a coarse mode accepts [m]: AERONET's coarse modes have volume median
radii 1.5-4 um with ln sigma_g 0.6-0.8 (Dubovik et al. 2002, J. Atmos. Sci. 59, 590, Table 1), number medians
0.2-1.3 um."""


def lognormal_mie_optics(wavelengths_nm: Tensor, median_radius: Tensor, geometric_sigma: Tensor,
                         refractive_index, coarse: tuple[Tensor, Tensor, Tensor] | None = None) -> LognormalOptics:
    """Mie optics of the aerosol: one log-normal mode (:func:`mode_mie_optics`) or, with ``coarse``, a fine and a
    coarse mode mixed.

    ``coarse = (r_c, sigma_c, eta)``: a second log-normal mode of the same spheres and the fine-mode fraction
    eta in [0, 1] of the aerosol's extinction at 550 nm (the quantity AERONET's spectral deconvolution reports
    at 500 nm; O'Neill et al. 2003, J. Geophys. Res. 108, 4559). Per unit extinction at 550 nm the modes hold
    n_f = eta / C_ext,f(550) and n_c = (1 - eta) / C_ext,c(550) particles, so that per particle of the mixture

        C(lambda) = (n_f C_f(lambda) + n_c C_c(lambda)) / (n_f + n_c)         (extinction and scattering)
        p(nu, lambda) = (n_f C_sca,f p_f + n_c C_sca,c p_c) / (n_f C_sca,f + n_c C_sca,c)

    and the asymmetry likewise (Hansen & Travis 1974, Sec. 2: averages over any size distribution weight each
    particle's phase by its scattering cross-section; a sum of two modes is one such distribution). AERONET
    retrieves every site's aerosol as two such modes (Dubovik et al. 2002): the fine mode sets the Angstrom
    exponent, the coarse mode the aureole's forward peak, which one mode cannot give both of.
    """
    if coarse is None:
        return mode_mie_optics(wavelengths_nm, median_radius, geometric_sigma, refractive_index)
    rc, sc, eta = coarse
    dt, dev = median_radius.dtype, median_radius.device
    r_val = float(rc.detach())
    if not (math.isfinite(r_val) and COARSE_RADIUS_RANGE_M[0] <= r_val <= COARSE_RADIUS_RANGE_M[1]):
        raise ValueError(f"coarse median radius must be in [{COARSE_RADIUS_RANGE_M[0]:g}, {COARSE_RADIUS_RANGE_M[1]:g}] m, "
                         f"got {r_val:g}")
    e_val = float(eta.detach())
    if not (math.isfinite(e_val) and 0.0 <= e_val <= 1.0):
        raise ValueError(f"fine-mode fraction must be in [0, 1], got {e_val:g}")
    # each mode once, on the wavelengths and 550 nm (the reference of eta), sliced apart
    lam = torch.cat([wavelengths_nm.to(dtype=dt, device=dev).reshape(-1), wavelengths_nm.new_tensor([550.0]).to(dt)])
    fine_all = mode_mie_optics(lam, median_radius, geometric_sigma, refractive_index)
    crs_all = mode_mie_optics(lam, rc.to(dtype=dt, device=dev), sc, refractive_index)
    fine, crs = (_optics_slice(o, slice(None, -1)) for o in (fine_all, crs_all))
    c550_f, c550_c = fine_all.extinction[-1], crs_all.extinction[-1]
    eta = eta.to(dtype=dt, device=dev).reshape(())
    n_f, n_c = eta / c550_f, (1.0 - eta) / c550_c
    n = n_f + n_c
    ext = (n_f * fine.extinction + n_c * crs.extinction) / n
    s_f, s_c = n_f * fine.scattering, n_c * crs.scattering
    sca = (s_f + s_c) / n
    s_tot = s_f + s_c
    return LognormalOptics(
        extinction=ext, scattering=sca, ssa=sca / ext,
        asymmetry=(s_f * fine.asymmetry + s_c * crs.asymmetry) / s_tot,
        phase=(s_f.unsqueeze(-1) * fine.phase + s_c.unsqueeze(-1) * crs.phase) / s_tot.unsqueeze(-1),
        cosines=fine.cosines,
    )


def _optics_slice(o: LognormalOptics, s: slice) -> LognormalOptics:
    """The optics of the wavelengths ``s`` of ``o``."""
    return LognormalOptics(extinction=o.extinction[s], scattering=o.scattering[s], ssa=o.ssa[s],
                           asymmetry=o.asymmetry[s], phase=o.phase[s], cosines=o.cosines)


def mode_mie_optics(wavelengths_nm: Tensor, median_radius: Tensor, geometric_sigma: Tensor,
                    refractive_index) -> LognormalOptics:
    """Mie optics of a log-normal size distribution of spheres, differentiable in r_g and sigma_g.

    With s = ln sigma_g and t = ln x, x = 2 pi r / lambda, the area-weighted distribution is
    N(t; mu_lambda, s), mu_lambda = ln(2 pi r_g / lambda) + 2 s^2 (module docstring), so

        C_ext(lambda) = pi r_g^2 e^{2 s^2} sum_k w_k Q_ext,k / F,   C_sca likewise,
        p(nu, lambda) = sum_k w_k Q_sca,k p_k(nu) / sum_k w_k Q_sca,k,
        g(lambda)     = sum_k w_k Q_sca,k g_k / sum_k w_k Q_sca,k,

    with w the :func:`lognormal_hat_weights` on the truncation [ln(2 pi r_min / lambda),
    ln(2 pi r_max / lambda)] and F the number fraction of the log-normal inside [r_min, r_max]
    (Bohren & Huffman 1983 eqs. 4.61, 4.62 for Q; Hansen & Travis 1974 Sec. 2 for the averages).
    The spectral shape of extinction replaces the Angstrom law, scattering / extinction the
    constant single-scattering albedo and p the Henyey-Greenstein phase.

    Args:
        wavelengths_nm: shape (W,), within :data:`WAVELENGTH_RANGE_NM`. [nm]
        median_radius: r_g of the number distribution, shape (), within MEDIAN_RADIUS_RANGE_M. [m]
        geometric_sigma: sigma_g in (1, 4], shape (). [1]
        refractive_index: (n, k) of m = n + ik, k >= 0 absorbing; fixed (not differentiated). [1]

    Returns:
        :class:`LognormalOptics` in the dtype and device of ``median_radius``.
    """
    n, k = check_refractive_index(refractive_index)
    dt, dev = median_radius.dtype, median_radius.device
    lam = wavelengths_nm.to(dtype=dt, device=dev)
    lam_lo, lam_hi = float(lam.min()), float(lam.max())
    if not (WAVELENGTH_RANGE_NM[0] <= lam_lo and lam_hi <= WAVELENGTH_RANGE_NM[1]):
        raise ValueError(f"the lognormal_mie table covers {WAVELENGTH_RANGE_NM[0]:g}-{WAVELENGTH_RANGE_NM[1]:g} nm; "
                         f"got wavelengths {lam_lo:g}-{lam_hi:g} nm")
    rg, sg = median_radius.reshape(()), geometric_sigma.reshape(()).to(dtype=dt, device=dev)
    r_val, s_val = float(rg.detach()), float(sg.detach())
    if not (math.isfinite(r_val) and MEDIAN_RADIUS_RANGE_M[0] <= r_val <= MEDIAN_RADIUS_RANGE_M[1]):
        raise ValueError(f"median radius must be in [{MEDIAN_RADIUS_RANGE_M[0]:g}, {MEDIAN_RADIUS_RANGE_M[1]:g}] m, "
                         f"got {r_val:g}")
    if not (math.isfinite(s_val) and GEOMETRIC_SIGMA_RANGE[0] < s_val <= GEOMETRIC_SIGMA_RANGE[1]):
        raise ValueError(f"geometric_sigma must be in ({GEOMETRIC_SIGMA_RANGE[0]:g}, {GEOMETRIC_SIGMA_RANGE[1]:g}], "
                         f"got {s_val:g}")
    s = torch.log(sg)
    two_pi_over_lam = 2 * math.pi / (lam * 1e-9)  # [1/m]
    mean = torch.log(rg * two_pi_over_lam) + 2 * s * s  # (W,)
    r_lo, r_hi = LOGNORMAL_RADIUS_RANGE_M
    lo, hi = torch.log(r_lo * two_pi_over_lam), torch.log(r_hi * two_pi_over_lam)
    # nodes that carry weight: within WINDOW_SIGMAS of every wavelength's mean, inside the truncation
    with torch.no_grad():
        t_lo = float(torch.maximum(lo, mean - WINDOW_SIGMAS * s).min())
        t_hi = float(torch.minimum(hi, mean + WINDOW_SIGMAS * s).max())
    k_lo = math.floor(t_lo / LN_X_STEP)
    k_hi = max(math.ceil(t_hi / LN_X_STEP), k_lo + 1)
    nodes, q_ext, q_sca, q_sca_g, sca_phase = _torch_table(n, k, k_lo, k_hi, dt, str(dev))
    w = lognormal_hat_weights(nodes, mean, s, lo, hi)  # (W, K)
    # number fraction of the log-normal inside [r_min, r_max]
    frac = _normal_mass((math.log(r_lo) - torch.log(rg)) / s, (math.log(r_hi) - torch.log(rg)) / s)
    area = math.pi * rg * rg * torch.exp(2 * s * s) / frac  # pi r_g^2 e^{2 s^2}: the area moment's scale [m^2]
    sum_ext, sum_sca = w @ q_ext, w @ q_sca
    phase = (w @ sca_phase) / sum_sca.unsqueeze(-1)
    return LognormalOptics(
        extinction=area * sum_ext, scattering=area * sum_sca, ssa=sum_sca / sum_ext,
        asymmetry=(w @ q_sca_g) / sum_sca, phase=phase,
        cosines=torch.as_tensor(PHASE_COSINES, dtype=torch.float64, device=dev),
    )


def effective_radius(median_radius, geometric_sigma):
    """Effective radius r_eff = int r^3 n dr / int r^2 n dr = r_g exp(5/2 ln^2 sigma_g) of the (untruncated)
    log-normal (Hansen & Travis 1974, eq. 2.53 for the definition) [m]."""
    s = math.log(float(geometric_sigma))
    return float(median_radius) * math.exp(2.5 * s * s)


def effective_variance(geometric_sigma) -> float:
    """Effective variance v_eff = exp(ln^2 sigma_g) - 1 of the log-normal (Hansen & Travis 1974, eq. 2.54) [1]."""
    s = math.log(float(geometric_sigma))
    return math.exp(s * s) - 1.0
