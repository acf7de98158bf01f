"""The camera from the image: fisheye circle, the sun in the photo, and cameras that put the computed sun there.

For an all-sky photo whose lens centre, radius, projection and heading are not known:

1. :func:`detect_circle` finds the image circle, the edge of the bright disc against the dark
   surround (Canny edges, a RANSAC circle, then a sub-pixel refinement along radial profiles).
2. :func:`symmetry_axis` finds the sun's direction from the circle's centre as the sky's mirror axis (the sky
   is symmetric about the sun's vertical), and :func:`detect_sun` the sun's image in the darkest frame (the
   centroid of its saturated core, or of a compact peak far above its surroundings; on that axis, for a
   saturated aureole cut by the horizon).
3. :func:`cameras_from_sun` builds one :class:`~skyfit.camera.fisheye.FisheyeCamera` per projection
   with the centre and radius from the circle and the heading that puts the computed (SPA) sun on the
   detected one, ranked by how well each projection maps the sun's zenith angle to its image radius.

Image convention (CONTRACT.md): pixel (row i, column j) has its centre at (x = j, y = i); zenith at the
circle's centre, North up, East left when ``up_azimuth_deg = 0``.
"""
from __future__ import annotations

import dataclasses
import math
import warnings

import numpy as np
import skimage  # lazy sub-packages: skimage.measure etc. load (with scipy, ~0.7 s) at first use, not at `import skyfit`
import torch

from .fisheye import CLASSICAL_PROJECTIONS, FisheyeCamera, rho_to_theta, theta_to_rho, validate_projection

__all__ = [
    "CalibrationError",
    "CameraGuess",
    "Circle",
    "SunDetection",
    "cameras_from_sun",
    "detect_circle",
    "detect_sun",
    "fill_small_holes",
    "heading_from_sun",
    "symmetry_axis",
]


class CalibrationError(ValueError):
    """The camera cannot be estimated from the image (no circle, no consistent sun); a one-line message."""


@dataclasses.dataclass
class Circle:
    """The fisheye's image circle.

    Attributes:
        cx, cy: centre, image convention (pixel (row i, col j) centre at (x = j, y = i)). [px]
        radius: radius of the bright disc's edge (half-level crossing). [px]
        inlier_fraction: fraction of the circle's visible circumference (the part inside the image)
            whose refined edge point lies within 1 px of the circle. [1]
        residual_px: RMS radial distance of those points from the circle. [px]
    """

    cx: float
    cy: float
    radius: float
    inlier_fraction: float
    residual_px: float


@dataclasses.dataclass
class SunDetection:
    """The sun's image in the darkest frame.

    Attributes:
        x, y: centroid, image convention. [px]
        radius_px: radius of the disc of the same area as the detected blob. [px]
        saturated: True when found as a saturated core, False as an unsaturated peak.
        n_pixels: pixels in the blob. [1]
        extended: True when the saturated region is no disc clear of the rim (a single frame exposed for the
            sky saturates the aureole, merged with the bright horizon, cut by the rim or squeezed at it): x, y
            are then on the sky's symmetry axis, the centre of the largest disc inside the region that touches
            its end nearest the zenith (:func:`detect_sun`), or without an axis the region's deepest point.
            Good for the sun's azimuth about the centre (the heading), within a few degrees for its radius
            (the projection).
    """

    x: float
    y: float
    radius_px: float
    saturated: bool
    n_pixels: int
    extended: bool = False


@dataclasses.dataclass
class CameraGuess:
    """One candidate camera (a projection) from the circle and the sun.

    Attributes:
        camera: centre and R90 from the circle, heading from the sun, no tilt.
        projection: the camera's projection name.
        score: |zenith angle this projection gives the detected sun's radius - computed sun zenith| [deg];
            lower is better, ``inf`` where the radius is beyond the projection's domain, NaN without a
            detected sun (no evidence: every projection tied).
        sun_model_px: (x, y) where ``camera`` puts the computed sun [px], None where outside its view.
        notes: what the guess assumed or could not determine, one line each.
        tolerance_deg: how far above the best score this projection's may lie and still be the right one:
            :data:`SUN_ZENITH_TOL_DEG` (the tilt), plus for an extended detection the zenith span of its
            ``radius_px`` along the radius under this projection (the sun lies within it of the detected
            point). NaN without a detected sun. [deg]
    """

    camera: FisheyeCamera
    projection: str
    score: float
    sun_model_px: tuple[float, float] | None
    notes: list[str]
    tolerance_deg: float = math.nan


# ----------------------------------------------------------------------------------- circle
_CANNY_SIGMA = 1.5
"""Gaussian smoothing of Canny [px]."""
_CANNY_PER_LOG_STEP = 1.9
"""Canny's gradient magnitude (scipy.ndimage.sobel, 8x the derivative) at a unit step after the
sigma = 1.5 Gaussian, measured on a synthetic step edge (8 x 0.2395). [1 per ln unit]"""
_FLOOR = 0.02
"""Luminance floor as a fraction of the bright level (90th percentile), so that the surround's noise
is flat in log luminance. [1]"""


def _check_image(a: np.ndarray, name: str) -> np.ndarray:
    a = np.asarray(a, dtype=np.float64)
    if a.ndim != 2 or min(a.shape) < 16:
        raise CalibrationError(f"{name} must be a 2-D image of at least 16x16 pixels, got shape {a.shape}")
    return a


def _sample(image: np.ndarray, x: np.ndarray, y: np.ndarray, order: int = 1) -> np.ndarray:
    """Bilinear (order 1) or nearest (0) samples of a 2-D image at points (x, y) [px]; NaN outside the image."""
    coords = np.stack([y.ravel(), x.ravel()])[:, None, :]  # skimage.transform.warp's (row, col) map, shape (2, 1, N)
    out = skimage.transform.warp(image, coords, order=order, mode="constant", cval=np.nan, preserve_range=True,
                                 clip=False)
    return out.reshape(x.shape)


BEYOND_PX = (2.0, 5.0)
"""Where beyond a crossing :func:`_radial_edges` looks for the unlit surround: past the rim's blur (a lens and
demosaicing spread a step over 1-2 px) and short of the window's end. [px]"""

OBSTACLE_LEVEL = 0.005
"""Above the outside level by this fraction of the sky's (inside) level, what lies beyond a crossing is lit: an
obstacle, not the surround outside the image circle (which no light reaches; JPEG codes 0-2 there). Daylit trees,
roofs and hills are 1-10 % of the sky. [1]"""


def _radial_edges(lin: np.ndarray, valid: np.ndarray, cx: float, cy: float, r: float, n_angles: int,
                  half_width: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """Sub-pixel edge along radial profiles through an approximate circle.

    Along each of ``n_angles`` rays from (cx, cy), the profile of ``lin`` over radii r +- half_width is
    sampled (bilinear); the edge is where it falls through the middle between the inside level (median
    over the inner quarter of the window) and the outside level (outer quarter), the crossing nearest r,
    interpolated linearly. A hand-written search: no library offers a sub-pixel step along given rays.

    A crossing is dropped where the profile 2-5 px beyond it (:data:`BEYOND_PX`) stays above the outside level by
    more than :data:`OBSTACLE_LEVEL` of the inside level: that is no rim with the unlit surround behind it but the
    top of a lit obstacle (a tree, a roof, a hill on the horizon; 1-7 % of the sky in the photos of docs/photos.md),
    whose crossings lie inside the circle and, a third of the horizon of them, pull a fitted circle in and aside.
    Where that would drop over half the rays the rim itself is soft (a lens whose field stop blurs over several
    pixels) and none is dropped.

    Returns:
        (x, y, visible, median outside/inside ratio): x, y shape (n,) of the rays with a clear edge [px];
        visible, number of rays whose window lies inside the image and ``valid`` and whose rim no lit obstacle hides.
    """
    phi = np.linspace(0, 2 * np.pi, n_angles, endpoint=False)
    radii = np.arange(r - half_width, r + half_width + 1e-9, 0.25)
    xx = cx + radii[None, :] * np.cos(phi)[:, None]
    yy = cy + radii[None, :] * np.sin(phi)[:, None]
    prof = _sample(lin, xx, yy, 1)
    ok = _sample(valid.astype(np.float64), xx, yy, 0)
    seen = np.all(np.isfinite(prof) & (ok > 0.5), axis=1)
    q = len(radii) // 4
    a = np.median(np.where(np.isfinite(prof[:, :q]), prof[:, :q], 0), axis=1)  # inside level
    b = np.median(np.where(np.isfinite(prof[:, -q:]), prof[:, -q:], 0), axis=1)  # outside level
    contrast = a - b
    ratio = float(np.median(b[seen] / np.maximum(a[seen], 1e-300))) if seen.any() else 1.0
    typical = np.median(contrast[seen]) if seen.any() else 0.0
    clear = seen & (contrast > 0.3 * typical) & (contrast > 0) & (b < 0.5 * a)
    xs, ys, lit = [], [], []
    j0 = len(radii) // 2
    for k in np.nonzero(clear)[0]:
        mid = 0.5 * (a[k] + b[k])
        p = prof[k]
        down = np.nonzero((p[:-1] >= mid) & (p[1:] < mid))[0]
        if len(down) == 0:
            continue
        j = down[np.argmin(np.abs(down - j0))]
        t = (p[j] - mid) / (p[j] - p[j + 1])
        rr = radii[j] + t * (radii[j + 1] - radii[j])
        beyond = p[(radii >= rr + BEYOND_PX[0]) & (radii <= rr + BEYOND_PX[1])]
        lit.append(bool(beyond.size) and float(np.median(beyond)) > b[k] + OBSTACLE_LEVEL * a[k])
        xs.append(cx + rr * np.cos(phi[k]))
        ys.append(cy + rr * np.sin(phi[k]))
    xs, ys, lit = np.asarray(xs), np.asarray(ys), np.asarray(lit, dtype=bool)
    if lit.sum() > 0.5 * max(int(seen.sum()), 1):  # most of the rim "lit": a soft rim, not obstacles; keep them all
        lit[:] = False
    return xs[~lit], ys[~lit], int(seen.sum()) - int(lit.sum()), ratio


def _circle_params(model) -> tuple[float, float, float]:
    """(cx, cy, radius) of a fitted ``skimage.measure.CircleModel``: ``center, radius`` from scikit-image 0.26,
    ``params`` before (deprecated since)."""
    if hasattr(model, "center"):
        (x0, y0), r0 = model.center, model.radius
    else:
        x0, y0, r0 = model.params
    return float(x0), float(y0), float(r0)


CIRCLE_MAX_SIDE = 1000
""":func:`detect_circle` works on a copy reduced by an integer factor (block means, ``skimage.transform.
downscale_local_mean``) to at most this many pixels on the longer side, and scales the circle back. Its pixel
thresholds (Canny's sigma 1.5, RANSAC's 2 and 1 px, :data:`BEYOND_PX`) were set on photos of 120-800 px, whose rim
blurs over 1-2 px; the same rim in a 3000 px photo spans 5-10 px and its crossings scatter beyond them (the 600 px
synthetic case 2 upscaled to 3000 px: "only 47 % of the visible rim lies on one circle"). [px]"""


def detect_circle(luminance: np.ndarray, valid: np.ndarray | None = None, *, seed: int = 0) -> Circle:
    """The fisheye's image circle: the edge of the bright disc against the dark surround.

    Canny edges (``skimage.feature.canny``) of the log luminance (floored at 2 % of the bright level,
    so the surround's noise makes no edges), kept where the gradient points toward the bright mass
    (bright inside, dark outside); a RANSAC circle (``skimage.measure.ransac`` with ``CircleModel``) on
    them; then twice a refinement: the half-level crossing along 720 radial profiles and a RANSAC
    circle (1 px threshold) on those points. Dark obstacles at the horizon (their edge lies inside the
    circle), a bright dome rim, the sun's disc and clouds are outliers of both fits; where an obstacle
    is brighter than the surround the crossing still marks the circle.

    Args:
        luminance: linear luminance (or any linear brightness), shape (H, W). [any unit]
        valid: pixels that carry data, shape (H, W) bool (default: finite ones).
        seed: seed of RANSAC's random generator.

    Returns:
        :class:`Circle`; a circle partly outside the image works while most of its edge is visible.

    Raises:
        CalibrationError: "no fisheye circle found: ..." when the image has no clear circle (e.g. a
            full-frame image with no dark surround, or under 50 % of the visible rim on one circle).
    """
    lum = _check_image(luminance, "luminance")
    valid = np.isfinite(lum) if valid is None else np.asarray(valid, dtype=bool)
    if valid.shape != lum.shape:
        raise CalibrationError(f"valid mask shape {valid.shape} differs from the image's {lum.shape}")
    valid = valid & np.isfinite(lum)
    lum = np.where(valid, lum, 0.0)
    k = math.ceil(max(lum.shape) / CIRCLE_MAX_SIDE)
    if k > 1:  # a block's centre (k - 1) / 2 px from its first pixel: x = k x' + (k - 1) / 2
        small = _detect_circle(skimage.transform.downscale_local_mean(lum, (k, k)),
                               skimage.transform.downscale_local_mean(valid.astype(np.float64), (k, k)) > 0.999, seed)
        return Circle(k * small.cx + 0.5 * (k - 1), k * small.cy + 0.5 * (k - 1), k * small.radius, small.inlier_fraction,
                      k * small.residual_px)
    return _detect_circle(lum, valid, seed)


def _detect_circle(lum: np.ndarray, valid: np.ndarray, seed: int) -> Circle:
    """:func:`detect_circle` on an image of at most :data:`CIRCLE_MAX_SIDE` pixels a side (``lum`` 0 where not
    ``valid``)."""
    h, w = lum.shape
    bright = float(np.percentile(lum[valid], 90)) if valid.any() else 0.0
    if not bright > 0:
        raise CalibrationError("no fisheye circle found: the image is black")
    lin = np.clip(lum / bright, 0.0, None)
    log_l = np.log(np.maximum(lin, _FLOOR))
    # edges of steps of at least ln 3 in log luminance (a factor of 3); smooth sky gradients stay far below
    high = 0.5 * _CANNY_PER_LOG_STEP * math.log(3.0)
    edges = skimage.feature.canny(log_l, sigma=_CANNY_SIGMA, low_threshold=0.5 * high, high_threshold=high,
                                  mask=valid, mode="nearest")
    rows, cols = np.nonzero(edges)
    if len(rows) < 30:
        raise CalibrationError(f"no fisheye circle found: only {len(rows)} edge pixels (no dark surround)")
    # gradient direction at each edge point; the disc's edge has bright inside, so its gradient points toward the
    # bright mass's centroid
    smooth = skimage.filters.gaussian(log_l, sigma=_CANNY_SIGMA, mode="nearest")
    gy, gx = np.gradient(smooth)
    my, mx = np.argwhere(lin > 0.1).mean(axis=0) if (lin > 0.1).any() else ((h - 1) / 2, (w - 1) / 2)
    g = np.stack([gx[rows, cols], gy[rows, cols]], 1)
    to_c = np.stack([mx - cols, my - rows], 1)
    cosang = (g * to_c).sum(1) / np.maximum(np.linalg.norm(g, axis=1) * np.linalg.norm(to_c, axis=1), 1e-12)
    keep = cosang > 0.5
    pts = np.stack([cols[keep], rows[keep]], 1).astype(np.float64)
    if len(pts) < 30:
        raise CalibrationError("no fisheye circle found: no edge with a bright inside and a dark outside")
    rmin, rmax = 0.15 * min(h, w), math.hypot(h, w)

    def plausible(model, *_):
        x0, y0, r0 = _circle_params(model)
        return rmin <= r0 <= rmax and -0.5 * w <= x0 <= 1.5 * w and -0.5 * h <= y0 <= 1.5 * h

    rng = np.random.default_rng(seed)
    with warnings.catch_warnings():  # "Estimated model is not valid": a failed fit is reported below, as one line
        warnings.simplefilter("ignore", UserWarning)
        model, inliers = skimage.measure.ransac(pts, skimage.measure.CircleModel, min_samples=3, residual_threshold=2.0,
                                                is_model_valid=plausible, max_trials=1000, rng=rng)
    if model is None or inliers is None or inliers.sum() < 30:
        raise CalibrationError("no fisheye circle found: the edges fit no circle")
    cx, cy, r = _circle_params(model)
    for _ in range(2):
        xs, ys, visible, ratio = _radial_edges(lin, valid, cx, cy, r, 720, max(6.0, 0.05 * r))
        if visible < 0.3 * 720:
            raise CalibrationError(f"no fisheye circle found: only {visible / 7.2:.0f} % of the candidate circle "
                                   "lies in the image with no lit obstacle over it")
        if ratio > 0.2:
            raise CalibrationError(f"no fisheye circle found: outside the candidate circle is {ratio:.0%} as "
                                   "bright as inside (no dark surround)")
        if len(xs) < 30:
            raise CalibrationError("no fisheye circle found: the candidate circle has no clear edge")
        ref = np.stack([xs, ys], 1)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)
            model, inl = skimage.measure.ransac(ref, skimage.measure.CircleModel, min_samples=3,
                                                residual_threshold=1.0, is_model_valid=plausible, max_trials=300, rng=rng)
        if model is None or inl is None:
            raise CalibrationError("no fisheye circle found: the refined edge fits no circle")
        cx, cy, r = _circle_params(model)
    res = model.residuals(ref[inl])
    frac = float(inl.sum()) / visible
    if frac < 0.5:
        raise CalibrationError(f"no fisheye circle found: only {frac:.0%} of the visible rim lies on one circle")
    return Circle(float(cx), float(cy), float(r), frac, float(np.sqrt(np.mean(res**2))))


# -------------------------------------------------------------------------------------- sun

def fill_small_holes(mask: np.ndarray, max_area: int) -> np.ndarray:
    """``mask`` (shape (H, W) bool) with its enclosed holes of at most ``max_area`` pixels filled (labels and
    counts; the ``remove_small_holes`` keyword changed in scikit-image 0.26)."""
    lab = skimage.measure.label(~mask, connectivity=1)
    area = np.bincount(lab.ravel())
    border = np.unique(np.concatenate([lab[0], lab[-1], lab[:, 0], lab[:, -1]]))
    small = area <= max_area
    small[border] = False
    small[0] = False
    return mask | small[lab]


SRGB_LUMA = np.array([0.2126, 0.7152, 0.0722])
"""Linear sRGB to relative luminance Y, to the 4 digits of IEC 61966-2-1 (the image-side steps: circle, sun, masks;
the fit's model uses the derived :func:`skyfit.render.colour.srgb_luminance_weights`). [1]"""


EXTENDED_MIN_PX = 20
"""A saturated region that is no disc counts as the sun's aureole from this many pixels on."""

SUN_HOLE_MAX_PX = 64
"""Holes in the saturated mask up to this many pixels (a JPEG block of 8 x 8) are filled: JPEG noise leaves codes
under the clip level inside the sun's disc and a saturated aureole (1-20 px each on the photos of docs/photos.md;
a fifth of the sun's disc in case 12); a larger unsaturated area enclosed by saturation (the sky inside a
saturated dome ring) is no hole. [px]"""

SYMMETRY_MAX_RATIO = 0.3
""":func:`symmetry_axis` accepts an axis whose median mirror difference of log luminance is under this
fraction of the median over all axes (0.03-0.13 on the 20 photos of docs/photos.md, clear skies with
skylines over up to a third of the horizon and tilts up to 2°; an overcast or cloudy sky has no axis). [1]"""


def symmetry_axis(luminance: np.ndarray, cx: float, cy: float, radius: float, valid: np.ndarray | None = None, *,
                  n_azimuths: int = 720, n_radii: int = 60) -> float | None:
    """The image direction of the sun from the circle's centre, as the sky's mirror-symmetry axis.

    A clear, horizontally uniform sky is symmetric about the vertical plane through the sun (the principal
    plane): its radiance depends on the zenith angle and on the azimuth from the sun's only through
    |azimuth difference|. An untilted fisheye maps that plane to a line through the circle's centre
    whatever its projection, and vignetting is symmetric about the centre, so the image is mirror-symmetric
    about that line. The log luminance is sampled on a polar grid (``n_azimuths`` directions, ``n_radii``
    radii over 10-95 % of ``radius``; bilinear), the axis minimising the median |log L(phi + d) - log L(phi - d)|
    over all d and radii wins (obstacles, a ghost and noise are outliers of the median), refined by a parabola
    through its neighbours; of its two ends, the brighter (median log luminance along it) is the sun's. A tilt
    of t degrees moves the axis by about t / sin(sun zenith) at most, as it moves the sun's image.

    Args:
        luminance: linear luminance (any linear brightness; saturated pixels at their clip value), shape (H, W).
        cx, cy, radius: the image circle, image convention. [px]
        valid: pixels that carry data, shape (H, W) bool (default: finite ones).
        n_azimuths, n_radii: the polar grid.

    Returns:
        atan2(y - cy, x - cx) of the sun's half of the axis [deg, in [0, 360)], image convention (y down);
        None where the sky has no clear mirror axis (median difference at the best axis over
        :data:`SYMMETRY_MAX_RATIO` of the typical one: clouds, an overcast sky).
    """
    lum = _check_image(luminance, "luminance")
    valid = np.isfinite(lum) if valid is None else np.asarray(valid, dtype=bool)
    if valid.shape != lum.shape:
        raise CalibrationError(f"valid mask shape {valid.shape} differs from the image's {lum.shape}")
    valid = valid & np.isfinite(lum)
    if not (radius > 0 and valid.any()):
        return None
    top = float(np.percentile(lum[valid], 99))
    if not top > 0:
        return None
    log_l = np.where(valid, np.log(np.maximum(lum, 1e-4 * top)), np.nan)
    phi = np.linspace(0.0, 2 * np.pi, n_azimuths, endpoint=False)
    radii = np.linspace(0.1, 0.95, n_radii) * radius
    polar = _sample(log_l, cx + radii[None, :] * np.cos(phi)[:, None], cy + radii[None, :] * np.sin(phi)[:, None], 1)
    d = np.arange(1, n_azimuths // 2)
    k = np.arange(n_azimuths)[:, None]
    with warnings.catch_warnings():  # all-NaN slices (a circle mostly outside the image) give NaN, handled below
        warnings.simplefilter("ignore", RuntimeWarning)
        diff = np.abs(polar[(k + d) % n_azimuths] - polar[(k - d) % n_azimuths])  # (axis, d, radius)
        score = np.nanmedian(diff.reshape(n_azimuths, -1), axis=1)
    if not np.isfinite(score).any():
        return None
    best = int(np.nanargmin(score))
    typical = float(np.nanmedian(score))
    if not score[best] < SYMMETRY_MAX_RATIO * typical:
        return None
    sm, s0, sp = score[(best - 1) % n_azimuths], score[best], score[(best + 1) % n_azimuths]
    curv = sm - 2 * s0 + sp
    off = 0.5 * (sm - sp) / curv if np.isfinite(curv) and curv > 0 else 0.0
    axis = (best + float(np.clip(off, -0.5, 0.5))) * 360.0 / n_azimuths
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        if np.nanmedian(polar[(best + n_azimuths // 2) % n_azimuths]) > np.nanmedian(polar[best]):
            axis += 180.0
    return axis % 360.0


def _compact(region, min_ratio: float = 0.2, min_solidity: float = 0.8) -> bool:
    """A blob is compact (disc-like): minor/major axis >= min_ratio and solidity >= min_solidity.

    The ratio allows the projection's own squeeze (an orthographic lens shrinks a disc radially by
    cos(zenith): 0.47 at 62°, 0.26 at 75°); streaks and lines are thinner or removed by the opening."""
    major = max(region.axis_major_length, 1e-9)
    return region.axis_minor_length / major >= min_ratio and region.solidity >= min_solidity


AXIS_TOL_DEG = 3.0
"""A saturated core counts as on the symmetry axis within this angle about the circle's centre (plus its own
radius and 3 px): a tilt of t moves the axis off the sun by about t / sin(zenith). [deg]"""


def _near_axis(region, centre: tuple[float, float], axis_deg: float) -> bool:
    """The region's centroid lies on the sun's half of the symmetry axis (:data:`AXIS_TOL_DEG`)."""
    y, x = region.centroid
    dx, dy = x - float(centre[0]), y - float(centre[1])
    ux, uy = math.cos(math.radians(axis_deg)), math.sin(math.radians(axis_deg))
    along, across = dx * ux + dy * uy, abs(-dx * uy + dy * ux)
    reach = math.sqrt(region.area / math.pi) + 3.0
    return along > -reach and across <= reach + max(along, 0.0) * math.sin(math.radians(AXIS_TOL_DEG))


def _sun_on_axis(blob: np.ndarray, saturated: np.ndarray, inside: np.ndarray, cx: float, cy: float, axis_deg: float,
                 max_hole: int) -> tuple[float, float, float] | None:
    """The sun in a saturated aureole: on the symmetry axis, the centre of the largest disc inside the region
    that touches the region's end nearest the centre (the zenith).

    The region is where aureole(psi) + sky(x) exceeds the clip level; the sky brightens toward the horizon,
    so the region reaches farthest from the sun there and least toward the zenith, and a disc around the sun
    through that nearest end stays inside the region. Along the axis from that end the distance to the
    region's edge (``scipy.ndimage.distance_transform_edt``; thin obstacles are bridged by a closing of 3 px)
    grows as fast as the distance from the end while that end is the nearest edge point, i.e. up to the
    centre of the disc. Where the rim (an edge here) cuts the aureole the disc stops halfway between the end
    and the rim, short of a sun nearer the rim; where the horizon's saturation widens the region faster than
    the aureole, past the sun. Measured: 1.2-1.4° from the sun on three of the study's photos
    (docs/photos.md), 4.2° on one 13° above the horizon; the sun lay within the returned distance of the
    point on all four and on the synthetic aureoles of tests/test_photo_autocal_sun.py.

    Returns:
        (x, y, distance from the end) [px], or None where the axis misses the region.
    """
    import scipy.ndimage  # scipy loads with skimage.measure anyway

    closed = fill_small_holes(skimage.morphology.closing(saturated, skimage.morphology.disk(3)) | saturated, max_hole)
    lab = skimage.measure.label(closed, connectivity=2)
    region = np.isin(lab, np.unique(lab[blob & closed])) & (lab > 0)  # the blob with what thin obstacles cut off
    depth = scipy.ndimage.distance_transform_edt(region & inside)
    ux, uy = math.cos(math.radians(axis_deg)), math.sin(math.radians(axis_deg))
    r = np.arange(0.0, math.hypot(*region.shape), 0.5)
    on = _sample(region.astype(np.float64), cx + r * ux, cy + r * uy, 0) > 0.5
    seen = _sample(inside.astype(np.float64), cx + r * ux, cy + r * uy, 0) > 0.5
    if not (on & seen).any():
        return None
    a = int(np.argmax(on & seen))
    dist = _sample(depth, cx + r * ux, cy + r * uy, 1)
    k = a
    while k + 1 < len(r) and seen[k + 1] and dist[k + 1] >= (r[k + 1] - r[a]) - 1.5:
        k += 1
    return cx + r[k] * ux, cy + r[k] * uy, float(r[k] - r[a])


def detect_sun(darkest_rgb: np.ndarray, darkest_saturated: np.ndarray, inside: np.ndarray, *,
               centre: tuple[float, float] | None = None, axis_deg: float | None = None) -> SunDetection | None:
    """The sun's image: centroid of its saturated core in the darkest frame, else of a compact peak.

    Saturated path: the saturated pixels inside the circle, their small holes filled
    (:data:`SUN_HOLE_MAX_PX`), are opened with a disc of radius 2 px
    (``skimage.morphology``; removes blooming streaks and lines under 5 px wide) and labelled
    (``skimage.measure.label``). The sun's core is the largest compact region (minor/major axis >= 0.2,
    solidity >= 0.8) clear of the circle's rim (or under :data:`EXTENDED_MIN_PX`), and with ``centre`` and
    ``axis_deg`` (:func:`symmetry_axis`) on the sun's half of that axis (:data:`AXIS_TOL_DEG`): lens-flare
    ghosts lie on the other half, bright bits of sky between obstacles at the rim off the axis. Its centroid.
    Without such a core the largest region (from :data:`EXTENDED_MIN_PX` on) is the saturated aureole,
    merged with the bright horizon or cut by the rim, whose centroid lies toward the horizon: the sun is
    placed on the axis (:func:`_sun_on_axis`), or without one at the region's deepest point; ``extended``
    is set. Without a core or a large region in the opened mask, the unopened one is searched the same way.
    Without saturation: the brightest pixel of the luminance (Gaussian sigma = 1 px) if it stands at least
    20x above the median of an annulus around it (5-10 % of the circle's radius away) and the region above
    half its height is compact and small; its centroid is weighted by the luminance above the annulus's.

    Args:
        darkest_rgb: linear RGB of the shortest exposure, shape (H, W, 3). [any unit]
        darkest_saturated: saturated pixels of that frame, shape (H, W) or (H, W, 3) (any channel) bool.
        inside: pixels inside the fisheye circle (and not masked), shape (H, W) bool.
        centre: (cx, cy) of the circle, image convention. [px]
        axis_deg: direction of the sun from ``centre`` (:func:`symmetry_axis`), image convention. [deg]

    Returns:
        :class:`SunDetection`, or None when the sun is hidden (clouds, an obstacle, outside the view).
    """
    import scipy.ndimage  # scipy loads with skimage.measure anyway

    rgb = np.asarray(darkest_rgb, dtype=np.float64)
    if rgb.ndim != 3 or rgb.shape[-1] != 3:
        raise CalibrationError(f"darkest_rgb must have shape (H, W, 3), got {rgb.shape}")
    sat = np.asarray(darkest_saturated, dtype=bool)
    if sat.ndim == 3:
        sat = sat.any(-1)
    inside = np.asarray(inside, dtype=bool)
    if sat.shape != rgb.shape[:2] or inside.shape != rgb.shape[:2]:
        raise CalibrationError(f"saturated {sat.shape} and inside {inside.shape} masks must match the image "
                               f"{rgb.shape[:2]}")
    max_hole = SUN_HOLE_MAX_PX
    sat = fill_small_holes(sat & inside, max_hole) & inside
    if sat.sum() >= 3:
        opened = skimage.morphology.opening(sat, skimage.morphology.disk(2))
        near_rim = skimage.morphology.dilation(~inside, skimage.morphology.disk(2))
        for mask in (opened, sat):  # a core under 5 px wide does not survive the opening: then the raw mask
            regions = [r for r in skimage.measure.regionprops(skimage.measure.label(mask, connectivity=2))
                       if r.area >= 3]
            if not regions:
                continue
            cores = [r for r in regions
                     if _compact(r) and (r.area < EXTENDED_MIN_PX or not near_rim[tuple(r.coords.T)].any())]
            if centre is not None and axis_deg is not None:
                cores = [r for r in cores if _near_axis(r, centre, axis_deg)]
            if cores:
                best = max(cores, key=lambda r: r.area)
                y, x = best.centroid
                return SunDetection(float(x), float(y), math.sqrt(best.area / math.pi), True, int(best.area))
            best = max(regions, key=lambda r: r.area)
            if best.area >= EXTENDED_MIN_PX:
                blob = np.zeros_like(sat)
                blob[tuple(best.coords.T)] = True
                on_axis = None
                if centre is not None and axis_deg is not None:
                    for end in (0.0, 180.0):  # the axis's brighter end, else the other (a bright anti-solar horizon)
                        on_axis = _sun_on_axis(blob, sat, inside, float(centre[0]), float(centre[1]),
                                               float(axis_deg) + end, max_hole)
                        if on_axis is not None:
                            break
                if on_axis is None:  # the region's deepest point
                    depth = scipy.ndimage.distance_transform_edt(blob)
                    i0, j0 = np.unravel_index(np.argmax(depth), depth.shape)
                    on_axis = (float(j0), float(i0), float(depth[i0, j0]))
                x, y, rad = on_axis
                return SunDetection(float(x), float(y), float(rad), True, int(best.area), extended=True)
    lum = np.where(inside, rgb @ SRGB_LUMA, 0.0)
    if not inside.any() or not np.isfinite(lum).all():
        return None
    sm = skimage.filters.gaussian(lum, sigma=1.0, mode="nearest")
    sm = np.where(inside, sm, 0.0)
    i0, j0 = np.unravel_index(np.argmax(sm), sm.shape)
    r_in = math.sqrt(inside.sum() / math.pi)
    r1, r2 = max(4.0, 0.05 * r_in), max(8.0, 0.10 * r_in)
    yy, xx = np.mgrid[: lum.shape[0], : lum.shape[1]]
    d = np.hypot(yy - i0, xx - j0)
    ring = inside & (d >= r1) & (d <= r2)
    if ring.sum() < 8:
        return None
    bg = float(np.median(sm[ring]))
    peak = float(sm[i0, j0])
    if not peak > 20.0 * max(bg, 1e-300):
        return None
    above = (sm - bg > 0.5 * (peak - bg)) & inside
    lab = skimage.measure.label(above, connectivity=2)
    blob = lab == lab[i0, j0]
    reg = skimage.measure.regionprops(blob.astype(np.uint8), intensity_image=np.clip(lum - bg, 0, None))[0]
    if reg.area > math.pi * r1**2 or not _compact(reg, 0.2, 0.7):
        return None
    y, x = reg.centroid_weighted
    return SunDetection(float(x), float(y), math.sqrt(reg.area / math.pi), False, int(reg.area))


# ---------------------------------------------------------------------------------- cameras
SUN_ZENITH_TOL_DEG = 2.0
"""Projections whose scores lie within this of the best cannot be told apart by the sun. [deg]

The guesses are untilted, and a tilt of t degrees toward or away from the sun moves its zenith angle by t:
2° covers a camera levelled by eye or with a bubble level (the photo study's tilts are 0-1.9°), the sun
core's centroid (<= 0.5°) and the circle's radius (<= 1 px). Normalised at 90°, equidistant and equisolid
put the sun more than 2° apart only between about 20° and 80° zenith, and at most 3.8° apart (50-60°):
elsewhere the sun alone cannot separate them, and within that band only on a camera levelled to 2°."""


def heading_from_sun(cx: float, cy: float, sun_x: float, sun_y: float, sun_azimuth_deg: float) -> float:
    """``up_azimuth_deg`` [deg, in [0, 360)] that puts azimuth ``sun_azimuth_deg`` on the ray from the centre
    (cx, cy) through the image point (sun_x, sun_y) [px], for an untilted camera.

    With up-azimuth A, a direction of azimuth a lands at (dx, dy) = r (-sin(a - A), -cos(a - A)) from the
    centre (the camera's x axis is (-cos A, sin A, 0) and y is (-sin A, -cos A, 0) in ENU, fisheye
    module), so A = a - atan2(-dx, -dy).
    """
    return (sun_azimuth_deg - math.degrees(math.atan2(-(sun_x - cx), -(sun_y - cy)))) % 360.0


def cameras_from_sun(
    shape: tuple[int, int],
    circle: Circle,
    sun: SunDetection | None,
    sun_zenith_deg: float,
    sun_azimuth_deg: float,
    projections=CLASSICAL_PROJECTIONS,
    *,
    max_zenith_deg: float = 90.0,
) -> list[CameraGuess]:
    """One camera per projection from the circle and the sun, best first.

    Each camera has its centre at the circle's, R90 such that the circle is the ``max_zenith_deg``
    circle (90°, the horizon, by default), no tilt, and the heading (``up_azimuth_deg``) that puts the
    computed (SPA) sun's azimuth on the detected sun's direction from the centre
    (:func:`heading_from_sun`). The score is the evidence for the projection: the zenith angle the
    projection gives the detected sun's radius minus the computed sun zenith [deg, absolute].

    What one sun point can and cannot determine: its direction from the centre fixes the heading
    (exactly, for an untilted camera; a tilt of t degrees moves it by up to about t / sin(zenith)). Its
    radius gives one zenith angle per projection, so it tells the projections apart only up to the
    tilt and the circle's own error: a tilt of t degrees toward or away from the sun changes its zenith
    angle by t, which is the same as another projection near the sun's zenith (the classical ones
    differ by 2-4° at 40-60° zenith, and not at all near the centre or, with this normalisation, at the
    horizon). The tilt starts at 0 and is left to the fit of the sky pattern, which compares the
    projections whose scores lie within their ``tolerance_deg`` of the best (:data:`SUN_ZENITH_TOL_DEG`,
    widened for a sun found in a saturated aureole); the best guess's notes then say the sun cannot tell
    them apart. Without a detected sun the heading is 0 and must come from the sky pattern.

    Args:
        shape: image (H, W). [px]
        circle: from :func:`detect_circle`.
        sun: from :func:`detect_sun`, or None.
        sun_zenith_deg, sun_azimuth_deg: the computed sun position (azimuth clockwise from North). [deg]
        projections: names from CLASSICAL_PROJECTIONS.
        max_zenith_deg: zenith angle of the circle's edge (e.g. 95 for a lens that sees below the
            horizon, or less when a dome cuts the view). [deg]

    Returns:
        list of :class:`CameraGuess`, ascending score (NaN scores, without a sun, keep ``projections``' order).
    """
    h, w = (int(shape[0]), int(shape[1]))
    if not (0.0 <= sun_zenith_deg <= 180.0 and math.isfinite(sun_azimuth_deg)):
        raise CalibrationError(f"sun zenith must be in [0, 180] deg and azimuth finite, got {sun_zenith_deg}, "
                               f"{sun_azimuth_deg}")
    if not circle.radius > 0:
        raise CalibrationError(f"circle radius must be > 0 px, got {circle.radius}")
    for p in projections:
        if validate_projection(p) not in CLASSICAL_PROJECTIONS:
            raise CalibrationError(f"cameras_from_sun takes the classical projections, not {p}")
    out = []
    zen_t = torch.tensor(math.radians(sun_zenith_deg), dtype=torch.float64)
    az_t = torch.tensor(math.radians(sun_azimuth_deg), dtype=torch.float64)
    for p in projections:
        notes: list[str] = []
        if p == "orthographic" and max_zenith_deg > 90.0:
            notes.append(f"orthographic cannot image beyond 90 deg; skipped max_zenith_deg {max_zenith_deg}")
            continue
        rho_edge = float(theta_to_rho(torch.tensor(math.radians(max_zenith_deg), dtype=torch.float64), p))
        r90 = circle.radius / rho_edge
        heading, score, tol = 0.0, math.nan, math.nan
        if sun is None:
            notes.append("sun not detected: heading 0, projections tied; the heading must come from the sky pattern")
        else:
            dx, dy = sun.x - circle.cx, sun.y - circle.cy
            r = math.hypot(dx, dy)
            heading = heading_from_sun(circle.cx, circle.cy, sun.x, sun.y, sun_azimuth_deg)
            if r < 0.05 * circle.radius:
                notes.append(f"sun within {r:.1f} px of the centre: heading poorly determined")
            zen_img = float(rho_to_theta(torch.tensor(r / r90, dtype=torch.float64), p))
            if math.isfinite(zen_img):
                zen_img = math.degrees(zen_img)
                score = abs(zen_img - sun_zenith_deg)
                tol = SUN_ZENITH_TOL_DEG
                notes.append(f"detected sun at zenith {zen_img:.2f} deg under {p}, computed {sun_zenith_deg:.2f} deg")
                if sun.extended:  # the sun within radius_px of the point along the axis (_sun_on_axis)
                    span = [math.degrees(float(rho_to_theta(torch.tensor(rr / r90, dtype=torch.float64), p)))
                            for rr in (max(r - sun.radius_px, 0.0), min(r + sun.radius_px, circle.radius))]
                    tol += max(zen_img - span[0], span[1] - zen_img, 0.0)
                    notes.append(f"the sun found in a saturated aureole: its zenith known to "
                                 f"{tol - SUN_ZENITH_TOL_DEG:.1f} deg under {p}")
            else:
                score = math.inf
                notes.append(f"detected sun radius {r:.1f} px is beyond the {p} projection's domain")
        notes.append("tilt assumed 0 (to be refined by the fit)")
        cam = FisheyeCamera(size=(h, w), projection=p, cx=circle.cx, cy=circle.cy, radius=r90,
                            up_azimuth_deg=heading, max_zenith_deg=max_zenith_deg)
        x, y = cam.angles_to_pixel(zen_t, az_t)
        model_px = (float(x), float(y)) if math.isfinite(float(x)) else None
        out.append(CameraGuess(cam, p, score, model_px, notes, tol))
    if sun is not None:
        out.sort(key=lambda g: g.score)
        tied = [g for g in out[1:] if g.score - out[0].score < g.tolerance_deg]
        if tied:
            out[0].notes.append(
                f"the sun cannot tell {out[0].projection} from {', '.join(g.projection for g in tied)}: their zenith "
                f"angles for the detected sun lie within {max(g.tolerance_deg for g in tied):.1f} deg of each other's "
                f"errors at zenith {sun_zenith_deg:.1f} deg (tilt allowance {SUN_ZENITH_TOL_DEG:g} deg); the sky "
                "pattern must decide")
    return out
