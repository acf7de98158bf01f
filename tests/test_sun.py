"""NREL SPA against the report's worked example and independent checks.

Reda & Andreas, NREL/TP-560-34302 (2008), Table A5.1 (the worked example:
2003-10-17 12:30:30 local time, UTC-7, Golden CO) lists intermediate and final
values; we assert them to the digits the report prints.
"""
import datetime as dt
import math

import numpy as np
import pytest
import torch
from torch.testing import assert_close

from skyfit.camera.sun import (
    delta_t_espenak_meeus,
    heliocentric_lbr,
    julian_day,
    nutation,
    parse_location,
    parse_time,
    sun_position,
)

EXAMPLE = dict(latitude=39.742476, longitude=-105.1786, elevation=1830.14,
               pressure_pa=82000.0, temperature_c=11.0, delta_t=67.0)
EXAMPLE_TIME = "2003-10-17T12:30:30-07:00"
KIDER_SITE = (42.443449, -76.481962, 250.0)


def t(x):
    return torch.as_tensor(np.asarray(x, dtype=np.float64))


def test_julian_day_report_example():
    assert_close(t(julian_day(EXAMPLE_TIME)), t(2452930.312847), atol=5e-7, rtol=0)
    # Naive time plus an explicit offset is the same instant.
    assert_close(t(julian_day(dt.datetime(2003, 10, 17, 12, 30, 30), utc_offset_hours=-7)),
                 t(2452930.312847), atol=5e-7, rtol=0)
    # J2000.0 is JD 2451545.0 (2000-01-01 12:00 TT; here UT, by definition of eq. 4).
    assert_close(t(julian_day("2000-01-01T12:00:00Z")), t(2451545.0), atol=1e-9, rtol=0)


def _example_jce_jme():
    jde = float(julian_day(EXAMPLE_TIME)) + 67.0 / 86400.0
    jce = (jde - 2451545.0) / 36525.0
    return jce, jce / 10.0


def test_periodic_term_tables_report_example():
    jce, jme = _example_jce_jme()
    # The report gives JDE 2452930.313623 and JME 0.003792781991685 (rounded JDE).
    assert_close(t(jme), t(0.003792781991685), atol=2e-12, rtol=0)
    lon, lat, r = heliocentric_lbr(jme)
    # Printed to 1e-10 deg and 1e-10 AU: a mistyped term of the smallest
    # magnitude in Table A4.2 (1e-8 rad = 6e-7 deg) would show.
    assert_close(t(lon), t(24.0182616917), atol=1e-9, rtol=0)
    assert_close(t(lat), t(-0.0001011219), atol=1e-9, rtol=0)
    assert_close(t(r), t(0.9965422974), atol=1e-9, rtol=0)
    dpsi, deps = nutation(jce)
    assert_close(t(dpsi), t(-0.00399840), atol=1e-8, rtol=0)
    assert_close(t(deps), t(0.00166657), atol=1e-8, rtol=0)


def test_topocentric_zenith_azimuth_report_example():
    p = sun_position(EXAMPLE_TIME, **EXAMPLE)
    assert_close(t(p.zenith), t(50.11162), atol=1e-5, rtol=0)
    assert_close(t(p.azimuth), t(194.34024), atol=1e-5, rtol=0)
    # e0 = 39.872046 deg before refraction, Δe = 0.016332 deg (report Table A5.1).
    assert_close(t(p.zenith_geometric), t(90 - 39.872046), atol=1e-6, rtol=0)
    assert_close(t(p.zenith_geometric - p.zenith), t(0.016332), atol=1e-6, rtol=0)
    q = sun_position(EXAMPLE_TIME, **EXAMPLE, refraction=False)
    assert_close(t(q.zenith), t(p.zenith_geometric), atol=1e-12, rtol=0)


def test_vectorised_over_times_matches_scalar_calls():
    times = ["2003-10-17T12:30:30-07:00", "2013-05-27T09:30:00-04:00", "2020-12-21T16:00:00Z"]
    many = sun_position(np.array(times, dtype=object).reshape(3, 1), *KIDER_SITE, delta_t=67.0)
    assert many.zenith.shape == (3, 1)
    for i, s in enumerate(times):
        one = sun_position(s, *KIDER_SITE, delta_t=67.0)
        assert_close(t(many.zenith[i, 0]), t(one.zenith), atol=1e-12, rtol=0)
        assert_close(t(many.azimuth[i, 0]), t(one.azimuth), atol=1e-12, rtol=0)


def test_earth_sun_distance_on_kider_day():
    # ../shared/data/README.md: 1.0133 AU on 2013-05-27.
    p = sun_position("2013-05-27T12:00:00-04:00", *KIDER_SITE)
    assert abs(float(p.distance_au) - 1.0133) < 5e-5


def _meeus_low_precision(jd):
    """Declination and equation of time from Meeus, Astronomical Algorithms
    (2nd ed.), ch. 25 (low accuracy, ~0.01 deg) and eq. 28.3 (Smart's series)."""
    T = (jd - 2451545.0) / 36525.0
    L0 = math.radians((280.46646 + 36000.76983 * T) % 360)
    M = math.radians(357.52911 + 35999.05029 * T)
    e = 0.016708634 - 0.000042037 * T
    C = (1.914602 - 0.004817 * T) * math.sin(M) + 0.019993 * math.sin(2 * M) + 0.000289 * math.sin(3 * M)
    omega = math.radians(125.04 - 1934.136 * T)
    lam = math.radians(math.degrees(L0) + C - 0.00569 - 0.00478 * math.sin(omega))
    eps = math.radians(23.439291 - 0.0130042 * T + 0.00256 * math.cos(omega))
    decl = math.degrees(math.asin(math.sin(eps) * math.sin(lam)))
    y = math.tan(eps / 2) ** 2
    eot_rad = (y * math.sin(2 * L0) - 2 * e * math.sin(M) + 4 * e * y * math.sin(M) * math.cos(2 * L0)
               - 0.5 * y * y * math.sin(4 * L0) - 1.25 * e * e * math.sin(2 * M))
    return decl, math.degrees(eot_rad) * 4  # [deg], [min]


def test_solar_noon_azimuth_south_at_northern_site():
    """At the transit predicted by Meeus's independent low-accuracy formulas,
    the sun is due South at zenith lat - decl."""
    lat, lon, elev = KIDER_SITE
    midnight = dt.datetime(2013, 5, 27, tzinfo=dt.timezone.utc)
    jd_noon = float(julian_day(midnight)) + (12 - lon / 15) / 24
    decl, eot_min = _meeus_low_precision(jd_noon)
    when = midnight + dt.timedelta(minutes=720 - 4 * lon - eot_min)
    p = sun_position(when, lat, lon, elev, refraction=False)
    # ~0.7 deg of azimuth per minute of time at this zenith; Smart's EoT is good to seconds.
    assert abs(float(p.azimuth) - 180.0) < 0.3
    # Parallax (< 0.0025 deg) and the low-accuracy declination (~0.01 deg).
    assert abs(float(p.zenith) - (lat - decl)) < 0.02


def test_delta_t_polynomials_continuous_and_near_observed():
    # Adjacent Espenak & Meeus segments meet within 0.1 s (a typo in a coefficient would break this).
    for y in (1920.0, 1941.0, 1961.0, 1986.0, 2005.0, 2050.0):
        a, b = delta_t_espenak_meeus([y - 1e-9, y])
        assert abs(a - b) < 0.5, y
    # Observed ΔT at 2000.0 is 63.83 s (IERS; Espenak & Meeus Table 2.2 quotes 63.8 s).
    assert abs(float(delta_t_espenak_meeus(2000.0)) - 63.83) < 0.2
    with pytest.raises(ValueError, match="1900-2150"):
        delta_t_espenak_meeus(1850.0)


def test_delta_t_default_changes_little():
    a = sun_position(EXAMPLE_TIME, **{**EXAMPLE, "delta_t": None})
    b = sun_position(EXAMPLE_TIME, **EXAMPLE)
    assert abs(float(a.zenith - b.zenith)) < 1e-3 and abs(float(a.azimuth - b.azimuth)) < 1e-3


def test_parse_time_forms():
    ref = dt.datetime(2013, 5, 27, 13, 30, tzinfo=dt.timezone.utc)
    assert parse_time("2013-05-27T09:30:00-04:00") == ref
    assert parse_time("2013-05-27T13:30:00Z") == ref
    assert parse_time("2013-05-27 09:30:00", utc_offset_hours=-4) == ref
    assert parse_time(dt.datetime(2013, 5, 27, 9, 30), utc_offset_hours=-4) == ref
    with pytest.raises(ValueError, match="no UTC offset"):
        parse_time("2013-05-27T09:30:00")
    with pytest.raises(ValueError, match="cannot parse"):
        parse_time("yesterday")
    with pytest.raises(ValueError, match="contradicts"):
        parse_time("2013-05-27T09:30:00-04:00", utc_offset_hours=-5)


def test_parse_location():
    assert parse_location("42.443449,-76.481962") == (42.443449, -76.481962, 0.0)
    assert parse_location(" 39.742476, -105.1786 , 1830.14") == (39.742476, -105.1786, 1830.14)
    for bad in ("42", "a,b", "1,2,3,4", "95,0", "0,200"):
        with pytest.raises(ValueError):
            parse_location(bad)
