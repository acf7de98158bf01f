"""Fisheye camera geometry against CONTRACT.md's conventions and the projections' closed forms.

Zenith at the image centre, North up, East on the LEFT, pixel (row i, col j)
centred at (x=j, y=i); rho (distance from the centre over the 90° radius) is
theta/(pi/2), sin(theta/2)/sin(45°), sin(theta), tan(theta/2).
"""
from __future__ import annotations

import math

import pytest
import torch

from skyfit.camera import PROJECTIONS, FisheyeCamera

# Closed forms written out here, independently of skyfit.camera.fisheye.
RHO = {
    "equidistant": lambda t: t / (math.pi / 2),
    "equisolid": lambda t: math.sin(t / 2) / math.sin(math.pi / 4),
    "orthographic": math.sin,
    "stereographic": lambda t: math.tan(t / 2),
}

SIZE, R90 = 101, 40.0  # odd size: pixel (50, 50) is the exact centre
C = (SIZE - 1) // 2


def _dirs(cam):
    zen, az, valid = cam.pixel_directions(torch.float64)
    return torch.rad2deg(zen), torch.rad2deg(az), valid


@pytest.mark.parametrize("projection", PROJECTIONS)
def test_cardinal_pixels(projection):
    cam = FisheyeCamera(SIZE, projection=projection, radius=R90)
    zen, az, valid = _dirs(cam)
    r = int(R90)
    assert zen[C, C].item() == pytest.approx(0.0, abs=1e-12)
    # (row, col) -> expected azimuth: top North, left East, bottom South, right West.
    for (i, j), azimuth in {(C - r, C): 0.0, (C, C - r): 90.0, (C + r, C): 180.0, (C, C + r): 270.0}.items():
        assert zen[i, j].item() == pytest.approx(90.0, abs=1e-9), (i, j)
        assert float((az[i, j] - azimuth + 180) % 360 - 180) == pytest.approx(0.0, abs=1e-9), (i, j)
        assert bool(valid[i, j])
    # one pixel further out is beyond the 90° circle
    assert not bool(valid[C, C - r - 1]) and not bool(valid[C - r - 1, C])


@pytest.mark.parametrize("projection", PROJECTIONS)
def test_intermediate_radius_matches_closed_form(projection):
    cam = FisheyeCamera(SIZE, projection=projection, radius=R90)
    zen, az, _ = _dirs(cam)
    for k in (5, 12, 20, 33):  # pixels straight up (North) at k px from the centre
        rho = k / R90
        theta = math.degrees(_invert(RHO[projection], rho))
        assert zen[C - k, C].item() == pytest.approx(theta, abs=1e-9)
        assert zen[C, C + k].item() == pytest.approx(theta, abs=1e-9)  # same radius due West
    assert az[C - 7, C - 7].item() == pytest.approx(45.0, abs=1e-9)  # up-left: NE
    assert az[C + 7, C - 7].item() == pytest.approx(135.0, abs=1e-9)  # down-left: SE


def _invert(f, rho, lo=0.0, hi=math.pi / 2):
    """Bisection for f(theta) = rho on [0, 90°] (f increasing)."""
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if f(mid) < rho else (lo, mid)
    return 0.5 * (lo + hi)


@pytest.mark.parametrize("up", [90.0, 200.0, -45.0])
def test_up_azimuth_rotates(up):
    base = FisheyeCamera(SIZE, radius=R90)
    rot = FisheyeCamera(SIZE, radius=R90, up_azimuth_deg=up)
    z0, a0, _ = _dirs(base)
    z1, a1, _ = _dirs(rot)
    torch.testing.assert_close(z1, z0, rtol=0, atol=0)
    diff = (a1 - a0 - up + 180) % 360 - 180  # every azimuth shifts by +up (mod 360)
    off_centre = torch.ones_like(diff, dtype=torch.bool)
    off_centre[C, C] = False
    torch.testing.assert_close(diff[off_centre], torch.zeros_like(diff[off_centre]), rtol=0, atol=1e-9)
    # with East up (up=90) the top pixel looks East and the left one South
    if up == 90.0:
        assert a1[C - 10, C].item() == pytest.approx(90.0, abs=1e-9)
        assert a1[C, C - 10].item() == pytest.approx(180.0, abs=1e-9)


@pytest.mark.parametrize("projection", PROJECTIONS)
@pytest.mark.parametrize("up", [0.0, 33.0])
def test_direction_to_pixel_round_trip(projection, up):
    cam = FisheyeCamera(64, projection=projection, up_azimuth_deg=up)  # default centre 31.5, radius 32
    zen, az, valid = cam.pixel_directions(torch.float64)
    x, y = cam.direction_to_pixel(zen, az)
    jj, ii = torch.meshgrid(torch.arange(64.0, dtype=torch.float64), torch.arange(64.0, dtype=torch.float64), indexing="xy")
    err = torch.hypot(x - jj, y - ii)[valid]
    assert valid.sum() > 3000
    assert err.max().item() < 1e-6


@pytest.mark.parametrize("projection", PROJECTIONS)
def test_valid_area_is_the_90_degree_disc(projection):
    cam = FisheyeCamera(256, projection=projection, radius=100.0)
    _, _, valid = cam.pixel_directions(torch.float64)
    area = valid.sum().item()
    assert area == pytest.approx(math.pi * 100.0**2, rel=0.01)


@pytest.mark.parametrize("projection", PROJECTIONS)
def test_valid_area_with_max_zenith(projection):
    cam = FisheyeCamera(256, projection=projection, radius=100.0, max_zenith_deg=60.0)
    _, _, valid = cam.pixel_directions(torch.float64)
    r = 100.0 * RHO[projection](math.radians(60.0))
    assert valid.sum().item() == pytest.approx(math.pi * r * r, rel=0.01)


def test_default_disc_touches_the_image_edges():
    cam = FisheyeCamera(64)
    zen, _, valid = cam.pixel_directions(torch.float64)
    assert cam.centre == (31.5, 31.5) and cam.r90 == 32.0
    # the pixel centres nearest the edge midpoints are 31.5 px out: inside, at 88.6°
    assert bool(valid[0, 31]) and not bool(valid[0, 0])
    assert math.degrees(zen[31, 0].item()) == pytest.approx(math.hypot(31.5, 0.5) / 32 * 90, abs=1e-9)


def test_metadata_records_the_geometry():
    cam = FisheyeCamera(50, projection="equisolid", up_azimuth_deg=12.5, radius=20.0, cx=24.0, cy=25.0)
    m = cam.metadata()
    assert (m["projection"], m["size"], m["cx"], m["cy"], m["radius_px"], m["up_azimuth_deg"]) == (
        "equisolid", 50, 24.0, 25.0, 20.0, 12.5)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(projection="fisheye"), "unknown projection"),
        (dict(radius=0.0), "radius"),
        (dict(radius=float("nan")), "radius"),
        (dict(up_azimuth_deg=float("nan")), "up_azimuth_deg"),
        (dict(cx=float("inf")), "cx"),
        (dict(projection="orthographic", max_zenith_deg=100.0), "max_zenith_deg"),
        (dict(projection="stereographic", max_zenith_deg=180.0), "max_zenith_deg"),
        (dict(max_zenith_deg=0.0), "max_zenith_deg"),
    ],
)
def test_bad_camera_raises(kwargs, match):
    with pytest.raises(ValueError, match=match):
        FisheyeCamera(32, **kwargs)


def test_float32_directions_match_float64():
    cam = FisheyeCamera(64, projection="stereographic")
    z64, a64, v64 = cam.pixel_directions(torch.float64)
    z32, a32, v32 = cam.pixel_directions(torch.float32)
    assert z32.dtype == torch.float32 and torch.equal(v32, v64)
    torch.testing.assert_close(z32.double()[v64], z64[v64], rtol=0, atol=1e-6)
    # azimuth wraps at 0/360: compare on the circle
    d = torch.remainder(a32.double() - a64 + math.pi, 2 * math.pi) - math.pi
    torch.testing.assert_close(d[v64], torch.zeros_like(d[v64]), rtol=0, atol=1e-5)
