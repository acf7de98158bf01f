"""The sun's detected position as a datum of a photo fit (skyfit.fit.photo.sun_datum, PhotoProblem.sun_penalty).

References are independent of the penalty's own path: the separation reported in RESULT.json is computed by
:func:`skyfit.fit.photo.fitted_camera` (a FisheyeCamera built from rotation matrices), the penalty by
:func:`skyfit.fit.model.tilt_directions` on the detected pixel's direction and the fitted sun.
"""
from __future__ import annotations

import math
import types

import numpy as np
import pytest
import torch

from skyfit.camera.autocal import SunDetection
from skyfit.camera.fisheye import FisheyeCamera, zenith_azimuth_to_enu
from skyfit.fit import photo as fp

F64 = torch.float64
SUN_ZEN, SUN_AZ = 40.0, 120.0


def _t(v):
    return torch.tensor(float(v), dtype=F64)


def _fake_problem(datum):
    """What sun_penalty reads of a PhotoProblem: the datum and the fitted sun (SPA's plus the heading)."""
    def sun_vectors(phys, i):
        return zenith_azimuth_to_enu(_t(math.radians(SUN_ZEN)), _t(math.radians(SUN_AZ)) + phys["sun_azimuth_offset"])
    return types.SimpleNamespace(sun=datum, sun_vectors=sun_vectors)


def _camera(projection="equidistant"):
    return FisheyeCamera(size=(240, 260), projection=projection, cx=131.0, cy=117.0, radius=100.0, up_azimuth_deg=35.0)


def _detection(cam, zen=SUN_ZEN + 1.3, az=SUN_AZ - 2.0, **kw):
    """A detection 1-2 deg off the computed sun, as an untilted guess camera leaves it."""
    with torch.no_grad():
        x, y = cam.direction_to_pixel(zenith_azimuth_to_enu(_t(math.radians(zen)), _t(math.radians(az))))
    return SunDetection(float(x), float(y), kw.pop("radius_px", 2.0), kw.pop("saturated", True), 12, **kw)


def _separation_reported(cam, det, off, tn, te):
    """RESULT.json's separation: the detected pixel under the fitted camera against SPA's sun. [deg]"""
    fitted = fp.fitted_camera(cam, off, tn, te)
    with torch.no_grad():
        d = fitted.pixel_to_direction(_t(det.x), _t(det.y)).numpy()
    s = zenith_azimuth_to_enu(_t(math.radians(SUN_ZEN)), _t(math.radians(SUN_AZ))).numpy()
    return math.degrees(math.atan2(np.linalg.norm(np.cross(d, s)), float(np.dot(d, s))))


@pytest.mark.parametrize("projection", ["equidistant", "orthographic", "stereographic"])
def test_penalty_is_the_reported_separation(projection):
    """0.5 (chord / sigma)^2 with chord = 2 sin(separation / 2) of the separation photo_result reports, for any
    heading and tilt (to 1e-9 deg)."""
    cam = _camera(projection)
    det = _detection(cam)
    datum = fp.sun_datum(cam, det)
    assert datum.sigma_deg == fp.SUN_DATUM_SIGMA_DEG
    prob = _fake_problem(datum)
    rng = np.random.default_rng(3)
    for off, tn, te in [(0.0, 0.0, 0.0), *rng.uniform(-0.06, 0.06, (6, 3))]:
        phys = {"sun_azimuth_offset": _t(off), "camera_tilt_north": _t(tn), "camera_tilt_east": _t(te)}
        pen = float(fp.PhotoProblem.sun_penalty(prob, phys))
        chord = math.sqrt(2.0 * pen) * math.radians(datum.sigma_deg)
        sep = math.degrees(2.0 * math.asin(chord / 2.0))
        assert sep == pytest.approx(_separation_reported(cam, det, off, tn, te), abs=1e-9)
        # sun_separation_deg (the lens refit's check) reads the same penalty at x
        prob.param = types.SimpleNamespace(to_physical=lambda x, p=phys: p)
        prob.sun_penalty = lambda p, prob=prob: fp.PhotoProblem.sun_penalty(prob, p)
        assert fp.sun_separation_deg(prob, None) == pytest.approx(sep, abs=1e-9)


def test_penalty_alone_puts_the_sun_on_the_detection():
    """Minimising the datum alone over heading and tilt (L-BFGS, autograd) brings the reported separation from
    1.8 deg to < 0.01 deg: the gradient points the right way in all three values."""
    cam = _camera()
    det = _detection(cam)
    prob = _fake_problem(fp.sun_datum(cam, det))
    v = torch.zeros(3, dtype=F64, requires_grad=True)
    opt = torch.optim.LBFGS([v], max_iter=200, tolerance_grad=1e-14, tolerance_change=1e-16, line_search_fn="strong_wolfe")

    def closure():
        opt.zero_grad()
        loss = fp.PhotoProblem.sun_penalty(prob, {"sun_azimuth_offset": v[0], "camera_tilt_north": v[1],
                                                  "camera_tilt_east": v[2]})
        loss.backward()
        return loss

    before = _separation_reported(cam, det, 0.0, 0.0, 0.0)
    opt.step(closure)
    off, tn, te = (float(a) for a in v.detach())
    assert before > 1.5
    assert _separation_reported(cam, det, off, tn, te) < 0.01


def test_extended_detection_is_weaker():
    """A sun placed in a saturated aureole counts with half the angle its span subtends (here radius_px 30 px
    of an equidistant lens with 100 px per 90 deg: 13.5 deg -> sigma 6.75 deg); no detection, no datum."""
    cam = _camera()
    det = _detection(cam, radius_px=30.0, extended=True)
    datum = fp.sun_datum(cam, det)
    assert datum.sigma_deg == pytest.approx(0.5 * 30.0 * 90.0 / 100.0, rel=0.02)
    assert fp.sun_datum(cam, None) is None
    core = fp.sun_datum(cam, _detection(cam, radius_px=30.0))
    assert core.sigma_deg == fp.SUN_DATUM_SIGMA_DEG
    assert torch.allclose(core.direction, datum.direction)


@pytest.mark.parametrize("tilt", [(0.0, 0.0), (0.012, -0.008)])
def test_lens_from_sun_measures_a_kannala_brandt_lens(tilt):
    """A Kannala-Brandt lens (k1 0.04, f from the same 90-degree circle, tilted by ``tilt``) guessed equidistant: the
    compact sun's pixel lies 1.5-2 deg from where the guess puts the computed sun; lens_from_sun's k (at the true
    heading and tilt) brings the reported separation of the fitted camera (camera_from_result: the Kannala-Brandt
    polynomial of :func:`lens_camera`) below 0.15 deg (the law is first order in k1), and is within 0.01 of k1."""
    tn, te = tilt
    truth_meta = _camera().to_metadata()
    k1, R = 0.04, 100.0
    truth_meta.update(projection="kannala_brandt", focal_px=R / (math.pi / 2 + k1 * (math.pi / 2) ** 3),
                      kb_coeffs=[k1, 0.0, 0.0, 0.0], tilt_deg=[math.degrees(te), math.degrees(tn)])
    truth = FisheyeCamera.from_metadata(truth_meta)
    guess = _camera()
    det = _detection(truth, zen=SUN_ZEN, az=SUN_AZ)
    datum = fp.sun_datum(guess, det)
    phys = {"sun_azimuth_offset": _t(0.0), "camera_tilt_north": _t(tn), "camera_tilt_east": _t(te)}
    prob = _fake_problem(datum)
    prob.param = types.SimpleNamespace(to_physical=lambda x: phys)
    before = _separation_reported(guess, det, 0.0, tn, te)
    k, why = fp.lens_from_sun(prob, None, "equidistant")
    assert before > 1.0 and k is not None and "from the equidistant" in why
    assert k == pytest.approx(k1, abs=0.01)
    fitted = fp.camera_from_result(guess, {"lens_radial": k, "camera_tilt_north": tn, "camera_tilt_east": te})
    with torch.no_grad():
        d = fitted.pixel_to_direction(_t(det.x), _t(det.y)).numpy()
    s = zenith_azimuth_to_enu(_t(math.radians(SUN_ZEN)), _t(math.radians(SUN_AZ))).numpy()
    assert math.degrees(math.atan2(np.linalg.norm(np.cross(d, s)), float(np.dot(d, s)))) < 0.15
    # no measurement where the sun is extended, the lens orthographic, or the miss small
    assert fp.lens_from_sun(prob, None, "orthographic")[0] is None
    wide = _fake_problem(dataclasses_replace(datum, sigma_deg=2.0))
    wide.param = prob.param
    assert fp.lens_from_sun(wide, None, "equidistant")[0] is None
    close = _fake_problem(fp.sun_datum(guess, _detection(guess, zen=SUN_ZEN + 0.3, az=SUN_AZ)))
    close.param = types.SimpleNamespace(to_physical=lambda x: {**phys, "camera_tilt_north": _t(0.0), "camera_tilt_east": _t(0.0)})
    assert fp.lens_from_sun(close, None, "equidistant")[0] is None


def dataclasses_replace(obj, **kw):
    import dataclasses

    return dataclasses.replace(obj, **kw)


def test_prior_strain_is_the_sum_of_squared_z_and_its_chi2_point():
    """The second-basin check of a photo fit: 2 x the camera prior penalty is sum z^2 over gains and saturations
    (log-normal) and vignetting (normal), and its threshold is chi^2's 95 % point with as many degrees of freedom as
    priors (11.07 for a photo fit's five)."""
    from scipy.stats import chi2

    priors = fp.camera_priors(["gain_red", "gain_blue", "vignetting", "mie_g"])
    assert set(priors) == {"gain_red", "gain_blue", "vignetting"}
    phys = {"gain_red": _t(1.48), "gain_blue": _t(0.56), "vignetting": _t(-0.49)}
    strain = 2.0 * float(fp.PhotoProblem.prior_penalty(types.SimpleNamespace(priors=priors), phys))
    mean_v, sig_v = fp.VIGNETTING_PRIOR
    want = ((math.log(1.48) / fp.GAIN_PRIOR_LOG_SIGMA) ** 2 + (math.log(0.56) / fp.GAIN_PRIOR_LOG_SIGMA) ** 2
            + ((-0.49 - mean_v) / sig_v) ** 2)
    limit = chi2.ppf(fp.PRIOR_STRAIN_LEVEL, len(priors))
    assert strain == pytest.approx(want, rel=1e-12) and strain > limit  # synthetic case 12's first fit
    five = fp.camera_priors(fp.PHOTO_FREE)
    assert set(five) == {"gain_red", "gain_blue", "saturation_red", "saturation_blue", "vignetting"}
    assert chi2.ppf(fp.PRIOR_STRAIN_LEVEL, len(five)) == pytest.approx(11.07, abs=0.01)
    phys.update(saturation_red=_t(0.35), saturation_blue=_t(0.82))  # a Foveon's colour rendering adds its share
    more = 2.0 * float(fp.PhotoProblem.prior_penalty(types.SimpleNamespace(priors=five), phys))
    assert more - strain == pytest.approx((math.log(0.35) ** 2 + math.log(0.82) ** 2) / fp.SATURATION_PRIOR_LOG_SIGMA**2,
                                          rel=1e-12)
    assert fp.PROBE_AOD[0] < fp.PROBE_AOD[1]


def test_a_probe_heads_back_only_at_its_trust_bound_toward_the_first_fit():
    """PROBE_HEADS_BACK's test (fit.photo.heads_back): a probe whose first refresh went a full trust step (a factor 2 in
    AOD) toward the first fit's AOD is on its way back; one that stopped short of the bound (a basin near its start),
    moved away from the first fit, or reached past the first fit's AOD is not."""
    two = math.exp(fp.MS_AOD_TRUST)
    assert two == pytest.approx(2.0)
    # the seven probes of session 16's suites: from 0.05 to the bound 0.1 toward 0.24-0.46, from 0.4 to 0.2 toward 0.06-0.11
    for first, start, after in ((0.2814, 0.05, 0.1001), (0.4620, 0.05, 0.1001), (0.2442, 0.05, 0.1000),
                                (0.1095, 0.4, 0.1998), (0.0797, 0.4, 0.1999), (0.0601, 0.4, 0.1998), (0.0989, 0.4, 0.1998)):
        assert fp.heads_back(start, first, after)
    assert not fp.heads_back(0.4, 0.065, 0.48)  # toward a hazy basin, away from the first fit (synthetic case 12's kind)
    assert not fp.heads_back(0.4, 0.065, 0.30)  # stopped inside the trust region: a basin near the probe's start
    assert not fp.heads_back(0.05, 0.08, 0.1)  # past the first fit's AOD: not a step back toward it
    assert not fp.heads_back(0.05, 0.3, 0.1, trust=math.log(3.0))  # short of a wider trust region's bound
