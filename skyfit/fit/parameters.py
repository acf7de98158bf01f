"""Fit parameters: physical values <-> an unconstrained vector, and the Atmosphere they describe.

Every parameter has a physical range that a smooth, invertible map enforces
(STYLE.md: reparametrise, never clamp):

==============  =====================================  =================================
transform       physical value v of the free number x  for
==============  =====================================  =================================
``log``         v = ref * exp(x)                       positive scales, heights, beta
``interval``    v = lo + (hi - lo) * sigmoid(x)        bounded: g in (-1, 1), ssa, albedo
``loginterval``  v = lo (hi / lo)^sigmoid(x)            positive and bounded: scale heights
``linear``      v = ref * x                            unbounded angles (azimuth offset)
==============  =====================================  =================================

``ref`` puts x on a scale of order one (a Mie extinction of 1e-5 /m is x = 0),
which is what Adam's step size and L-BFGS's first step assume.

Names, units and meanings are listed in :data:`PARAMETERS` and in docs/fitting.md.
*Shared* parameters describe the atmosphere; the *nuisance* parameters
(``exposure``, ``sun_azimuth_offset``, ``sun_zenith_offset``, ``camera_tilt_north``,
``camera_tilt_east``, ``noise_scale``, and for photos ``gain_red``, ``gain_blue``, ``vignetting``, ``lens_radial``) describe the instrument and may take one value per observation in a joint fit.
"""
from __future__ import annotations

import dataclasses
import math
from typing import Iterable, Mapping, Sequence

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from ..atmosphere import Atmosphere
from ..atmosphere.config import spectral_tables
from ..atmosphere.constants import DOBSON_UNIT_PER_M2
from ..atmosphere.mie import effective_radius, effective_variance, lognormal_mie_optics


class FitError(ValueError):
    """A fit that cannot be set up or run as asked (unknown parameter, value out of range...)."""


TRANSFORMS = ("log", "interval", "loginterval", "linear")


SIGMOID_EDGE = {torch.float64: 30.0, torch.float32: 15.0}
"""The unconstrained value of an interval parameter is clamped to +-this (by dtype) before the sigmoid: in float64
the sigmoid is exactly 1 from about 37 on (float32: 17), which put an open-interval parameter on its bound (a
5-iteration photo fit's first steps took ``mie_g`` to 1.0 and the atmosphere refused it); at 30 (15) it stays 2e-13
(6e-7) of the range inside. [1]"""


def _inside(x: Tensor) -> Tensor:
    edge = SIGMOID_EDGE.get(x.dtype, 15.0)
    return torch.sigmoid(x.clamp(-edge, edge))


@dataclasses.dataclass(frozen=True)
class ParameterSpec:
    """One fit parameter.

    Attributes:
        name: the name used in configs, ``--free`` and RESULT.json.
        unit: SI unit of the physical value.
        transform: one of TRANSFORMS (module table).
        ref: reference value of ``log`` and ``linear`` (x = 0 <-> v = ref for log; v = ref x for linear).
        lo, hi: open interval of ``interval`` and ``loginterval`` (and the range a user's value must lie in).
        typical: physically plausible span used to spread multi-start points. [unit]
        nuisance: an instrument parameter (may be per observation) rather than an atmospheric one.
        prior: default prior of ``skyfit sample`` (:data:`skyfit.fit.priors.DEFAULT_PRIORS`): a kind
            (``uniform`` / ``loguniform``) over the range (lo, hi) above, or (kind, lo, hi) where that
            range is unbounded or wider than physical; None: no default prior.
        description: one line for docs and reports.
    """

    name: str
    unit: str
    transform: str
    ref: float = 1.0
    lo: float = -math.inf
    hi: float = math.inf
    typical: tuple[float, float] = (1.0, 1.0)
    nuisance: bool = False
    prior: str | tuple[str, float, float] | None = None
    description: str = ""

    def forward(self, x: Tensor, hi: float | None = None) -> Tensor:
        """Physical value of the unconstrained ``x`` (``hi`` overrides the upper bound)."""
        if self.transform == "log":
            return self.ref * torch.exp(x)
        if self.transform == "interval":
            top = self.hi if hi is None else hi
            return self.lo + (top - self.lo) * _inside(x)
        if self.transform == "loginterval":
            return self.lo * torch.exp(math.log(self.hi / self.lo) * _inside(x))
        return self.ref * x

    def log_abs_dvdx(self, x: Tensor, hi: float | None = None) -> Tensor:
        """log |dv/dx| of the transform at ``x``, elementwise (carries a prior density on v over to x)."""
        if self.transform == "log":
            return math.log(self.ref) + x
        if self.transform == "interval":
            top = self.hi if hi is None else hi
            return math.log(top - self.lo) + F.logsigmoid(x) + F.logsigmoid(-x)
        if self.transform == "loginterval":
            return self.forward(x).log() + math.log(math.log(self.hi / self.lo)) + F.logsigmoid(x) + F.logsigmoid(-x)
        return torch.full_like(x, math.log(abs(self.ref)))

    def inverse(self, v: float, hi: float | None = None) -> float:
        """Unconstrained value of the physical ``v``; FitError when v is outside the range."""
        top = self.hi if hi is None else hi
        unit = "" if self.unit == "1" else f" {self.unit}"  # a dimensionless value has no unit to print
        if not math.isfinite(v):
            raise FitError(f"{self.name} must be finite, got {v}")
        if self.transform == "log":
            if not v > 0:
                raise FitError(f"{self.name} must be > 0{unit}, got {v}")
            return math.log(v / self.ref)
        if self.transform in ("interval", "loginterval"):
            if not self.lo < v < top:
                raise FitError(f"{self.name} must lie in the open interval ({self.lo:g}, {top:g}){unit}, got {v}")
            if self.transform == "interval":
                u = (v - self.lo) / (top - self.lo)
            else:
                u = math.log(v / self.lo) / math.log(top / self.lo)
            return math.log(u) - math.log1p(-u)
        return v / self.ref


_DEG = math.pi / 180.0
BOUND_EDGE: float = 1e-12
"""Position u in its range (0 and 1: the bounds) that :func:`inside_bounds` moves a fitted value at a bound to [1]."""


def inside_bounds(name: str, v):
    """A fitted value of a bounded parameter moved just inside its range when it sits on a bound (or a list of them).

    A fit that ran into a bound reports the sigmoid's rounded end, exactly the bound, which the open range of
    :meth:`ParameterSpec.inverse` refuses; results are read back (evaluate, the selection's refit) through this,
    user values are not. Other values, and values outside the closed range, are returned unchanged."""
    spec = PARAMETERS.get(name)
    if isinstance(v, (list, tuple)):
        return [inside_bounds(name, x) for x in v]
    if spec is None or spec.transform not in ("interval", "loginterval") or not isinstance(v, (int, float)):
        return v
    lo, hi = spec.lo, spec.hi
    u = BOUND_EDGE if v == lo else 1.0 - BOUND_EDGE if v == hi else None
    if u is None:
        return v
    if not math.isfinite(hi):  # a data-dependent upper bound (ground_albedo_scale): only the lower one is reached
        return lo + BOUND_EDGE
    return lo + (hi - lo) * u if spec.transform == "interval" else lo * math.exp(math.log(hi / lo) * u)


PARAMETERS: dict[str, ParameterSpec] = {
    s.name: s
    for s in (
        ParameterSpec("rayleigh_scale", "1", "log", 1.0, 0.0, math.inf, (0.85, 1.15), prior=("loguniform", 0.2, 5.0),
                      description="factor on the config's Rayleigh scattering spectrum"),
        ParameterSpec("rayleigh_scale_height", "m", "loginterval", 1.0, 500.0, 50_000.0, (6500.0, 9500.0), prior="loguniform",
                      description="Rayleigh density scale height, within 0.5-50 km"),
        ParameterSpec("mie_beta_550", "1/m", "log", 1e-5, 0.0, math.inf, (3e-6, 8e-5), prior=("loguniform", 1e-7, 1e-3),
                      description="sea-level aerosol extinction coefficient at 550 nm"),
        ParameterSpec("mie_aod_550", "1", "log", 0.1, 0.0, math.inf, (0.02, 0.4), prior=("loguniform", 1e-4, 5.0),
                      description="aerosol optical depth at 550 nm, beta_550 x H_M, or beta_550 x (h_mix + H_M) for the "
                                  "boundary layer (instead of mie_beta_550)"),
        ParameterSpec("mie_angstrom_alpha", "1", "interval", 1.0, -1.0, 4.0, (0.2, 1.8), prior="uniform",
                      description="Angstrom exponent: extinction ~ (lambda / 550 nm)^-alpha"),
        ParameterSpec("mie_ssa", "1", "interval", 1.0, 0.0, 1.0, (0.75, 0.98), prior="uniform",
                      description="aerosol single-scattering albedo (grey)"),
        ParameterSpec("mie_scale_height", "m", "loginterval", 1.0, 10.0, 20_000.0, (700.0, 2500.0), prior="loguniform",
                      description="aerosol density scale height, within 10 m - 20 km"),
        ParameterSpec("mie_g", "1", "interval", 1.0, -1.0, 1.0, (0.55, 0.85), prior="uniform",
                      description="aerosol phase-function asymmetry (the forward lobe g1 of two_term_hg)"),
        ParameterSpec("mie_g2", "1", "interval", 1.0, -1.0, 0.0, (-0.5, -0.1), prior="uniform",
                      description="backward lobe g2 of the two-term Henyey-Greenstein phase (makes the phase two_term_hg)"),
        ParameterSpec("mie_hg_weight", "1", "interval", 1.0, 0.0, 1.0, (0.8, 0.98), prior="uniform",
                      description="weight f of the forward lobe: f HG(mie_g) + (1 - f) HG(mie_g2) (makes the phase two_term_hg)"),
        ParameterSpec("mie_mixing_height", "m", "loginterval", 1.0, 10.0, 5000.0, (200.0, 2000.0), prior="loguniform",
                      description="aerosol boundary-layer top: density 1 below, exp(-(h - h_mix) / H_M) above "
                                  "(makes the profile boundary_layer)"),
        ParameterSpec("mie_median_radius", "m", "loginterval", 1.0, 0.01e-6, 2e-6, (0.05e-6, 0.3e-6), prior="loguniform",
                      description="median radius r_g of the aerosol's log-normal number distribution (makes the phase "
                                  "lognormal_mie: Mie extinction spectrum, single-scattering albedo and phase)"),
        ParameterSpec("mie_geometric_sigma", "1", "loginterval", 1.0, 1.05, 3.0, (1.4, 2.2), prior="loguniform",
                      description="geometric standard deviation sigma_g of that distribution (makes the phase lognormal_mie)"),
        ParameterSpec("mie_coarse_radius", "m", "loginterval", 1.0, 0.1e-6, 10e-6, (0.4e-6, 1.2e-6), prior="loguniform",
                      description="median radius of a second, coarse log-normal mode of the same spheres (makes the "
                                  "phase lognormal_mie with two modes)"),
        ParameterSpec("mie_coarse_sigma", "1", "loginterval", 1.0, 1.05, 3.0, (1.7, 2.2), prior="loguniform",
                      description="geometric standard deviation of the coarse mode (makes the phase lognormal_mie with two modes)"),
        ParameterSpec("mie_fine_fraction", "1", "interval", 1.0, 0.0, 1.0, (0.5, 0.95), prior="uniform",
                      description="fine mode's share of the aerosol extinction at 550 nm (AERONET's fine-mode fraction; "
                                  "makes the phase lognormal_mie with two modes)"),
        ParameterSpec("ground_albedo", "1", "interval", 1.0, 0.0, 1.0, (0.05, 0.35), prior="uniform",
                      description="grey Lambertian ground albedo (replaces the config's spectrum)"),
        ParameterSpec("ground_albedo_scale", "1", "interval", 1.0, 0.0, math.inf, (0.6, 1.4),
                      prior=("uniform", 0.0, 1.0),  # hi replaced by 1 / max(config albedo) (skyfit.fit.priors.make_priors)
                      description="factor on the config's albedo spectrum, in (0, 1 / max albedo)"),
        ParameterSpec("ozone_column", "DU", "log", 300.0, 0.0, math.inf, (220.0, 420.0),
                      description="total ozone column in Dobson units (scales the config's ozone absorption)"),
        ParameterSpec("exposure", "1", "log", 1.0, 0.0, math.inf, (0.7, 1.4), nuisance=True, prior=("loguniform", 1e-6, 1e6),
                      description="calibration scale: data = exposure x model (data units per W/(m^2 sr nm))"),
        ParameterSpec("noise_scale", "1", "log", 1.0, 0.0, math.inf, (1.0, 1.0), nuisance=True, prior=("loguniform", 1e-2, 1e2),
                      description="factor on the data's sigma (fitted, it adds log(noise_scale) per element)"),
        ParameterSpec("sun_azimuth_offset", "rad", "linear", 10 * _DEG, -math.inf, math.inf, (-0.2, 0.2), nuisance=True,
                      prior=("uniform", -45 * _DEG, 45 * _DEG),
                      description="added to the sun azimuth (clockwise); = minus a camera up-azimuth offset"),
        ParameterSpec("sun_zenith_offset", "rad", "interval", 1.0, -10 * _DEG, 10 * _DEG, (-0.02, 0.02), nuisance=True, prior="uniform",
                      description="added to the sun zenith angle, within +-10 degrees"),
        ParameterSpec("camera_tilt_north", "rad", "interval", 1.0, -10 * _DEG, 10 * _DEG, (-0.02, 0.02), nuisance=True, prior="uniform",
                      description="the instrument's zenith axis tilted toward North, within +-10 degrees"),
        ParameterSpec("camera_tilt_east", "rad", "interval", 1.0, -10 * _DEG, 10 * _DEG, (-0.02, 0.02), nuisance=True, prior="uniform",
                      description="the instrument's zenith axis tilted toward East, within +-10 degrees"),
        ParameterSpec("gain_red", "1", "loginterval", 1.0, 0.1, 10.0, (0.8, 1.25), nuisance=True, prior="loguniform",
                      description="RGB data: the red channel's gain relative to green (a camera's white balance)"),
        ParameterSpec("gain_blue", "1", "loginterval", 1.0, 0.1, 10.0, (0.8, 1.25), nuisance=True, prior="loguniform",
                      description="RGB data: the blue channel's gain relative to green (a camera's white balance)"),
        ParameterSpec("saturation_red", "1", "loginterval", 1.0, 0.1, 5.0, (0.8, 1.25), nuisance=True, prior="loguniform",
                      description="RGB data: the red channel's contrast against luminance relative to CIE colorimetry, "
                                  "Y + s (R - Y) (1: a colorimetric camera)"),
        ParameterSpec("saturation_blue", "1", "loginterval", 1.0, 0.1, 5.0, (0.8, 1.25), nuisance=True, prior="loguniform",
                      description="RGB data: the blue channel's contrast against luminance relative to CIE colorimetry, "
                                  "Y + s (B - Y) (1: a colorimetric camera)"),
        ParameterSpec("vignetting", "1", "interval", 1.0, -0.9, 0.5, (-0.2, 0.0), nuisance=True, prior="uniform",
                      description="image data: relative illumination 1 + v r^2 at normalised image radius r (r = 1 at 90 deg)"),
        ParameterSpec("lens_radial", "1", "interval", 1.0, -0.15, 0.15, (-0.03, 0.03), nuisance=True, prior="uniform",
                      description="image data: the lens's departure from its projection, theta = theta_p + k theta_p "
                                  "((pi/2)^2 - theta_p^2) (centre and 90-degree circle kept; skyfit.fit.model.lens_directions)"),
    )
}
"""Every fittable parameter by name: the one table of parameter facts (unit, transform, range, typical span,
nuisance, default prior of ``skyfit sample``); docs/fitting.md has the same table."""

NUISANCE: tuple[str, ...] = tuple(n for n, s in PARAMETERS.items() if s.nuisance)
ATMOSPHERE_PARAMETERS: tuple[str, ...] = tuple(n for n, s in PARAMETERS.items() if not s.nuisance)
ORIENTATION: tuple[str, ...] = ("sun_azimuth_offset", "sun_zenith_offset", "camera_tilt_north", "camera_tilt_east")
"""The instrument's orientation: sun offsets and the tilt of its zenith axis (a camera yaw is -sun_azimuth_offset)."""
CAMERA_RESPONSE: tuple[str, ...] = ("gain_red", "gain_blue", "saturation_red", "saturation_blue", "vignetting")
"""A camera's colour balance and relative illumination: act on RGB image data only (:class:`skyfit.fit.model.FitProblem`)."""
DEFAULT_PER_OBSERVATION: tuple[str, ...] = ("exposure",) + ORIENTATION + ("gain_red", "gain_blue")
"""Nuisance parameters that take one value per observation unless the config says otherwise
(``vignetting``, a property of the lens, the saturations, of the camera, and ``noise_scale`` are shared)."""

TWO_TERM_HG: tuple[str, ...] = ("mie_g2", "mie_hg_weight")
"""Parameters of the two-term Henyey-Greenstein phase: free or set, they make the phase ``two_term_hg`` (g1 = mie_g)."""
MIE_G2_DEFAULT: float = -0.3
"""Start of mie_g2 when the config's phase is single-lobed [1]: a weak backward lobe (Kattawar 1975's fits to Mie
phase functions of haze have g2 of -0.2 to -0.6)."""
MIE_HG_WEIGHT_DEFAULT: float = 0.9
"""Start of mie_hg_weight when the config's phase is single-lobed [1]: mostly the forward lobe (close to the config's HG)."""
LOGNORMAL_MIE: tuple[str, ...] = ("mie_median_radius", "mie_geometric_sigma")
"""Parameters of the lognormal_mie phase: free or set, they make the phase ``lognormal_mie`` (skyfit/atmosphere/mie.py)."""
COARSE_MODE: tuple[str, ...] = ("mie_coarse_radius", "mie_coarse_sigma", "mie_fine_fraction")
"""Parameters of the lognormal_mie phase's optional coarse mode: free or set, they add it (and make the phase
lognormal_mie; skyfit.atmosphere.mie.lognormal_mie_optics)."""
MIE_COARSE_RADIUS_DEFAULT: float = 0.7e-6
"""Start of mie_coarse_radius [m]: the number median of AERONET's coarse modes (volume median radii 1.5-4 um with
ln sigma_g 0.6-0.8; Dubovik et al. 2002, Table 1): 2.5 um x exp(-3 x 0.65^2)."""
MIE_COARSE_SIGMA_DEFAULT: float = 1.9
"""Start of mie_coarse_sigma [1]: exp(0.65), the same coarse mode."""
MIE_FINE_FRACTION_DEFAULT: float = 0.8
"""Start of mie_fine_fraction [1]: mostly fine aerosol, as continental haze at 500 nm (O'Neill et al. 2003)."""
LOGNORMAL_DERIVED: tuple[str, ...] = ("mie_g", "mie_angstrom_alpha", "mie_ssa", "mie_g2", "mie_hg_weight")
"""Parameters the lognormal_mie phase derives from the size distribution and the refractive index: refused with it."""
MIE_MEDIAN_RADIUS_DEFAULT: float = 0.1e-6
"""Start of mie_median_radius when the config's phase is another [m]: about the number median of the fine mode that
AERONET retrieves (volume median radii 0.12-0.2 um with ln sigma_g 0.38-0.5; Dubovik et al. 2002, J. Atmos. Sci. 59,
590, Table 1; number median = volume median x exp(-3 ln^2 sigma_g))."""
MIE_GEOMETRIC_SIGMA_DEFAULT: float = 1.6
"""Start of mie_geometric_sigma when the config's phase is another [1]: exp(0.47), the same fine mode."""
MIE_REFRACTIVE_INDEX_DEFAULT: tuple[float, float] = (1.45, 0.005)
"""Refractive index (n, k) of the lognormal_mie phase when the config's phase is another [1]: within the range
AERONET retrieves at 440-1020 nm (n 1.39-1.56, k 0-0.02 across its aerosol types; Dubovik et al. 2002, Table 1)."""
MIE_MIXING_HEIGHT_DEFAULT: float = 200.0
"""Start of mie_mixing_height when the config's aerosol is exponential [m]: a shallow layer, close to that profile
(h_mix -> 0 is the exponential)."""

_NUISANCE_DEFAULTS = {"exposure": 1.0, "noise_scale": 1.0, **{n: 0.0 for n in ORIENTATION},
                      "gain_red": 1.0, "gain_blue": 1.0, "saturation_red": 1.0, "saturation_blue": 1.0, "vignetting": 0.0,
                      "lens_radial": 0.0}


def as_number(value, name: str) -> float:
    """``value`` as a float; FitError naming the parameter when it is not a number (a string, a list, None, a bool)."""
    if isinstance(value, (Tensor, np.ndarray)) and value.ndim == 0:  # a 0-d tensor or array holds one number
        value = value.item()
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise FitError(f"{name} must be a number, got {value!r}")
    return float(value)


def check_names(names: Iterable[str], what: str = "free parameter") -> list[str]:
    """Names as a list; FitError naming the unknown one and listing the valid names."""
    out = []
    for n in names:
        if n not in PARAMETERS:
            raise FitError(f"unknown {what} {n!r}; valid: {', '.join(PARAMETERS)}")
        if n in out:
            raise FitError(f"{what} {n!r} given twice")
        out.append(n)
    return out


def ozone_column_du(atm: Atmosphere) -> float | None:
    """Total vertical ozone column of ``atm`` in Dobson units, None without ozone. [DU]

    The config builds ``ozone_absorption = peak_density x sigma(lambda)`` with peak_density =
    column x DOBSON_UNIT_PER_M2 / ((top - bottom) / 2) (the tent's vertical column of unit
    peak) and sigma the shipped ozone cross-section table (skyfit/atmosphere/config.py);
    this inverts it by least squares over the wavelengths the table covers (exact for shipped
    configs); NaN when it covers none of them.
    """
    if atm.ozone_absorption is None:
        return None
    tab = spectral_tables()["ozone_cross_section_233K"]
    wl = np.asarray(tab["wavelength_nm"], float)
    lam = atm.wavelengths.detach().cpu().double().numpy()
    inside = (lam >= wl[0] - 5.0) & (lam <= wl[-1] + 5.0)  # the table's bins (config.table's range)
    sigma = np.interp(lam[inside], wl, np.asarray(tab["values"], float))
    k = atm.ozone_absorption.detach().cpu().double().numpy()[inside]
    if not inside.any() or not np.dot(sigma, sigma) > 0:
        return math.nan
    peak = float(np.dot(k, sigma) / np.dot(sigma, sigma))
    lo, _, hi = atm.ozone_layer_m
    return peak * 0.5 * (hi - lo) / DOBSON_UNIT_PER_M2


def mie_power_law(wavelengths: Tensor, extinction: Tensor) -> tuple[float, float]:
    """Least-squares fit of ``log ext = log b + (-alpha) log(lambda / 550)``: (b at 550 nm [1/m], alpha [1]).

    Exact for an Angstrom-law extinction (every shipped config). One wavelength gives alpha = 0.
    """
    lam = wavelengths.detach().cpu().double().numpy()
    ext = extinction.detach().cpu().double().numpy()
    if np.any(ext <= 0):
        return 0.0, 0.0
    if lam.size == 1:
        return float(ext[0]), 0.0
    xl = np.log(lam / 550.0)
    slope, intercept = np.polyfit(xl, np.log(ext), 1)
    return float(math.exp(intercept)), float(-slope)


class Parameterisation:
    """Maps an unconstrained vector x (P,) to physical parameters and to an :class:`Atmosphere`.

    Args:
        base: the atmosphere of the config (its spectra and its non-free values are kept).
        free: names of the fitted parameters (see :data:`PARAMETERS`).
        n_observations: number of observations in the fit.
        per_observation: nuisance names that take one value per observation
            (default :data:`DEFAULT_PER_OBSERVATION`; only those that are free or fixed
            at per-observation values matter).
        values: physical values overriding the defaults: starting points of free
            parameters and fixed values of the others. A per-observation value may be a
            sequence of length ``n_observations``. [SI]

    Defaults come from ``base``: the Mie extinction at 550 nm and Angstrom exponent
    from a power-law fit of its spectrum (:func:`mie_power_law`), ssa as the mean
    scattering / extinction, grey albedo as the mean albedo; nuisance defaults are
    exposure 1, offsets 0, noise_scale 1.

    The vector layout is :attr:`names`: each shared free name once, each
    per-observation free name as ``name[i]``.
    """

    def __init__(
        self,
        base: Atmosphere,
        free: Sequence[str],
        n_observations: int = 1,
        per_observation: Sequence[str] | None = None,
        values: Mapping[str, float | Sequence[float]] | None = None,
    ):
        self.base = base
        self.free = check_names(free)
        if n_observations < 1:
            raise FitError(f"a fit needs at least one observation, got {n_observations}")
        self.n_observations = int(n_observations)
        per = DEFAULT_PER_OBSERVATION if per_observation is None else tuple(per_observation)
        check_names(per, "per-observation parameter")
        for n in per:
            if not PARAMETERS[n].nuisance:
                raise FitError(f"{n!r} describes the atmosphere, which observations share; per-observation "
                               f"parameters must be among {', '.join(NUISANCE)}")
        self.per_observation = tuple(per)
        if "ground_albedo" in self.free and "ground_albedo_scale" in self.free:
            raise FitError("free ground_albedo (grey) or ground_albedo_scale (of the config's spectrum), not both")
        if "mie_beta_550" in self.free and "mie_aod_550" in self.free:
            raise FitError("free mie_beta_550 (extinction) or mie_aod_550 (optical depth = beta x H_M), not both")
        self._ozone_du = ozone_column_du(base)  # the config's column; ozone_column scales its absorption
        if "ozone_column" in self.free and self._ozone_du is None:
            raise FitError(f"ozone_column is free but config {base.name!r} has no ozone; add an ozone: section "
                           "(column_du, layer_m) to the config")
        if "ozone_column" in self.free and not self._ozone_du > 0:
            raise FitError(f"ozone_column is free but the ozone of config {base.name!r} has no column to scale "
                           "(zero absorption, or no wavelength inside the ozone cross-section table)")

        # Base spectral shapes: the fitted numbers act on them.
        self._lam = base.wavelengths
        b550, alpha0 = mie_power_law(base.wavelengths, base.mie_extinction)
        self._mie_alpha0 = alpha0
        if b550 > 0:
            law = b550 * (base.wavelengths / 550.0) ** (-alpha0)
            self._mie_shape = base.mie_extinction / law  # 1 for an Angstrom-law config
        else:
            self._mie_shape = torch.ones_like(base.mie_extinction)
        ext = base.mie_extinction
        ratio = torch.where(ext > 0, base.mie_scattering / torch.where(ext > 0, ext, torch.ones_like(ext)),
                            torch.zeros_like(ext))
        self._ssa_ratio = ratio
        albedo_max = float(base.ground_albedo.max())
        self._albedo_scale_hi = 1.0 / albedo_max if albedo_max > 0 else math.inf
        self.defaults: dict[str, float] = {
            "rayleigh_scale": 1.0,
            "rayleigh_scale_height": float(base.rayleigh_scale_height),
            "mie_beta_550": b550,
            "mie_aod_550": b550 * float(base.mie_column_height),
            "mie_angstrom_alpha": alpha0,
            "mie_ssa": float(ratio.mean()) if bool((ext > 0).any()) else 0.9,
            "mie_scale_height": float(base.mie_scale_height),
            "mie_g": float(base.mie_g),
            "mie_g2": float(base.mie_g2) if base.mie_g2 is not None else MIE_G2_DEFAULT,
            "mie_hg_weight": float(base.mie_hg_weight) if base.mie_hg_weight is not None else MIE_HG_WEIGHT_DEFAULT,
            "mie_mixing_height": (float(base.mie_mixing_height) if base.mie_mixing_height is not None
                                  else MIE_MIXING_HEIGHT_DEFAULT),
            "mie_median_radius": (float(base.mie_median_radius) if base.mie_median_radius is not None
                                  else MIE_MEDIAN_RADIUS_DEFAULT),
            "mie_geometric_sigma": (float(base.mie_geometric_sigma) if base.mie_geometric_sigma is not None
                                    else MIE_GEOMETRIC_SIGMA_DEFAULT),
            "mie_coarse_radius": (float(base.mie_coarse_radius) if base.mie_coarse_radius is not None
                                  else MIE_COARSE_RADIUS_DEFAULT),
            "mie_coarse_sigma": float(base.mie_coarse_sigma) if base.mie_coarse_sigma is not None else MIE_COARSE_SIGMA_DEFAULT,
            "mie_fine_fraction": (float(base.mie_fine_fraction) if base.mie_fine_fraction is not None
                                  else MIE_FINE_FRACTION_DEFAULT),
            "ground_albedo": float(base.ground_albedo.mean()),
            "ground_albedo_scale": 1.0,
            "ozone_column": self._ozone_du if self._ozone_du is not None and self._ozone_du > 0 else 0.0,
            **_NUISANCE_DEFAULTS,
        }
        self.values: dict[str, float | list[float]] = dict(self.defaults)
        self._overridden: set[str] = set()  # atmosphere parameters set away from the base (fixed overrides count)
        for name, v in (values or {}).items():
            self.set_value(name, v)
        self._refractive_index = base.mie_refractive_index or MIE_REFRACTIVE_INDEX_DEFAULT
        if self.lognormal_mie():
            derived = [n for n in LOGNORMAL_DERIVED if n in set(self.free) | self._overridden]
            if derived:
                raise FitError(f"{', '.join(derived)} (free or set): the lognormal_mie phase derives the asymmetry, "
                               "Angstrom exponent and single-scattering albedo from the size distribution and the "
                               "refractive index; free mie_median_radius, mie_geometric_sigma instead, or set mie.phase "
                               "to henyey_greenstein")
            if base.mie_phase == "lognormal_mie" and bool((base.mie_extinction > 0).all()):
                # mie_beta_550 is the extinction at 550 nm itself (the spectrum is no power law)
                with torch.no_grad():
                    shape = self._lognormal_optics(base.mie_median_radius, base.mie_geometric_sigma, base.mie_coarse_mode)[0]
                b550 = float((base.mie_extinction / shape).mean())
                self.defaults["mie_beta_550"] = b550
                self.defaults["mie_aod_550"] = b550 * float(base.mie_column_height)
                for n in ("mie_beta_550", "mie_aod_550"):
                    if n not in self._overridden:
                        self.values[n] = self.defaults[n]
        two_term = (set(self.free) | self._overridden) & set(TWO_TERM_HG)
        if two_term and base.mie_phase == "cornette_shanks":
            raise FitError(f"{', '.join(sorted(two_term))} (free or set) describe the two-term Henyey-Greenstein "
                           f"phase, but config {base.name!r} has the Cornette-Shanks phase; set mie.phase to "
                           "henyey_greenstein or two_term_hg")

        self.names: list[str] = []
        self._slots: dict[str, list[int]] = {}
        for n in self.free:
            if self.is_per_observation(n):
                self._slots[n] = list(range(len(self.names), len(self.names) + self.n_observations))
                self.names += [f"{n}[{i}]" for i in range(self.n_observations)]
            else:
                self._slots[n] = [len(self.names)]
                self.names.append(n)

    # -- bookkeeping --------------------------------------------------------------
    @property
    def size(self) -> int:
        """Length P of the unconstrained vector."""
        return len(self.names)

    def is_per_observation(self, name: str) -> bool:
        return name in self.per_observation and PARAMETERS[name].nuisance

    def _hi(self, name: str) -> float | None:
        return self._albedo_scale_hi if name == "ground_albedo_scale" else None

    def set_value(self, name: str, value) -> None:
        """Set a physical value (start of a free parameter, or a fixed value); checks its range."""
        check_names([name], "parameter")
        spec = PARAMETERS[name]
        if isinstance(value, (list, tuple, np.ndarray)):
            vals = [as_number(v, name) for v in value]
            if not self.is_per_observation(name):
                if len(set(vals)) != 1:
                    raise FitError(f"{name} is shared by all observations; got one value per observation {vals}")
                vals = vals[:1]
            elif len(vals) != self.n_observations:
                raise FitError(f"{name}: {len(vals)} values for {self.n_observations} observation(s)")
        else:
            vals = [as_number(value, name)]
        for v in vals:
            spec.inverse(v, self._hi(name))  # range check
        if self.is_per_observation(name) and len(vals) == 1:
            vals = vals * self.n_observations
        self.values[name] = vals if self.is_per_observation(name) else vals[0]
        if not spec.nuisance:
            self._overridden.add(name)

    # -- vector <-> physical ------------------------------------------------------
    def initial_vector(self, dtype=torch.float64, device="cpu") -> Tensor:
        """x of the current values (:attr:`values`), shape (P,)."""
        return self.to_unconstrained(self.values, dtype, device)

    def to_unconstrained(self, values: Mapping[str, float | Sequence[float]], dtype=torch.float64, device="cpu") -> Tensor:
        """x (P,) of physical values (missing free names take :attr:`values`)."""
        x = torch.empty(self.size, dtype=dtype, device=device)
        for n in self.free:
            v = values.get(n, self.values[n])
            spec = PARAMETERS[n]
            slots = self._slots[n]
            vs = list(v) if isinstance(v, (list, tuple, np.ndarray)) else [v] * len(slots)
            if len(vs) != len(slots):
                raise FitError(f"{n}: {len(vs)} values for {len(slots)} slot(s)")
            for k, vi in zip(slots, vs):
                x[k] = spec.inverse(float(vi), self._hi(n))
        return x

    def to_physical(self, x: Tensor) -> dict[str, Tensor]:
        """Every parameter's physical value as a tensor (differentiable in x for the free ones).

        Shared parameters have shape (); per-observation ones shape (n_observations,).
        """
        if x.shape != (self.size,):
            raise FitError(f"parameter vector must have shape ({self.size},), got {tuple(x.shape)}")
        out: dict[str, Tensor] = {}
        for n, spec in PARAMETERS.items():
            if n in self._slots:
                v = spec.forward(x[self._slots[n]], self._hi(n))
                out[n] = v if self.is_per_observation(n) else v.reshape(())
            else:
                v = self.values[n]
                out[n] = torch.as_tensor(v, dtype=x.dtype, device=x.device)
        return out

    def physical_dict(self, x: Tensor) -> dict[str, float | list[float]]:
        """Plain floats of every parameter, SI units; per-observation ones as lists when there are several observations."""
        out = {}
        with torch.no_grad():
            phys = self.to_physical(x)
            for n, t in phys.items():
                t = t.detach().cpu()
                # per-observation values as lists (one per observation); a single observation's as a number
                out[n] = t.tolist() if t.ndim and self.n_observations > 1 else float(t.reshape(-1)[0]) if t.ndim else float(t)
            # mie_beta_550 and mie_aod_550 consistent with the scale height (and the lognormal_mie phase's g, alpha, ssa)
            out.update({n: v for n, v in self.derived(phys).items() if n in PARAMETERS})
        return out

    def free_dict(self, x: Tensor) -> dict[str, float | list[float]]:
        """Physical values of the free parameters only."""
        d = self.physical_dict(x)
        return {n: d[n] for n in self.free}

    # -- the atmosphere -----------------------------------------------------------
    def atmosphere(self, phys: Mapping[str, Tensor]) -> Atmosphere:
        """The Atmosphere of physical values ``phys`` (from :meth:`to_physical`), differentiably.

        Parameters neither free nor overridden keep the base atmosphere's exact spectra.
        """
        b = self.base
        dt, dev = b.dtype, b.device
        T = lambda v: torch.as_tensor(v, dtype=dt, device=dev)  # noqa: E731
        touched = set(self.free) | self._overridden
        kw: dict = {}
        if "rayleigh_scale" in touched:
            kw["rayleigh_scattering"] = b.rayleigh_scattering * T(phys["rayleigh_scale"])
        if "rayleigh_scale_height" in touched:
            kw["rayleigh_scale_height"] = T(phys["rayleigh_scale_height"]).reshape(())
        if "mie_scale_height" in touched:
            kw["mie_scale_height"] = T(phys["mie_scale_height"]).reshape(())
        if "mie_g" in touched:
            kw["mie_g"] = T(phys["mie_g"]).reshape(())
        if touched & set(TWO_TERM_HG):  # the phase becomes two-term HG (g1 = mie_g); the untouched one keeps its value
            kw["mie_phase"] = "two_term_hg"
            kw["mie_g2"] = T(phys["mie_g2"]).reshape(())
            kw["mie_hg_weight"] = T(phys["mie_hg_weight"]).reshape(())
        if "mie_mixing_height" in touched:  # the profile becomes a boundary layer
            kw["mie_profile"] = "boundary_layer"
            kw["mie_mixing_height"] = T(phys["mie_mixing_height"]).reshape(())
        if self.lognormal_mie(touched) and touched & {*LOGNORMAL_MIE, *COARSE_MODE, "mie_beta_550", "mie_aod_550"}:
            # the size distribution's spectrum: beta_550 C_ext(lambda) / C_ext(550), albedo C_sca / C_ext, its phase
            rg, sg = T(phys["mie_median_radius"]).reshape(()), T(phys["mie_geometric_sigma"]).reshape(())
            coarse = (tuple(T(phys[n]).reshape(()) for n in COARSE_MODE) if self.coarse_mode(touched) else None)
            shape, ssa, g550 = self._lognormal_optics(rg, sg, coarse)
            ext = self._beta_550(phys, touched) * shape
            kw.update(mie_extinction=ext, mie_scattering=ext * ssa, mie_g=g550, mie_phase="lognormal_mie",
                      mie_median_radius=rg, mie_geometric_sigma=sg, mie_refractive_index=self._refractive_index,
                      **dict(zip(COARSE_MODE, coarse or (None, None, None))))
        elif touched & {"mie_beta_550", "mie_aod_550", "mie_angstrom_alpha", "mie_ssa"}:
            ext = b.mie_extinction
            if touched & {"mie_beta_550", "mie_aod_550", "mie_angstrom_alpha"}:
                beta = self._beta_550(phys, touched)
                # beta_550 (lambda / 550)^-alpha times the base's departure from a power law (1 for Angstrom configs)
                ext = beta * (self._lam / 550.0) ** (-T(phys["mie_angstrom_alpha"])) * self._mie_shape
            scat = ext * (T(phys["mie_ssa"]) if "mie_ssa" in touched else self._ssa_ratio)
            kw["mie_extinction"], kw["mie_scattering"] = ext, scat
        if "ground_albedo" in touched and "ground_albedo_scale" in touched:
            raise FitError("ground_albedo (grey) and ground_albedo_scale (of the config's spectrum) both set; use one")
        if "ground_albedo" in touched:
            kw["ground_albedo"] = T(phys["ground_albedo"]) * torch.ones_like(b.ground_albedo)
        elif "ground_albedo_scale" in touched:
            kw["ground_albedo"] = b.ground_albedo * T(phys["ground_albedo_scale"])
        if "ozone_column" in touched and self._ozone_du is not None and self._ozone_du > 0:
            # absorption is linear in the column: the config's spectrum times column / config column
            kw["ozone_absorption"] = b.ozone_absorption * (T(phys["ozone_column"]) / self._ozone_du)
        if not kw:
            return b
        try:
            return b.replace(**kw)
        except ValueError as e:  # cannot happen inside the transforms' ranges; name it if it does
            raise FitError(f"parameters give an invalid atmosphere: {e}") from None

    def lognormal_mie(self, touched: set[str] | None = None) -> bool:
        """True when the aerosol phase is lognormal_mie (the config's, or mie_median_radius / mie_geometric_sigma
        free or set)."""
        touched = set(self.free) | self._overridden if touched is None else touched
        return self.base.mie_phase == "lognormal_mie" or bool(touched & {*LOGNORMAL_MIE, *COARSE_MODE})

    def coarse_mode(self, touched: set[str] | None = None) -> bool:
        """True when the lognormal_mie aerosol has a coarse mode (the config's, or a COARSE_MODE parameter free or set)."""
        touched = set(self.free) | self._overridden if touched is None else touched
        return self.base.mie_coarse_mode is not None or bool(touched & set(COARSE_MODE))

    def _lognormal_optics(self, median_radius: Tensor, geometric_sigma: Tensor,
                          coarse: tuple[Tensor, Tensor, Tensor] | None = None) -> tuple[Tensor, Tensor, Tensor]:
        """(C_ext(lambda) / C_ext(550 nm), single-scattering albedo (W,), asymmetry at 550 nm ()) of the size
        distribution (with its coarse mode) on the model wavelengths (:func:`skyfit.atmosphere.mie.lognormal_mie_optics`)."""
        lam = torch.cat([self._lam, self._lam.new_tensor([550.0])])
        o = lognormal_mie_optics(lam, median_radius, geometric_sigma, self._refractive_index, coarse)
        return o.extinction[:-1] / o.extinction[-1], o.ssa[:-1], o.asymmetry[-1]

    def boundary_layer(self, touched: set[str] | None = None) -> bool:
        """True when the aerosol has the boundary-layer profile (the config's, or ``mie_mixing_height`` free or set)."""
        touched = set(self.free) | self._overridden if touched is None else touched
        return self.base.mie_profile == "boundary_layer" or "mie_mixing_height" in touched

    def _column_height(self, phys: Mapping[str, Tensor], touched: set[str] | None = None) -> Tensor:
        """Vertical column of the aerosol's relative density [m]: H_M, or h_mix + H_M for the boundary layer
        (:attr:`skyfit.atmosphere.Atmosphere.mie_column_height`)."""
        if self.boundary_layer(touched):
            return phys["mie_mixing_height"] + phys["mie_scale_height"]
        return phys["mie_scale_height"]

    def _beta_550(self, phys: Mapping[str, Tensor], touched: set[str] | None = None) -> Tensor:
        """Mie extinction at 550 nm [1/m]: from mie_aod_550 / (column height) when the optical depth is fitted or
        set (H_M, or h_mix + H_M for the boundary layer)."""
        touched = set(self.free) | self._overridden if touched is None else touched
        if "mie_aod_550" in touched:
            return phys["mie_aod_550"] / self._column_height(phys, touched)
        return phys["mie_beta_550"]

    def derived(self, phys: Mapping[str, Tensor]) -> dict[str, float]:
        """Derived quantities for reports: aerosol optical depth and extinction at 550 nm
        (AOD = beta_550 H_M; beta_550 (h_mix + H_M) for the boundary layer)."""
        with torch.no_grad():
            beta = self._beta_550(phys)
            out = {"mie_aod_550": float(beta * self._column_height(phys)), "mie_beta_550": float(beta)}
            if self.lognormal_mie():
                out.update(self.lognormal_derived(phys))
            return out

    def lognormal_derived(self, phys: Mapping[str, Tensor]) -> dict[str, float]:
        """What the lognormal_mie size distribution implies (floats, for reports): the Angstrom exponent between 440
        and 870 nm (AERONET's pair) -ln(C_ext(440) / C_ext(870)) / ln(440 / 870), the asymmetry and single-scattering
        albedo at 550 nm, the effective radius r_g exp(5/2 ln^2 sigma_g) [m] and variance exp(ln^2 sigma_g) - 1
        (Hansen & Travis 1974, eqs. 2.53-2.54). Those with parameter names replace the config's values in reports."""
        with torch.no_grad():
            rg, sg = phys["mie_median_radius"].reshape(()), phys["mie_geometric_sigma"].reshape(())
            out = {n: float(v) for n, v in self.lognormal_optics_derived(phys).items()}
            out.update({"mie_effective_radius": effective_radius(float(rg), float(sg)),
                        "mie_effective_variance": effective_variance(float(sg))})
            if self.coarse_mode():  # the effective radius and variance above are the fine mode's
                out["mie_coarse_effective_radius"] = effective_radius(float(phys["mie_coarse_radius"]),
                                                                      float(phys["mie_coarse_sigma"]))
            return out

    def lognormal_optics_derived(self, phys: Mapping[str, Tensor]) -> dict[str, Tensor]:
        """The lognormal_mie aerosol's Angstrom exponent (440/870 nm), asymmetry and single-scattering albedo at
        550 nm as differentiable float64 tensors of ``phys`` (for :meth:`lognormal_derived` and the Laplace sigma
        of derived quantities, :func:`skyfit.fit.laplace.derived_functions`)."""
        D = lambda v: v.reshape(()).to(torch.float64)  # noqa: E731
        rg, sg = D(phys["mie_median_radius"]), D(phys["mie_geometric_sigma"])
        lam = torch.tensor([440.0, 550.0, 870.0], dtype=torch.float64, device=rg.device)
        coarse = tuple(D(phys[n]) for n in COARSE_MODE) if self.coarse_mode() else None
        o = lognormal_mie_optics(lam, rg, sg, self._refractive_index, coarse)
        alpha = -torch.log(o.extinction[0] / o.extinction[2]) / math.log(440.0 / 870.0)
        return {"mie_angstrom_alpha": alpha, "mie_g": o.asymmetry[1], "mie_ssa": o.ssa[1]}

    def nuisance(self, phys: Mapping[str, Tensor], i: int) -> dict[str, Tensor]:
        """Observation ``i``'s nuisance values (shape ()) from :meth:`to_physical`'s dict."""
        out = {}
        for n in NUISANCE:
            v = phys[n]
            out[n] = v[i] if v.ndim else v
        return out

    def units(self) -> dict[str, str]:
        return {n: s.unit for n, s in PARAMETERS.items()}

    def spread_starts(self, n: int, generator: torch.Generator, dtype=torch.float64, device="cpu") -> list[Tensor]:
        """``n`` start vectors: the current values, then a Latin-hypercube spread over each free
        parameter's ``typical`` span (per-observation offsets start at their current value)."""
        x0 = self.initial_vector(dtype, device)
        starts = [x0]
        if n <= 1:
            return starts
        m = n - 1
        for k in range(m):
            starts.append(x0.clone())
        for name in self.free:
            spec = PARAMETERS[name]
            lo, hi = spec.typical
            if name == "ground_albedo_scale":
                hi = min(hi, 0.99 * self._albedo_scale_hi)
            if lo == hi or name in ORIENTATION or name in CAMERA_RESPONSE or name == "exposure":
                continue
            perm = torch.randperm(m, generator=generator)
            u = (perm.to(torch.float64) + torch.rand(m, generator=generator, dtype=torch.float64)) / m
            for k in range(m):
                if spec.transform in ("log", "loginterval"):
                    v = math.exp(math.log(lo) + float(u[k]) * (math.log(hi) - math.log(lo)))
                else:
                    v = lo + float(u[k]) * (hi - lo)
                for s in self._slots[name]:
                    starts[k + 1][s] = spec.inverse(v, self._hi(name))
        return starts
