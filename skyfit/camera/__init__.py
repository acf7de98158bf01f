"""Fisheye cameras (directions per pixel, masks), fisheye sky images, the sun's position, and photos (LDR and synthetic,
calibrated responses); the camera from a photo (circle, sun, heading: autocal) and what is not sky in it (masks)."""
from .autocal import (
    CalibrationError,
    CameraGuess,
    Circle,
    SunDetection,
    cameras_from_sun,
    detect_circle,
    detect_sun,
    heading_from_sun,
    symmetry_axis,
)
from .fisheye import (
    CLASSICAL_PROJECTIONS,
    PROJECTIONS,
    FisheyeCamera,
    enu_to_zenith_azimuth,
    reproject,
    rho_to_theta,
    theta_to_rho,
    zenith_azimuth_to_enu,
)
from .image import SkyImage, render_fisheye
from .kannala_brandt import check_kb_monotone, kb_derivative, kb_polynomial, kb_theta
from .likelihood import censored_gaussian_nll, fit_exposure_scale
from .masks import grow_outlier_mask, obstacle_mask, sun_mask
from .photo_io import PhotoObservation, load_ldr_photo
from .response import ResponseError, TabulatedResponse, debevec_response, robertson_response, table_response
from .sensor import SyntheticPhoto, spectral_response_matrix, synthesize_photo, vignetting_map
from .srgb import srgb_decode, srgb_encode
from .sun import SunPosition, delta_t_espenak_meeus, julian_day, parse_location, parse_time, sun_position

__all__ = [
    "CLASSICAL_PROJECTIONS",
    "PROJECTIONS",
    "CalibrationError",
    "CameraGuess",
    "Circle",
    "FisheyeCamera",
    "PhotoObservation",
    "ResponseError",
    "SkyImage",
    "SunDetection",
    "SunPosition",
    "SyntheticPhoto",
    "TabulatedResponse",
    "cameras_from_sun",
    "censored_gaussian_nll",
    "check_kb_monotone",
    "debevec_response",
    "delta_t_espenak_meeus",
    "detect_circle",
    "detect_sun",
    "enu_to_zenith_azimuth",
    "fit_exposure_scale",
    "grow_outlier_mask",
    "heading_from_sun",
    "julian_day",
    "kb_derivative",
    "kb_polynomial",
    "kb_theta",
    "load_ldr_photo",
    "obstacle_mask",
    "parse_location",
    "parse_time",
    "render_fisheye",
    "reproject",
    "robertson_response",
    "rho_to_theta",
    "spectral_response_matrix",
    "srgb_decode",
    "srgb_encode",
    "sun_mask",
    "sun_position",
    "symmetry_axis",
    "synthesize_photo",
    "table_response",
    "theta_to_rho",
    "vignetting_map",
    "zenith_azimuth_to_enu",
]
