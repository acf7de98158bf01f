"""Fisheye sky cameras looking (nearly) at the zenith, CONTRACT.md conventions.

Zenith at the image centre, North up, East on the LEFT (a camera pointing up).
Pixel (row i, column j) has its centre at (x = j, y = i). World directions are
unit vectors in the local East-North-Up (ENU) frame; zenith angle from Up,
azimuth clockwise from North (North 0, East 90°).

Camera frame (OpenCV's, right-handed): x along the image's +x (right), y along
the image's +y (down), z the optical axis. With no tilt and up-azimuth 0 the
camera's x points West, y South, z Up. The camera-to-world rotation is
``R = R_tilt @ R_up``:

- ``R_up``: the image's up direction (-y) points to azimuth ``up_azimuth_deg``
  (clockwise from North), so with ``up_azimuth_deg = 90`` East is up and South
  is on the left.
- ``R_tilt``: the optical axis leans away from the zenith by the small angle
  ``|tilt_deg|``, toward azimuth ``atan2(tilt_E, tilt_N)``; ``tilt_deg =
  (tilt_E, tilt_N)`` is the rotation vector ``(-tilt_N, tilt_E, 0)`` in ENU
  (degrees), smooth at zero tilt unlike (zenith, azimuth) pairs.

Projections (model families), with theta the angle from the optical axis, r the
image radius [px], f the focal length [px/rad] and R90 the radius of the 90°
circle [px]; all have dr/dtheta = f at the centre:

===============  ============================  ==========================
equidistant      r = f theta                   R90 = f pi/2
equisolid        r = 2 f sin(theta/2)          R90 = f sqrt(2)
orthographic     r = f sin(theta)              R90 = f       (theta <= 90°)
stereographic    r = 2 f tan(theta/2)          R90 = 2 f
kannala_brandt   r = f (theta + k1 theta^3     R90 = f P(pi/2)
                 + k2 theta^5 + k3 theta^7
                 + k4 theta^9)
===============  ============================  ==========================

The first four are the classical fisheye mappings (Miyamoto 1964, "Fish eye
lens", JOSA 54(8) 1060–1061); the polynomial is Kannala & Brandt 2006 (see :mod:`.kannala_brandt`). The
classical ones are parametrised by R90 (``radius``), Kannala–Brandt by ``f``
(``focal``), each stored exactly as given.

Every pixel <-> direction map is written so that its gradient with respect to
the camera parameters and to the inputs is finite everywhere in the field of
view, including the centre pixel and the optical axis (no ``atan2(0, 0)``, no
normalisation by a zero radius: the radial factors are smooth functions of
``theta^2`` written in closed form or with ``sinc``).
"""
from __future__ import annotations

import dataclasses
import math
from typing import Sequence

import torch
from torch import Tensor

# The ENU direction conversions live in the base layer (render needs them too) and stay importable from here.
from ..geometry import enu_to_zenith_azimuth, safe_norm2, zenith_azimuth_to_enu  # noqa: F401
from .kannala_brandt import check_kb_monotone, kb_polynomial, kb_ratio, kb_theta

CLASSICAL_PROJECTIONS = ("equidistant", "equisolid", "orthographic", "stereographic")
PROJECTIONS = CLASSICAL_PROJECTIONS + ("kannala_brandt",)

_R90_OVER_F = {"equidistant": math.pi / 2, "equisolid": math.sqrt(2.0), "orthographic": 1.0, "stereographic": 2.0}
"""Radius of the 90° circle over the focal length for the classical projections (table above)."""

CONVENTION = "zenith at centre, North up, East left; pixel (row i, col j) centre at (x=j, y=i)"


def validate_projection(name: str) -> str:
    if name not in PROJECTIONS:
        raise ValueError(f"unknown projection {name!r}; valid: {', '.join(PROJECTIONS)}")
    return name


def theta_to_rho(theta: Tensor, projection: str) -> Tensor:
    """Normalised image radius r / R90 of an angle from the optical axis, classical projections.

    Args:
        theta: shape (...). [rad]
        projection: one of CLASSICAL_PROJECTIONS.

    Returns:
        rho, shape (...); 1 at theta = 90°. [1]
    """
    if validate_projection(projection) == "kannala_brandt":
        raise ValueError("theta_to_rho covers the classical projections; use kb_polynomial for kannala_brandt")
    if projection == "equidistant":
        return theta / (math.pi / 2)
    if projection == "equisolid":
        return torch.sin(theta / 2) / math.sin(math.pi / 4)
    if projection == "orthographic":
        return torch.sin(theta)
    return torch.tan(theta / 2)


def rho_to_theta(rho: Tensor, projection: str) -> Tensor:
    """Inverse of :func:`theta_to_rho`: angle from the optical axis [rad] of rho = r / R90.

    Outside a projection's domain (rho > 1 orthographic, rho > sqrt(2) equisolid) the result is NaN.
    """
    if validate_projection(projection) == "kannala_brandt":
        raise ValueError("rho_to_theta covers the classical projections; use kb_theta for kannala_brandt")
    if projection == "equidistant":
        return rho * (math.pi / 2)
    if projection == "equisolid":
        return 2 * torch.asin(rho * math.sin(math.pi / 4))
    if projection == "orthographic":
        return torch.asin(rho)
    return 2 * torch.atan(rho)


# -- smooth helpers ----------------------------------------------------------------
def _fill_nan(v: Tensor, keep: Tensor) -> Tensor:
    """v (..., 3) where keep (...), NaN elsewhere; the NaN is a constant, so gradients stay finite."""
    return torch.where(keep[..., None], v, torch.full_like(v, math.nan))


def _sinc(theta: Tensor) -> Tensor:
    """sin(theta) / theta, 1 at 0 (torch.sinc is the normalised sin(pi x)/(pi x))."""
    return torch.sinc(theta / math.pi)


def _as_param(value, name: str, shape: tuple, like: Tensor | None) -> Tensor:
    if isinstance(value, Tensor):
        t = value
    else:
        t = torch.as_tensor(value, dtype=torch.float64 if like is None else like.dtype,
                            device=None if like is None else like.device)
    if not t.is_floating_point():
        t = t.to(torch.float64)
    if tuple(t.shape) != shape:
        raise ValueError(f"fisheye {name} must have shape {shape}, got {tuple(t.shape)}")
    if not bool(torch.isfinite(t.detach()).all()):
        raise ValueError(f"fisheye {name} must be finite, got {t.detach().cpu().tolist()}")
    return t


@dataclasses.dataclass(frozen=True, eq=False)
class FisheyeCamera:
    """An upward-looking fisheye camera whose parameters are tensors (differentiable).

    Floats given to the constructor become float64 CPU tensors; tensors are kept as they are
    (so ``requires_grad`` tensors stay leaves of the caller's graph). Methods follow the
    dtype and device of their inputs (``pixel_directions`` takes them as arguments).

    Attributes:
        size: image width = height, or (height, width). [px]
        projection: one of PROJECTIONS.
        cx, cy: image position of the optical axis, shape () (default: the middle of the image,
            ((width - 1) / 2, (height - 1) / 2)). [px]
        radius: radius R90 of the 90° circle, shape () (classical projections; default
            min(height, width) / 2). Given for kannala_brandt, it sets ``focal = radius / P(pi/2)``. [px]
        focal: focal length f, shape () (kannala_brandt). Given for a classical projection, it sets
            ``radius = f * R90/f`` (module table). [px/rad]
        kb_coeffs: (k1, k2, k3, k4), shape (4,) (kannala_brandt only; default zeros, i.e. equidistant).
        up_azimuth_deg: azimuth of the image's up direction, shape (). [deg]
        tilt_deg: (toward East, toward North) lean of the optical axis, shape (2,); the axis points at
            zenith angle |tilt| and azimuth atan2(tilt_E, tilt_N). Must be < 90°. [deg]
        max_zenith_deg: field of view, as the largest angle from the optical axis that the lens images
            (pixels beyond are invalid); the zenith angle itself when there is no tilt. A float. [deg]
    """

    size: int | tuple[int, int]
    projection: str = "equidistant"
    cx: Tensor | float | None = None
    cy: Tensor | float | None = None
    radius: Tensor | float | None = None
    focal: Tensor | float | None = None
    kb_coeffs: Tensor | Sequence[float] | None = None
    up_azimuth_deg: Tensor | float = 0.0
    tilt_deg: Tensor | Sequence[float] = (0.0, 0.0)
    max_zenith_deg: float = 90.0

    def __post_init__(self):
        set_ = lambda name, value: object.__setattr__(self, name, value)  # noqa: E731
        validate_projection(self.projection)
        size = self.size
        if isinstance(size, (tuple, list)):
            if len(size) != 2:
                raise ValueError(f"image size must be N or (height, width), got {size}")
            size = (int(size[0]), int(size[1])) if size[0] != size[1] else int(size[0])
        else:
            size = int(size)
        set_("size", size)
        if min(self.height, self.width) < 1:
            raise ValueError(f"image size must be >= 1, got {self.size}")
        like = next((v for v in (self.cx, self.cy, self.radius, self.focal, self.kb_coeffs, self.up_azimuth_deg,
                                 self.tilt_deg) if isinstance(v, Tensor) and v.is_floating_point()), None)
        cx = (self.width - 1) / 2.0 if self.cx is None else self.cx
        cy = (self.height - 1) / 2.0 if self.cy is None else self.cy
        set_("cx", _as_param(cx, "cx", (), like))
        set_("cy", _as_param(cy, "cy", (), like))
        set_("up_azimuth_deg", _as_param(self.up_azimuth_deg, "up_azimuth_deg", (), like))
        set_("tilt_deg", _as_param(self.tilt_deg, "tilt_deg", (2,), like))
        if not (float(self.tilt_deg.detach().norm()) < 90.0):
            raise ValueError(f"fisheye tilt must be < 90 deg from the zenith, got {self.tilt_deg.detach().tolist()}")
        if not math.isfinite(self.max_zenith_deg):
            raise ValueError(f"max_zenith_deg must be finite, got {self.max_zenith_deg}")
        set_("max_zenith_deg", float(self.max_zenith_deg))
        if self.radius is not None and self.focal is not None:
            raise ValueError("give the fisheye radius (of the 90° circle) or the focal length, not both")
        for name in ("radius", "focal"):
            v = getattr(self, name)
            if v is not None:
                v = _as_param(v, name, (), like)
                if not float(v.detach()) > 0:
                    raise ValueError(f"fisheye {name} must be > 0 px, got {float(v.detach())}")
                set_(name, v)
        # Beyond these the projection is not one-to-one (orthographic folds back at 90°,
        # stereographic reaches infinity at 180°, equisolid's r peaks at 180°).
        if self.projection == "orthographic":
            ok, span = 0 < self.max_zenith_deg <= 90, "(0, 90]"
        else:
            ok, span = 0 < self.max_zenith_deg < 180, "(0, 180)"
        if not ok:
            raise ValueError(f"max_zenith_deg must be in {span} for the {self.projection} projection, got {self.max_zenith_deg}")
        default_r90 = min(self.height, self.width) / 2.0
        if self.projection == "kannala_brandt":
            k = _as_param((0.0,) * 4 if self.kb_coeffs is None else self.kb_coeffs, "kb_coeffs", (4,), like)
            set_("kb_coeffs", k)
            check_kb_monotone(k, math.radians(self.max_zenith_deg))
            if self.focal is None:
                r90 = self.radius if self.radius is not None else _as_param(default_r90, "radius", (), like)
                p90 = kb_polynomial(torch.tensor(math.pi / 2, dtype=k.dtype, device=k.device), k)
                set_("focal", r90.to(k.dtype) / p90)
                set_("radius", None)
        else:
            if self.kb_coeffs is not None:
                raise ValueError(f"kb_coeffs apply to the kannala_brandt projection only, not {self.projection}")
            if self.radius is None:
                r90 = self.focal * _R90_OVER_F[self.projection] if self.focal is not None else default_r90
                set_("radius", _as_param(r90, "radius", (), like))
                set_("focal", None)

    # -- shape and parameters ------------------------------------------------------
    @property
    def height(self) -> int:
        return self.size[0] if isinstance(self.size, tuple) else self.size

    @property
    def width(self) -> int:
        return self.size[1] if isinstance(self.size, tuple) else self.size

    @property
    def shape(self) -> tuple[int, int]:
        """(height, width) of the image. [px]"""
        return (self.height, self.width)

    @property
    def r90(self) -> Tensor:
        """Radius of the 90° circle, shape (). [px] (differentiable; for kannala_brandt f P(pi/2))."""
        if self.projection == "kannala_brandt":
            return self.focal * kb_polynomial(torch.tensor(math.pi / 2, dtype=self.focal.dtype, device=self.focal.device), self.kb_coeffs)
        return self.radius

    @property
    def focal_length(self) -> Tensor:
        """dr/dtheta at the image centre, shape (). [px/rad]"""
        if self.projection == "kannala_brandt":
            return self.focal
        return self.radius / _R90_OVER_F[self.projection]

    def parameters(self) -> dict[str, Tensor]:
        """The camera's tensors by name (``radius`` or ``focal`` as stored; ``kb_coeffs`` for kannala_brandt)."""
        names = ["cx", "cy", "focal" if self.projection == "kannala_brandt" else "radius", "up_azimuth_deg", "tilt_deg"]
        if self.projection == "kannala_brandt":
            names.append("kb_coeffs")
        return {n: getattr(self, n) for n in names}

    def to(self, dtype: torch.dtype | None = None, device=None) -> "FisheyeCamera":
        """A camera with every tensor converted (differentiably) to ``dtype`` / ``device``."""
        return dataclasses.replace(self, **{n: t.to(dtype=dtype, device=device) for n, t in self.parameters().items()})

    def rotation(self, dtype: torch.dtype | None = None, device=None) -> Tensor:
        """Camera-to-world rotation ``R_tilt @ R_up`` (columns: camera x, y, z in ENU), shape (3, 3). [1]"""
        from kornia.geometry.conversions import axis_angle_to_rotation_matrix

        a = torch.deg2rad(self.up_azimuth_deg.to(dtype=dtype, device=device))
        t = torch.deg2rad(self.tilt_deg.to(dtype=dtype, device=device))
        c, s = torch.cos(a), torch.sin(a)
        z, o = torch.zeros_like(c), torch.ones_like(c)
        # columns x_c = (-cos a, sin a, 0) (image right), y_c = (-sin a, -cos a, 0) (image down), z_c = Up
        r_up = torch.stack([torch.stack([-c, -s, z]), torch.stack([s, -c, z]), torch.stack([z, z, o])])
        omega = torch.stack([-t[1], t[0], torch.zeros_like(t[0])])
        return axis_angle_to_rotation_matrix(omega) @ r_up

    def _scale(self, dtype, device) -> Tensor:
        return (self.focal if self.projection == "kannala_brandt" else self.radius).to(dtype=dtype, device=device)

    def _rim(self) -> float:
        """Image radius of the field-of-view edge over the scale (R90 or f), a float (no gradient)."""
        th = math.radians(self.max_zenith_deg)
        if self.projection == "kannala_brandt":
            return float(kb_polynomial(torch.tensor(th, dtype=torch.float64), self.kb_coeffs.detach().double().cpu()))
        return float(theta_to_rho(torch.tensor(th, dtype=torch.float64), self.projection))

    # -- pixel <-> direction ---------------------------------------------------------
    def pixel_to_camera(self, x: Tensor, y: Tensor) -> tuple[Tensor, Tensor]:
        """Unit ray in the camera frame of image points, and whether they are inside the field of view.

        Args:
            x, y: image coordinates, same shape (...). [px]

        Returns:
            (d, inside): d shape (..., 3) [1], NaN where not ``inside`` (beyond max_zenith_deg); inside (...) bool.
        """
        d, inside = self._unproject(x, y)
        return _fill_nan(d, inside), inside

    def _unproject(self, x: Tensor, y: Tensor) -> tuple[Tensor, Tensor]:
        """As :meth:`pixel_to_camera` but finite everywhere (the optical axis where not inside), so that
        later operations mixing all entries (a rotation's matmul backward) stay NaN-free."""
        x, y = torch.broadcast_tensors(torch.as_tensor(x), torch.as_tensor(y))
        if not x.is_floating_point():
            x, y = x.to(torch.float64), y.to(torch.float64)
        dtype, device = x.dtype, x.device
        s = self._scale(dtype, device)
        u = x - self.cx.to(dtype=dtype, device=device)
        w = y - self.cy.to(dtype=dtype, device=device)
        rim = self._rim()
        with torch.no_grad():
            r2 = (u * u + w * w) / (s * s)
            # pixels on the rim are inside despite rounding; the orthographic 90° rim is the domain's edge
            tol = 0.0 if (self.projection == "orthographic" and self.max_zenith_deg == 90.0) else 1e-12
            inside = r2 <= rim * rim * (1 + tol)
        zero = torch.zeros_like(u)
        u = torch.where(inside, u, zero)
        w = torch.where(inside, w, zero)
        rho2 = (u * u + w * w) / (s * s)
        p = self.projection
        if p == "equidistant":  # theta = (pi/2) rho; sin(theta)/r = sinc(theta) (pi/2)/R90
            theta = (math.pi / 2) * safe_norm2(u, w) / s
            sr, cos_t = _sinc(theta) * (math.pi / 2) / s, torch.cos(theta)
        elif p == "equisolid":  # rho = sqrt2 sin(theta/2)
            sr, cos_t = math.sqrt(2.0) * torch.sqrt(1 - rho2 / 2) / s, 1 - rho2
        elif p == "orthographic":  # rho = sin(theta)
            sr, cos_t = 1 / s * torch.ones_like(rho2), torch.sqrt(1 - rho2)
        elif p == "stereographic":  # rho = tan(theta/2)
            sr, cos_t = 2 / (s * (1 + rho2)), (1 - rho2) / (1 + rho2)
        else:  # r = f P(theta): sin(theta)/r = sinc(theta) / (f Q(theta))
            k = self.kb_coeffs.to(dtype=dtype, device=device)
            theta = kb_theta(safe_norm2(u, w) / s, k, math.radians(self.max_zenith_deg))
            sr, cos_t = _sinc(theta) / (s * kb_ratio(theta, k)), torch.cos(theta)
        return torch.stack([u * sr, w * sr, cos_t], -1), inside

    def camera_to_pixel(self, d: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """Image coordinates of rays given in the camera frame (any non-zero length).

        Args:
            d: shape (..., 3). [1]

        Returns:
            (x, y, inside): x, y shape (...) [px], NaN where not ``inside`` (beyond max_zenith_deg).
        """
        dtype, device = d.dtype, d.device
        s = self._scale(dtype, device)
        with torch.no_grad():
            cos_lim = math.cos(math.radians(self.max_zenith_deg))
            inside = d[..., 2] >= (cos_lim - 1e-12) * d.norm(dim=-1)
        d = torch.where(inside[..., None], d, torch.tensor([0.0, 0.0, 1.0], dtype=dtype, device=device))
        dx, dy, dz = d.unbind(-1)
        n = d.norm(dim=-1)
        p = self.projection
        if p == "equidistant":  # r / sin(theta) = R90 (2/pi) / sinc(theta)
            theta = torch.atan2(safe_norm2(dx, dy), dz)
            t = s * (2 / math.pi) / (_sinc(theta) * n)
        elif p == "equisolid":  # sqrt2 sin(theta/2) / sin(theta) = 1 / sqrt(1 + cos(theta))
            t = s / torch.sqrt(n * (n + dz))
        elif p == "orthographic":
            t = s / n
        elif p == "stereographic":  # tan(theta/2) / sin(theta) = 1 / (1 + cos(theta))
            t = s / (n + dz)
        else:  # f P(theta) / sin(theta) = f Q(theta) / sinc(theta)
            theta = torch.atan2(safe_norm2(dx, dy), dz)
            t = s * kb_ratio(theta, self.kb_coeffs.to(dtype=dtype, device=device)) / (_sinc(theta) * n)
        nan = torch.full_like(t, math.nan)
        x = torch.where(inside, self.cx.to(dtype=dtype, device=device) + t * dx, nan)
        y = torch.where(inside, self.cy.to(dtype=dtype, device=device) + t * dy, nan)
        return x, y, inside

    def pixel_to_direction(self, x: Tensor, y: Tensor) -> Tensor:
        """World directions (unit vectors in ENU) of image points.

        Args:
            x, y: image coordinates (column, row), same shape (...). [px]

        Returns:
            shape (..., 3). [1] NaN beyond the field of view (see :meth:`pixel_valid`); the gradient is
            finite everywhere else, the centre included.
        """
        d, inside = self._unproject(x, y)
        return _fill_nan(d @ self.rotation(d.dtype, d.device).transpose(-1, -2), inside)

    def direction_to_pixel(self, v: Tensor) -> tuple[Tensor, Tensor]:
        """Image coordinates (x, y) [px] of world directions ``v`` (ENU, shape (..., 3), any non-zero length).

        Directions beyond the field of view (more than max_zenith_deg from the optical axis) give NaN.
        """
        d = v @ self.rotation(v.dtype, v.device)
        x, y, _ = self.camera_to_pixel(d)
        return x, y

    def angles_to_pixel(self, zenith: Tensor, azimuth: Tensor) -> tuple[Tensor, Tensor]:
        """(x, y) [px] of directions given as zenith and azimuth (clockwise from North) [rad], shape (...)."""
        return self.direction_to_pixel(zenith_azimuth_to_enu(zenith, azimuth))

    def pixel_valid(self, x: Tensor, y: Tensor) -> Tensor:
        """Inside the image (-0.5 <= x <= width - 0.5, same for y) and inside the field of view, bool (...)."""
        with torch.no_grad():
            x, y = torch.as_tensor(x), torch.as_tensor(y)
            _, inside = self.pixel_to_camera(x, y)
            return inside & (x >= -0.5) & (x <= self.width - 0.5) & (y >= -0.5) & (y <= self.height - 0.5)

    # -- whole image ---------------------------------------------------------------
    def pixel_grid(self, dtype=torch.float64, device="cpu") -> tuple[Tensor, Tensor]:
        """(x, y) of every pixel centre, each shape (height, width). [px]"""
        yy, xx = torch.meshgrid(torch.arange(self.height, dtype=dtype, device=device),
                                torch.arange(self.width, dtype=dtype, device=device), indexing="ij")
        return xx, yy

    def pixel_vectors(self, dtype=torch.float64, device="cpu") -> tuple[Tensor, Tensor]:
        """ENU unit vectors of every pixel centre (NaN where invalid), shape (H, W, 3), and the valid mask (H, W)."""
        x, y = self.pixel_grid(dtype, device)
        d, inside = self._unproject(x, y)
        return _fill_nan(d @ self.rotation(dtype, device).transpose(-1, -2), inside), inside

    def pixel_directions(self, dtype=torch.float64, device="cpu") -> tuple[Tensor, Tensor, Tensor]:
        """Zenith and azimuth of every pixel centre, and the valid mask.

        Returns:
            (zenith [rad], azimuth [rad, clockwise from North, in [0, 2 pi)], valid): shapes (H, W).
            Invalid pixels (beyond the field of view) hold NaN. The angles' gradients are zeroed where a
            pixel looks exactly at the zenith (see :func:`enu_to_zenith_azimuth`).
        """
        v, valid = self.pixel_vectors(dtype, device)
        zen, az = enu_to_zenith_azimuth(torch.where(valid[..., None], v, torch.zeros_like(v)))
        nan = torch.full_like(zen, math.nan)
        return torch.where(valid, zen, nan), torch.where(valid, az, nan), valid

    def valid_mask(self, device="cpu") -> Tensor:
        """Pixels inside the lens's field of view (max_zenith_deg from the optical axis), bool (H, W)."""
        x, y = self.pixel_grid(torch.float64, device)
        return self.pixel_valid(x, y)

    def below_horizon_mask(self, device="cpu") -> Tensor:
        """Valid pixels that look below the horizon (world zenith angle > 90°), bool (H, W).

        Without tilt these exist only when max_zenith_deg > 90; a tilted camera with a 90° field of
        view sees up to |tilt| below the horizon on the side it leans to.
        """
        with torch.no_grad():
            v, valid = self.pixel_vectors(torch.float64, device)
            return valid & (v[..., 2] < 0)

    # -- metadata ------------------------------------------------------------------
    def to_metadata(self) -> dict:
        """JSON-ready description from which :meth:`from_metadata` rebuilds an identical camera."""
        f = lambda t: float(t.detach())  # noqa: E731
        tilt = [float(v) for v in self.tilt_deg.detach().cpu().tolist()]
        meta = {
            "projection": self.projection,
            "size": self.size if isinstance(self.size, int) else list(self.size),
            "width": self.width,
            "height": self.height,
            "cx": f(self.cx),
            "cy": f(self.cy),
            "radius_px": f(self.r90),
            "focal_px": f(self.focal_length),
            "up_azimuth_deg": f(self.up_azimuth_deg),
            "tilt_deg": tilt,
            "tilt_zenith_deg": math.hypot(*tilt),
            "tilt_azimuth_deg": math.degrees(math.atan2(tilt[0], tilt[1])) % 360.0,
            "max_zenith_deg": self.max_zenith_deg,
            "convention": CONVENTION,
            "rotation": "camera-to-ENU R = R_tilt R_up; tilt_deg = (toward East, toward North), rotation vector (-tilt_N, tilt_E, 0)",
        }
        if self.projection == "kannala_brandt":
            meta["kb_coeffs"] = [float(v) for v in self.kb_coeffs.detach().cpu().tolist()]
            meta["model"] = "r = focal_px (theta + k1 theta^3 + k2 theta^5 + k3 theta^7 + k4 theta^9), Kannala & Brandt 2006"
        return meta

    metadata = to_metadata

    @classmethod
    def from_metadata(cls, meta: dict) -> "FisheyeCamera":
        """Rebuild a camera from :meth:`to_metadata`'s dict (e.g. an EXR header's ``camera`` entry).

        The classical projections read ``radius_px``, kannala_brandt reads ``focal_px`` and ``kb_coeffs``;
        ``up_azimuth_deg``, ``tilt_deg`` and ``max_zenith_deg`` default to 0, (0, 0) and 90 when absent
        (files written before they existed). Raises ``ValueError`` naming a missing or bad entry.
        """
        if not isinstance(meta, dict):
            raise ValueError(f"camera metadata must be a dict, got {type(meta).__name__}")
        projection = meta.get("projection")
        validate_projection(projection)
        kb = projection == "kannala_brandt"
        need = ["size", "cx", "cy"] + (["focal_px", "kb_coeffs"] if kb else ["radius_px"])
        missing = [k for k in need if k not in meta]
        if missing:
            raise ValueError(f"camera metadata lacks {', '.join(missing)} for the {projection} projection")
        size = meta["size"]
        try:
            return cls(
                size=tuple(size) if isinstance(size, list) else size,
                projection=projection,
                cx=float(meta["cx"]),
                cy=float(meta["cy"]),
                radius=None if kb else float(meta["radius_px"]),
                focal=float(meta["focal_px"]) if kb else None,
                kb_coeffs=[float(v) for v in meta["kb_coeffs"]] if kb else None,
                up_azimuth_deg=float(meta.get("up_azimuth_deg", 0.0)),
                tilt_deg=[float(v) for v in meta.get("tilt_deg", (0.0, 0.0))],
                max_zenith_deg=float(meta.get("max_zenith_deg", 90.0)),
            )
        except (TypeError, ValueError) as e:
            raise ValueError(f"bad camera metadata: {e}") from None


def reproject(image: Tensor, src: FisheyeCamera, dst: FisheyeCamera, mode: str = "bilinear") -> tuple[Tensor, Tensor]:
    """Resample an image taken with camera ``src`` into the geometry of camera ``dst``.

    Every destination pixel's direction is projected into the source image
    (``dst.pixel_to_direction`` then ``src.direction_to_pixel``) and sampled with
    ``kornia.geometry.transform.remap`` (pixel coordinates, ``align_corners=True``
    so that pixel j's centre is x = j). Differentiable with respect to the image
    and both cameras' parameters.

    Args:
        image: shape (C, H, W) or (B, C, H, W) with (H, W) = src.shape.
        src, dst: the cameras.
        mode: 'bilinear' or 'nearest'.

    Returns:
        (out, valid): out shape (C or B,C, dst.height, dst.width), 0 where not valid; valid (H', W') bool:
        inside dst's field of view, seen by src, and inside src's image (within half a pixel of the
        image's edge the edge pixels are repeated, ``padding_mode='border'``). Within about a pixel of
        src's field-of-view edge the samples blend in whatever src holds outside it.
    """
    from kornia.geometry.transform import remap

    squeeze = image.dim() == 3
    img = image[None] if squeeze else image
    if img.dim() != 4 or tuple(img.shape[-2:]) != src.shape:
        raise ValueError(f"reproject: image must be (C, H, W) or (B, C, H, W) with (H, W) = {src.shape}, got {tuple(image.shape)}")
    v, valid = dst.pixel_vectors(img.dtype, img.device)
    up = torch.tensor([0.0, 0.0, 1.0], dtype=v.dtype, device=v.device)
    xs, ys = src.direction_to_pixel(torch.where(valid[..., None], v, up))
    with torch.no_grad():
        ok = valid & torch.isfinite(xs) & torch.isfinite(ys)
        ok &= (xs >= -0.5) & (xs <= src.width - 0.5) & (ys >= -0.5) & (ys <= src.height - 0.5)
    outside = torch.full_like(xs, -2.0)
    map_x = torch.where(ok, xs, outside)[None].expand(img.shape[0], -1, -1)
    map_y = torch.where(ok, ys, outside)[None].expand(img.shape[0], -1, -1)
    out = remap(img, map_x, map_y, mode=mode, padding_mode="border", align_corners=True)
    out = torch.where(ok, out, torch.zeros_like(out))
    return (out[0] if squeeze else out), ok
