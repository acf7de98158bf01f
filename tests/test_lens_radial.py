"""The lens's departure from its nominal projection (``lens_radial``): the ray law, the Kannala-Brandt camera
that writes it, its gradient, and its way through calibrate-camera's combined camera.

References: Kannala & Brandt 2006 (IEEE TPAMI 28, 1335), eq. 6, r = f (theta + k1 theta^3 + ...); against an
equidistant camera normalised to the same 90-degree circle, theta_eq = (theta + k1 theta^3) / (1 + k1 (pi/2)^2)
= theta - k1 theta ((pi/2)^2 - theta^2) + O(k1^2): the ray at theta_eq is at theta_eq + k1 theta_eq ((pi/2)^2 - theta_eq^2) + O(k1^2), so the fit's k is k1 to first order."""
from __future__ import annotations

import math

import pytest
import torch

from skyfit.camera import FisheyeCamera
from skyfit.fit.model import lens_directions
from skyfit.fit.photo import lens_camera
from skyfit.fit.photo_calibration import camera_from_calibration, combine_cameras

F64 = torch.float64


def _zenith(d):
    return torch.atan2(torch.linalg.vector_norm(d[..., :2], dim=-1), d[..., 2])


def test_law_keeps_axis_horizon_and_azimuth_and_moves_theta_by_the_cubic():
    th = torch.tensor([0.0, 1e-8, 0.3, 0.9068996821, 1.3, math.pi / 2], dtype=F64)
    az = torch.tensor([0.0, 1.0, 2.0, -2.5, 0.4, 3.0], dtype=F64)
    d = torch.stack([torch.sin(th) * torch.cos(az), torch.sin(th) * torch.sin(az), torch.cos(th)], -1)
    for k in (0.0, 0.03, -0.05):
        out = lens_directions(d, torch.tensor(k, dtype=F64))
        assert torch.allclose(torch.linalg.vector_norm(out, dim=-1), torch.ones(6, dtype=F64), atol=1e-14)
        want = th + k * th * ((math.pi / 2) ** 2 - th**2)
        assert torch.allclose(_zenith(out), want, atol=1e-12)
        moved = th > 1e-6
        assert torch.allclose(torch.atan2(out[moved, 1], out[moved, 0]), az[moved], atol=1e-12)
    # the largest shift at theta = (pi/2) / sqrt(3): 2.6 deg for k = 0.03 (LENS_RADIAL_PRIOR_SIGMA's docstring)
    peak = (math.pi / 2) / math.sqrt(3)
    assert math.degrees(0.03 * peak * ((math.pi / 2) ** 2 - peak**2)) == pytest.approx(2.56, abs=0.01)


def test_gradcheck_in_k_and_directions():
    g = torch.Generator().manual_seed(3)
    d = torch.randn(7, 3, generator=g, dtype=F64)
    d[:, 2] = d[:, 2].abs()
    d = (d / torch.linalg.vector_norm(d, dim=-1, keepdim=True)).requires_grad_(True)
    k = torch.tensor(0.02, dtype=F64, requires_grad=True)
    assert torch.autograd.gradcheck(lens_directions, (d, k))


@pytest.mark.parametrize("projection", ["equidistant", "equisolid", "stereographic"])
@pytest.mark.parametrize("k", [-0.05, 0.03])
def test_kannala_brandt_camera_sees_what_the_law_moves(projection, k):
    """lens_camera's Kannala-Brandt polynomial, least squares on 200 angles, puts every pixel's ray within 0.005 deg
    of the nominal camera's ray moved by the law (centre, heading and circle kept)."""
    cam = FisheyeCamera(240, projection=projection, cx=118.3, cy=121.6, radius=110.0, up_azimuth_deg=37.0)
    kb = lens_camera(cam, k)
    assert kb.projection == "kannala_brandt" and float(kb.r90) == pytest.approx(110.0, rel=2e-3)
    v0, ok0 = cam.pixel_vectors(F64)
    v1, ok1 = kb.pixel_vectors(F64)
    m = ok0 & ok1
    assert int(m.sum()) >= int(ok0.sum()) - 8  # at most a few rim pixels change sides of the 90-degree circle
    moved = lens_directions(v0[m], torch.tensor(k, dtype=F64))
    err = torch.rad2deg(torch.acos((moved * v1[m]).sum(-1).clamp(-1.0, 1.0)))
    assert float(err.max()) < 5e-3
    assert lens_camera(cam, 0.0) is cam


def test_small_k_is_minus_k1_of_a_kannala_brandt_lens_seen_as_equidistant():
    """An equidistant fit of a KB lens (k1 = -0.01, f from the same circle) moved by k = k1 sees it within
    the second-order error (0.032 deg here; 0.88 deg without the law)."""
    k1, R = -0.01, 110.0
    f = R / (math.pi / 2 + k1 * (math.pi / 2) ** 3)
    truth = FisheyeCamera(240, projection="kannala_brandt", focal=f, kb_coeffs=(k1, 0.0, 0.0, 0.0))
    eq = FisheyeCamera(240, projection="equidistant", radius=R)
    v_t, ok_t = truth.pixel_vectors(F64)
    v_e, ok_e = eq.pixel_vectors(F64)
    m = ok_t & ok_e
    ang = lambda a, b: torch.rad2deg(torch.acos((a * b).sum(-1).clamp(-1.0, 1.0)))  # noqa: E731
    before = float(ang(v_e[m], v_t[m]).max())
    after = float(ang(lens_directions(v_e[m], torch.tensor(k1, dtype=F64)), v_t[m]).max())
    assert before > 0.8 and after < 0.04


def test_calibration_writes_the_median_lens_as_a_kannala_brandt_camera():
    shape = [96, 112]
    entry = lambda k: {"path": f"p{k}", "time": "2024-06-01T12:00:00+00:00", "projection": "equisolid", "lens_radial": k,  # noqa: E731
                       "cx": 58.0, "cy": 47.0, "radius_px": 40.0, "up_azimuth_deg": 30.0, "tilt_deg": [0.0, 0.0],
                       "max_zenith_deg": 90.0, "vignetting": -0.1, "gain_red": 1.0, "gain_blue": 1.0,
                       "projection_evidence": {}, "shape": shape}
    cam, spread = combine_cameras([entry(0.01), entry(0.03), entry(0.02)])
    assert cam["nominal_projection"] == "equisolid" and cam["projection"] == "kannala_brandt"
    assert cam["lens_radial"] == pytest.approx(0.02) and spread["lens_radial"]["max_abs_dev"] == pytest.approx(0.01)
    got = camera_from_calibration(cam)
    want = lens_camera(FisheyeCamera((96, 112), projection="equisolid", cx=58.0, cy=47.0, radius=40.0, up_azimuth_deg=30.0),
                       0.02)
    v1, ok1 = got.pixel_vectors(F64)
    v2, ok2 = want.pixel_vectors(F64)
    assert bool((ok1 == ok2).all()) and torch.allclose(v1[ok1], v2[ok2], atol=1e-12)
    plain, _ = combine_cameras([entry(0.0), entry(0.0)])
    assert plain["projection"] == "equisolid" and "kb_coeffs" not in plain
