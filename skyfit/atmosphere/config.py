"""Build an :class:`Atmosphere` from a YAML config (only the CLI reads files).

Config layout (all SI; see configs/earth.yaml for a commented example)::

    name: earth
    planet: {bottom_radius_m: 6360000, top_radius_m: 6420000}
    rayleigh: {coefficient: 1.24062e-6, exponent: 4, scale_height_m: 8000}
             # or {table: penndorf_rayleigh_sea_level_15C, scale_height_m: 8000}
    mie: {angstrom_alpha: 0.0, angstrom_beta: 5.328e-3, single_scattering_albedo: 0.9,
          scale_height_m: 1200, g: 0.8, phase: cornette_shanks}
    ozone: {column_du: 300, layer_m: [10000, 25000, 40000], cross_section: ozone_cross_section_233K}
    ground: {albedo: 0.1}      # or {table: grass_albedo}
    sun: {distance_au: 1.0}
"""
from __future__ import annotations

import functools
import json
from pathlib import Path
from typing import Any

import numpy as np
import torch

from . import constants as C
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
    """Linearly interpolate a shipped spectral table at ``wavelengths_nm`` (held flat outside)."""
    tabs = spectral_tables()
    if name not in tabs:
        raise ConfigError(f"unknown spectral table {name!r}; known: {sorted(tabs)}")
    t = tabs[name]
    return np.interp(wavelengths_nm, np.asarray(t["wavelength_nm"], float), np.asarray(t["values"], float))


def _get(d: dict, key: str, default: Any, section: str) -> float:
    v = d.get(key, default)
    if v is None:
        raise ConfigError(f"{section}.{key} is required")
    try:
        return float(v)
    except (TypeError, ValueError):
        raise ConfigError(f"{section}.{key} must be a number, got {v!r}") from None


def load_yaml(path: str | Path) -> dict:
    """Read a YAML config file into a dict, with one-line errors."""
    import yaml

    p = Path(path)
    if not p.is_file():
        raise ConfigError(f"config file not found: {p}")
    try:
        data = yaml.safe_load(p.read_text())
    except yaml.YAMLError as e:
        line = getattr(getattr(e, "problem_mark", None), "line", None)
        where = f" (line {line + 1})" if line is not None else ""
        raise ConfigError(f"bad YAML in {p}{where}: {getattr(e, 'problem', e)}") from None
    if not isinstance(data, dict):
        raise ConfigError(f"config {p} must be a YAML mapping")
    return data


def atmosphere_from_config(
    cfg: dict,
    wavelengths_nm,
    dtype: torch.dtype = torch.float64,
    device: torch.device | str = "cpu",
) -> Atmosphere:
    """Build a validated :class:`Atmosphere` on ``wavelengths_nm`` from a config dict."""
    lam = np.atleast_1d(np.asarray(wavelengths_nm, float))
    T = functools.partial(torch.as_tensor, dtype=dtype, device=device)
    known = {"name", "source", "description", "planet", "rayleigh", "mie", "ozone", "ground", "sun", "notes"}
    unknown = set(cfg) - known
    if unknown:
        raise ConfigError(f"unknown config section(s) {sorted(unknown)}; known: {sorted(known)}")
    planet = cfg.get("planet", {}) or {}
    ray = cfg.get("rayleigh", {}) or {}
    mie = cfg.get("mie", {}) or {}
    oz = cfg.get("ozone", {}) or {}
    gnd = cfg.get("ground", {}) or {}
    sun = cfg.get("sun", {}) or {}

    bottom = _get(planet, "bottom_radius_m", C.EARTH_BOTTOM_RADIUS_M, "planet")
    top = _get(planet, "top_radius_m", C.EARTH_TOP_RADIUS_M, "planet")

    h_r = _get(ray, "scale_height_m", C.RAYLEIGH_SCALE_HEIGHT_M, "rayleigh")
    if "table" in ray:
        beta_r = table(ray["table"], lam)
    else:
        beta_r = rayleigh_power_law(
            lam, _get(ray, "coefficient", C.RAYLEIGH_COEFF_PER_M_UM4, "rayleigh"), _get(ray, "exponent", 4.0, "rayleigh")
        )
    beta_r = beta_r * _get(ray, "scale", 1.0, "rayleigh")

    h_m = _get(mie, "scale_height_m", C.MIE_SCALE_HEIGHT_M, "mie")
    if h_m <= 0 or h_r <= 0:
        raise ConfigError(f"scale heights must be > 0 m, got rayleigh {h_r}, mie {h_m}")
    if "extinction_550" in mie:
        ext_m = _get(mie, "extinction_550", None, "mie") * (lam / 550.0) ** (-_get(mie, "angstrom_alpha", 0.0, "mie"))
    else:
        ext_m = angstrom_extinction(
            lam,
            _get(mie, "angstrom_beta", C.MIE_EXTINCTION_PER_M * C.MIE_SCALE_HEIGHT_M, "mie"),
            _get(mie, "angstrom_alpha", 0.0, "mie"),
            h_m,
        )
    ssa = _get(mie, "single_scattering_albedo", C.MIE_SINGLE_SCATTERING_ALBEDO, "mie")
    if not 0 <= ssa <= 1:
        raise ConfigError(f"mie.single_scattering_albedo must be in [0, 1], got {ssa}")
    g = _get(mie, "g", C.MIE_G, "mie")

    if "table" in gnd:
        albedo = table(gnd["table"], lam)
    else:
        albedo = np.full_like(lam, _get(gnd, "albedo", C.GROUND_ALBEDO, "ground"))

    dist = _get(sun, "distance_au", 1.0, "sun")
    if dist <= 0:
        raise ConfigError(f"sun.distance_au must be > 0, got {dist}")
    e_sun = solar_irradiance(lam, sun.get("bandwidth_nm")) / dist**2

    ozone_abs = None
    layer = tuple(float(x) for x in oz.get("layer_m", (10_000.0, 25_000.0, 40_000.0)))
    if oz:
        du = _get(oz, "column_du", 300.0, "ozone")
        lo, peak, hi = layer
        # Tent profile of unit peak density integrates to (hi - lo) / 2 metres, so
        # peak number density = column / that (Bruneton 2017, kMaxOzoneNumberDensity).
        peak_density = du * C.DOBSON_UNIT_PER_M2 / ((hi - lo) / 2.0)
        ozone_abs = peak_density * table(oz.get("cross_section", "ozone_cross_section_233K"), lam)

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
            mie_phase=str(mie.get("phase", "cornette_shanks")),
            name=str(cfg.get("name", "atmosphere")),
        )
    except ValueError as e:
        raise ConfigError(str(e)) from None


def load_atmosphere(path_or_name: str | Path, wavelengths_nm, dtype=torch.float64, device="cpu") -> Atmosphere:
    """Load a config by path, or by the name of a shipped config (``earth``, ``mars`` ...)."""
    p = Path(path_or_name)
    if not p.exists() and not p.suffix:
        shipped = Path(__file__).resolve().parents[1] / "configs" / f"{path_or_name}.yaml"
        if shipped.is_file():
            p = shipped
    return atmosphere_from_config(load_yaml(p), wavelengths_nm, dtype, device)
