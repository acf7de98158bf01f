"""Fisheye camera geometry against CONTRACT.md's conventions, the projections' closed forms and kornia.

Zenith at the image centre, North up, East on the LEFT, pixel (row i, col j)
centred at (x=j, y=i); rho (distance from the centre over the 90° radius) is
theta/(pi/2), sin(theta/2)/sin(45°), sin(theta), tan(theta/2), and for
Kannala-Brandt P(theta)/P(90°) with P(t) = t + k1 t^3 + k2 t^5 + k3 t^7 + k4 t^9
(Kannala & Brandt 2006), each written out below independently of skyfit.
"""
from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch
from torch.autograd import gradcheck

from skyfit.camera.fisheye import CLASSICAL_PROJECTIONS, PROJECTIONS, FisheyeCamera, reproject
from skyfit.camera.kannala_brandt import kb_theta

D = torch.float64
KB = (0.03, -0.006, 0.0004, -0.00002)  # P' > 0 up to about 123°, so the lens may see 100°


def _kb_poly(t, k=KB):
    return t + k[0] * t**3 + k[1] * t**5 + k[2] * t**7 + k[3] * t**9


# Closed forms written out here, independently of skyfit.camera.fisheye.
RHO = {
    "equidistant": lambda t: t / (math.pi / 2),
    "equisolid": lambda t: math.sin(t / 2) / math.sin(math.pi / 4),
    "orthographic": math.sin,
    "stereographic": lambda t: math.tan(t / 2),
    "kannala_brandt": lambda t: _kb_poly(t) / _kb_poly(math.pi / 2),
}
EXTRA = {"kannala_brandt": {"kb_coeffs": KB}}  # constructor arguments each projection needs

SIZE, R90 = 101, 40.0  # odd size: pixel (50, 50) is the exact centre
C = (SIZE - 1) // 2


def _cam(projection, size=SIZE, **kw):
    return FisheyeCamera(size, projection=projection, **{**EXTRA.get(projection, {}), **kw})


def _dirs(cam):
    zen, az, valid = cam.pixel_directions(D)
    return torch.rad2deg(zen), torch.rad2deg(az), valid


def _invert(f, rho, lo=0.0, hi=math.pi / 2):
    """Bisection for f(theta) = rho on [lo, hi] (f increasing)."""
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if f(mid) < rho else (lo, mid)
    return 0.5 * (lo + hi)


def _angle(a, b):
    """Angle between vectors (..., 3), robust near 0. [rad]"""
    return torch.atan2(torch.linalg.cross(a, b).norm(dim=-1), (a * b).sum(-1))


# -- conventions -------------------------------------------------------------------
@pytest.mark.parametrize("projection", PROJECTIONS)
def test_cardinal_pixels(projection):
    cam = _cam(projection, radius=R90)
    zen, az, valid = _dirs(cam)
    r = int(R90)
    assert zen[C, C].item() == pytest.approx(0.0, abs=1e-12)
    # (row, col) -> expected azimuth: top North, left East, bottom South, right West.
    for (i, j), azimuth in {(C - r, C): 0.0, (C, C - r): 90.0, (C + r, C): 180.0, (C, C + r): 270.0}.items():
        assert zen[i, j].item() == pytest.approx(90.0, abs=1e-9), (i, j)
        assert float((az[i, j] - azimuth + 180) % 360 - 180) == pytest.approx(0.0, abs=1e-9), (i, j)
        assert bool(valid[i, j])
    # one pixel further out is beyond the 90° circle, and its direction is NaN
    assert not bool(valid[C, C - r - 1]) and not bool(valid[C - r - 1, C])
    assert math.isnan(zen[C, C - r - 1].item()) and math.isnan(az[C, C - r - 1].item())


@pytest.mark.parametrize("projection", PROJECTIONS)
def test_intermediate_radius_matches_closed_form(projection):
    cam = _cam(projection, radius=R90)
    zen, az, _ = _dirs(cam)
    for k in (5, 12, 20, 33):  # pixels straight up (North) at k px from the centre
        theta = math.degrees(_invert(RHO[projection], k / R90))
        assert zen[C - k, C].item() == pytest.approx(theta, abs=1e-9)
        assert zen[C, C + k].item() == pytest.approx(theta, abs=1e-9)  # same radius due West
    assert az[C - 7, C - 7].item() == pytest.approx(45.0, abs=1e-9)  # up-left: NE
    assert az[C + 7, C - 7].item() == pytest.approx(135.0, abs=1e-9)  # down-left: SE


@pytest.mark.parametrize("up", [90.0, 200.0, -45.0])
def test_up_azimuth_rotates(up):
    base = FisheyeCamera(SIZE, radius=R90)
    rot = FisheyeCamera(SIZE, radius=R90, up_azimuth_deg=up)
    z0, a0, v0 = _dirs(base)
    z1, a1, _ = _dirs(rot)
    torch.testing.assert_close(z1[v0], z0[v0], rtol=0, atol=1e-12)
    diff = (a1 - a0 - up + 180) % 360 - 180  # every azimuth shifts by +up (mod 360)
    off_centre = v0.clone()
    off_centre[C, C] = False
    torch.testing.assert_close(diff[off_centre], torch.zeros_like(diff[off_centre]), rtol=0, atol=1e-9)
    # with East up (up=90) the top pixel looks East and the left one South
    if up == 90.0:
        assert a1[C - 10, C].item() == pytest.approx(90.0, abs=1e-9)
        assert a1[C, C - 10].item() == pytest.approx(180.0, abs=1e-9)


@pytest.mark.parametrize("projection", PROJECTIONS)
def test_tilt_leans_the_optical_axis(projection):
    """tilt_deg = (5, 0): the axis leans 5° toward East. The centre pixel then looks at zenith 5°,
    azimuth 90°, and the zenith lies 5° from the axis toward West, which is image right (x > cx)."""
    cam = _cam(projection, radius=R90, cx=float(C), cy=float(C), tilt_deg=(5.0, 0.0))
    zen, az, _ = _dirs(cam)
    assert zen[C, C].item() == pytest.approx(5.0, abs=1e-9) and az[C, C].item() == pytest.approx(90.0, abs=1e-9)
    x, y = cam.direction_to_pixel(torch.tensor([0.0, 0.0, 1.0], dtype=D))
    assert x.item() == pytest.approx(C + R90 * RHO[projection](math.radians(5.0)), abs=1e-9)
    assert y.item() == pytest.approx(C, abs=1e-9)
    # a tilt toward North moves the zenith down the image (North is up)
    x, y = _cam(projection, radius=R90, cx=float(C), cy=float(C), tilt_deg=(0.0, 5.0)).direction_to_pixel(
        torch.tensor([0.0, 0.0, 1.0], dtype=D))
    assert x.item() == pytest.approx(C, abs=1e-9) and y.item() > C + 1


def test_horizon_mask_follows_the_tilt():
    flat = FisheyeCamera(SIZE, radius=R90)
    assert not bool(flat.below_horizon_mask().any())
    cam = FisheyeCamera(SIZE, radius=R90, tilt_deg=(5.0, 0.0))  # leans East: East (left) rim dips below
    below = cam.below_horizon_mask()
    x, _ = cam.pixel_grid(D)
    assert below.sum() > 20 and bool((x[below] < C).all()) and bool(below[C, C - int(R90)])
    zen, _, valid = _dirs(cam)
    torch.testing.assert_close(below, valid & (zen > 90))


# -- round trips -------------------------------------------------------------------
ROUND_TRIP_CAMERAS = [(p, 90.0) for p in PROJECTIONS] + [(p, 100.0) for p in PROJECTIONS if p != "orthographic"]


@pytest.mark.parametrize("projection, max_zenith", ROUND_TRIP_CAMERAS)
def test_pixel_direction_pixel_round_trip(projection, max_zenith):
    cam = _cam(projection, size=64, cx=30.7, cy=32.9, radius=27.0, up_azimuth_deg=33.0, tilt_deg=(2.5, -1.5),
               max_zenith_deg=max_zenith)
    x, y = cam.pixel_grid(D)
    v = cam.pixel_to_direction(x, y)
    valid = cam.valid_mask()
    assert torch.equal(torch.isfinite(v).all(-1), valid)
    torch.testing.assert_close(v[valid].norm(dim=-1), torch.ones(int(valid.sum()), dtype=D), rtol=0, atol=1e-14)
    xx, yy = cam.direction_to_pixel(v)
    err = torch.hypot(xx - x, yy - y)[valid]
    rim = RHO[projection](math.radians(max_zenith)) * 27.0
    assert valid.sum() >= math.pi * (rim - 1.5) ** 2  # the whole disc is in the test
    assert err.max().item() < 1e-6


@pytest.mark.parametrize("projection, max_zenith", ROUND_TRIP_CAMERAS)
def test_direction_pixel_direction_round_trip(projection, max_zenith):
    cam = _cam(projection, size=64, cx=32.4, cy=30.2, radius=30.0, up_azimuth_deg=-120.0, tilt_deg=(-3.0, 1.0),
               max_zenith_deg=max_zenith)
    g = torch.Generator().manual_seed(1)
    # directions uniform in solid angle within the field of view, around the (tilted) optical axis
    cos_t = 1 - torch.rand(4000, generator=g, dtype=D) * (1 - math.cos(math.radians(max_zenith) * 0.9999))
    phi = torch.rand(4000, generator=g, dtype=D) * 2 * math.pi
    sin_t = torch.sqrt(1 - cos_t**2)
    d = torch.stack([sin_t * torch.cos(phi), sin_t * torch.sin(phi), cos_t], -1)
    v = d @ cam.rotation().T
    x, y = cam.direction_to_pixel(v)
    assert bool(torch.isfinite(x).all())
    back = cam.pixel_to_direction(x, y)
    assert _angle(back, v).max().item() < 1e-12


def test_outside_the_field_of_view_is_nan():
    cam = FisheyeCamera(SIZE, radius=R90, max_zenith_deg=80.0)
    v = cam.pixel_to_direction(torch.tensor([C - 37.0, C - 35.0], dtype=D), torch.tensor([float(C), float(C)], dtype=D))
    assert bool(torch.isnan(v[0]).all()) and bool(torch.isfinite(v[1]).all())  # 83.25° and 78.75°
    x, _ = cam.angles_to_pixel(torch.tensor([math.radians(85.0), math.radians(75.0)], dtype=D), torch.zeros(2, dtype=D))
    assert math.isnan(x[0].item()) and math.isfinite(x[1].item())
    assert cam.pixel_valid(torch.tensor([float(C), -0.6]), torch.tensor([float(C), float(C)])).tolist() == [True, False]


# -- gradients ---------------------------------------------------------------------
def _camera_builder(projection, size=64):
    kb = projection == "kannala_brandt"

    def build(cx, cy, scale, up, tilt, k=None):
        return FisheyeCamera(size, projection=projection, cx=cx, cy=cy, radius=None if kb else scale,
                             focal=scale if kb else None, kb_coeffs=k, up_azimuth_deg=up, tilt_deg=tilt)

    def params(tilt):
        vals = [torch.tensor(v, dtype=D, requires_grad=True) for v in (31.0, 30.0, 25.0 if kb else 30.0, 33.0)]
        vals.append(torch.tensor(tilt, dtype=D, requires_grad=True))
        if kb:
            vals.append(torch.tensor(KB, dtype=D, requires_grad=True))
        return vals

    return build, params


@pytest.mark.parametrize("tilt", [(0.0, 0.0), (3.0, -2.0)])
@pytest.mark.parametrize("projection", PROJECTIONS)
def test_gradcheck_pixel_to_direction(projection, tilt):
    """d(direction)/d(every camera parameter and the pixel), float64, at the exact centre pixel (where
    a naive atan2 or division by the radius gives NaN), off-centre and near the rim (about 80°)."""
    build, params = _camera_builder(projection)
    x = torch.tensor([31.0, 31.5, 20.0, 40.0, 31.0], dtype=D, requires_grad=True)
    y = torch.tensor([30.0, 30.0, 12.0, 45.0, 3.5], dtype=D, requires_grad=True)
    ps = params(tilt)
    v = build(*ps).pixel_to_direction(x, y)
    assert bool(torch.isfinite(v).all())
    assert gradcheck(lambda x, y, *p: build(*p).pixel_to_direction(x, y), (x, y, *ps))


@pytest.mark.parametrize("tilt", [(0.0, 0.0), (3.0, -2.0)])
@pytest.mark.parametrize("projection", PROJECTIONS)
def test_gradcheck_direction_to_pixel(projection, tilt):
    """d(pixel)/d(parameters and direction), including the zenith, which is the optical axis at zero tilt."""
    build, params = _camera_builder(projection)
    v = torch.tensor([[0.0, 0.0, 1.0], [0.3, 0.2, 0.9], [-0.5, 0.4, 0.3], [0.1, -0.9, 0.2]], dtype=D, requires_grad=True)
    ps = params(tilt)
    assert gradcheck(lambda v, *p: torch.stack(build(*p).direction_to_pixel(v)), (v, *ps))


def test_masked_image_loss_has_finite_gradients_at_the_centre():
    """A loss over the valid pixels of an odd-sized image (one pixel exactly at the centre, NaN outside
    the disc) has finite gradients with respect to every parameter; also through (zenith, azimuth)."""
    cx = torch.tensor(float(C), dtype=D, requires_grad=True)
    up = torch.tensor(10.0, dtype=D, requires_grad=True)
    tilt = torch.zeros(2, dtype=D, requires_grad=True)
    cam = FisheyeCamera(SIZE, cx=cx, cy=float(C), radius=R90, up_azimuth_deg=up, tilt_deg=tilt)
    v, valid = cam.pixel_vectors(D)
    zen, az, _ = cam.pixel_directions(D)
    loss = (v[valid] * torch.tensor([0.3, -0.2, 1.0], dtype=D)).sum() + (torch.cos(zen) + torch.sin(zen) * torch.cos(az))[valid].sum()
    loss.backward()
    for t in (cx, up, tilt):
        assert bool(torch.isfinite(t.grad).all()) and bool((t.grad != 0).any())


# -- Kannala-Brandt ----------------------------------------------------------------
def test_kannala_brandt_matches_kornia_inside_80_degrees():
    """kornia 0.9's z = 1 plane model (theta = atan r) agrees where it applies. Tolerances: 1e-9 px for
    direction -> pixel (measured 6e-12 at 80°, f = 60 px) and 1e-12 relative on the z = 1 point for
    pixel -> direction (kornia runs 10 Gauss-Newton steps; measured 1.4e-15)."""
    from kornia.geometry.camera.distortion_kannala_brandt import (
        distort_points_kannala_brandt,
        undistort_points_kannala_brandt,
    )

    cam = FisheyeCamera(200, projection="kannala_brandt", focal=60.0, cx=101.3, cy=98.6, kb_coeffs=KB)
    g = torch.Generator().manual_seed(0)
    theta = torch.rand(2000, generator=g, dtype=D) * math.radians(80)
    phi = torch.rand(2000, generator=g, dtype=D) * 2 * math.pi
    d = torch.stack([theta.sin() * phi.cos(), theta.sin() * phi.sin(), theta.cos()], -1)  # camera frame
    params = torch.tensor([60.0, 60.0, 101.3, 98.6, *KB], dtype=D)
    x, y, _ = cam.camera_to_pixel(d)
    expected = distort_points_kannala_brandt(d[:, :2] / d[:, 2:], params)
    torch.testing.assert_close(torch.stack([x, y], -1), expected, rtol=0, atol=1e-9)
    z1 = undistort_points_kannala_brandt(expected, params)
    ours, _ = cam.pixel_to_camera(expected[:, 0], expected[:, 1])
    torch.testing.assert_close(ours[:, :2] / ours[:, 2:], z1, rtol=1e-12, atol=1e-12)


def test_kannala_brandt_at_and_beyond_90_degrees():
    """kornia's z = 1 plane cannot hold theta >= 90°; here r(theta) keeps increasing through 100° and the
    inverse agrees with a bisection of the polynomial written in this file."""
    cam = FisheyeCamera(SIZE, projection="kannala_brandt", focal=25.0, cx=float(C), cy=float(C), kb_coeffs=KB,
                        max_zenith_deg=100.0)
    th = torch.linspace(0, math.radians(100), 1001, dtype=D)
    d = torch.stack([th.sin(), torch.zeros_like(th), th.cos()], -1)
    x, y, inside = cam.camera_to_pixel(d)
    assert bool(inside.all())
    assert bool((torch.diff(x) > 0).all())  # monotone
    torch.testing.assert_close(x - C, 25.0 * _kb_poly(th), rtol=0, atol=1e-12)
    for deg in (90.0, 95.0, 99.9):
        r = 25.0 * _kb_poly(math.radians(deg))
        theta = _invert(_kb_poly, r / 25.0, 0.0, math.radians(100.0))
        v, _ = cam.pixel_to_camera(torch.tensor(C + r, dtype=D), torch.tensor(float(C), dtype=D))
        assert math.degrees(math.atan2(v[0].item(), v[2].item())) == pytest.approx(math.degrees(theta), abs=1e-10)
        assert math.degrees(theta) == pytest.approx(deg, abs=1e-10)
    # gradient of the inverse with respect to the coefficients at 95° (implicit-function gradient)
    rho = torch.tensor([_kb_poly(math.radians(95.0)), 0.3, 1e-3], dtype=D, requires_grad=True)
    k = torch.tensor(KB, dtype=D, requires_grad=True)
    assert gradcheck(lambda r, k: kb_theta(r, k, math.radians(100.0)), (rho, k))


def test_kannala_brandt_refuses_a_polynomial_that_turns_back():
    with pytest.raises(ValueError, match=r"not monotone: r\(theta\) stops increasing at 45.57 deg"):
        FisheyeCamera(32, projection="kannala_brandt", kb_coeffs=(0.0, -0.5, 0.0, 0.0))
    # the same lens is fine if it only sees 40°
    FisheyeCamera(32, projection="kannala_brandt", kb_coeffs=(0.0, -0.5, 0.0, 0.0), max_zenith_deg=40.0)


# -- reprojection ----------------------------------------------------------------
def _pattern(v):
    """A smooth test image as a function of the world direction (ENU), two channels."""
    e, n, u = torch.nan_to_num(v).unbind(-1)
    return torch.stack([1 + 0.5 * e + 0.3 * n * u, 0.5 + 0.4 * u * u - 0.2 * e * n], 0)


def test_reproject_equidistant_to_equisolid_and_back():
    """Bilinear remap of a smooth pattern; compared away from the source disc's edge (2 px, where the
    samples blend with the zeros outside). Interpolation error measured 2.5e-4 one way, 3.8e-4 round trip."""
    a = FisheyeCamera(96, projection="equidistant", cx=47.3, cy=48.1, radius=44.0, up_azimuth_deg=10.0)
    b = FisheyeCamera(96, projection="equisolid", cx=48.0, cy=47.5, radius=45.0, up_azimuth_deg=-20.0, tilt_deg=(1.0, 0.5))
    va, ok_a = a.pixel_vectors(D)
    img = torch.where(ok_a, _pattern(va), torch.zeros(()))
    out, ok_b = reproject(img, a, b)
    vb, _ = b.pixel_vectors(D)
    xa, ya = a.direction_to_pixel(torch.where(ok_b[..., None], vb, torch.tensor([0.0, 0.0, 1.0], dtype=D)))
    inner = ok_b & (torch.hypot(xa - 47.3, ya - 48.1) < 42.0)
    assert inner.sum() > 5000
    expected = _pattern(vb)
    assert (out - expected)[:, inner].abs().max().item() < 1e-3
    assert (img - expected)[:, inner].abs().max().item() > 0.1  # the two geometries do differ
    assert bool((out[:, ~ok_b] == 0).all())
    back, ok_back = reproject(out, b, a)
    x, y = a.pixel_grid(D)
    inner = ok_back & (torch.hypot(x - 47.3, y - 48.1) < 40.0)
    assert inner.sum() > 4500
    assert (back - img)[:, inner].abs().max().item() < 2e-3


def test_reproject_onto_itself_is_the_identity():
    a = FisheyeCamera(40, projection="kannala_brandt", kb_coeffs=KB, tilt_deg=(2.0, 1.0), up_azimuth_deg=70.0)
    va, ok = a.pixel_vectors(D)
    img = torch.where(ok, _pattern(va), torch.zeros(()))[None]  # (B, C, H, W)
    out, ok2 = reproject(img, a, a)
    assert out.shape == img.shape and torch.equal(ok2, ok)
    torch.testing.assert_close(out, img, rtol=0, atol=1e-12)


# -- metadata ----------------------------------------------------------------------
META_CAMERAS = [
    dict(projection="equisolid", size=50, cx=24.0, cy=25.0, radius=20.0, up_azimuth_deg=12.5),
    dict(projection="stereographic", size=(48, 64), tilt_deg=(1.25, -0.5), max_zenith_deg=100.0),
    dict(projection="orthographic", size=33, focal=15.3, cx=16.1),
    dict(projection="equidistant", size=64, up_azimuth_deg=-170.0, tilt_deg=(0.1, 0.2)),
    dict(projection="kannala_brandt", size=64, focal=18.7, kb_coeffs=KB, cx=31.9, cy=30.1, up_azimuth_deg=0.3,
         tilt_deg=(3.0, 4.0), max_zenith_deg=95.0),
]


@pytest.mark.parametrize("kw", META_CAMERAS, ids=lambda kw: kw["projection"])
def test_metadata_round_trip_rebuilds_an_identical_camera(kw):
    cam = FisheyeCamera(**kw)
    meta = json.loads(json.dumps(cam.to_metadata()))  # as in the EXR header
    back = FisheyeCamera.from_metadata(meta)
    assert (back.size, back.projection, back.max_zenith_deg) == (cam.size, cam.projection, cam.max_zenith_deg)
    assert back.parameters().keys() == cam.parameters().keys()
    for name, t in cam.parameters().items():
        assert torch.equal(back.parameters()[name], t), name
    v0, ok0 = cam.pixel_vectors(D)
    v1, ok1 = back.pixel_vectors(D)
    assert torch.equal(ok0, ok1) and torch.equal(v0[ok0], v1[ok1])


def test_metadata_records_the_geometry():
    cam = FisheyeCamera(50, projection="equisolid", up_azimuth_deg=12.5, radius=20.0, cx=24.0, cy=25.0, tilt_deg=(3.0, 4.0))
    m = cam.metadata()
    assert (m["projection"], m["size"], m["cx"], m["cy"], m["radius_px"], m["up_azimuth_deg"]) == (
        "equisolid", 50, 24.0, 25.0, 20.0, 12.5)
    assert m["focal_px"] == pytest.approx(20.0 / math.sqrt(2))
    assert m["tilt_zenith_deg"] == pytest.approx(5.0) and m["tilt_azimuth_deg"] == pytest.approx(math.degrees(math.atan2(3, 4)))
    kb = FisheyeCamera(64, projection="kannala_brandt", focal=18.7, kb_coeffs=KB).metadata()
    assert kb["radius_px"] == pytest.approx(18.7 * _kb_poly(math.pi / 2)) and kb["kb_coeffs"] == list(KB)


def test_metadata_without_the_newer_keys_reads_with_defaults():
    """Files written before tilt and max_zenith existed (the dict of tests/test_io.py)."""
    cam = FisheyeCamera.from_metadata(
        {"projection": "equidistant", "size": 11, "cx": 5.0, "cy": 3.0, "radius_px": 5.5, "up_azimuth_deg": 0.0})
    assert cam.max_zenith_deg == 90.0 and torch.equal(cam.tilt_deg, torch.zeros(2, dtype=D))
    with pytest.raises(ValueError, match="lacks focal_px, kb_coeffs"):
        FisheyeCamera.from_metadata({"projection": "kannala_brandt", "size": 11, "cx": 5.0, "cy": 3.0, "radius_px": 5.5})
    with pytest.raises(ValueError, match="unknown projection"):
        FisheyeCamera.from_metadata({"size": 11})


# -- shapes, dtypes, bad input -------------------------------------------------------
@pytest.mark.parametrize("projection", CLASSICAL_PROJECTIONS)
def test_valid_area_is_the_90_degree_disc(projection):
    cam = FisheyeCamera(256, projection=projection, radius=100.0)
    area = cam.valid_mask().sum().item()
    assert area == pytest.approx(math.pi * 100.0**2, rel=0.01)


@pytest.mark.parametrize("projection", PROJECTIONS)
def test_valid_area_with_max_zenith(projection):
    cam = _cam(projection, size=256, radius=100.0, max_zenith_deg=60.0)
    r = 100.0 * RHO[projection](math.radians(60.0))
    assert cam.valid_mask().sum().item() == pytest.approx(math.pi * r * r, rel=0.01)


def test_default_disc_touches_the_image_edges():
    cam = FisheyeCamera(64)
    zen, _, valid = cam.pixel_directions(D)
    assert (cam.cx.item(), cam.cy.item(), cam.r90.item()) == (31.5, 31.5, 32.0)
    # the pixel centres nearest the edge midpoints are 31.5 px out: inside, at 88.6°
    assert bool(valid[0, 31]) and not bool(valid[0, 0])
    assert math.degrees(zen[31, 0].item()) == pytest.approx(math.hypot(31.5, 0.5) / 32 * 90, abs=1e-9)


def test_rectangular_image():
    cam = FisheyeCamera((48, 64))
    assert cam.shape == (48, 64) and (cam.cx.item(), cam.cy.item(), cam.r90.item()) == (31.5, 23.5, 24.0)
    zen, _, valid = cam.pixel_directions(D)
    assert zen.shape == (48, 64) and valid.sum().item() == pytest.approx(math.pi * 24**2, rel=0.03)


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
        (dict(radius=10.0, focal=5.0), "not both"),
        (dict(kb_coeffs=(0.1, 0, 0, 0)), "kannala_brandt projection only"),
        (dict(projection="kannala_brandt", kb_coeffs=(0.1, 0.0)), r"shape \(4,\)"),
        (dict(tilt_deg=(90.0, 10.0)), "tilt must be < 90"),
        (dict(tilt_deg=(1.0,)), r"shape \(2,\)"),
    ],
)
def test_bad_camera_raises(kwargs, match):
    with pytest.raises(ValueError, match=match):
        FisheyeCamera(32, **kwargs)


@pytest.mark.parametrize("projection", PROJECTIONS)
def test_float32_directions_match_float64(projection):
    cam = _cam(projection, size=64, tilt_deg=(1.0, 2.0), up_azimuth_deg=20.0)
    z64, a64, v64 = cam.pixel_directions(D)
    z32, a32, v32 = cam.pixel_directions(torch.float32)
    assert z32.dtype == torch.float32 and torch.equal(v32, v64)
    torch.testing.assert_close(z32.double()[v64], z64[v64], rtol=0, atol=2e-6)
    # azimuth wraps at 0/360: compare on the circle
    d = torch.remainder(a32.double() - a64 + math.pi, 2 * math.pi) - math.pi
    torch.testing.assert_close(d[v64], torch.zeros_like(d[v64]), rtol=0, atol=2e-5)


def test_to_converts_parameters_differentiably():
    cx = torch.tensor(31.5, dtype=D, requires_grad=True)
    cam32 = FisheyeCamera(64, cx=cx).to(torch.float32)
    assert all(t.dtype == torch.float32 for t in cam32.parameters().values())
    x, y = cam32.pixel_grid(torch.float32)
    cam32.pixel_to_direction(x, y)[cam32.valid_mask()].sum().backward()
    assert cx.grad is not None and math.isfinite(cx.grad.item())


# -- CLI -----------------------------------------------------------------------------
def test_cli_render_kannala_brandt_metadata_rebuilds_the_camera(tmp_path):
    from skyfit.cli import main
    from skyfit.io import read_exr

    out = tmp_path / "kb.exr"
    rc = main(["render", "earth", "--out", str(out), "--size", "16", "--projection", "kannala_brandt",
               "--kb-coeffs", ",".join(map(str, KB)), "--focal", "5.5", "--center", "7.2,7.9", "--up-azimuth", "20",
               "--tilt", "5,60", "--max-zenith", "95", "--sun-zenith", "40", "--view-samples", "4",
               "--wavelengths", "450,550,650"])
    assert rc == 0
    chans, meta = read_exr(out)
    cam = FisheyeCamera.from_metadata(meta["camera"])
    b = math.radians(60.0)
    expected = FisheyeCamera(16, projection="kannala_brandt", focal=5.5, cx=7.2, cy=7.9, kb_coeffs=KB,
                             up_azimuth_deg=20.0, tilt_deg=(5 * math.sin(b), 5 * math.cos(b)), max_zenith_deg=95.0)
    for name, t in expected.parameters().items():
        torch.testing.assert_close(cam.parameters()[name], t, rtol=0, atol=1e-12, msg=name)
    assert cam.max_zenith_deg == 95.0 and meta["camera"]["tilt_zenith_deg"] == pytest.approx(5.0)
    np.testing.assert_array_equal(chans["Y"] > 0, cam.valid_mask().numpy())


@pytest.mark.parametrize(
    "opts, match",
    [
        (["--kb-coeffs", "1,2"], "--kb-coeffs takes 4"),
        (["--kb-coeffs", "0,0,0,0"], "needs --projection kannala_brandt"),
        (["--focal", "3", "--radius", "4"], "not both"),
        (["--tilt", "95,0"], "--tilt"),
        (["--center", "3"], "--center takes 2"),
        (["--projection", "kannala_brandt", "--kb-coeffs", "0,-0.5,0,0"], "not monotone"),
        (["--max-zenith", "200"], "--max-zenith"),  # the flag range check names the flag (docs/reliability.md)
    ],
)
def test_cli_render_bad_camera_options(tmp_path, capsys, opts, match):
    from skyfit.cli import main

    out = tmp_path / "x.exr"
    rc = main(["render", "earth", "--out", str(out), "--size", "8", "--sun-zenith", "30", *opts])
    err = capsys.readouterr().err
    assert rc == 2 and match in err and len(err.strip().splitlines()) == 1
    assert not out.exists()
