"""skyfit: fit a physically based atmosphere to measured skies.

Data flow: atmosphere (parameters) -> transmittance (optical depth integrators)
-> scattering (phase functions, single scattering) -> render (directions in,
radiance and colour out) -> camera (fisheye) -> io (OpenEXR).
"""
__version__ = "0.1.0"
