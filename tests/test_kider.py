"""Kider 2014 loader: the data conventions, checked on the files themselves.

Data tests skip when ../shared/data is absent (a fresh clone has none).
Synthetic-folder tests (errors, band averages) run everywhere.
"""
import datetime as dt
import math
from pathlib import Path

import numpy as np
import pytest
import torch
from torch.testing import assert_close

from skyfit.camera.sun import sun_position
from skyfit.io.kider import (
    RING_SLICES,
    KiderError,
    load_kider_capture,
    ring_symmetry_azimuths,
    symmetry_azimuth,
)

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
DAY = DATA / "kider2014" / "2013-05-27"
needs_data = pytest.mark.skipif(not DAY.is_dir(), reason=f"Kider 2014 data not found at {DAY}")


def wrap_deg(a):
    return (np.asarray(a) + 180.0) % 360.0 - 180.0


@pytest.fixture(scope="module")
def captures():
    if not DAY.is_dir():
        pytest.skip(f"Kider 2014 data not found at {DAY}")
    return [load_kider_capture(p) for p in sorted(DAY.iterdir()) if p.is_dir()]


def _raw(capture, index):
    """Independent read of one file with numpy.loadtxt."""
    (f,) = capture.path.glob(f"{capture.name}_-_{index}____*.asd.rad.txt")
    return np.loadtxt(f, skiprows=1)


# --------------------------------------------------------------------------
# Loading
# --------------------------------------------------------------------------

@needs_data
def test_every_capture_of_the_day_loads(captures):
    assert len(captures) == 15  # README: 15 captures, 09:30 to 13:30 (13:00, 13:15 absent)
    for c in captures:
        assert c.radiance.shape == (81, 2151) and c.wavelengths[0] == 350 and c.wavelengths[-1] == 2500
        assert np.all(np.isfinite(c.radiance)) and c.valid.all()
        assert [int(np.sum(c.ring == r)) for r in range(5)] == [32, 24, 16, 8, 1]
        assert abs(c.sun_distance_au - 1.0133) < 5e-5  # README
    c = captures[0]
    ref = _raw(c, 37)
    assert_close(torch.from_numpy(c.radiance[37]), torch.from_numpy(ref[:, 1]), rtol=0, atol=0)
    # File 37 is named azimuth 270 (counter-clockwise) at elevation 33.749 -> West is East.
    f64 = dict(dtype=torch.float64)
    assert_close(torch.tensor(math.degrees(c.view_azimuth[37]), **f64), torch.tensor(90.0, **f64))
    assert_close(torch.tensor(math.degrees(c.view_zenith[37]), **f64), torch.tensor(90 - 33.749, **f64))


@needs_data
def test_time_is_scan_mid_time_from_the_irradiance_log(captures):
    # The log has one line per sample: 81 lines, starting at the folder's time.
    lines = (DATA / "kider2014" / "irradiance" / "2013.05.27.09.30.00.txt").read_text().split("\n")
    stamps = [ln.split()[1] for ln in lines if ln.strip()]
    assert len(stamps) == 81 and stamps[0] == "2013.05.27.09.30.00" and stamps[-1] == "2013.05.27.09.35.43"
    c = captures[0]
    edt = dt.timezone(dt.timedelta(hours=-4))
    assert c.time_source == "irradiance log"
    assert c.time == dt.datetime(2013, 5, 27, 9, 32, 51, 500000, tzinfo=edt)
    assert c.start_time == dt.datetime(2013, 5, 27, 9, 30, tzinfo=edt)
    assert c.sample_times[-1] == dt.datetime(2013, 5, 27, 9, 35, 43, tzinfo=edt)
    # 13:30 has no log (README): nominal timing over the median 342 s scan.
    last = captures[-1]
    assert last.name.endswith("13.30.00") and last.time_source.startswith("nominal") and last.ghi is None
    assert (last.time - last.start_time).total_seconds() == 171.0
    # The sun moves up to ~4 deg in azimuth during a scan (README).
    sweep = [abs(wrap_deg(math.degrees(c.sample_sun_azimuth[-1] - c.sample_sun_azimuth[0]))) for c in captures]
    assert 3.0 < max(sweep) < 4.5


# --------------------------------------------------------------------------
# Convention (a): azimuth counter-clockwise from North in the file names
# --------------------------------------------------------------------------

def test_symmetry_estimator_recovers_a_known_axis():
    phi = np.radians(np.arange(24) * 15.0)
    for axis in (7.3, 101.7, 200.0, 355.55):
        a = math.radians(axis)
        v = 2 * np.exp(np.cos(phi - a)) + 0.3 * np.cos(2 * (phi - a))
        got = math.degrees(symmetry_azimuth(phi, np.log(v)))
        assert abs(wrap_deg(got - axis)) < 0.1, (axis, got)


@needs_data
def test_file_azimuth_is_counter_clockwise_from_north(captures):
    """Read counter-clockwise, each ring's symmetry axis lies near the SPA sun;
    read clockwise, it is far from it whenever the sun is not near the
    North-South line (where the two readings coincide)."""
    offsets = []
    for c in captures:
        sun = math.degrees(c.sun_azimuth)
        ours = np.degrees(ring_symmetry_azimuths(c, rings=(1, 2)))
        offsets.append(wrap_deg(ours - sun))
        band = (c.wavelengths >= 360) & (c.wavelengths <= 720)
        logL = np.log(c.radiance[:, band].mean(1))
        for r in (1, 2):
            sl = RING_SLICES[r]
            cw = math.degrees(symmetry_azimuth(np.radians(c.file_azimuth_deg[sl]), logL[sl]))
            if abs(wrap_deg(sun - 180)) > 40:
                assert abs(wrap_deg(cw - sun)) > 60, (c.name, r, cw, sun)
    offsets = np.array(offsets)  # (15, 2) [deg], ring 1 and ring 2
    assert np.all(np.abs(offsets) < 25), offsets
    # The data's own fact (docs/data.md): the pattern trails the computed sun by
    # 7-21 deg, more in the afternoon than at 09:30.
    assert np.all(offsets < -5), offsets
    assert offsets[-1].mean() < offsets[0].mean() - 8


# --------------------------------------------------------------------------
# Convention (b): sample 0 is systematically wrong
# --------------------------------------------------------------------------

@needs_data
def test_sample0_is_low_and_is_repaired(captures):
    ratios = []
    for c in captures:
        band = (c.wavelengths >= 360) & (c.wavelengths <= 720)
        ring0 = c.radiance[:32, band].mean(1)
        ring0[0] = _raw(c, 0)[band, 1].mean()  # the loaded sample 0 is repaired: use the file
        ratios.append(ring0 / (0.5 * (np.roll(ring0, 1) + np.roll(ring0, -1))))
    ratios = np.array(ratios)  # (15, 32)
    med = np.median(ratios, axis=0)
    # Samples 2..30 (whose neighbours are both ordinary) agree with their neighbours...
    assert np.all(np.abs(med[2:31] - 1) < 0.03), med
    # ...while sample 0 is far below them in most captures.
    assert med[0] < 0.75 and np.sum(ratios[:, 0] < 0.8) >= 12, ratios[:, 0]
    # The loader replaces it by the mean of its ring neighbours 1 and 31.
    for c in captures[:3]:
        assert_close(torch.from_numpy(c.radiance[0]),
                     torch.from_numpy(0.5 * (_raw(c, 1)[:, 1] + _raw(c, 31)[:, 1])), rtol=1e-15, atol=0)
        assert 0 in c.repaired and "31" in c.repaired[0]
    raw = load_kider_capture(captures[2].path, repair_sample0=False)
    assert raw.repaired == {}
    assert_close(torch.from_numpy(raw.radiance[0]), torch.from_numpy(_raw(raw, 0)[:, 1]), rtol=0, atol=0)


@needs_data
def test_noise_model_is_not_optimistic(captures):
    """The random part of the model bounds a robust (MAD) estimate of the
    1 nm noise from second differences, which also holds real spectral
    structure and so over-estimates noise."""
    c = captures[7]
    d2 = c.radiance[:, :-2] - 2 * c.radiance[:, 1:-1] + c.radiance[:, 2:]
    wl = c.wavelengths[1:-1]
    for lo, hi in [(400, 700), (1350, 1400), (1820, 1940)]:
        m = (wl >= lo) & (wl < hi)
        measured = np.median(np.abs(d2[1:, m])) / 0.6745 / math.sqrt(6)
        model = np.median(c.sigma_random[1:, 1:-1][:, m])
        assert 0.5 * measured < model < 3 * measured, (lo, hi, measured, model)


@needs_data
def test_band_average_against_numpy_trapezoid(captures):
    c = captures[0]
    centres, rad, sig = c.band_average(10, 360, 720)
    assert_close(torch.from_numpy(centres), torch.arange(365.0, 720.0, 10.0, dtype=torch.float64))
    raw = _raw(c, 50)
    sel = (raw[:, 0] >= 400) & (raw[:, 0] <= 410)
    want = np.trapezoid(raw[sel, 1], raw[sel, 0]) / 10
    assert_close(torch.tensor(rad[50, 4]), torch.tensor(want), rtol=1e-12, atol=0)
    # Away from the sun only the random part remains (0.2 % per nm over ~10 nm),
    # except for the repaired sample 0 (interpolation error >= 2 %).
    far = np.degrees(c.sun_angle) > 30
    far[0] = False
    assert np.all(sig[0] > 0.02 * rad[0])
    assert np.all(sig > 0) and np.all(sig[far] < 0.002 * rad[far])


# --------------------------------------------------------------------------
# Synthetic folders: errors and exact band averages (no data needed)
# --------------------------------------------------------------------------

RINGS = [(12.1151, [i * 11.25 for i in range(32)]), (33.749, [345.0 - 15 * i for i in range(24)]),
         (53.3665, [22.5 * i for i in range(16)]), (71.9187, [315.0 - 45 * i for i in range(8)]), (90.0, [0.0])]


def _synthetic(tmp_path, spectrum=lambda wl: 0.05 + 1e-5 * wl, name="2013-05-27___10.00.00"):
    folder = tmp_path / "2013-05-27" / name
    folder.mkdir(parents=True)
    wl = np.arange(350, 2501)
    body = "".join(f"{w}\t{float(v)!r}\n" for w, v in zip(wl, spectrum(wl.astype(float))))
    k = 0
    for el, azs in RINGS:
        for az in azs:
            (folder / f"{name}_-_{k}____{az}___{el}.asd.rad.txt").write_text(f"Wavelength\t{name}\n" + body)
            k += 1
    return folder


def test_synthetic_capture_loads_with_nominal_timing(tmp_path):
    c = load_kider_capture(_synthetic(tmp_path))
    assert c.time_source.startswith("nominal") and c.radiance.shape == (81, 2151)
    p = sun_position(c.time, 42.443449, -76.481962, 250.0)
    assert abs(math.degrees(c.sun_zenith) - float(p.zenith)) < 1e-9
    # A linear spectrum averages to its value at each bin centre (any bin width).
    for width, lo, hi in [(10, 360, 720), (11.75, 360, 830), (1, 400, 403)]:
        centres, rad, _ = c.band_average(width, lo, hi)
        assert_close(torch.from_numpy(rad), torch.from_numpy(np.broadcast_to(0.05 + 1e-5 * centres, rad.shape).copy()),
                     rtol=1e-12, atol=0)
    with pytest.raises(KiderError, match="multiple"):
        c.band_average(7, 360, 720)


def test_clear_errors(tmp_path):
    with pytest.raises(KiderError, match="not found"):
        load_kider_capture(tmp_path / "2013-05-27___10.00.00")
    folder = _synthetic(tmp_path)
    odd = tmp_path / "not_a_capture"
    folder.rename(odd)
    with pytest.raises(KiderError, match="not a Kider capture"):
        load_kider_capture(odd)
    odd.rename(folder)
    victim = next(folder.glob("*_-_5____*"))
    text = victim.read_text()
    victim.write_text(text.replace("\n360\t", "\n360\tabc "))
    with pytest.raises(KiderError, match="_-_5____.*non-numeric"):
        load_kider_capture(folder)
    victim.write_text(text.replace("\n360\t", "\n360.5\t"))
    with pytest.raises(KiderError, match="wavelength"):
        load_kider_capture(folder)
    victim.unlink()
    with pytest.raises(KiderError, match="holds 80 .* expected 81"):
        load_kider_capture(folder)
