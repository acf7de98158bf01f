"""The synthetic all-sky photo generator (skyfit.tools.photo_synth): its truth must be true.

Small images (96-160 px) and single scattering (TEST_SETTINGS) keep this file fast; the
multiple-scattering default is timed in the module's report, not here.
"""
from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch
from PIL import Image

from skyfit.camera import FisheyeCamera, parse_location, parse_time, sun_position
from skyfit.camera.fisheye import PROJECTIONS, zenith_azimuth_to_enu
from skyfit.camera.srgb import srgb_decode
from skyfit.tools import photo_synth as ps

S = ps.TEST_SETTINGS


def _read(path) -> np.ndarray:
    return np.asarray(Image.open(path)).astype(np.float64)


def _linear(path) -> np.ndarray:
    return srgb_decode(torch.from_numpy(_read(path) / 255.0)).numpy()


@pytest.fixture(scope="module")
def cases(tmp_path_factory):
    """One single photo per projection (sun zenith 30-58°, 2 EV under the metered exposure so that the
    saturated core is the sun's and not the aureole's), made once for the module."""
    root = tmp_path_factory.mktemp("synth")
    out = {}
    for i, proj in enumerate(PROJECTIONS):
        out[proj] = (root / proj, ps.make_case(100 + i, root / proj, size=96, projection=proj,
                                               sun_zenith_deg=30.0 + 7.0 * i, exposure_ev=-2.0, settings=S))
    return out


@pytest.fixture(scope="module")
def bracket(tmp_path_factory):
    root = tmp_path_factory.mktemp("bracket")
    return root, ps.make_case(7, root, size=96, bracket=True, projection="equisolid", sun_zenith_deg=40.0,
                              settings=S)


def test_truth_camera_puts_the_spa_sun_on_the_saturated_core(cases):
    from skimage.measure import label

    for proj, (folder, truth) in cases.items():
        cam = FisheyeCamera.from_metadata(truth["camera"])
        lat, lon, elev = parse_location(truth["location"])
        sp = sun_position(parse_time(truth["time"]), lat, lon, elev)
        sun = zenith_azimuth_to_enu(torch.tensor(math.radians(float(sp.zenith_geometric)), dtype=torch.float64),
                                    torch.tensor(math.radians(float(sp.azimuth)), dtype=torch.float64))
        x, y = (float(v) for v in cam.direction_to_pixel(sun))
        assert math.hypot(x - truth["sun"]["model_px"][0], y - truth["sun"]["model_px"][1]) < 1e-6, proj
        img = _read(folder / "photo.jpg")
        sat = (img >= 250).all(-1)
        lab = label(sat)
        k = lab[int(round(y)), int(round(x))]
        assert k > 0, f"{proj}: the SPA sun's pixel is not saturated"
        rows, cols = np.nonzero(lab == k)
        assert rows.size < 0.25 * sat.size  # a core, not the whole picture
        # the core's centroid on the sphere (a fisheye stretches a big blob unevenly), through the truth camera
        d = cam.pixel_to_direction(torch.from_numpy(cols).double(), torch.from_numpy(rows).double()).mean(0)
        px, py = (float(v) for v in cam.direction_to_pixel(d))
        assert math.hypot(px - x, py - y) < 2.0, proj
        assert math.hypot(cols.mean() - x, rows.mean() - y) < 3.0, proj  # and plainly in the image
        # and the saturated core is where the sun is, not anywhere: the antipode is not saturated
        cx, cy = float(cam.cx), float(cam.cy)
        assert not sat[int(round(2 * cy - y)), int(round(2 * cx - x))]


def test_time_and_location_give_the_asked_sun_zenith():
    rng = np.random.default_rng(5)
    for z in (20.0, 47.3, 80.0):
        tp = ps.find_time_for_zenith(z, rng)
        assert "+" in tp["time"][-6:] or "-" in tp["time"][-6:]  # ISO 8601 with a UTC offset
        t = parse_time(tp["time"])
        assert t.utcoffset() is not None and t.microsecond == 0
        sp = sun_position(t, tp["latitude"], tp["longitude"], tp["elevation"])
        assert abs(float(sp.zenith_geometric) - z) < 0.01
        assert abs(tp["sun"]["zenith_deg"] - z) < 0.01


def test_truth_json_time_location_reproduce_the_sun(cases):
    for folder, truth in cases.values():
        on_disk = json.loads((folder / "truth.json").read_text())
        lat, lon, elev = parse_location(on_disk["location"])
        sp = sun_position(parse_time(on_disk["time"]), lat, lon, elev)
        assert abs(float(sp.zenith_geometric) - on_disk["sun"]["asked_zenith_deg"]) < 0.01
        assert abs(float(sp.azimuth) - on_disk["sun"]["azimuth_deg"]) < 1e-6
        for key in ("mie_aod_550", "mie_angstrom_alpha", "mie_g", "rayleigh_scale"):
            assert key in on_disk["atmosphere"]["parameters"]


def test_obstacle_mask_is_low_and_covers_the_asked_share_of_the_horizon(tmp_path):
    for seed, frac in ((21, 0.33), (22, 0.1)):
        truth = ps.make_case(seed, tmp_path / str(seed), size=160, projection="equidistant",
                             horizon_fraction=frac, sun_zenith_deg=35.0, settings=S)
        cam = FisheyeCamera.from_metadata(truth["camera"])
        mask = np.asarray(Image.open(tmp_path / str(seed) / "mask_truth.png"))
        assert set(np.unique(mask)) <= {0, 64, 255}
        zen, az, valid = cam.pixel_directions()
        zen, az, valid = np.degrees(zen.numpy()), np.degrees(az.numpy()), valid.numpy()
        obstacle = (mask == 255) & valid
        assert np.array_equal(mask == 64, ~valid)
        # every obstacle pixel has some part below 15° elevation: its centre is within half a pixel of it
        half_px = 0.75 * 90.0 / truth["camera"]["r90_px"] * 1.5
        assert (90.0 - zen[obstacle]).max() <= 15.0 + half_px
        assert truth["obstacles"]["max_elevation_deg"] <= 15.0
        # the share of the horizon: from the skyline truth and from the mask's azimuths near the horizon
        assert abs(truth["obstacles"]["horizon_fraction"] - frac) < 0.08
        near = valid & (zen > 80.0) & (zen < 89.0)
        bins = np.floor(az[near]).astype(int) % 360
        hit = np.zeros(360, bool)
        seen = np.zeros(360, bool)
        seen[bins] = True
        hit[bins[obstacle[near]]] = True
        assert abs(hit[seen].mean() - truth["obstacles"]["horizon_fraction"]) < 0.1
        # obstacles are dark but not black (lit like the sky)
        img = _read(tmp_path / str(seed) / "photo.jpg")
        inner = obstacle & (zen < 86.0)
        if inner.sum() > 20:
            sky = (mask == 0) & valid
            assert 2.0 < np.median(img[inner].mean(-1)) < np.median(img[sky].mean(-1))


def test_bracket_frames_agree_once_linearised_and_divided_by_their_exposures(bracket):
    folder, truth = bracket
    frames = truth["frames"]
    assert 3 <= len(frames) <= 7
    rel = [f["relative_exposure"] for f in frames]
    assert all(b > a for a, b in zip(rel, rel[1:]))
    steps = np.log2(np.array(rel[1:]) / np.array(rel[:-1]))
    assert ((steps > 0.9) & (steps < 2.1)).all()  # 1-2 EV, jittered by a few per cent
    # the sun saturates in all but the shortest frame(s): never in the first, always in the last, and
    # once saturated in every longer frame
    sat = [f["sun_saturated"] for f in frames]
    assert not sat[0] and sat[-1] and sat == sorted(sat)
    assert truth["bracket"]["sun_unsaturated_frames"] == [i for i, v in enumerate(sat) if not v]
    img0 = _read(folder / frames[0]["file"])
    cam = FisheyeCamera.from_metadata(truth["camera"])
    sx, sy = truth["sun"]["model_px"]
    assert img0.max() < 250 and img0[int(round(sy)), int(round(sx))].max() > 20
    mask = np.asarray(Image.open(folder / "mask_truth.png"))
    checked = 0
    for a, b in zip(frames, frames[1:]):
        ca, cb = _read(folder / a["file"]), _read(folder / b["file"])
        la, lb = _linear(folder / a["file"]), _linear(folder / b["file"])
        good = (mask == 0) & (ca > 40).all(-1) & (ca < 215).all(-1) & (cb > 40).all(-1) & (cb < 215).all(-1)
        # 4 x 4 blocks wholly good, summed over channels: averages the shot noise, the demosaicing and
        # the JPEG's chroma subsampling down to ~1 %, so what is left would be a wrong exposure ratio
        h4, w4 = good.shape[0] // 4, good.shape[1] // 4
        blk = lambda a: a[: 4 * h4, : 4 * w4].reshape(h4, 4, w4, 4, *a.shape[2:]).sum((1, 3))  # noqa: E731
        ok = blk(good.astype(float)) == 16
        if ok.sum() < 5:
            continue
        sa, sb = blk(la).sum(-1)[ok], blk(lb).sum(-1)[ok]
        log_r = np.log((sb / b["exposure_electrons_per_signal"]) / (sa / a["exposure_electrons_per_signal"]))
        assert abs(np.median(log_r)) < 0.02
        assert 1.4826 * np.median(np.abs(log_r - np.median(log_r))) < 0.03
        # per pixel the scatter is the noise of the shorter frame (shot + read noise, demosaic, JPEG)
        per_px = np.log((lb[good].sum(-1) / b["exposure_electrons_per_signal"])
                        / (la[good].sum(-1) / a["exposure_electrons_per_signal"]))
        assert abs(np.median(per_px)) < 0.03
        # the test can fail: without the exposures the frames disagree by the step
        assert abs(np.median(np.log(sb / sa))) > 0.5
        checked += 1
    assert checked >= 1
    assert cam.shape == (96, 96)


def test_vignetting_at_the_rim_is_within_the_asked_range(cases, tmp_path):
    rims = []
    for folder, truth in cases.values():
        v = truth["vignetting"]
        assert 0.7 <= v["rim_value"] <= 1.0
        assert abs(sum(v["coeffs"]) - v["rim_value"]) < 1e-12  # V(rho = 1)
        vig = np.load(folder / "truth_arrays.npz")["vignetting"]
        cam = FisheyeCamera.from_metadata(truth["camera"])
        x, y = cam.pixel_grid()
        rho = (torch.hypot(x - cam.cx, y - cam.cy) / cam.r90).numpy()
        ring = (rho > 0.97) & (rho <= 1.0)
        assert np.all(vig[ring] >= 0.7 - 1e-6) and np.all(vig[ring] <= 1.0)
        assert abs(vig[ring].min() - v["rim_value"]) < 0.02
        assert abs(vig[np.unravel_index(np.argmin(rho), rho.shape)] - 1.0) < 1e-3  # 1 on the axis
        rims.append(v["rim_value"])
    assert min(rims) < 0.9  # the cases do vignette


def test_reproducible_by_seed(tmp_path, cases):
    folder, truth = cases["orthographic"]
    again = ps.make_case(truth["seed"], tmp_path / "again", size=96, projection="orthographic",
                         sun_zenith_deg=30.0 + 7.0 * 2, exposure_ev=-2.0, settings=S)
    assert (folder / "photo.jpg").read_bytes() == (tmp_path / "again" / "photo.jpg").read_bytes()
    assert (folder / "mask_truth.png").read_bytes() == (tmp_path / "again" / "mask_truth.png").read_bytes()
    strip = lambda t: {k: v for k, v in t.items() if k != "generator"}  # noqa: E731
    assert strip(json.loads(json.dumps(again))) == strip(json.loads(json.dumps(truth)))
    other = ps.make_case(truth["seed"] + 1, tmp_path / "other", size=96, projection="orthographic",
                         sun_zenith_deg=44.0, settings=S)
    assert (tmp_path / "other" / "photo.jpg").read_bytes() != (folder / "photo.jpg").read_bytes()
    assert other["atmosphere"]["parameters"] != truth["atmosphere"]["parameters"]


def test_photo_is_a_jpeg_with_black_outside_and_exif_when_said(cases):
    exif_seen = set()
    for folder, truth in cases.values():
        im = Image.open(folder / "photo.jpg")
        assert im.format == "JPEG" and im.size == (96, 96)
        ifd = im.getexif().get_ifd(0x8769)
        has = 0x829A in ifd
        assert has == truth["sensor"]["exif_exposure_time"]
        if has:
            assert abs(float(ifd[0x829A]) - truth["frames"][0]["exposure_time_s_exif"]) < 1e-9
        exif_seen.add(has)
        assert ifd[0x9003].replace(":", "-", 2).replace(" ", "T") == truth["time"][:19]
        img = _read(folder / "photo.jpg")
        mask = np.asarray(Image.open(folder / "mask_truth.png"))
        assert np.median(img[mask == 64]) < 4
        assert 0.0 <= truth["camera"]["tilt_magnitude_deg"] <= 2.0
        assert 0.40 * 96 - 1e-9 <= truth["camera"]["r90_px"] <= 0.48 * 96 + 1e-9


def test_cameras_and_colour_pipeline():
    for name in ps.CAMERA_SENSITIVITIES:
        wl, s = ps.camera_sensitivities(name)
        assert s.shape == (wl.size, 3) and s.min() >= 0 and abs(s[:, 1].max() - 1) < 1e-12
        pipe = ps.colour_pipeline(name)
        assert np.allclose(pipe["matrix"] @ np.ones(3), 1.0)  # neutral stays neutral
        assert np.all(pipe["daylight_gains"] > 0)
        # a camera is not a CIE observer: its matrix is not the identity
        assert np.abs(pipe["matrix"] - np.eye(3)).max() > 0.05
    with pytest.raises(ValueError, match="unknown camera"):
        ps.camera_sensitivities("Kodak Brownie")


def test_atmosphere_overrides_reach_the_atmosphere():
    atm = ps.make_atmosphere({"mie_aod_550": 0.3, "mie_angstrom_alpha": 1.5, "mie_g": 0.7, "rayleigh_scale": 0.9},
                             "400:700:50")
    base = ps.make_atmosphere({}, "400:700:50")
    lam = atm.wavelengths
    i550 = int(torch.argmin((lam - 550).abs()))
    assert abs(float(atm.mie_extinction[i550] * atm.mie_scale_height) - 0.3) < 1e-9
    ratio = atm.mie_extinction[0] / atm.mie_extinction[-1]
    assert abs(float(ratio) - (400 / 700) ** -1.5) < 1e-9
    assert abs(float(atm.mie_g) - 0.7) < 1e-12
    assert torch.allclose(atm.rayleigh_scattering, 0.9 * base.rayleigh_scattering)


def test_skyline_shapes_and_sun_gap():
    rng = np.random.default_rng(3)
    sl = ps.make_skyline(rng, 0.35, sun_azimuth_deg=100.0, sun_elevation_deg=8.0)
    assert sl["elevation_deg"].max() <= 15.0
    near = np.abs((sl["azimuth_deg"] - 100.0 + 180) % 360 - 180) < 12
    assert sl["elevation_deg"][near].max() <= 5.0 + 1e-12
    assert 0.2 < sl["fraction"] < 0.5
    assert set(s["kind"] for s in sl["segments"]) <= {"trees", "building", "ridge", "mast"}


def test_suite_plan_spreads_projections_brackets_aod_and_sun():
    plan = ps.suite_plan(10, seed=4)
    combos = {(kw["projection"], kw["bracket"]) for kw in plan}
    assert combos == {(p, b) for p in PROJECTIONS for b in (False, True)}
    aod = [kw["aod_550"] for kw in plan]
    assert min(aod) == pytest.approx(0.05) and max(aod) == pytest.approx(0.5)
    zen = [kw["sun_zenith_deg"] for kw in plan]
    assert min(zen) == pytest.approx(20.0) and max(zen) == pytest.approx(80.0)
    assert any(isinstance(kw["size"], tuple) and kw["size"][0] != kw["size"][1] for kw in plan)  # a 3:4 sensor
    assert all(kw["size"] == 300 for kw in plan if kw["bracket"])
    # pairs share the atmosphere and the site's elevation (one Bruneton precomputation), not the sun
    for a, b in zip(plan[::2], plan[1::2]):
        assert all(a[k] == b[k] for k in ("aod_550", "angstrom_alpha", "mie_g", "elevation_m"))
        assert a["sun_zenith_deg"] != b["sun_zenith_deg"]


def test_the_generators_tables_use_its_density_directions():
    """The sky grid's multiple scattering is that of Bruneton tables built with the settings' density directions (the
    generator's finer Delta J, 32 x 64 by default) and the sun's mu_s window: equal to a render from tables precomputed
    directly with them, and
    different from one with 2017's 16 x 32 (small tables and a coarse grid keep it fast)."""
    from skyfit.fit.model import SkyModel
    from skyfit.fit.problem import FitSettings, make_model
    from skyfit.scattering.bruneton_tables import TableSizes
    from skyfit.scattering.multiple import Quadrature, precompute

    sizes = (32, 8, 8, 4, 4, 16, 4, 4)
    values = {"mie_aod_550": 0.3, "mie_angstrom_alpha": 1.3, "mie_g": 0.8, "rayleigh_scale": 1.0}
    base = dict(wavelengths="500:600:100", orders=2, table_sizes=sizes, zenith_step_deg=15.0, azimuth_step_deg=45.0,
                max_zenith_deg=90.0)
    assert ps.SynthSettings().density_directions == (32, 64)
    fine = ps.sky_grid(values, 40.0, ps.SynthSettings(**base, density_directions=(8, 16)))
    coarse = ps.sky_grid(values, 40.0, ps.SynthSettings(**base, density_directions=(4, 8)))
    assert fine.info["density_directions"] == [8, 16]
    atm = ps.make_atmosphere(values, "500:600:100")
    # the tables of one sun: its zenith angle +- 10 deg in 16 texels (SynthSettings.sun_window)
    assert fine.info["sun_window"] == [10.0, 16]
    tables = precompute(atm, orders=2, sizes=TableSizes(*sizes[:6], 16, sizes[7]), progress=False,
                        mu_s_range=(math.cos(math.radians(50.0)), math.cos(math.radians(30.0))),
                        quadrature=Quadrature(ray_rule="gauss", density_theta=8, density_phi=16))
    model = SkyModel(make_model(FitSettings()).integrator, orders=2, multiple="bruneton", table_sizes=sizes, ray_rule="gauss")
    zen = torch.deg2rad(torch.arange(7, dtype=torch.float64) * 15.0)
    daz = torch.deg2rad(torch.arange(5, dtype=torch.float64) * 45.0)
    zz, aa = torch.meshgrid(zen, daz, indexing="ij")
    sun = zenith_azimuth_to_enu(torch.tensor(math.radians(40.0), dtype=torch.float64), torch.tensor(0.0, dtype=torch.float64))
    with torch.no_grad():
        direct = model.renderer(atm, 0.0, tables=tables)(zenith_azimuth_to_enu(zz, aa).reshape(-1, 3), sun)
    torch.testing.assert_close(fine.radiance, direct.reshape(7, 5, -1).clamp(min=0.0), rtol=1e-12, atol=0.0)
    assert float(((coarse.radiance - fine.radiance).abs() / fine.radiance.clamp_min(1e-30)).max()) > 1e-4
