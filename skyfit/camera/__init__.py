"""Fisheye cameras (directions per pixel, masks) and the sun's position."""
from .fisheye import PROJECTIONS, FisheyeCamera, rho_to_theta, theta_to_rho
from .sun import SunPosition, delta_t_espenak_meeus, julian_day, parse_location, parse_time, sun_position

__all__ = [
    "PROJECTIONS",
    "FisheyeCamera",
    "SunPosition",
    "delta_t_espenak_meeus",
    "julian_day",
    "parse_location",
    "parse_time",
    "rho_to_theta",
    "sun_position",
    "theta_to_rho",
]
