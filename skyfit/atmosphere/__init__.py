"""Atmosphere parameters, density profiles, constants with sources, and config loading."""
from .config import ConfigError, atmosphere_from_config, load_atmosphere, load_yaml, read_config, spectral_tables
from .params import MIE_PHASES, MIE_PROFILES, Atmosphere, angstrom_extinction, rayleigh_power_law
from .profiles import boundary_layer_density, ozone_tent_density, profile_densities, with_mie_profile
from .solar import solar_irradiance
from .wavelengths import DEFAULT_WAVELENGTHS, parse_wavelengths

__all__ = [
    "Atmosphere",
    "ConfigError",
    "DEFAULT_WAVELENGTHS",
    "MIE_PHASES",
    "MIE_PROFILES",
    "angstrom_extinction",
    "atmosphere_from_config",
    "boundary_layer_density",
    "load_atmosphere",
    "load_yaml",
    "ozone_tent_density",
    "parse_wavelengths",
    "profile_densities",
    "rayleigh_power_law",
    "read_config",
    "solar_irradiance",
    "spectral_tables",
    "with_mie_profile",
]
