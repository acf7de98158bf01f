"""Fisheye cameras (directions per pixel, masks)."""
from .fisheye import PROJECTIONS, FisheyeCamera, rho_to_theta, theta_to_rho

__all__ = ["PROJECTIONS", "FisheyeCamera", "rho_to_theta", "theta_to_rho"]
