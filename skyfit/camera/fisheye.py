"""Fisheye sky cameras looking at the zenith (CONTRACT.md conventions).

Zenith at the image centre, North up, East on the LEFT (a camera pointing up),
the 90° circle of radius ``radius`` pixels. Image azimuth of a pixel is
measured clockwise from the image's up direction, which points to azimuth
``up_azimuth_deg``. Pixel (row i, column j) has its centre at (x=j, y=i).

Projections, with rho the distance from the centre divided by the radius of
the 90° circle (so rho = 1 at theta = 90° for all of them):

=============== ==============================
equidistant     rho = theta / (pi/2)
equisolid       rho = sin(theta/2) / sin(pi/4)
orthographic    rho = sin(theta)          (theta <= 90°)
stereographic   rho = tan(theta/2)
=============== ==============================

Written by hand: kornia's camera models are pinhole/z=1-plane models that
cannot represent rays at 90° from the optical axis (see issue 4).
"""
from __future__ import annotations

import dataclasses
import math

import torch
from torch import Tensor

PROJECTIONS = ("equidistant", "equisolid", "orthographic", "stereographic")


def validate_projection(name: str) -> str:
    if name not in PROJECTIONS:
        raise ValueError(f"unknown projection {name!r}; valid: {', '.join(PROJECTIONS)}")
    return name


def theta_to_rho(theta: Tensor, projection: str) -> Tensor:
    """Normalised image radius of a zenith angle [rad] -> [1]."""
    validate_projection(projection)
    if projection == "equidistant":
        return theta / (math.pi / 2)
    if projection == "equisolid":
        return torch.sin(theta / 2) / math.sin(math.pi / 4)
    if projection == "orthographic":
        return torch.sin(theta)
    return torch.tan(theta / 2)


def rho_to_theta(rho: Tensor, projection: str) -> Tensor:
    """Zenith angle [rad] of a normalised image radius; NaN-free (clamped to the valid range)."""
    validate_projection(projection)
    if projection == "equidistant":
        return rho * (math.pi / 2)
    if projection == "equisolid":
        return 2 * torch.asin(torch.clamp(rho * math.sin(math.pi / 4), -1.0, 1.0))
    if projection == "orthographic":
        return torch.asin(torch.clamp(rho, -1.0, 1.0))
    return 2 * torch.atan(rho)


@dataclasses.dataclass(frozen=True)
class FisheyeCamera:
    """An upward-looking fisheye of ``size`` x ``size`` pixels.

    Attributes:
        size: image width and height. [px]
        projection: one of PROJECTIONS.
        cx, cy: image centre (default: the middle of the image). [px]
        radius: radius of the 90° circle (default size / 2). [px]
        up_azimuth_deg: azimuth of the image's up direction (0 = North up). [deg]
        max_zenith_deg: pixels beyond this zenith angle are invalid. [deg]
    """

    size: int
    projection: str = "equidistant"
    cx: float | None = None
    cy: float | None = None
    radius: float | None = None
    up_azimuth_deg: float = 0.0
    max_zenith_deg: float = 90.0

    def __post_init__(self):
        validate_projection(self.projection)
        if self.size < 1:
            raise ValueError(f"image size must be >= 1, got {self.size}")
        if self.radius is not None and not 0 < self.radius < math.inf:
            raise ValueError(f"fisheye radius must be > 0 px, got {self.radius}")
        for name in ("cx", "cy", "up_azimuth_deg"):
            v = getattr(self, name)
            if v is not None and not math.isfinite(v):
                raise ValueError(f"fisheye {name} must be finite, got {v}")
        # Beyond these the projection is not one-to-one (orthographic folds back at 90°,
        # stereographic reaches infinity at 180°, equisolid's rho peaks at 180°).
        if self.projection == "orthographic":
            ok, span = 0 < self.max_zenith_deg <= 90, "(0, 90]"
        else:
            ok, span = 0 < self.max_zenith_deg < 180, "(0, 180)"
        if not ok:
            raise ValueError(f"max_zenith_deg must be in {span} for the {self.projection} projection, got {self.max_zenith_deg}")

    @property
    def centre(self) -> tuple[float, float]:
        c = (self.size - 1) / 2.0
        return (c if self.cx is None else self.cx, c if self.cy is None else self.cy)

    @property
    def r90(self) -> float:
        return self.size / 2.0 if self.radius is None else self.radius

    def pixel_directions(self, dtype=torch.float64, device="cpu") -> tuple[Tensor, Tensor, Tensor]:
        """Zenith and azimuth of every pixel centre, and the valid mask.

        Returns:
            (zenith [rad], azimuth [rad, clockwise from North], valid): shapes (size, size).
        """
        cx, cy = self.centre
        idx = torch.arange(self.size, dtype=dtype, device=device)
        yy, xx = torch.meshgrid(idx, idx, indexing="ij")
        dx, dy = xx - cx, cy - yy  # right, up
        rho = torch.hypot(dx, dy) / self.r90
        theta = rho_to_theta(rho, self.projection)
        # East on the left: a pixel left of centre (dx < 0) is at image azimuth +90°.
        az = torch.atan2(-dx, dy) + math.radians(self.up_azimuth_deg)
        limit = math.radians(self.max_zenith_deg)
        rho_max = float(theta_to_rho(torch.tensor(limit, dtype=torch.float64), self.projection))
        valid = rho <= rho_max * (1 + 1e-12)
        return theta, torch.remainder(az, 2 * math.pi), valid

    def direction_to_pixel(self, zenith: Tensor, azimuth: Tensor) -> tuple[Tensor, Tensor]:
        """(x, y) pixel coordinates of directions (zenith, azimuth in rad)."""
        cx, cy = self.centre
        rho = theta_to_rho(zenith, self.projection) * self.r90
        a = azimuth - math.radians(self.up_azimuth_deg)
        return cx - rho * torch.sin(a), cy - rho * torch.cos(a)

    def metadata(self) -> dict:
        cx, cy = self.centre
        return {
            "projection": self.projection,
            "size": self.size,
            "cx": cx,
            "cy": cy,
            "radius_px": self.r90,
            "up_azimuth_deg": self.up_azimuth_deg,
            "convention": "zenith at centre, North up, East left; pixel (row i, col j) centre at (x=j, y=i)",
        }
