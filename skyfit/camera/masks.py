"""What is not sky in a fisheye photo: the sun and its flare, horizon obstacles, outliers of a first fit.

Every mask is a bool array of shape (H, W), True = masked (not used by the fit). Pixel (row i, col j)
has its centre at (x = j, y = i); directions come from the :class:`~skyfit.camera.fisheye.FisheyeCamera`.
"""
from __future__ import annotations

import math

import numpy as np
import skimage  # lazy sub-packages: skimage.morphology etc. load (with scipy, ~0.7 s) at first use, not at `import skyfit`
import torch

from .autocal import SRGB_LUMA, CalibrationError, SunDetection, fill_small_holes
from .fisheye import FisheyeCamera

__all__ = ["SUN_MASK_MAX_DEG", "grow_outlier_mask", "obstacle_mask", "sun_mask"]

SUN_HALO_MARGIN_DEG = 3.0
"""How far beyond the saturated blob's angular radius the sun mask reaches: a lens's flare halo falls off
within a few degrees (a power law past 0.5-2 deg), while the unsaturated aureole beyond it is the photo's best
measure of the aerosol. (Twice the blob's radius, tried first, masked 20-40 deg around the sun of a hazy sky
and left the aerosol to the horizon, where vignetting mimics it: docs/photos.md.) [deg]"""


SUN_MASK_MAX_DEG = 8.0
"""Largest angular radius of the sun mask of a photo fit (``max_radius_deg`` of :func:`sun_mask`): a single photo
exposed for the sky saturates the aureole of a hazy sky 10-30 deg around the sun, and masking all of it (blob +
margin) threw away its censored bounds and the unsaturated ring beyond; past 8 deg a lens's flare halo adds under
1 % (the synthetic generator's power-law halo: 0.5 % at 8 deg on case 6), so the saturated pixels there are fitted
as lower bounds. [deg]"""


def _check_shape(shape, camera: FisheyeCamera) -> tuple[int, int]:
    shape = (int(shape[0]), int(shape[1]))
    if shape != camera.shape:
        raise CalibrationError(f"mask shape {shape} differs from the camera's {camera.shape}")
    return shape


def _vectors(camera: FisheyeCamera) -> tuple[np.ndarray, np.ndarray]:
    """ENU unit vectors (H, W, 3) (0 where invalid) and the valid mask (H, W) of every pixel."""
    with torch.no_grad():
        v, valid = camera.pixel_vectors(torch.float64)
    v = torch.where(valid[..., None], v, torch.zeros_like(v))
    return v.numpy(), valid.numpy()


def _unit(zenith_deg: float, azimuth_deg: float) -> np.ndarray:
    z, a = math.radians(zenith_deg), math.radians(azimuth_deg)
    return np.array([math.sin(z) * math.sin(a), math.sin(z) * math.cos(a), math.cos(z)])


def _pixel_dir(camera: FisheyeCamera, x: float, y: float) -> np.ndarray | None:
    with torch.no_grad():
        d = camera.pixel_to_direction(torch.tensor(x, dtype=torch.float64), torch.tensor(y, dtype=torch.float64))
    d = d.numpy()
    return d if np.isfinite(d).all() else None


def sun_mask(shape, sun: SunDetection | None, camera: FisheyeCamera, sun_zenith_deg: float, sun_azimuth_deg: float,
             *, min_radius_deg: float = 3.0, max_radius_deg: float | None = None) -> np.ndarray:
    """The sun's disc and its flare halo, around both the detected and the computed sun.

    The angular radius of the saturated blob (the mean angle between the blob's centre and four points
    ``radius_px`` away from it) plus :data:`SUN_HALO_MARGIN_DEG`, at least ``min_radius_deg``, is masked
    around the computed sun's direction and around the detected sun's direction (they differ by the
    camera's error).

    Args:
        shape: (H, W) of the image = camera.shape. [px]
        sun: from :func:`~skyfit.camera.autocal.detect_sun`, or None (then the computed sun only,
            ``min_radius_deg``).
        camera: the camera fitted or guessed for the image.
        sun_zenith_deg, sun_azimuth_deg: computed sun position. [deg]
        min_radius_deg: smallest angular radius masked. [deg]
        max_radius_deg: largest angular radius masked (None: no limit; :data:`SUN_MASK_MAX_DEG` in a photo fit,
            which fits the saturated aureole beyond it as censored bounds). [deg]

    Returns:
        shape (H, W) bool, True = masked (only pixels in the camera's field of view).
    """
    _check_shape(shape, camera)
    if not min_radius_deg >= 0:
        raise CalibrationError(f"min_radius_deg must be >= 0, got {min_radius_deg}")
    if max_radius_deg is not None and not max_radius_deg >= min_radius_deg:
        raise CalibrationError(f"max_radius_deg must be >= min_radius_deg ({min_radius_deg}), got {max_radius_deg}")
    v, valid = _vectors(camera)
    centres = [_unit(sun_zenith_deg, sun_azimuth_deg)]
    radius = min_radius_deg
    if sun is not None:
        d0 = _pixel_dir(camera, sun.x, sun.y)
        if d0 is not None:
            centres.append(d0)
            angles = []
            for dx, dy in ((1, 0), (-1, 0), (0, 1), (0, -1)):
                d1 = _pixel_dir(camera, sun.x + dx * sun.radius_px, sun.y + dy * sun.radius_px)
                if d1 is not None:
                    angles.append(math.degrees(math.acos(min(1.0, float(d0 @ d1)))))
            if angles:
                radius = max(radius, float(np.mean(angles)) + SUN_HALO_MARGIN_DEG)
    if max_radius_deg is not None:
        radius = min(radius, max_radius_deg)
    cos_r = math.cos(math.radians(radius))
    out = np.zeros(camera.shape, dtype=bool)
    for c in centres:
        out |= (v @ c) >= cos_r
    return out & valid


def _robust_smooth_fit(values: np.ndarray, elev: np.ndarray, az: np.ndarray, use: np.ndarray, *,
                       low: float, high: float, outliers_high: bool = False) -> np.ndarray:
    """A smooth function of (elevation, azimuth) fitted to ``values`` on ``use`` by trimmed least squares.

    Basis: Legendre-like powers of elevation/90 (degree 3) times azimuthal harmonics (orders 0-2), 20
    columns. The first pass fits the lower 60 % of each 3° elevation band with ``outliers_high`` (reddish
    obstacles in a colour ratio), else the upper 60 % (obstacles are dark and would pull a plain fit
    down); seven more drop residuals below -max(2.5 sigma, low) or above
    max(4 sigma, high) (the sun), sigma from the MAD of the kept residuals. Hand-written: a 20-column
    trimmed regression is a few lines of numpy; scikit-image's RANSAC would need a model class for it.

    Args:
        values, elev [deg], az [rad]: shape (H, W).
        use: pixels to fit, shape (H, W) bool.

    Returns:
        the fitted function at every pixel, shape (H, W) (NaN where elev or az is NaN).
    """
    def terms(e: np.ndarray, z: np.ndarray) -> tuple[np.ndarray, list[np.ndarray]]:
        u, a = np.nan_to_num(e) / 90.0, np.nan_to_num(z)
        return u, [np.ones_like(a)] + [f(k * a) for k in (1, 2) for f in (np.cos, np.sin)]

    def basis(e: np.ndarray, z: np.ndarray) -> np.ndarray:
        u, waves = terms(e, z)
        return np.stack([u**p * w for p in range(4) for w in waves], -1)

    def model(coef: np.ndarray) -> np.ndarray:
        """sum_p u^p sum_k c_pk wave_k at every pixel, without the (H, W, 20) basis."""
        u, waves = terms(elev, az)
        out = np.zeros_like(u)
        for p in reversed(range(4)):  # Horner in u
            out = out * u + sum(c * w for c, w in zip(coef[5 * p:5 * p + 5], waves))
        return out

    idx = np.flatnonzero(use)
    if len(idx) < 200:
        raise CalibrationError(f"too few sky pixels ({len(idx)}) near the horizon to model the sky")
    idx = idx[:: max(1, len(idx) // 200_000)]  # a subsample keeps a 4000 px photo fast
    x, y = basis(elev.ravel()[idx], az.ravel()[idx]), values.ravel()[idx]
    band = np.floor(np.nan_to_num(elev.ravel()[idx]) / 3.0).astype(np.int64)
    keep = np.zeros(len(idx), dtype=bool)
    for b in np.unique(band):
        sel = band == b
        keep[sel] = (y[sel] <= np.percentile(y[sel], 60)) if outliers_high else (y[sel] >= np.percentile(y[sel], 40))
    for _ in range(7):
        xk = x[keep]
        # the normal equations where they are well conditioned (a sky around the horizon: condition number ~500, so
        # ~1e-11 in float64), 5x faster than an SVD least squares on 10^5 rows (seven per fit, two fits for each
        # camera a photo fit tries); the SVD where the sky's pixels leave the basis nearly degenerate
        gram = xk.T @ xk
        if np.linalg.cond(gram) < 1e10:
            coef = np.linalg.solve(gram, xk.T @ y[keep])
        else:
            coef, *_ = np.linalg.lstsq(xk, y[keep], rcond=None)
        res = y - x @ coef
        sigma = 1.4826 * np.median(np.abs(res[keep] - np.median(res[keep])))
        keep = (res > -max(2.5 * sigma, low)) & (res < max(4.0 * sigma, high))
        if keep.sum() < 100:
            raise CalibrationError("the sky near the horizon fits no smooth model (too little clear sky)")
    return model(coef)


def _texture(img: np.ndarray, use: np.ndarray, sigma: float) -> np.ndarray:
    """Local roughness of ``img``: |img - its 3x3 median| averaged in a Gaussian window (sigma [px]) over the
    pixels ``use`` only. A median keeps step edges, so a skyline's outline scores low and only texture
    (foliage, windows, rock) scores high, unlike a local standard deviation. Shape (H, W)."""
    dev = np.abs(img - skimage.filters.median(img, footprint=np.ones((3, 3), dtype=bool), mode="nearest"))
    g = lambda a: skimage.filters.gaussian(a, sigma=sigma, mode="constant", preserve_range=True)  # noqa: E731
    return g(np.where(use, dev, 0.0)) / np.maximum(g(use.astype(np.float64)), 1e-12)


def _touching(components: np.ndarray, seed: np.ndarray) -> np.ndarray:
    """Pixels of the labelled ``components`` (int, 0 = background) whose component meets ``seed``."""
    ids = np.unique(components[seed & (components > 0)])
    return np.isin(components, ids) & (components > 0)


def obstacle_mask(linear_rgb: np.ndarray, inside: np.ndarray, camera: FisheyeCamera, *,
                  max_elevation_deg: float = 35.0) -> np.ndarray:
    """Horizon obstacles (buildings, trees, mountains, masts, the dome's rim) connected to the circle's rim.

    Below ``max_elevation_deg`` a pixel is an obstacle candidate when it is

    - dark: luminance below 1/3 of a smooth sky model (robust fit of log luminance over elevation and
      azimuth, which follows the horizon brightening and the sun's side), or
    - textured: the local mean of |log luminance - its 3x3 median| (Gaussian window, 1 px; edges do
      not count, texture does) is over 5x the sky's median (and over 0.1), or
    - non-sky coloured: ln((R + G) / 2B) over 0.35 above a smooth model of the sky's (green, brown).

    Candidates are closed (disc of 2 px), kept where connected to the rim of the circle (a band 2 px
    wide inside ``inside``'s edge) or to pixels below the horizon, their small enclosed holes (sky
    seen through foliage, under 0.5 % of the circle) filled, grown by a disc of 2 px, and joined with
    every pixel below the horizon. A bright, smooth horizon sky stays unmasked.

    Args:
        linear_rgb: linear RGB, shape (H, W, 3). [any unit]
        inside: pixels inside the fisheye circle that carry data, shape (H, W) bool.
        camera: gives each pixel's elevation and azimuth.
        max_elevation_deg: obstacles are sought below this elevation. [deg]

    Returns:
        shape (H, W) bool, True = obstacle (within ``inside``).
    """
    rgb = np.asarray(linear_rgb, dtype=np.float64)
    inside = np.asarray(inside, dtype=bool)
    if rgb.ndim != 3 or rgb.shape[-1] != 3 or rgb.shape[:2] != inside.shape:
        raise CalibrationError(f"linear_rgb must be (H, W, 3) and inside (H, W), got {rgb.shape} and {inside.shape}")
    _check_shape(inside.shape, camera)
    with torch.no_grad():
        zen, az, valid = camera.pixel_directions(torch.float64)
        below = camera.below_horizon_mask().numpy()
    elev = 90.0 - np.degrees(zen.numpy())
    az = az.numpy()
    inside = inside & valid.numpy() & np.isfinite(rgb).all(-1)
    y = rgb @ SRGB_LUMA
    scale = float(np.median(y[inside])) if inside.any() else 0.0
    if not scale > 0:
        raise CalibrationError("the image is black inside the circle: cannot tell obstacles from sky")
    tiny = 1e-4 * scale
    log_y = np.log(np.maximum(y, tiny))
    zone = inside & (elev < max_elevation_deg) & ~below
    fit_region = inside & (elev >= 0) & (elev < max_elevation_deg + 15.0)
    sky_log = _robust_smooth_fit(log_y, elev, az, fit_region, low=0.15, high=0.3)
    dark = log_y - sky_log < -math.log(3.0)
    rough = _texture(log_y, inside, 1.0)
    textured = rough > max(5.0 * float(np.median(rough[fit_region])), 0.1)
    chroma = np.log(np.maximum(rgb[..., 0] + rgb[..., 1], 2 * tiny) / np.maximum(2 * rgb[..., 2], 2 * tiny))
    sky_chroma = _robust_smooth_fit(chroma, elev, az, fit_region & ~dark, low=0.1, high=0.1,
                                    outliers_high=True)
    coloured = chroma - sky_chroma > 0.35
    cand = zone & (dark | textured | coloured)
    cand = skimage.morphology.closing(cand, skimage.morphology.disk(2)) & zone
    rim = inside & ~skimage.morphology.erosion(inside, skimage.morphology.disk(2))
    seed = rim | skimage.morphology.dilation(below & valid.numpy(), skimage.morphology.disk(1))
    mask = _touching(skimage.measure.label(cand, connectivity=2), seed)
    mask = fill_small_holes(mask, int(0.005 * inside.sum()))
    mask = skimage.morphology.dilation(mask, skimage.morphology.disk(2))
    return (mask | below) & inside


def grow_outlier_mask(relative_residual: np.ndarray, used: np.ndarray, camera: FisheyeCamera, *,
                      threshold: float = 0.25, max_elevation_deg: float = 40.0, min_blob_px: int = 12) -> np.ndarray:
    """Pixels to drop in the second pass of a robust fit: outliers of the first that form structures.

    Pixels of ``used`` with |relative residual| > ``threshold`` are labelled (8-connected); a component
    is kept when it is connected to the rim (it meets, through a 1 px dilation, the unused pixels
    connected to the image's border: outside the circle or already masked there) and lies below
    ``max_elevation_deg`` — a missed obstacle — or when it is a compact blob (at least ``min_blob_px``
    pixels, solidity >= 0.5) anywhere — a cloud, a bird, a reflection. Scattered noisy pixels are not
    kept. The kept pixels are grown by a disc of 2 px.

    Args:
        relative_residual: (photo - model) / model of the first fit, shape (H, W) (NaN = unknown). [1]
        used: pixels the first fit used, shape (H, W) bool.
        camera: gives each pixel's elevation.
        threshold: |relative residual| above which a pixel is an outlier. [1]
        max_elevation_deg: rim-connected outliers are kept below this elevation. [deg]
        min_blob_px: smallest compact blob kept away from the rim. [px]

    Returns:
        shape (H, W) bool, True = newly masked (within ``used``).
    """
    res = np.asarray(relative_residual, dtype=np.float64)
    used = np.asarray(used, dtype=bool)
    if res.shape != used.shape or res.ndim != 2:
        raise CalibrationError(f"relative_residual {res.shape} and used {used.shape} must be the same (H, W)")
    _check_shape(res.shape, camera)
    if not threshold > 0:
        raise CalibrationError(f"outlier threshold must be > 0, got {threshold}")
    with torch.no_grad():
        zen, _, _ = camera.pixel_directions(torch.float64)
    elev = 90.0 - np.degrees(np.nan_to_num(zen.numpy(), nan=math.pi))
    bad = used & np.isfinite(res) & (np.abs(np.nan_to_num(res)) > threshold)
    lab = skimage.measure.label(bad, connectivity=2)
    keep = np.zeros(bad.shape, dtype=bool)
    if lab.max() == 0:
        return keep
    unused = ~used
    ulab = skimage.measure.label(unused, connectivity=2)
    border_ids = np.unique(np.concatenate([ulab[0], ulab[-1], ulab[:, 0], ulab[:, -1]]))
    outer = np.isin(ulab, border_ids[border_ids > 0])
    low = bad & (elev < max_elevation_deg)
    low_lab = skimage.measure.label(low, connectivity=2)
    keep |= _touching(low_lab, skimage.morphology.dilation(outer, skimage.morphology.disk(1)))
    for r in skimage.measure.regionprops(lab):
        if r.area >= min_blob_px and r.solidity >= 0.5:
            keep[tuple(r.coords.T)] = True
    keep = skimage.morphology.dilation(keep, skimage.morphology.disk(2))
    return keep & used
