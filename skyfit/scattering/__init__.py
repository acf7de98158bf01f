"""Phase functions, single scattering, and multiple scattering (Bruneton tables, Hillaire LUT)."""
from .bruneton_tables import TableSizes
from .multiple import PrecomputedAtmosphere, Quadrature, precompute, sky_radiance
from .phase import (
    PHASE_FUNCTIONS, atmosphere_mie_phase, cornette_shanks_phase, henyey_greenstein_phase, lognormal_mie_phase, mie_phase,
    rayleigh_phase, spectral_mie_phase, tabulated_phase, two_term_hg_phase,
)
from .single import single_scattering, sun_visible_fraction, transmittance_to_sun, view_ray_samples

__all__ = [
    "PHASE_FUNCTIONS",
    "PrecomputedAtmosphere",
    "Quadrature",
    "TableSizes",
    "atmosphere_mie_phase",
    "cornette_shanks_phase",
    "henyey_greenstein_phase",
    "lognormal_mie_phase",
    "mie_phase",
    "precompute",
    "rayleigh_phase",
    "single_scattering",
    "spectral_mie_phase",
    "sky_radiance",
    "sun_visible_fraction",
    "tabulated_phase",
    "transmittance_to_sun",
    "two_term_hg_phase",
    "view_ray_samples",
]
