"""Sun position: NREL's Solar Position Algorithm (SPA), in numpy float64.

Reda, I. & Andreas, A., "Solar Position Algorithm for Solar Radiation
Applications", NREL/TP-560-34302 (revised January 2008); also Solar Energy
76(5), 577-589 (2004) with the corrigendum in Solar Energy 81(6), 838 (2007).
Equation numbers below are the report's (§3.1-3.14). The algorithm gives the
topocentric solar zenith and azimuth with an uncertainty of ±0.0003° for the
years -2000 to 6000, given the right ΔT and ΔUT1; the periodic-term tables
are the report's Table A4.2 (Earth heliocentric longitude L, latitude B,
radius R; from VSOP87 as abridged by Meeus) and Table A4.3 (nutation).

Times are UTC (the report's UT differs from UTC by ΔUT1 < 0.9 s, a parameter,
0 by default: 0.9 s moves the sun by less than 0.004°). ΔT = TT - UT1 only
enters the ephemeris; a 1 s error in it moves the sun by ~1e-5°.

Conventions (CONTRACT.md): zenith angle from the local vertical, azimuth
clockwise from North (North 0, East 90) — the SPA's own "topocentric azimuth
angle Φ, measured eastward from north", eq. 46. Angles here are degrees, as in
the report, because the callers (CLI, data loaders) speak degrees.
"""
from __future__ import annotations

import dataclasses
import datetime as _dt
import math
import re

import numpy as np

__all__ = [
    "SunPosition",
    "sun_position",
    "julian_day",
    "heliocentric_lbr",
    "nutation",
    "delta_t_espenak_meeus",
    "parse_time",
    "parse_location",
]

# --------------------------------------------------------------------------
# Periodic terms. Each row is A, B, C of the term A cos(B + C * JME) (report
# eq. 9); A in 1e-8 rad (L, B) or 1e-8 AU (R), B in rad, C in rad per Julian
# millennium. Typed from Table A4.2 of NREL/TP-560-34302 (2008).
# --------------------------------------------------------------------------

_L0 = """
175347046 0 0
3341656 4.6692568 6283.07585
34894 4.6261 12566.1517
3497 2.7441 5753.3849
3418 2.8289 3.5231
3136 3.6277 77713.7715
2676 4.4181 7860.4194
2343 6.1352 3930.2097
1324 0.7425 11506.7698
1273 2.0371 529.691
1199 1.1096 1577.3435
990 5.233 5884.927
902 2.045 26.298
857 3.508 398.149
780 1.179 5223.694
753 2.533 5507.553
505 4.583 18849.228
492 4.205 775.523
357 2.92 0.067
317 5.849 11790.629
284 1.899 796.298
271 0.315 10977.079
243 0.345 5486.778
206 4.806 2544.314
205 1.869 5573.143
202 2.458 6069.777
156 0.833 213.299
132 3.411 2942.463
126 1.083 20.775
115 0.645 0.98
103 0.636 4694.003
102 0.976 15720.839
102 4.267 7.114
99 6.21 2146.17
98 0.68 155.42
86 5.98 161000.69
85 1.3 6275.96
85 3.67 71430.7
80 1.81 17260.15
79 3.04 12036.46
75 1.76 5088.63
74 3.5 3154.69
74 4.68 801.82
70 0.83 9437.76
62 3.98 8827.39
61 1.82 7084.9
57 2.78 6286.6
56 4.39 14143.5
56 3.47 6279.55
52 0.19 12139.55
52 1.33 1748.02
51 0.28 5856.48
49 0.49 1194.45
41 5.37 8429.24
41 2.4 19651.05
39 6.17 10447.39
37 6.04 10213.29
37 2.57 1059.38
36 1.71 2352.87
36 1.78 6812.77
33 0.59 17789.85
30 0.44 83996.85
30 2.74 1349.87
25 3.16 4690.48
"""

_L1 = """
628331966747 0 0
206059 2.678235 6283.07585
4303 2.6351 12566.1517
425 1.59 3.523
119 5.796 26.298
109 2.966 1577.344
93 2.59 18849.23
72 1.14 529.69
68 1.87 398.15
67 4.41 5507.55
59 2.89 5223.69
56 2.17 155.42
45 0.4 796.3
36 0.47 775.52
29 2.65 7.11
21 5.34 0.98
19 1.85 5486.78
19 4.97 213.3
17 2.99 6275.96
16 0.03 2544.31
16 1.43 2146.17
15 1.21 10977.08
12 2.83 1748.02
12 3.26 5088.63
12 5.27 1194.45
12 2.08 4694
11 0.77 553.57
10 1.3 6286.6
10 4.24 1349.87
9 2.7 242.73
9 5.64 951.72
8 5.3 2352.87
6 2.65 9437.76
6 4.67 4690.48
"""

_L2 = """
52919 0 0
8720 1.0721 6283.0758
309 0.867 12566.152
27 0.05 3.52
16 5.19 26.3
16 3.68 155.42
10 0.76 18849.23
9 2.06 77713.77
7 0.83 775.52
5 4.66 1577.34
4 1.03 7.11
4 3.44 5573.14
3 5.14 796.3
3 6.05 5507.55
3 1.19 242.73
3 6.12 529.69
3 0.31 398.15
3 2.28 553.57
2 4.38 5223.69
2 3.75 0.98
"""

_L3 = """
289 5.844 6283.076
35 0 0
17 5.49 12566.15
3 5.2 155.42
1 4.72 3.52
1 5.3 18849.23
1 5.97 242.73
"""

_L4 = """
114 3.142 0
8 4.13 6283.08
1 3.84 12566.15
"""

_L5 = """
1 3.14 0
"""

_B0 = """
280 3.199 84334.662
102 5.422 5507.553
80 3.88 5223.69
44 3.7 2352.87
32 4 1577.34
"""

_B1 = """
9 3.9 5507.55
6 1.73 5223.69
"""

_R0 = """
100013989 0 0
1670700 3.0984635 6283.07585
13956 3.05525 12566.1517
3084 5.1985 77713.7715
1628 1.1739 5753.3849
1576 2.8469 7860.4194
925 5.453 11506.77
542 4.564 3930.21
472 3.661 5884.927
346 0.964 5507.553
329 5.9 5223.694
307 0.299 5573.143
243 4.273 11790.629
212 5.847 1577.344
186 5.022 10977.079
175 3.012 18849.228
110 5.055 5486.778
98 0.89 6069.78
86 5.69 15720.84
86 1.27 161000.69
65 0.27 17260.15
63 0.92 529.69
57 2.01 83996.85
56 5.24 71430.7
49 3.25 2544.31
47 2.58 775.52
45 5.54 9437.76
43 6.01 6275.96
39 5.36 4694
38 2.39 8827.39
37 0.83 19651.05
37 4.9 12139.55
36 1.67 12036.46
35 1.84 2942.46
33 0.24 7084.9
32 0.18 5088.63
32 1.78 398.15
28 1.21 6286.6
28 1.9 6279.55
26 4.59 10447.39
"""

_R1 = """
103019 1.10749 6283.07585
1721 1.0644 12566.1517
702 3.142 0
32 1.02 18849.23
31 2.84 5507.55
25 1.32 5223.69
18 1.42 1577.34
10 5.91 10977.08
9 1.42 6275.96
9 0.27 5486.78
"""

_R2 = """
4359 5.7846 6283.0758
124 5.579 12566.152
12 3.14 0
9 3.63 77713.77
6 1.87 5573.14
3 5.47 18849.23
"""

_R3 = """
145 4.273 6283.076
7 3.92 12566.15
"""

_R4 = """
4 2.56 6283.08
"""

# Nutation, Table A4.3: multipliers of X0..X4 (eqs. 15-19), then the
# coefficients a, b (Δψ, in 0.0001 arcsec and per Julian century) and c, d
# (Δε), eqs. 20-21.
_NUTATION = """
0 0 0 0 1 -171996 -174.2 92025 8.9
-2 0 0 2 2 -13187 -1.6 5736 -3.1
0 0 0 2 2 -2274 -0.2 977 -0.5
0 0 0 0 2 2062 0.2 -895 0.5
0 1 0 0 0 1426 -3.4 54 -0.1
0 0 1 0 0 712 0.1 -7 0
-2 1 0 2 2 -517 1.2 224 -0.6
0 0 0 2 1 -386 -0.4 200 0
0 0 1 2 2 -301 0 129 -0.1
-2 -1 0 2 2 217 -0.5 -95 0.3
-2 0 1 0 0 -158 0 0 0
-2 0 0 2 1 129 0.1 -70 0
0 0 -1 2 2 123 0 -53 0
2 0 0 0 0 63 0 0 0
0 0 1 0 1 63 0.1 -33 0
2 0 -1 2 2 -59 0 26 0
0 0 -1 0 1 -58 -0.1 32 0
0 0 1 2 1 -51 0 27 0
-2 0 2 0 0 48 0 0 0
0 0 -2 2 1 46 0 -24 0
2 0 0 2 2 -38 0 16 0
0 0 2 2 2 -31 0 13 0
0 0 2 0 0 29 0 0 0
-2 0 1 2 2 29 0 -12 0
0 0 0 2 0 26 0 0 0
-2 0 0 2 0 -22 0 0 0
0 0 -1 2 1 21 0 -10 0
0 2 0 0 0 17 -0.1 0 0
2 0 -1 0 1 16 0 -8 0
-2 2 0 2 2 -16 0.1 7 0
0 1 0 0 1 -15 0 9 0
-2 0 1 0 1 -13 0 7 0
0 -1 0 0 1 -12 0 6 0
0 0 2 -2 0 11 0 0 0
2 0 -1 2 1 -10 0 5 0
2 0 1 2 2 -8 0 3 0
0 1 0 2 2 7 0 -3 0
-2 1 1 0 0 -7 0 0 0
0 -1 0 2 2 -7 0 3 0
2 0 0 2 1 -7 0 3 0
2 0 1 0 0 6 0 0 0
-2 0 2 2 2 6 0 -3 0
-2 0 1 2 1 6 0 -3 0
2 0 -2 0 1 -6 0 3 0
2 0 0 0 1 -6 0 3 0
0 -1 1 0 0 5 0 0 0
-2 -1 0 2 1 -5 0 3 0
-2 0 0 0 1 -5 0 3 0
0 0 2 2 1 -5 0 3 0
-2 0 2 0 1 4 0 0 0
-2 1 0 2 1 4 0 0 0
0 0 1 -2 0 4 0 0 0
-1 0 1 0 0 -4 0 0 0
-2 1 0 0 0 -4 0 0 0
1 0 0 0 0 -4 0 0 0
0 0 1 2 0 3 0 0 0
0 0 -2 2 2 -3 0 0 0
-1 -1 1 0 0 -3 0 0 0
0 1 1 0 0 -3 0 0 0
0 -1 1 2 2 -3 0 0 0
2 -1 -1 2 2 -3 0 0 0
0 0 3 2 2 -3 0 0 0
2 -1 0 2 2 -3 0 0 0
"""


def _table(text: str) -> np.ndarray:
    return np.array([[float(v) for v in line.split()] for line in text.strip().splitlines()])


_L_TABLES = tuple(_table(t) for t in (_L0, _L1, _L2, _L3, _L4, _L5))
_B_TABLES = tuple(_table(t) for t in (_B0, _B1))
_R_TABLES = tuple(_table(t) for t in (_R0, _R1, _R2, _R3, _R4))
_NUT = _table(_NUTATION)
_NUT_Y, _NUT_ABCD = _NUT[:, :5], _NUT[:, 5:]

EARTH_EQUATORIAL_RADIUS_M: float = 6378140.0
"""Earth's equatorial radius used by the SPA's parallax terms [m]. Report eqs. 38-40."""

ATMOS_REFRACT_DEG: float = 0.5667
"""Refraction of the sun at the horizon, the SPA's default [deg]. Report §3.14.1."""

SUN_RADIUS_DEG: float = 0.26667
"""Apparent solar radius used by the SPA's refraction switch [deg]. Report §3.14.1."""


# --------------------------------------------------------------------------
# Time
# --------------------------------------------------------------------------

_SUFFIX = re.compile(r"^(?P<time>[^\[\]]+?)(?P<tags>(?:\[[^\[\]]*\])+)$")
"""An RFC 9557 timestamp: ISO 8601 followed by bracketed suffixes, ``...[America/New_York][u-ca=iso8601]``."""
_TIME_HELP = ("use ISO 8601 with a UTC offset or a time zone name, e.g. 2013-05-27T09:30:00-04:00, "
              "2013-05-27T09:30:00 America/New_York or 2013-05-27T09:30:00[America/New_York]")


def _zone(name: str):
    """The IANA time zone ``name`` (zoneinfo, with the tzdata package where the system has no database)."""
    import zoneinfo

    try:
        return zoneinfo.ZoneInfo(name)
    except (zoneinfo.ZoneInfoNotFoundError, ValueError, OSError):
        raise ValueError(f"unknown time zone {name!r}; use an IANA name such as America/New_York or Europe/Berlin, "
                         "or a UTC offset such as -04:00") from None


def _split_zone(text: str) -> tuple[str, str | None]:
    """(ISO 8601 part, zone name or None) of ``TIME ZONE`` or RFC 9557's ``TIME[ZONE]`` (extension tags
    ``[key=value]`` are ignored unless marked critical with ``!``)."""
    m = _SUFFIX.match(text)
    if m:
        zone = None
        for tag in re.findall(r"\[([^\[\]]*)\]", m["tags"]):
            critical, tag = tag.startswith("!"), tag.lstrip("!")
            if "=" in tag:
                if critical:
                    raise ValueError(f"timestamp {text!r}: unsupported critical suffix tag [!{tag}]")
                continue
            if zone is not None or not tag:
                raise ValueError(f"timestamp {text!r}: {'two time zones' if tag else 'empty time zone'} in the suffix")
            zone = tag
        return m["time"].strip(), zone
    head, _, tail = text.rpartition(" ")
    if head and tail and any(c.isalpha() for c in tail):
        return head.strip(), tail
    return text, None


def _localize(value: _dt.datetime, tz, text: str) -> _dt.datetime:
    """``value`` (naive wall time, or aware with the offset written beside the zone) in zone ``tz``.

    A wall time that the zone skips (spring forward) is an error; one it repeats (fall back) needs
    the offset (RFC 9557: ``2013-11-03T01:30:00-05:00[America/New_York]``)."""
    wall = value.replace(tzinfo=None)
    options = {}
    for fold in (0, 1):
        t = wall.replace(tzinfo=tz, fold=fold)
        if t.astimezone(_dt.timezone.utc).astimezone(tz).replace(tzinfo=None) == wall:  # a wall time that exists
            options.setdefault(t.utcoffset(), t)
    if not options:
        raise ValueError(f"timestamp {text!r}: {wall.isoformat()} does not exist in {tz.key} (skipped by a clock change)")
    if value.tzinfo is not None:
        if value.utcoffset() not in options:
            have = ", ".join(_offset_text(o) for o in options)
            raise ValueError(f"timestamp {text!r}: offset {_offset_text(value.utcoffset())} is not {tz.key}'s ({have}) "
                             f"at {wall.isoformat()}")
        return options[value.utcoffset()]
    if len(options) > 1:
        have = " or ".join(_offset_text(o) for o in options)
        raise ValueError(f"timestamp {text!r}: {wall.isoformat()} happens twice in {tz.key} (clock change: {have}); "
                         f"write the offset, e.g. {wall.isoformat()}{_offset_text(next(iter(options)))}[{tz.key}]")
    return next(iter(options.values()))


def _offset_text(off: _dt.timedelta) -> str:
    m = round(off.total_seconds() / 60)
    return f"{'-' if m < 0 else '+'}{abs(m) // 60:02d}:{abs(m) % 60:02d}"


def parse_time(value, utc_offset_hours: float | None = None) -> _dt.datetime:
    """One timestamp as an aware datetime.

    Args:
        value: an aware ``datetime``; a naive ``datetime`` with
            ``utc_offset_hours``; or an ISO 8601 string with a UTC offset
            (``2013-05-27T09:30:00-04:00``, ``...Z``) or an IANA time zone name,
            after a space (``2013-05-27T09:30:00 America/New_York``) or as
            RFC 9557's suffix (``2013-05-27T09:30:00[America/New_York]``, also
            with the offset: ``...-04:00[America/New_York]``). A zone's offset is
            the one in force at that time (daylight saving time from the tz
            database, via zoneinfo). A string without offset or zone needs
            ``utc_offset_hours``.
        utc_offset_hours: offset of local time from UTC for naive input, e.g.
            -4 for EDT. An aware input with a different offset is an error. [h]

    Returns:
        An aware datetime with its own offset (a zone's: the offset in force then).

    Raises:
        ValueError: unparsable text, an unknown zone, a local time the zone skips
            or repeats (without an offset to choose), or a naive time without an offset.
    """
    if isinstance(value, str):
        text = value.strip()
        body, zone = _split_zone(text)
        tz = _zone(zone) if zone is not None else None
        try:
            value = _dt.datetime.fromisoformat(body)
        except ValueError:
            raise ValueError(f"cannot parse timestamp {text!r}; {_TIME_HELP}") from None
        if tz is not None:  # as a fixed offset: arithmetic between two results is then exact across clock changes
            local = _localize(value, tz, text)
            value = local.replace(tzinfo=_dt.timezone(local.utcoffset()), fold=0)
    elif isinstance(value, np.datetime64):
        value = value.astype("datetime64[us]").astype(_dt.datetime)
    if not isinstance(value, _dt.datetime):
        raise ValueError(f"not a timestamp: {value!r}")
    if utc_offset_hours is not None:
        off = float(utc_offset_hours)
        if not math.isfinite(off) or abs(off) > 18:
            raise ValueError(f"UTC offset {utc_offset_hours!r} h is outside [-18, 18]")
        tz = _dt.timezone(_dt.timedelta(hours=off))
        if value.tzinfo is None:
            return value.replace(tzinfo=tz)
        if value.utcoffset() != tz.utcoffset(None):
            raise ValueError(f"timestamp {value.isoformat()} carries offset {value.utcoffset()}, "
                             f"which contradicts the given UTC offset {off:+g} h")
        return value
    if value.tzinfo is None or value.utcoffset() is None:
        raise ValueError(f"timestamp {value.isoformat()} has no UTC offset; add one (e.g. +00:00) "
                         "or give the UTC offset explicitly")
    return value


def _as_time_list(times, utc_offset_hours) -> tuple[list[_dt.datetime], tuple[int, ...]]:
    if isinstance(times, (str, _dt.datetime, np.datetime64)):
        return [parse_time(times, utc_offset_hours)], ()
    arr = np.asarray(times, dtype=object) if not isinstance(times, np.ndarray) else times
    shape = arr.shape
    return [parse_time(t, utc_offset_hours) for t in np.ravel(arr)], shape


def julian_day(times, utc_offset_hours: float | None = None, delta_ut1: float = 0.0) -> np.ndarray:
    """Julian Day (UT1) of timestamps, report eq. 4 (proleptic Gregorian calendar).

    Args:
        times: a timestamp or an array-like of them (see ``parse_time``).
        utc_offset_hours: for naive inputs. [h]
        delta_ut1: UT1 - UTC. [s]

    Returns:
        Julian Day, float64, shape of ``times`` (() for one). [day]
    """
    items, shape = _as_time_list(times, utc_offset_hours)
    out = np.empty(len(items))
    for i, t in enumerate(items):
        u = t.astimezone(_dt.timezone.utc)
        y, m = u.year, u.month
        if m <= 2:
            y, m = y - 1, m + 12
        secs = u.hour * 3600 + u.minute * 60 + u.second + u.microsecond * 1e-6 + delta_ut1
        d = u.day + secs / 86400.0
        a = y // 100
        b = 2 - a + a // 4  # Gregorian correction
        out[i] = math.floor(365.25 * (y + 4716)) + math.floor(30.6001 * (m + 1)) + d + b - 1524.5
    return out.reshape(shape)


def delta_t_espenak_meeus(decimal_year) -> np.ndarray:
    """ΔT = TT - UT1 from the polynomials of Espenak & Meeus (NASA, "Five
    Millennium Canon of Solar Eclipses", 2006, §2.6), 1900-2150.

    Args:
        decimal_year: year + (month - 0.5) / 12 as in the source, shape (...). [yr]

    Returns:
        ΔT, shape (...). [s] Observed values are within ~1 s before 2020.

    Raises:
        ValueError: outside 1900-2150 (pass an explicit ΔT there).
    """
    y = np.asarray(decimal_year, dtype=float)
    if np.any((y < 1900) | (y >= 2150)):
        raise ValueError("the Espenak & Meeus ΔT polynomials used here cover 1900-2150; pass delta_t explicitly")
    out = np.empty_like(y)
    t = y - 1900
    s = y < 1920
    out[s] = -2.79 + 1.494119 * t[s] - 0.0598939 * t[s] ** 2 + 0.0061966 * t[s] ** 3 - 0.000197 * t[s] ** 4
    t = y - 1920
    s = (y >= 1920) & (y < 1941)
    out[s] = 21.20 + 0.84493 * t[s] - 0.076100 * t[s] ** 2 + 0.0020936 * t[s] ** 3
    t = y - 1950
    s = (y >= 1941) & (y < 1961)
    out[s] = 29.07 + 0.407 * t[s] - t[s] ** 2 / 233 + t[s] ** 3 / 2547
    t = y - 1975
    s = (y >= 1961) & (y < 1986)
    out[s] = 45.45 + 1.067 * t[s] - t[s] ** 2 / 260 - t[s] ** 3 / 718
    t = y - 2000
    s = (y >= 1986) & (y < 2005)
    out[s] = (63.86 + 0.3345 * t[s] - 0.060374 * t[s] ** 2 + 0.0017275 * t[s] ** 3
              + 0.000651814 * t[s] ** 4 + 0.00002373599 * t[s] ** 5)
    s = (y >= 2005) & (y < 2050)
    out[s] = 62.92 + 0.32217 * t[s] + 0.005589 * t[s] ** 2
    s = y >= 2050
    out[s] = -20 + 32 * ((y[s] - 1820) / 100) ** 2 - 0.5628 * (2150 - y[s])
    return out


# --------------------------------------------------------------------------
# Ephemeris
# --------------------------------------------------------------------------

def _series(tables, jme: np.ndarray) -> np.ndarray:
    """Sum_i jme^i * Sum_rows A cos(B + C jme) / 1e8 (report eqs. 9-11)."""
    total = np.zeros_like(jme)
    for power, tab in enumerate(tables):
        terms = tab[:, 0] * np.cos(tab[:, 1] + tab[:, 2] * jme[..., None])
        total = total + terms.sum(-1) * jme**power
    return total / 1e8


def heliocentric_lbr(jme) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Earth's heliocentric longitude, latitude and radius (report §3.2).

    Args:
        jme: Julian ephemeris millennium from J2000, shape (...). [millennium]

    Returns:
        L in [0, 360) [deg], B [deg], R [AU], each shape (...).
    """
    jme = np.asarray(jme, dtype=float)
    lon = np.degrees(_series(_L_TABLES, jme)) % 360.0
    lat = np.degrees(_series(_B_TABLES, jme))
    rad = _series(_R_TABLES, jme)
    return lon, lat, rad


def nutation(jce) -> tuple[np.ndarray, np.ndarray]:
    """Nutation in longitude and obliquity (report §3.4, eqs. 15-23).

    Args:
        jce: Julian ephemeris century from J2000, shape (...). [century]

    Returns:
        Δψ, Δε, each shape (...). [deg]
    """
    t = np.asarray(jce, dtype=float)
    x = np.stack([
        297.85036 + 445267.111480 * t - 0.0019142 * t**2 + t**3 / 189474,  # mean elongation Moon-Sun
        357.52772 + 35999.050340 * t - 0.0001603 * t**2 - t**3 / 300000,  # mean anomaly Sun
        134.96298 + 477198.867398 * t + 0.0086972 * t**2 + t**3 / 56250,  # mean anomaly Moon
        93.27191 + 483202.017538 * t - 0.0036825 * t**2 + t**3 / 327270,  # Moon's argument of latitude
        125.04452 - 1934.136261 * t + 0.0020708 * t**2 + t**3 / 450000,  # Moon's ascending node
    ], axis=-1)
    arg = np.radians(x @ _NUT_Y.T)  # (..., 63)
    a, b, c, d = (_NUT_ABCD[:, k] for k in range(4))
    dpsi = ((a + b * t[..., None]) * np.sin(arg)).sum(-1) / 36e6
    deps = ((c + d * t[..., None]) * np.cos(arg)).sum(-1) / 36e6
    return dpsi, deps


@dataclasses.dataclass(frozen=True)
class SunPosition:
    """Topocentric sun position; arrays of the shape of the input times.

    Attributes:
        zenith: topocentric zenith angle, refracted if requested. [deg]
        azimuth: clockwise from North (East 90), in [0, 360). [deg]
        distance_au: Earth-Sun distance R. [AU]
        zenith_geometric: zenith angle without refraction. [deg]
        julian_day: UT1 Julian Day. [day]
    """

    zenith: np.ndarray
    azimuth: np.ndarray
    distance_au: np.ndarray
    zenith_geometric: np.ndarray
    julian_day: np.ndarray


def _check_site(latitude, longitude, elevation):
    lat, lon, elev = float(latitude), float(longitude), float(elevation)
    if not (math.isfinite(lat) and -90 <= lat <= 90):
        raise ValueError(f"latitude {latitude!r} is outside [-90, 90] degrees")
    if not (math.isfinite(lon) and -180 <= lon <= 180):
        raise ValueError(f"longitude {longitude!r} is outside [-180, 180] degrees (East positive)")
    if not (math.isfinite(elev) and -500 <= elev <= 10000):
        raise ValueError(f"elevation {elevation!r} m is outside [-500, 10000] m")
    return lat, lon, elev


def sun_position(times, latitude: float, longitude: float, elevation: float = 0.0, *,
                 utc_offset_hours: float | None = None,
                 pressure_pa: float = 101325.0, temperature_c: float = 12.0,
                 refraction: bool = True, delta_t: float | None = None,
                 delta_ut1: float = 0.0, atmos_refract: float = ATMOS_REFRACT_DEG) -> SunPosition:
    """Topocentric solar zenith and azimuth by NREL's SPA (Reda & Andreas 2008).

    Args:
        times: a timestamp or array-like of them: aware datetimes, ISO 8601
            strings with offset, or naive values with ``utc_offset_hours``.
        latitude: geodetic, North positive. [deg]
        longitude: East positive. [deg]
        elevation: above sea level. [m]
        utc_offset_hours: offset of naive local times from UTC (-4 for EDT). [h]
        pressure_pa: local pressure for refraction (annual mean). [Pa]
        temperature_c: local temperature for refraction (annual mean). [°C]
        refraction: apply the SPA's refraction (eq. 42); False gives the
            geometric (airless) zenith.
        delta_t: TT - UT1; None uses ``delta_t_espenak_meeus``. [s]
        delta_ut1: UT1 - UTC. [s]
        atmos_refract: refraction at sunrise; below -(0.26667° + this) no
            refraction is applied (report §3.14.1). [deg]

    Returns:
        SunPosition with arrays of the shape of ``times``.
    """
    lat, lon, elev = _check_site(latitude, longitude, elevation)
    items, shape = _as_time_list(times, utc_offset_hours)
    jd = julian_day(items, None, delta_ut1)
    if delta_t is None:
        utc = [t.astimezone(_dt.timezone.utc) for t in items]
        delta_t_arr = delta_t_espenak_meeus(np.array([u.year + (u.month - 0.5) / 12 for u in utc]))
    else:
        delta_t_arr = np.full(len(items), float(delta_t))
    jde = jd + delta_t_arr / 86400.0  # eq. 5
    jc = (jd - 2451545.0) / 36525.0  # eq. 6
    jce = (jde - 2451545.0) / 36525.0  # eq. 7
    jme = jce / 10.0  # eq. 8

    lon_h, lat_h, r = heliocentric_lbr(jme)
    theta = (lon_h + 180.0) % 360.0  # geocentric longitude, eq. 13
    beta = -lat_h  # eq. 14
    dpsi, deps = nutation(jce)
    u = jme / 10.0
    eps0 = (84381.448 - 4680.93 * u - 1.55 * u**2 + 1999.25 * u**3 - 51.38 * u**4 - 249.67 * u**5
            - 39.05 * u**6 + 7.12 * u**7 + 27.87 * u**8 + 5.79 * u**9 + 2.45 * u**10)  # eq. 24 [arcsec]
    eps = eps0 / 3600.0 + deps  # eq. 25
    dtau = -20.4898 / (3600.0 * r)  # aberration, eq. 26
    lam = theta + dpsi + dtau  # apparent sun longitude, eq. 27
    nu0 = (280.46061837 + 360.98564736629 * (jd - 2451545.0) + 0.000387933 * jc**2
           - jc**3 / 38710000.0) % 360.0  # eq. 28
    nu = nu0 + dpsi * np.cos(np.radians(eps))  # eq. 29
    lam_r, eps_r, beta_r = np.radians(lam), np.radians(eps), np.radians(beta)
    alpha = np.degrees(np.arctan2(np.sin(lam_r) * np.cos(eps_r) - np.tan(beta_r) * np.sin(eps_r),
                                  np.cos(lam_r))) % 360.0  # eq. 30
    delta = np.degrees(np.arcsin(np.sin(beta_r) * np.cos(eps_r)
                                 + np.cos(beta_r) * np.sin(eps_r) * np.sin(lam_r)))  # eq. 31
    h = (nu + lon - alpha) % 360.0  # local hour angle, eq. 32

    # Topocentric correction (parallax), eqs. 33-40.
    xi = np.radians(8.794 / (3600.0 * r))
    phi = math.radians(lat)
    uu = math.atan(0.99664719 * math.tan(phi))
    x = math.cos(uu) + elev / EARTH_EQUATORIAL_RADIUS_M * math.cos(phi)
    y = 0.99664719 * math.sin(uu) + elev / EARTH_EQUATORIAL_RADIUS_M * math.sin(phi)
    h_r, delta_r = np.radians(h), np.radians(delta)
    denom = np.cos(delta_r) - x * np.sin(xi) * np.cos(h_r)
    dalpha = np.arctan2(-x * np.sin(xi) * np.sin(h_r), denom)  # eq. 38 [rad]
    delta_p = np.arctan2((np.sin(delta_r) - y * np.sin(xi)) * np.cos(dalpha), denom)  # eq. 39 [rad]
    h_p = h_r - dalpha  # eq. 40 [rad]

    # Topocentric zenith and azimuth, eqs. 41-46.
    e0 = np.degrees(np.arcsin(math.sin(phi) * np.sin(delta_p) + math.cos(phi) * np.cos(delta_p) * np.cos(h_p)))
    if refraction:
        p_mbar = float(pressure_pa) / 100.0
        de = ((p_mbar / 1010.0) * (283.0 / (273.0 + float(temperature_c)))
              * 1.02 / (60.0 * np.tan(np.radians(e0 + 10.3 / (e0 + 5.11)))))
        de = np.where(e0 >= -(SUN_RADIUS_DEG + atmos_refract), de, 0.0)
    else:
        de = np.zeros_like(e0)
    zen = 90.0 - (e0 + de)
    gamma = np.degrees(np.arctan2(np.sin(h_p), np.cos(h_p) * math.sin(phi) - np.tan(delta_p) * math.cos(phi)))
    azi = (gamma + 180.0) % 360.0
    rs = lambda a: np.asarray(a, dtype=float).reshape(shape)  # noqa: E731
    return SunPosition(zenith=rs(zen), azimuth=rs(azi), distance_au=rs(r), zenith_geometric=rs(90.0 - e0),
                       julian_day=rs(jd))


# --------------------------------------------------------------------------
# CLI parsing
# --------------------------------------------------------------------------

_NUM = r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?"


def parse_location(text: str) -> tuple[float, float, float]:
    """Parse ``"LAT,LON[,ELEV]"`` (degrees North, degrees East, metres; ELEV 0 by default).

    Raises:
        ValueError: one-line message for malformed text or out-of-range values.
    """
    parts = [p.strip() for p in str(text).split(",")]
    if len(parts) not in (2, 3) or not all(re.fullmatch(_NUM, p) for p in parts):
        raise ValueError(f"location {text!r} is not LAT,LON[,ELEV] (degrees North, degrees East, metres)")
    vals = [float(p) for p in parts] + ([0.0] if len(parts) == 2 else [])
    return _check_site(*vals)
