"""The camera from the image (skyfit.camera.autocal) and what is not sky (skyfit.camera.masks).

Every image here is synthetic: an analytic sky brightness over the pixel directions of a known
FisheyeCamera (brighter toward the horizon, an aureole and a saturating sun), black with sensor noise
outside an off-centre circle. The expected values are that camera's parameters and the pixel where it
puts the sun (FisheyeCamera.angles_to_pixel), i.e. the truth the image was made from.
"""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from skimage.morphology import dilation, disk

from skyfit.camera import (
    CLASSICAL_PROJECTIONS,
    CalibrationError,
    Circle,
    FisheyeCamera,
    SunDetection,
    cameras_from_sun,
    detect_circle,
    detect_sun,
    grow_outlier_mask,
    heading_from_sun,
    obstacle_mask,
    sun_mask,
)
from skyfit.geometry import zenith_azimuth_to_enu

LUMA = np.array([0.2126, 0.7152, 0.0722])


def _t(deg: float) -> torch.Tensor:
    return torch.tensor(math.radians(deg), dtype=torch.float64)


def sky_angles(cam, sun_zen: float, sun_az: float):
    """(view vectors (H, W, 3) with zeros outside the circle, inside mask (H, W), scattering angle from the sun [deg],
    view zenith angle [deg]) of every pixel of ``cam`` for a sun at (sun_zen, sun_az) [deg]."""
    v, valid = cam.pixel_vectors()
    valid = valid.numpy()
    v = torch.where(torch.from_numpy(valid)[..., None], v, torch.zeros_like(v))
    s = zenith_azimuth_to_enu(_t(sun_zen), _t(sun_az))
    gam = np.degrees(np.arccos(np.clip((v @ s).numpy(), -1, 1)))
    zen = np.degrees(np.arccos(np.clip(v[..., 2].numpy(), -1, 1)))
    return v, valid, gam, zen


def make_sky(shape=(240, 260), cx=137.3, cy=112.6, radius=100.0, projection="equidistant", heading=0.0,
             sun_zen=50.0, sun_az=140.0, *, sun_peak=30.0, sky_scale=1.0, skyline=None, dome_rim=False, overcast=False,
             streak=False, ghost=False, seed=0):
    """A darkest-frame fisheye photo (linear RGB clipped at 1) of a known camera.

    Sky: 0.1 sky_scale (1 + 2 (zenith/90°)^4) (1 + 3 exp(-gamma/20°)), bluish at the zenith; sun: sun_peak
    exp(-gamma/1.5°) (saturates within ~5° for sun_peak 30: the core and its flare halo). 2 %
    multiplicative noise; outside the circle 0.002 |N(0,1)|. ``skyline``: 'dark' (textured, ~1/20 of the
    sky) or 'green' (smooth, as bright as the sky, green) over azimuths 200-320° up to 8-15° elevation.
    """
    cam = FisheyeCamera(size=shape, projection=projection, cx=cx, cy=cy, radius=radius, up_azimuth_deg=heading)
    v, valid, gam, zen = sky_angles(cam, sun_zen, sun_az)
    az = np.degrees(np.arctan2(v[..., 0].numpy(), v[..., 1].numpy())) % 360
    rng = np.random.default_rng(seed)
    if overcast:
        lum = 0.2 * (1 + 0.5 * np.cos(np.radians(zen)))
        col = np.ones(shape + (3,))
    else:
        lum = 0.1 * sky_scale * (1 + 2.0 * (zen / 90.0) ** 4) * (1 + 3 * np.exp(-gam / 20.0)) + sun_peak * np.exp(-gam / 1.5)
        col = np.stack([0.7 + 0.1 * zen / 90, 0.9 + 0.05 * zen / 90, 1.2 - 0.2 * zen / 90], -1)
    rgb = lum[..., None] * col
    obst = np.zeros(shape, bool)
    if skyline is not None:
        top = 15.0 * (0.55 + 0.45 * np.abs(np.sin(np.radians(az) * 7)))
        obst = valid & (az > 200) & (az < 320) & (90 - zen < top)
        if skyline == "dark":
            o = 0.015 * np.exp(0.6 * rng.standard_normal(shape))[..., None] * np.array([0.8, 1.0, 0.4])
        else:
            o = (0.1 * (1 + 2.0 * (zen / 90.0) ** 4))[..., None] * np.array([1.0, 1.3, 0.35])
        rgb = np.where(obst[..., None], o, rgb)
    if dome_rim:  # a bright reflection along the rim, 4 px wide, 4-8 px inside the circle over 100° of it
        yy, xx = np.mgrid[: shape[0], : shape[1]]
        r = np.hypot(xx - cx, yy - cy)
        ang = np.degrees(np.arctan2(yy - cy, xx - cx)) % 360
        rgb = np.where(((r > radius - 8) & (r < radius - 4) & (ang > 20) & (ang < 120))[..., None], 0.9, rgb)
    rgb = rgb * (1 + 0.02 * rng.standard_normal(rgb.shape))
    rgb = np.where(valid[..., None], rgb, 0.0) + 0.002 * np.abs(rng.standard_normal(rgb.shape))
    sx, sy = cam.angles_to_pixel(_t(sun_zen), _t(sun_az))
    if streak:  # a blooming column through the sun, 2 px wide, to the image's top
        rgb[: int(sy), int(round(float(sx))) - 1: int(round(float(sx))) + 1] = 2.0
    if ghost:  # a small saturated flare ghost opposite the sun
        gx, gy = 2 * cx - float(sx), 2 * cy - float(sy)
        yy, xx = np.mgrid[: shape[0], : shape[1]]
        rgb[np.hypot(xx - gx, yy - gy) < 2.5] = 2.0
    sat = (rgb >= 1.0).any(-1) & valid
    return cam, np.minimum(rgb, 1.0), sat, valid, obst, (float(sx), float(sy))


# ------------------------------------------------------------------------------------ circle
@pytest.mark.parametrize("cx, cy, radius", [(137.3, 112.6, 100.0), (121.7, 96.2, 120.0)],
                         ids=["off-centre", "cut-by-border"])
def test_circle_recovered_within_a_pixel(cx, cy, radius):
    _, rgb, _, _, _, _ = make_sky(cx=cx, cy=cy, radius=radius)  # the second circle crosses the top and left edges
    c = detect_circle(rgb @ LUMA)
    assert math.hypot(c.cx - cx, c.cy - cy) < 1.0
    assert abs(c.radius - radius) < 1.0
    assert c.inlier_fraction > 0.9 and c.residual_px < 0.5


def test_circle_robust_to_skyline_and_bright_dome_rim():
    _, rgb, _, _, obst, _ = make_sky(skyline="dark", dome_rim=True)
    c = detect_circle(rgb @ LUMA)
    assert math.hypot(c.cx - 137.3, c.cy - 112.6) < 1.5
    assert abs(c.radius - 100.0) < 1.5
    assert 0.5 < c.inlier_fraction < 0.8  # the black skyline hides a third of the rim


def _low_skyline(level: float = 0.03):
    """make_sky's camera with a low lit skyline (trees, roofs: ``level`` of the sky's brightness there) over azimuths
    200-320°, its top 2-5° above the horizon (2-6 px inside the rim), smooth along it: the image."""
    cam, rgb, _, valid, _, _ = make_sky()
    v, _, _, zen = sky_angles(cam, 50.0, 140.0)
    az = np.degrees(np.arctan2(v[..., 0].numpy(), v[..., 1].numpy())) % 360
    top = 3.5 + 1.5 * np.sin(np.radians(az) * 2)
    low = valid & (az > 200) & (az < 320) & (90 - zen < top)
    return np.where(low[..., None], level * rgb, rgb)


def test_circle_not_pulled_in_by_a_low_lit_skyline(monkeypatch):
    """Crossings with lit ground 2-5 px beyond them are obstacle tops, not the rim: dropped, the circle is that of the
    clean rim (within 0.5 px); without the check (OBSTACLE_LEVEL infinite) the third of the rim they cover pulls the
    circle in and aside by over 2 px. A soft rim (the whole image blurred, sigma 2.5 px: every crossing has some
    light beyond it) keeps all its crossings and is found within 1 px. (Obstacles under 2 px deep are not told from
    the rim: their surround lies within the window looked at.)"""
    import skimage.filters

    from skyfit.camera import autocal

    rgb = _low_skyline()
    c = detect_circle(rgb @ LUMA)
    assert math.hypot(c.cx - 137.3, c.cy - 112.6) < 0.5 and abs(c.radius - 100.0) < 0.5, c
    monkeypatch.setattr(autocal, "OBSTACLE_LEVEL", math.inf)
    naive = detect_circle(rgb @ LUMA)
    assert math.hypot(naive.cx - 137.3, naive.cy - 112.6) > 2.0 and naive.radius < 99.0, naive
    monkeypatch.undo()
    _, clean, _, _, _, _ = make_sky()
    soft = detect_circle(skimage.filters.gaussian(clean @ LUMA, sigma=2.5))
    assert math.hypot(soft.cx - 137.3, soft.cy - 112.6) < 1.0 and abs(soft.radius - 100.0) < 1.0, soft


def test_no_circle_in_a_full_frame_image():
    yy, xx = np.mgrid[:200, :240]
    rng = np.random.default_rng(1)
    sky = 0.2 + 0.1 * yy / 200 + 0.05 * np.sin(xx / 17.0)  # a full-frame sky with a smooth gradient ...
    sky = np.where((xx - 60) ** 2 + (yy - 150) ** 2 < 25**2, 0.5, sky)  # ... a bright cloud ...
    sky = np.where(yy > 170, 0.04, sky)  # ... and a dark strip of ground along the bottom
    with pytest.raises(CalibrationError, match="^no fisheye circle found: "):
        detect_circle(sky * (1 + 0.02 * rng.standard_normal(sky.shape)))


def test_bad_input_raises_a_value_error():
    with pytest.raises(ValueError, match="2-D image"):
        detect_circle(np.zeros((10, 10, 3)))
    with pytest.raises(CalibrationError, match="black"):
        detect_circle(np.zeros((50, 50)))


# --------------------------------------------------------------------------------------- sun
@pytest.mark.parametrize("extra", [{}, {"streak": True, "ghost": True}], ids=["core", "streak-and-ghost"])
def test_sun_detected_within_a_pixel(extra):
    _, rgb, sat, valid, _, (sx, sy) = make_sky(sun_zen=48.0, sun_az=115.0, **extra)
    sun = detect_sun(rgb, sat, valid)
    assert sun is not None and sun.saturated
    assert math.hypot(sun.x - sx, sun.y - sy) < 1.0
    assert 4.0 < sun.radius_px < 9.0  # 30 exp(-gamma/1.5°) >= 1 within ~5°: ~5.6 px at 1.11 px/°


def test_unsaturated_sun_peak_detected():
    # the shortest frame of a bracket: a dim sky, the sun's peak ~25x above the sky 5-10 % of the radius from it
    _, rgb, sat, valid, _, (sx, sy) = make_sky(sun_zen=35.0, sun_az=300.0, sun_peak=0.8, sky_scale=0.02)
    assert not sat.any()
    sun = detect_sun(rgb, sat, valid)
    assert sun is not None and not sun.saturated
    assert math.hypot(sun.x - sx, sun.y - sy) < 1.0


@pytest.mark.parametrize("kw", [{"overcast": True}, {"sun_zen": 100.0, "sun_az": 60.0}], ids=["overcast", "below-horizon"])
def test_hidden_sun_gives_none_and_a_note(kw):
    _, rgb, sat, valid, _, _ = make_sky(**kw)
    assert detect_sun(rgb, sat, valid) is None
    circle = Circle(137.3, 112.6, 100.0, 1.0, 0.2)
    guesses = cameras_from_sun((240, 260), circle, None, 60.0, 200.0)
    assert [g.projection for g in guesses] == list(CLASSICAL_PROJECTIONS)
    for g in guesses:
        assert math.isnan(g.score) and float(g.camera.up_azimuth_deg) == 0.0
        assert any("heading must come from the sky pattern" in n for n in g.notes)


# ------------------------------------------------------------------------------- heading, projection
def test_heading_formula_round_trip_through_angles_to_pixel():
    rng = np.random.default_rng(3)
    for _ in range(20):
        heading, zen, az = rng.uniform(0, 360), rng.uniform(5, 85), rng.uniform(0, 360)
        cam = FisheyeCamera(size=(200, 220), projection="equisolid", cx=105.2, cy=98.7, radius=90.0,
                            up_azimuth_deg=heading)
        x, y = cam.angles_to_pixel(_t(zen), _t(az))
        got = heading_from_sun(105.2, 98.7, float(x), float(y), az)
        assert abs((got - heading + 180) % 360 - 180) < 1e-9


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_heading_recovered_from_the_image(seed):
    rng = np.random.default_rng(seed)
    heading, sun_az, sun_zen = rng.uniform(0, 360), rng.uniform(0, 360), rng.uniform(45, 65)
    cam, rgb, sat, valid, _, (sx, sy) = make_sky(heading=heading, sun_zen=sun_zen, sun_az=sun_az, seed=seed)
    circle = detect_circle(rgb @ LUMA, seed=seed)
    sun = detect_sun(rgb, sat, circle_inside(circle, rgb.shape[:2]))
    (best,) = cameras_from_sun(rgb.shape[:2], circle, sun, sun_zen, sun_az, projections=("equidistant",))
    err = (float(best.camera.up_azimuth_deg) - heading + 180) % 360 - 180
    assert abs(err) < 0.5
    assert math.hypot(best.sun_model_px[0] - sx, best.sun_model_px[1] - sy) < 1.5


def circle_inside(circle: Circle, shape) -> np.ndarray:
    yy, xx = np.mgrid[: shape[0], : shape[1]]
    return np.hypot(xx - circle.cx, yy - circle.cy) <= circle.radius


@pytest.mark.parametrize("projection", CLASSICAL_PROJECTIONS)
def test_true_projection_ranked_first(projection):
    rng = np.random.default_rng(CLASSICAL_PROJECTIONS.index(projection))
    for sun_zen in (40.0 + rng.uniform(0, 4), 56.0 + rng.uniform(0, 4)):
        sun_az = rng.uniform(0, 360)
        _, rgb, sat, _, _, _ = make_sky(projection=projection, heading=rng.uniform(0, 360), sun_zen=sun_zen,
                                        sun_az=sun_az)
        circle = detect_circle(rgb @ LUMA)
        sun = detect_sun(rgb, sat, circle_inside(circle, rgb.shape[:2]))
        guesses = cameras_from_sun(rgb.shape[:2], circle, sun, sun_zen, sun_az)
        assert guesses[0].projection == projection, [(g.projection, g.score) for g in guesses]
        # the winner is off by the centroid bias of a squeezed blob (orthographic at 60°: ~0.7°); the next by >= 3.5°
        assert guesses[0].score < 1.0 and guesses[1].score > 2.5


# ------------------------------------------------------------------------------------ masks
def test_obstacle_mask_covers_a_dark_textured_skyline_not_the_sky():
    cam, rgb, _, valid, obst, _ = make_sky(skyline="dark", sun_zen=70.0, sun_az=160.0)
    m = obstacle_mask(rgb, valid, cam)
    clear = valid & ~obst
    assert m[obst].mean() >= 0.90
    assert m[clear].mean() <= 0.03  # includes the 2 px growth along the skyline
    assert m[clear & ~dilation(obst, disk(4))].mean() <= 0.005


def test_obstacle_mask_finds_a_smooth_green_hill_as_bright_as_the_sky():
    cam, rgb, _, valid, obst, _ = make_sky(skyline="green", sun_zen=60.0, sun_az=100.0, projection="equisolid")
    m = obstacle_mask(rgb, valid, cam)
    assert m[obst].mean() >= 0.90
    assert m[valid & ~obst].mean() <= 0.03


def test_obstacle_mask_leaves_a_bright_clear_horizon():
    cam, rgb, _, valid, _, _ = make_sky(sun_zen=82.0, sun_az=250.0)  # low sun: bright aureole at the horizon
    assert (rgb @ LUMA)[valid & (cam.pixel_directions()[0].numpy() > math.radians(85))].mean() > 2.5 * 0.1
    assert obstacle_mask(rgb, valid, cam).sum() <= 0.005 * valid.sum()


def test_the_sky_models_trimmed_fit_recovers_a_smooth_sky_under_dark_obstacles():
    """The obstacle mask's smooth sky model (normal equations where well conditioned): a log sky that lies in its basis
    (degree 3 in elevation times azimuthal orders 0-2) is recovered to 1e-9 under a dark skyline over a quarter of the
    horizon, at every pixel; a region of one azimuth only (a degenerate basis) takes the SVD and still fits its data."""
    from skyfit.camera.masks import _robust_smooth_fit

    rng = np.random.default_rng(3)
    elev = rng.uniform(0.0, 50.0, (200, 300))
    az = rng.uniform(-math.pi, math.pi, (200, 300))
    u = elev / 90.0
    truth = (-1.0 + 0.8 * u - 0.5 * u**2 + 0.3 * u**3 + 0.2 * np.cos(az) - 0.1 * u * np.sin(2 * az)
             + 0.05 * u**2 * np.cos(2 * az))
    values = truth.copy()
    skyline = (elev < 12.0) & (az > 0.0) & (az < math.pi / 2)
    values[skyline] -= 2.0  # dark: e^-2 of the sky
    fitted = _robust_smooth_fit(values, elev, az, np.ones_like(values, bool), low=0.15, high=0.3)
    assert np.abs(fitted - truth).max() < 1e-9
    one_azimuth = np.full_like(az, 0.7)
    line = -1.0 + 0.5 * u
    fitted = _robust_smooth_fit(line, elev, one_azimuth, np.ones_like(line, bool), low=0.15, high=0.3)
    assert np.isfinite(fitted).all() and np.abs(fitted - line).max() < 1e-6


def test_sun_mask_covers_detected_and_computed_sun_and_grows_with_the_blob():
    cam = FisheyeCamera(size=(240, 260), projection="equidistant", cx=137.3, cy=112.6, radius=100.0)
    sx, sy = cam.angles_to_pixel(_t(50.0), _t(140.0))
    # detected 6 px away from the computed sun: both must be masked
    small = SunDetection(float(sx) + 6.0, float(sy), 1.0, False, 3)
    big = SunDetection(float(sx) + 6.0, float(sy), 6.0, True, 113)
    m_small = sun_mask(cam.shape, small, cam, 50.0, 140.0)
    m_big = sun_mask(cam.shape, big, cam, 50.0, 140.0)
    for m in (m_small, m_big):
        assert m[int(round(float(sy))), int(round(float(sx)))] and m[int(round(float(sy))), int(round(float(sx) + 6))]
    # angular radii from the spherical law of cosines: the computed sun at zenith 50°, r = R90 50/90 px from the
    # centre (equidistant, 100/90 px per degree radially); a blob of 6 px spans 6 / (100/90) = 5.40° radially
    # and 2 asin(sin(50°) sin(3 / r)) = 4.74° tangentially: mask radius mean + SUN_HALO_MARGIN_DEG (3°) = 8.07°
    r = 100.0 * 50.0 / 90.0

    def blob_deg(px):
        return (2 * px / (100.0 / 90.0) + 2 * math.degrees(2 * math.asin(math.sin(math.radians(50)) * math.sin(px / 2 / r)))) / 4

    alpha = blob_deg(6.0) + 3.0
    alpha_small = blob_deg(1.0) + 3.0  # a 1 px blob: 0.90° + 3°
    v, valid = cam.pixel_vectors()
    v = torch.where(valid[..., None], v, torch.zeros_like(v))

    def gamma(d):
        return torch.rad2deg(torch.arccos((v @ d).clamp(-1, 1))).numpy()

    g_comp = gamma(zenith_azimuth_to_enu(_t(50.0), _t(140.0)))
    g_det = gamma(cam.pixel_to_direction(torch.tensor(float(sx) + 6.0, dtype=torch.float64),
                                         torch.tensor(float(sy), dtype=torch.float64)))
    assert m_small[(g_comp < alpha_small - 0.3) | (g_det < alpha_small - 0.3)].all()
    assert not m_small[(g_comp > alpha_small + 0.3) & (g_det > alpha_small + 0.3)].any()
    assert m_big[(g_comp < alpha - 0.3) | (g_det < alpha - 0.3)].all()
    assert not m_big[(g_comp > alpha + 0.3) & (g_det > alpha + 0.3)].any()
    # a cap below the blob's radius + margin (SUN_MASK_MAX_DEG in a photo fit: the saturated aureole beyond it is
    # fitted as censored bounds) masks that many degrees around both suns and no more
    m_cap = sun_mask(cam.shape, big, cam, 50.0, 140.0, max_radius_deg=5.0)
    assert m_cap[(g_comp < 4.7) | (g_det < 4.7)].all()
    assert not m_cap[(g_comp > 5.3) & (g_det > 5.3)].any()
    assert m_big[(g_comp > 5.3) & (g_det > 5.3)].any()  # the cap took something away
    with pytest.raises(CalibrationError, match="max_radius_deg must be >= min_radius_deg"):
        sun_mask(cam.shape, big, cam, 50.0, 140.0, max_radius_deg=2.0)


def test_grow_outlier_mask_keeps_structures_not_noise():
    cam = FisheyeCamera(size=(200, 200), projection="equidistant", radius=95.0)
    used = cam.valid_mask().numpy()
    zen = np.degrees(np.nan_to_num(cam.pixel_directions()[0].numpy(), nan=math.pi))
    rng = np.random.default_rng(0)
    res = 0.08 * rng.standard_normal((200, 200))  # 0.25 is 3.1 sigma: ~0.2 % isolated outliers
    yy, xx = np.mgrid[:200, :200]
    missed = used & (zen > 78) & (xx < 60) & (yy > 100)  # a missed obstacle on the rim, up to 12° elevation
    cloud = np.hypot(xx - 110, yy - 80) < 6  # a compact cloud near the zenith
    res = np.where(missed, 0.7, np.where(cloud, -0.5, res))
    m = grow_outlier_mask(res, used, cam)
    assert m[missed].all() and m[cloud].all()
    noise = used & ~dilation(missed | cloud, disk(4))
    assert m[noise].mean() < 0.01


def test_circle_of_a_large_photo_found_on_a_reduced_copy(monkeypatch):
    """make_sky's image (with its dark skyline) 8 times larger and blurred by 8 px, as a 2000 px photo's rim spans
    several pixels: detect_circle finds it on a copy reduced to CIRCLE_MAX_SIDE and scales it back (centre within
    1 px, radius within 1.5 px of 800); at full size its 1-2 px thresholds find no circle."""
    import skimage.filters
    import skimage.transform

    from skyfit.camera import autocal

    _, rgb, _, _, _, _ = make_sky(skyline="dark")
    big = skimage.filters.gaussian(skimage.transform.rescale(rgb @ LUMA, 8, order=1), sigma=8.0)
    cx, cy = (137.3 + 0.5) * 8 - 0.5, (112.6 + 0.5) * 8 - 0.5  # pixel centres: x -> 8 (x + 1/2) - 1/2
    c = detect_circle(big)
    assert math.hypot(c.cx - cx, c.cy - cy) < 1.0 and abs(c.radius - 800.0) < 1.5, c
    monkeypatch.setattr(autocal, "CIRCLE_MAX_SIDE", 10**6)
    with pytest.raises(CalibrationError, match="no fisheye circle found"):
        detect_circle(big)
