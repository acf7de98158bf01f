"""Phase functions, single scattering, and multiple scattering (Bruneton tables, Hillaire LUT)."""
from .bruneton_tables import TableSizes
from .multiple import PrecomputedAtmosphere, Quadrature, precompute, sky_radiance
from .phase import PHASE_FUNCTIONS, cornette_shanks_phase, henyey_greenstein_phase, mie_phase, rayleigh_phase
from .single import single_scattering, sun_visible_fraction, transmittance_to_sun, view_ray_samples

__all__ = [
    "PHASE_FUNCTIONS",
    "PrecomputedAtmosphere",
    "Quadrature",
    "TableSizes",
    "cornette_shanks_phase",
    "henyey_greenstein_phase",
    "mie_phase",
    "precompute",
    "rayleigh_phase",
    "single_scattering",
    "sky_radiance",
    "sun_visible_fraction",
    "transmittance_to_sun",
    "view_ray_samples",
]
