"""Build an :class:`Atmosphere` from a YAML config (only the CLI reads files).

Config layout (all SI; see configs/earth.yaml for a commented example)::

    name: earth
    planet: {bottom_radius_m: 6360000, top_radius_m: 6420000}
    rayleigh: {coefficient: 1.24062e-6, exponent: 4, scale_height_m: 8000}
             # or {table: penndorf_rayleigh_sea_level_15C, scale_height_m: 8000}
    mie: {angstrom_alpha: 0.0, angstrom_beta: 5.328e-3, single_scattering_albedo: 0.9,
          scale_height_m: 1200, g: 0.8, phase: cornette_shanks}
         # phase: two_term_hg adds g2 (backward lobe, in (-1, 1)) and hg_weight (f of the forward lobe g,
         # in (0, 1]); profile: boundary_layer adds mixing_height_m (docs/aerosol.md). With the boundary
         # layer, angstrom_beta is still the optical depth at 1 um: extinction = beta / (h_mix + H_M).
         # phase: lognormal_mie takes median_radius_um, geometric_sigma and refractive_index [n, k] (m = n + ik) and
         # derives the extinction's spectral shape, the single-scattering albedo and the phase from them (Mie theory,
         # skyfit/atmosphere/mie.py); extinction_550 or angstrom_beta still set the amount; angstrom_alpha,
         # single_scattering_albedo and g are refused with it. A coarse mode adds coarse_median_radius_um,
         # coarse_geometric_sigma and fine_fraction (the fine mode's share of the extinction at 550 nm).
    ozone: {column_du: 300, layer_m: [10000, 25000, 40000], cross_section: ozone_cross_section_233K}
    ground: {albedo: 0.1}      # or {table: grass_albedo}
    sun: {distance_au: 1.0}
"""
from __future__ import annotations

import copy

import functools
import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import torch

from . import constants as C
from .mie import check_refractive_index, lognormal_mie_optics
from .params import Atmosphere, angstrom_extinction, rayleigh_power_law
from .solar import solar_irradiance


class ConfigError(ValueError):
    """A config file or value that cannot describe an atmosphere."""


@functools.lru_cache(maxsize=1)
def spectral_tables() -> dict:
    """Published spectral tables shipped with skyfit (sources in each entry's ``source``)."""
    path = Path(__file__).resolve().parents[1] / "data" / "spectral_tables.json"
    return json.loads(path.read_text())


def table(name: str, wavelengths_nm: np.ndarray) -> np.ndarray:
    """Linearly interpolate a shipped spectral table at ``wavelengths_nm``.

    Within half a sample spacing beyond either end the end value is held (a
    sample stands for its bin); further out the table says nothing, so the
    wavelength is refused rather than extrapolated (STYLE.md).
    """
    tabs = spectral_tables()
    if not isinstance(name, str) or name not in tabs:
        raise ConfigError(f"unknown spectral table {name!r}; known: {sorted(tabs)}")
    t = tabs[name]
    wl, val = np.asarray(t["wavelength_nm"], float), np.asarray(t["values"], float)
    lam = np.asarray(wavelengths_nm, float)
    lo, hi = wl[0] - (wl[1] - wl[0]) / 2, wl[-1] + (wl[-1] - wl[-2]) / 2
    outside = lam[(lam < lo - 1e-9) | (lam > hi + 1e-9)]
    if outside.size:
        raise ConfigError(
            f"spectral table {name!r} covers {lo:g}-{hi:g} nm; wavelength(s) {outside.tolist()} nm lie outside it"
        )
    return np.interp(lam, wl, val)


def _get(d: dict, key: str, default: Any, section: str) -> float:
    v = d.get(key, default)
    if v is None:
        raise ConfigError(f"{section}.{key} is required")
    try:
        return float(v)
    except (TypeError, ValueError):
        raise ConfigError(f"{section}.{key} must be a number, got {v!r}") from None


SECTION_KEYS: dict[str, frozenset[str]] = {
    "planet": frozenset({"bottom_radius_m", "top_radius_m"}),
    "rayleigh": frozenset({"coefficient", "exponent", "scale_height_m", "table", "scale"}),
    "mie": frozenset({
        "angstrom_alpha", "angstrom_beta", "extinction_550", "single_scattering_albedo", "scale_height_m", "g", "phase",
        "g2", "hg_weight", "profile", "mixing_height_m", "median_radius_um", "geometric_sigma", "refractive_index",
        "coarse_median_radius_um", "coarse_geometric_sigma", "fine_fraction",
    }),
    "ozone": frozenset({"column_du", "layer_m", "cross_section"}),
    "ground": frozenset({"albedo", "table"}),
    "sun": frozenset({"distance_au", "bandwidth_nm", "angular_radius_rad"}),
}
"""Keys each config section accepts; anything else is refused (a typo would silently keep a default)."""

RUN_SECTIONS = ("fit", "sample")
"""Sections of a config that set up a fit or a sampler run (skyfit.fit reads them); the atmosphere ignores them,
so a fit's config (e.g. the shipped ``kider``) also renders."""


def _section(cfg: dict, name: str) -> dict:
    d = cfg.get(name)
    if d is None:
        return {}
    if not isinstance(d, dict):
        raise ConfigError(f"config section {name!r} must be a mapping of key: value, got {d!r}")
    unknown = set(d) - SECTION_KEYS[name]
    if unknown:
        raise ConfigError(f"unknown key(s) {sorted(unknown)} in section {name!r}; known: {sorted(SECTION_KEYS[name])}")
    return d


def _nonneg(value: float, what: str) -> float:
    if not value >= 0:
        raise ConfigError(f"{what} must be >= 0, got {value}")
    return value


def load_yaml(path: str | Path) -> dict:
    """Read a YAML config file into a dict, with one-line errors."""
    import yaml

    p = Path(path)
    if p.is_dir():
        raise ConfigError(f"config {p} is a folder, not a YAML file")
    if not p.is_file():
        raise ConfigError(f"config file not found: {p}")
    try:
        text = p.read_text()
    except (OSError, UnicodeDecodeError) as e:
        raise ConfigError(f"cannot read config {p}: {getattr(e, 'strerror', None) or 'not UTF-8 text'}") from None
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as e:
        line = getattr(getattr(e, "problem_mark", None), "line", None)
        where = f" (line {line + 1})" if line is not None else ""
        raise ConfigError(f"bad YAML in {p}{where}: {getattr(e, 'problem', e)}") from None
    if not isinstance(data, dict):
        raise ConfigError(f"config {p} must be a YAML mapping")
    return data


def _quiet_numpy(fn):
    """Run ``fn`` with numpy's floating-point warnings off: an overflow there becomes a non-finite value
    that :func:`_check_spectra` reports in one line naming the keys, not a warning before it."""
    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        with np.errstate(all="ignore"):
            return fn(*args, **kwargs)

    return wrapper


def _check_spectra(spectra: dict, lam: np.ndarray, dtype: torch.dtype) -> None:
    """ConfigError naming the keys behind a spectrum that is NaN, infinite or beyond ``dtype``'s range."""
    top = torch.finfo(dtype).max
    for keys, arr in spectra.items():
        if arr is None:
            continue
        a = np.broadcast_to(np.asarray(arr, float), lam.shape)
        bad = ~(np.abs(a) <= top)
        if bad.any():
            k = int(np.argmax(bad))
            raise ConfigError(f"{keys} give {a[k]:.3g} at {lam[k]:g} nm, not a finite {str(dtype).replace('torch.', '')} value")


@_quiet_numpy
def atmosphere_from_config(
    cfg: dict,
    wavelengths_nm,
    dtype: torch.dtype = torch.float64,
    device: torch.device | str = "cpu",
    sun_distance_au: float | None = None,
) -> Atmosphere:
    """Build a validated :class:`Atmosphere` on ``wavelengths_nm`` from a config dict.

    ``sun_distance_au`` overrides the config's ``sun.distance_au`` (e.g. the
    Earth-Sun distance of a dated observation, from :func:`skyfit.camera.sun_position`).
    """
    lam = np.atleast_1d(np.asarray(wavelengths_nm, float))
    T = functools.partial(torch.as_tensor, dtype=dtype, device=device)
    known = {"name", "source", "description", "notes", *SECTION_KEYS, *RUN_SECTIONS}
    unknown = set(cfg) - known
    if unknown:
        raise ConfigError(f"unknown config section(s) {sorted(unknown)}; known: {sorted(known)}")
    planet, ray, mie, oz, gnd, sun = (_section(cfg, s) for s in ("planet", "rayleigh", "mie", "ozone", "ground", "sun"))

    bottom = _get(planet, "bottom_radius_m", C.EARTH_BOTTOM_RADIUS_M, "planet")
    top = _get(planet, "top_radius_m", C.EARTH_TOP_RADIUS_M, "planet")

    h_r = _get(ray, "scale_height_m", C.RAYLEIGH_SCALE_HEIGHT_M, "rayleigh")
    if "table" in ray:
        beta_r = table(ray["table"], lam)
    else:
        coeff = _nonneg(_get(ray, "coefficient", C.RAYLEIGH_COEFF_PER_M_UM4, "rayleigh"), "rayleigh.coefficient")
        beta_r = rayleigh_power_law(lam, coeff, _get(ray, "exponent", 4.0, "rayleigh"))
    beta_r = beta_r * _nonneg(_get(ray, "scale", 1.0, "rayleigh"), "rayleigh.scale")

    h_m = _get(mie, "scale_height_m", C.MIE_SCALE_HEIGHT_M, "mie")
    for key, h in (("rayleigh.scale_height_m", h_r), ("mie.scale_height_m", h_m)):
        if not h > 0:
            raise ConfigError(f"{key} must be > 0 m (scale heights), got {h}")
    phase = str(mie.get("phase", "cornette_shanks"))
    g2 = weight = None
    if phase == "two_term_hg":
        g2 = _get(mie, "g2", None, "mie")
        weight = _get(mie, "hg_weight", None, "mie")
    elif "g2" in mie or "hg_weight" in mie:
        raise ConfigError(f"mie.g2 and mie.hg_weight belong to phase: two_term_hg, not {phase!r}")
    lognormal = _lognormal_section(mie, phase, lam)
    profile = str(mie.get("profile", "exponential"))
    h_mix = None
    if profile == "boundary_layer":
        h_mix = _get(mie, "mixing_height_m", None, "mie")
        if not h_mix > 0:
            raise ConfigError(f"mie.mixing_height_m must be > 0 m, got {h_mix}")
    elif "mixing_height_m" in mie:
        raise ConfigError(f"mie.mixing_height_m belongs to profile: boundary_layer, not {profile!r}")
    # the aerosol's vertical column int rho dh: AOD = extinction x this (H_M, or h_mix + H_M for the boundary layer)
    column_m = h_m if h_mix is None else h_mix + h_m
    if lognormal is not None:  # the size distribution's spectral shape: C_ext(lambda) / C_ext(550 or 1000 nm)
        shape = lognormal["extinction"][: lam.size]
        if "extinction_550" in mie:
            ext_m = _nonneg(_get(mie, "extinction_550", None, "mie"), "mie.extinction_550") * shape / lognormal["extinction"][-2]
        else:
            beta = _get(mie, "angstrom_beta", C.MIE_EXTINCTION_PER_M * C.MIE_SCALE_HEIGHT_M, "mie")
            ext_m = _nonneg(beta, "mie.angstrom_beta") / column_m * shape / lognormal["extinction"][-1]
    elif "extinction_550" in mie:
        ext_550 = _nonneg(_get(mie, "extinction_550", None, "mie"), "mie.extinction_550")
        ext_m = ext_550 * (lam / 550.0) ** (-_get(mie, "angstrom_alpha", 0.0, "mie"))
    else:
        beta = _get(mie, "angstrom_beta", C.MIE_EXTINCTION_PER_M * C.MIE_SCALE_HEIGHT_M, "mie")
        ext_m = angstrom_extinction(lam, _nonneg(beta, "mie.angstrom_beta"), _get(mie, "angstrom_alpha", 0.0, "mie"), column_m)
    ssa = _get(mie, "single_scattering_albedo", C.MIE_SINGLE_SCATTERING_ALBEDO, "mie")
    if not 0 <= ssa <= 1:
        raise ConfigError(f"mie.single_scattering_albedo must be in [0, 1], got {ssa}")
    g = _get(mie, "g", C.MIE_G, "mie")
    if lognormal is not None:  # per wavelength, and g at 550 nm (for reports and the one-lobe exports)
        ssa, g = lognormal["ssa"][: lam.size], float(lognormal["asymmetry"][-2])

    if "table" in gnd:
        albedo = table(gnd["table"], lam)
    else:
        albedo = np.full_like(lam, _get(gnd, "albedo", C.GROUND_ALBEDO, "ground"))

    dist = _get(sun, "distance_au", 1.0, "sun") if sun_distance_au is None else float(sun_distance_au)
    if not 0 < dist < math.inf:
        raise ConfigError(f"sun.distance_au must be > 0, got {dist}")
    bandwidth = None
    if sun.get("bandwidth_nm") is not None:
        bandwidth = _get(sun, "bandwidth_nm", None, "sun")
        if not 0 < bandwidth < math.inf:
            raise ConfigError(f"sun.bandwidth_nm must be > 0 nm, got {bandwidth}")
    try:
        e_sun = solar_irradiance(lam, bandwidth) / dist**2
    except ValueError as e:
        raise ConfigError(str(e)) from None

    ozone_abs = None
    layer_raw = oz.get("layer_m", (10_000.0, 25_000.0, 40_000.0))
    try:
        layer = tuple(float(x) for x in layer_raw)
        if len(layer) != 3:
            raise ValueError
    except (TypeError, ValueError):
        raise ConfigError(f"ozone.layer_m must be three altitudes [bottom, peak, top] in m, got {layer_raw!r}") from None
    if oz:
        du = _nonneg(_get(oz, "column_du", 300.0, "ozone"), "ozone.column_du")
        lo, peak, hi = layer
        # Tent profile of unit peak density integrates to (hi - lo) / 2 metres, so
        # peak number density = column / that (Bruneton 2017, kMaxOzoneNumberDensity).
        peak_density = du * C.DOBSON_UNIT_PER_M2 / ((hi - lo) / 2.0)
        ozone_abs = peak_density * table(oz.get("cross_section", "ozone_cross_section_233K"), lam)

    _check_spectra({"rayleigh.coefficient, exponent and scale (or table)": beta_r,
                    "mie.angstrom_beta (or extinction_550), angstrom_alpha and scale_height_m": ext_m,
                    "ground.albedo (or table)": albedo, "sun.distance_au and bandwidth_nm": e_sun,
                    "ozone.column_du and layer_m": ozone_abs}, lam, dtype)
    try:
        return Atmosphere(
            wavelengths=T(lam),
            bottom_radius=bottom,
            top_radius=top,
            rayleigh_scattering=T(beta_r),
            rayleigh_scale_height=T(h_r),
            mie_scattering=T(ext_m * ssa),
            mie_extinction=T(ext_m),
            mie_scale_height=T(h_m),
            mie_g=T(g),
            ground_albedo=T(albedo),
            solar_irradiance=T(e_sun),
            ozone_absorption=None if ozone_abs is None else T(ozone_abs),
            ozone_layer_m=layer,  # type: ignore[arg-type]
            sun_angular_radius=_get(sun, "angular_radius_rad", C.SUN_ANGULAR_RADIUS_RAD, "sun"),
            mie_phase=phase,
            name=str(cfg.get("name", "atmosphere")),
            mie_g2=None if g2 is None else T(g2),
            mie_hg_weight=None if weight is None else T(weight),
            mie_profile=profile,
            mie_mixing_height=None if h_mix is None else T(h_mix),
            mie_median_radius=None if lognormal is None else T(lognormal["median_radius_m"]),
            mie_geometric_sigma=None if lognormal is None else T(lognormal["geometric_sigma"]),
            mie_refractive_index=None if lognormal is None else lognormal["refractive_index"],
            **({} if lognormal is None or lognormal["coarse"] is None else
               dict(zip(("mie_coarse_radius", "mie_coarse_sigma", "mie_fine_fraction"), (T(v) for v in lognormal["coarse"])))),
            config=copy.deepcopy(cfg),
        )
    except ValueError as e:
        raise ConfigError(str(e)) from None


LOGNORMAL_KEYS = ("median_radius_um", "geometric_sigma", "refractive_index")
"""Keys of the ``mie`` section that belong to ``phase: lognormal_mie`` (all three required there)."""
COARSE_KEYS = ("coarse_median_radius_um", "coarse_geometric_sigma", "fine_fraction")
"""Keys of an optional coarse mode of ``phase: lognormal_mie`` (all three or none): its number median radius, its
sigma_g and the fine mode's share of the extinction at 550 nm."""
LOGNORMAL_DERIVED_KEYS = ("angstrom_alpha", "single_scattering_albedo", "g")
"""Keys the lognormal_mie phase derives from the size distribution and refuses."""


def _lognormal_section(mie: dict, phase: str, lam: np.ndarray) -> dict | None:
    """The lognormal_mie optics on ``lam`` + [550, 1000] nm (float64 numpy) and the section's values, or None
    for another phase; ConfigError for a key that does not belong or a value out of range."""
    present = [k for k in LOGNORMAL_KEYS + COARSE_KEYS if k in mie]
    if phase != "lognormal_mie":
        if present:
            raise ConfigError(f"mie.{', mie.'.join(present)} belong to phase: lognormal_mie, not {phase!r}")
        return None
    derived = [k for k in LOGNORMAL_DERIVED_KEYS if k in mie]
    if derived:
        raise ConfigError(f"mie.{', mie.'.join(derived)}: phase lognormal_mie derives the Angstrom exponent, "
                          "single-scattering albedo and asymmetry from median_radius_um, geometric_sigma and "
                          "refractive_index; remove them")
    r_um = _get(mie, "median_radius_um", None, "mie")
    sigma = _get(mie, "geometric_sigma", None, "mie")
    raw = mie.get("refractive_index")
    if not isinstance(raw, (list, tuple)) or len(raw) != 2:
        raise ConfigError(f"mie.refractive_index must be [real, imaginary] (m = n + ik), got {raw!r}")
    given = [k for k in COARSE_KEYS if k in mie]
    if given and len(given) != len(COARSE_KEYS):
        raise ConfigError(f"mie: a coarse mode needs all of {', '.join(COARSE_KEYS)}; missing "
                          f"{', '.join(k for k in COARSE_KEYS if k not in mie)}")
    coarse = None
    if given:
        coarse = (_get(mie, "coarse_median_radius_um", None, "mie") * 1e-6, _get(mie, "coarse_geometric_sigma", None, "mie"),
                  _get(mie, "fine_fraction", None, "mie"))
    try:
        index = check_refractive_index(raw)
        r = torch.tensor(r_um * 1e-6, dtype=torch.float64)
        if coarse is not None and not 1.0 < coarse[1] <= 4.0:
            raise ValueError(f"coarse_geometric_sigma must be in (1, 4], got {coarse[1]:g}")
        optics = lognormal_mie_optics(torch.as_tensor(np.concatenate([lam, [550.0, 1000.0]]), dtype=torch.float64),
                                      r, torch.tensor(sigma, dtype=torch.float64), index,
                                      None if coarse is None else tuple(torch.tensor(v, dtype=torch.float64) for v in coarse))
    except ValueError as e:
        raise ConfigError(f"mie (phase lognormal_mie): {e}") from None
    with torch.no_grad():
        return {"extinction": optics.extinction.numpy(), "ssa": optics.ssa.numpy(), "asymmetry": optics.asymmetry.numpy(),
                "median_radius_m": r_um * 1e-6, "geometric_sigma": sigma, "refractive_index": index, "coarse": coarse}


SHIPPED_CONFIGS = Path(__file__).resolve().parents[1] / "configs"
"""The configs shipped with skyfit (earth, earth_clear_sky_eval, earth_hazy, kider, kider_two_mode, mars)."""


def read_config(config: str | Path | dict) -> tuple[dict, str]:
    """A config dict and where it came from: a dict as is, a YAML path, or the name of a shipped config."""
    if isinstance(config, dict):
        return config, "<dict>"
    p = Path(config)
    if not p.exists() and not p.suffix:
        shipped = SHIPPED_CONFIGS / f"{config}.yaml"
        if shipped.is_file():
            p = shipped
    return load_yaml(p), str(p)


def load_atmosphere(
    config: str | Path | dict, wavelengths_nm, dtype=torch.float64, device="cpu", sun_distance_au: float | None = None
) -> Atmosphere:
    """An atmosphere from a config (a path, the name of a shipped config: ``earth``, ``mars`` ..., or a dict)."""
    cfg, source = read_config(config)
    try:
        return atmosphere_from_config(cfg, wavelengths_nm, dtype, device, sun_distance_au)
    except ConfigError as e:  # name the file (CONTRACT.md: the message names the problem and the file)
        raise ConfigError(f"config {source}: {e}") from None
