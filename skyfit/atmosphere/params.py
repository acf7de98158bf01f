"""The atmosphere a renderer sees: per-wavelength coefficients as tensors, validated.

All quantities are SI (metres, 1/m, nm for wavelengths, W/(m^2 nm) for
irradiance). Every coefficient is a tensor so that gradients can flow to it;
the object never changes the dtype or device it is given.
"""
from __future__ import annotations

import dataclasses
import math

import torch
from torch import Tensor

from . import constants as C
from .mie import (COARSE_RADIUS_RANGE_M, GEOMETRIC_SIGMA_RANGE, MEDIAN_RADIUS_RANGE_M, WAVELENGTH_RANGE_NM,
                  check_refractive_index)

COARSE_FIELDS = ("mie_coarse_radius", "mie_coarse_sigma", "mie_fine_fraction")
"""Fields of the optional coarse mode of the ``lognormal_mie`` phase (all three or none)."""
MIE_PHASES = ("cornette_shanks", "henyey_greenstein", "two_term_hg", "lognormal_mie")
"""Aerosol phase functions by name (:func:`skyfit.scattering.phase.mie_phase`; ``lognormal_mie``, per wavelength:
:func:`skyfit.scattering.phase.lognormal_mie_phase`)."""
MIE_PROFILES = ("exponential", "boundary_layer")
"""Aerosol density profiles by name (:mod:`skyfit.atmosphere.profiles`): exp(-h / H_M), or 1 up to the
mixing height h_mix and exp(-(h - h_mix) / H_M) above."""


@dataclasses.dataclass
class Atmosphere:
    """Spectral description of a planet's atmosphere (Bruneton & Neyret 2008, Sec. 2).

    Attributes (W = number of wavelengths):
        wavelengths: shape (W,). [nm]
        bottom_radius, top_radius: planet and top-of-atmosphere radii. [m]
        rayleigh_scattering: sea-level Rayleigh scattering, shape (W,). [1/m]
        rayleigh_scale_height: shape (). [m]
        mie_scattering, mie_extinction: sea-level aerosol coefficients, shape (W,). [1/m]
        mie_scale_height: shape (). [m]
        mie_g: phase asymmetry in (-1, 1), shape (). [1]
        ground_albedo: Lambertian albedo, shape (W,). [1]
        solar_irradiance: extraterrestrial irradiance at the planet, shape (W,). [W/(m^2 nm)]
        ozone_absorption: absorption at peak ozone density, shape (W,), or None for no
            ozone; every renderer applies it with the tent profile (docs/ozone.md). [1/m]
        ozone_layer_m: (bottom, peak, top) altitudes of the ozone tent profile. [m]
        sun_angular_radius: [rad]
        mie_phase: one of MIE_PHASES.
        name: label for reports.
        mie_g2: backward asymmetry g2 in (-1, 1) of the two-term Henyey-Greenstein phase, shape ();
            required (and only used) when ``mie_phase == "two_term_hg"``; ``mie_g`` is its forward g1. [1]
        mie_hg_weight: weight f in (0, 1] of the forward lobe, p = f HG(g1) + (1 - f) HG(g2), shape ();
            with ``mie_g2``. [1]
        mie_profile: one of MIE_PROFILES.
        mie_mixing_height: top h_mix of the well-mixed aerosol layer, shape (); required (and only
            used) when ``mie_profile == "boundary_layer"``. [m]
        mie_median_radius: median radius r_g of the log-normal number distribution of aerosol spheres, shape ();
            required (and only used) when ``mie_phase == "lognormal_mie"`` (:mod:`skyfit.atmosphere.mie`); the
            phase then comes from it, and ``mie_extinction`` / ``mie_scattering`` / ``mie_g`` should be the
            distribution's (the config and the fit set them so). [m]
        mie_geometric_sigma: geometric standard deviation sigma_g in (1, 4] of that distribution, shape (). [1]
        mie_refractive_index: (n, k) of the spheres' refractive index m = n + ik, k >= 0; with ``lognormal_mie``. [1]
        mie_coarse_radius, mie_coarse_sigma: an optional second (coarse) log-normal mode of ``lognormal_mie``,
            median radius [m] within COARSE_RADIUS_RANGE_M and sigma_g in (1, 4], shape () each; with
        mie_fine_fraction: the fine mode's share eta in [0, 1] of the aerosol's extinction at 550 nm, shape ()
            (all three or none; :func:`skyfit.atmosphere.mie.lognormal_mie_optics`). [1]
    """

    wavelengths: Tensor
    bottom_radius: float
    top_radius: float
    rayleigh_scattering: Tensor
    rayleigh_scale_height: Tensor
    mie_scattering: Tensor
    mie_extinction: Tensor
    mie_scale_height: Tensor
    mie_g: Tensor
    ground_albedo: Tensor
    solar_irradiance: Tensor
    ozone_absorption: Tensor | None = None
    ozone_layer_m: tuple[float, float, float] = (10_000.0, 25_000.0, 40_000.0)
    sun_angular_radius: float = C.SUN_ANGULAR_RADIUS_RAD
    mie_phase: str = "cornette_shanks"
    name: str = "atmosphere"
    mie_g2: Tensor | None = None
    mie_hg_weight: Tensor | None = None
    mie_profile: str = "exponential"
    mie_mixing_height: Tensor | None = None
    mie_median_radius: Tensor | None = None
    mie_geometric_sigma: Tensor | None = None
    mie_refractive_index: tuple[float, float] | None = None
    mie_coarse_radius: Tensor | None = None
    mie_coarse_sigma: Tensor | None = None
    mie_fine_fraction: Tensor | None = None
    config: dict | None = dataclasses.field(default=None, repr=False, compare=False)
    """The config this atmosphere was built from (None when built by hand); :func:`skyfit.fit` rebuilds it on
    the data's wavelengths, after checking that the atmosphere still equals it."""

    def __post_init__(self) -> None:
        self.validate()

    # -- checks -----------------------------------------------------------
    def validate(self) -> None:
        """Raise ValueError naming the first out-of-range parameter."""
        if not (0 < self.bottom_radius < math.inf):
            raise ValueError(f"bottom_radius must be > 0 m, got {self.bottom_radius}")
        if not (self.bottom_radius < self.top_radius < math.inf):
            raise ValueError(
                f"top_radius ({self.top_radius} m) must be greater than bottom_radius ({self.bottom_radius} m)"
            )
        required = (
            "wavelengths", "rayleigh_scattering", "rayleigh_scale_height", "mie_scattering", "mie_extinction",
            "mie_scale_height", "mie_g", "ground_albedo", "solar_irradiance",
        )
        for name in required + (("ozone_absorption",) if self.ozone_absorption is not None else ()):
            if not isinstance(getattr(self, name), Tensor):
                raise ValueError(f"{name} must be a torch.Tensor, got {type(getattr(self, name)).__name__}")
        w = self.wavelengths.shape
        if self.wavelengths.ndim != 1 or w[0] < 1:
            raise ValueError("wavelengths must be a 1-D tensor with at least one entry [nm]")
        if not bool(torch.isfinite(self.wavelengths).all()) or bool((self.wavelengths <= 0).any()):
            raise ValueError("wavelengths must be finite and positive [nm]")
        for name in ("rayleigh_scale_height", "mie_scale_height", "mie_g"):
            if getattr(self, name).numel() != 1:
                raise ValueError(f"{name} must be a scalar tensor (shape ()), got shape {tuple(getattr(self, name).shape)}")
        for name in ("rayleigh_scattering", "mie_scattering", "mie_extinction", "ground_albedo", "solar_irradiance"):
            t = getattr(self, name)
            if t.shape != w:
                raise ValueError(f"{name} must have shape {tuple(w)} (one value per wavelength), got {tuple(t.shape)}")
            if not bool(torch.isfinite(t).all()):
                raise ValueError(f"{name} must be finite")
            if bool((t < 0).any()):
                raise ValueError(f"{name} must be >= 0, got min {float(t.min()):.4g}")
        if bool((self.mie_scattering > self.mie_extinction * (1 + 1e-12)).any()):
            raise ValueError("mie_scattering must not exceed mie_extinction (single-scattering albedo <= 1)")
        if bool((self.ground_albedo > 1).any()):
            raise ValueError("ground_albedo must be in [0, 1]")
        for name in ("rayleigh_scale_height", "mie_scale_height"):
            h = getattr(self, name)
            if not bool(torch.isfinite(h).all()) or bool((h <= 0).any()):
                raise ValueError(f"{name} must be > 0 m, got {h.detach().cpu().numpy()}")
        g = self.mie_g
        if not bool(torch.isfinite(g).all()) or bool((g <= -1).any()) or bool((g >= 1).any()):
            raise ValueError(f"mie_g must be in the open interval (-1, 1), got {g.detach().cpu().numpy()}")
        if self.mie_phase not in MIE_PHASES:
            raise ValueError(f"mie_phase must be one of {MIE_PHASES}, got {self.mie_phase!r}")
        if self.mie_phase == "two_term_hg":
            for name, lo, hi, closed in (("mie_g2", -1.0, 1.0, False), ("mie_hg_weight", 0.0, 1.0, True)):
                v = getattr(self, name)
                if not isinstance(v, Tensor) or v.numel() != 1:
                    raise ValueError(f"mie_phase two_term_hg needs {name} as a scalar tensor, got {v!r}")
                ok = bool(torch.isfinite(v).all()) and bool((v > lo).all()) and bool((v <= hi if closed else v < hi).all())
                if not ok:
                    raise ValueError(f"{name} must be in ({lo:g}, {hi:g}{']' if closed else ')'}, got {v.detach().cpu().numpy()}")
        if self.mie_phase == "lognormal_mie":
            self._validate_lognormal()
        if self.mie_profile not in MIE_PROFILES:
            raise ValueError(f"mie_profile must be one of {MIE_PROFILES}, got {self.mie_profile!r}")
        if self.mie_profile == "boundary_layer":
            h = self.mie_mixing_height
            if not isinstance(h, Tensor) or h.numel() != 1:
                raise ValueError(f"mie_profile boundary_layer needs mie_mixing_height as a scalar tensor [m], got {h!r}")
            if not bool(torch.isfinite(h).all()) or bool((h <= 0).any()) or float(h.detach()) >= self.top_radius - self.bottom_radius:
                raise ValueError(f"mie_mixing_height must be > 0 m and below the top of the atmosphere, got {float(h.detach())}")
        if self.ozone_absorption is not None:
            if self.ozone_absorption.shape != w or bool((self.ozone_absorption < 0).any()):
                raise ValueError("ozone_absorption must be >= 0 with one value per wavelength")
        lo, peak, hi = self.ozone_layer_m
        if not (0 <= lo < peak < hi):
            raise ValueError(f"ozone_layer_m must satisfy 0 <= bottom < peak < top, got {self.ozone_layer_m}")
        if not (0 < self.sun_angular_radius < 0.1):
            raise ValueError(f"sun_angular_radius must be in (0, 0.1) rad, got {self.sun_angular_radius}")

    def _validate_lognormal(self) -> None:
        for name, (lo, hi), open_lo in (("mie_median_radius", MEDIAN_RADIUS_RANGE_M, False),
                                        ("mie_geometric_sigma", GEOMETRIC_SIGMA_RANGE, True)):
            v = getattr(self, name)
            if not isinstance(v, Tensor) or v.numel() != 1:
                raise ValueError(f"mie_phase lognormal_mie needs {name} as a scalar tensor, got {v!r}")
            x = float(v.detach())
            if not (math.isfinite(x) and (lo < x if open_lo else lo <= x) and x <= hi):
                raise ValueError(f"{name} must be in {'(' if open_lo else '['}{lo:g}, {hi:g}], got {x:g}")
        coarse = {n: getattr(self, n) for n in COARSE_FIELDS}
        if any(v is not None for v in coarse.values()):
            for name, (lo, hi), open_lo in (("mie_coarse_radius", COARSE_RADIUS_RANGE_M, False),
                                            ("mie_coarse_sigma", GEOMETRIC_SIGMA_RANGE, True),
                                            ("mie_fine_fraction", (0.0, 1.0), False)):
                v = coarse[name]
                if not isinstance(v, Tensor) or v.numel() != 1:
                    raise ValueError(f"a coarse mode needs {', '.join(COARSE_FIELDS)} as scalar tensors; {name} is {v!r}")
                x = float(v.detach())
                if not (math.isfinite(x) and (lo < x if open_lo else lo <= x) and x <= hi):
                    raise ValueError(f"{name} must be in {'(' if open_lo else '['}{lo:g}, {hi:g}], got {x:g}")
        if self.mie_refractive_index is None:
            raise ValueError("mie_phase lognormal_mie needs mie_refractive_index (n, k)")
        self.mie_refractive_index = check_refractive_index(self.mie_refractive_index)
        lam = self.wavelengths
        if float(lam.min()) < WAVELENGTH_RANGE_NM[0] or float(lam.max()) > WAVELENGTH_RANGE_NM[1]:
            raise ValueError(f"mie_phase lognormal_mie covers {WAVELENGTH_RANGE_NM[0]:g}-{WAVELENGTH_RANGE_NM[1]:g} nm, "
                             f"got wavelengths {float(lam.min()):g}-{float(lam.max()):g} nm")

    # -- conveniences -----------------------------------------------------
    @property
    def mie_coarse_mode(self) -> tuple[Tensor, Tensor, Tensor] | None:
        """(mie_coarse_radius, mie_coarse_sigma, mie_fine_fraction) of a two-mode ``lognormal_mie``, else None."""
        if self.mie_phase != "lognormal_mie" or self.mie_coarse_radius is None:
            return None
        return (self.mie_coarse_radius, self.mie_coarse_sigma, self.mie_fine_fraction)

    @property
    def scale_heights(self) -> Tensor:
        """(H_R, H_M) stacked, shape (2,). [m]"""
        return torch.stack([self.rayleigh_scale_height.reshape(()), self.mie_scale_height.reshape(())])

    @property
    def mixing_heights(self) -> dict[int, Tensor] | None:
        """Boundary-layer tops by layer index of :attr:`scale_heights` ({1: h_mix} for a boundary-layer
        aerosol), None when every layer is exponential; what the integrators'
        :meth:`~skyfit.transmittance.base.OpticalDepthIntegrator.prepare_layers` take. [m]"""
        if self.mie_profile == "exponential":
            return None
        return {1: self.mie_mixing_height.reshape(())}

    @property
    def mie_column_height(self) -> Tensor:
        """Vertical column of the aerosol's relative density, int_0^inf rho dh (flat Earth, no top): H_M for
        the exponential profile, h_mix + H_M for the boundary layer; AOD = beta x this, shape (). [m]"""
        if self.mie_profile == "boundary_layer":
            return self.mie_mixing_height.reshape(()) + self.mie_scale_height.reshape(())
        return self.mie_scale_height.reshape(())

    @property
    def extinction_matrix(self) -> Tensor:
        """Rows (Rayleigh, Mie) of sea-level extinction, shape (2, W): tau = column @ this. [1/m]"""
        return torch.stack([self.rayleigh_scattering, self.mie_extinction])

    @property
    def dtype(self) -> torch.dtype:
        return self.rayleigh_scattering.dtype

    @property
    def device(self) -> torch.device:
        return self.rayleigh_scattering.device

    def tensor_fields(self) -> list[str]:
        return [f.name for f in dataclasses.fields(self) if isinstance(getattr(self, f.name), Tensor)]

    def to(self, dtype: torch.dtype | None = None, device: torch.device | str | None = None) -> "Atmosphere":
        """A copy with every tensor moved to ``dtype`` / ``device``."""
        kw = {}
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            kw[f.name] = v.to(dtype=dtype, device=device) if isinstance(v, Tensor) else v
        return Atmosphere(**kw)

    def replace(self, **changes) -> "Atmosphere":
        """A validated copy with some fields replaced (e.g. a tensor requiring grad)."""
        return dataclasses.replace(self, **changes)

    def summary(self) -> dict:
        """Plain-Python description for JSON reports and EXR headers."""
        def val(x):
            if isinstance(x, Tensor):
                x = x.detach().cpu()
                return x.item() if x.ndim == 0 else x.tolist()
            return x

        return {f.name: val(getattr(self, f.name)) for f in dataclasses.fields(self) if f.name != "config"}


def angstrom_extinction(wavelengths_nm: Tensor, beta: float | Tensor, alpha: float | Tensor, scale_height_m) -> Tensor:
    """Sea-level aerosol extinction from the Angstrom turbidity law.

    The aerosol optical depth is tau(lambda) = beta * (lambda / 1 um)^-alpha
    (Angstrom 1929); spread over an exponential layer of scale height H the
    sea-level extinction is tau / H. This is how Bruneton's 2017 evaluation
    sets Mie extinction (clear-sky-models, atmosphere.cc).

    Args:
        wavelengths_nm: shape (W,). [nm]
        beta: Angstrom turbidity (optical depth at 1 um). [1]
        alpha: Angstrom exponent. [1]
        scale_height_m: aerosol scale height H, or the vertical column of the layer's relative density
            (h_mix + H for the boundary-layer profile, :attr:`Atmosphere.mie_column_height`). [m]

    Returns:
        Extinction coefficient at sea level, shape (W,). [1/m]
    """
    lam_um = wavelengths_nm / 1000.0
    return beta / scale_height_m * lam_um ** (-alpha)


def rayleigh_power_law(wavelengths_nm: Tensor, coefficient: float, exponent: float = 4.0) -> Tensor:
    """Sea-level Rayleigh scattering ``coefficient * (lambda / 1 um)^-exponent`` [1/m].

    Bruneton 2017 uses coefficient 1.24062e-6 /m and exponent 4.
    """
    return coefficient * (wavelengths_nm / 1000.0) ** (-exponent)


def _check_finite(x: float, what: str) -> float:
    if not math.isfinite(x):
        raise ValueError(f"{what} must be finite, got {x}")
    return x
