"""Phase functions and single scattering."""
from .phase import PHASE_FUNCTIONS, cornette_shanks_phase, henyey_greenstein_phase, mie_phase, rayleigh_phase
from .single import single_scattering, sun_visible_fraction, transmittance_to_sun

__all__ = [
    "PHASE_FUNCTIONS",
    "cornette_shanks_phase",
    "henyey_greenstein_phase",
    "mie_phase",
    "rayleigh_phase",
    "single_scattering",
    "sun_visible_fraction",
    "transmittance_to_sun",
]
