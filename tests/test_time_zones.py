"""Timestamps with an IANA time zone name (``TIME ZONE`` and RFC 9557's ``TIME[ZONE]``): offsets against
fixed known values, daylight saving time, clock-change edge cases and the CLI's one-line error."""
from __future__ import annotations

import datetime as dt

import pytest

from skyfit.camera import parse_time, sun_position
from skyfit.cli import main

H = dt.timedelta(hours=1)


@pytest.mark.parametrize("text, offset", [
    ("2013-05-27T12:00:00 America/New_York", -4 * H),        # EDT
    ("2013-05-27T12:00:00[America/New_York]", -4 * H),       # RFC 9557 suffix
    ("2013-01-15T12:00:00 America/New_York", -5 * H),        # EST
    ("2013-01-15T12:00:00[America/New_York]", -5 * H),
    ("2013-05-27 12:00:00 Europe/Berlin", 2 * H),            # CEST, space-separated date and time
    ("2013-12-27T12:00:00[Europe/Berlin]", 1 * H),           # CET
    ("2013-07-01T12:00:00[Australia/Sydney]", 10 * H),       # southern winter: AEST
    ("2013-01-01T12:00:00[Australia/Sydney]", 11 * H),       # southern summer: AEDT
    ("2013-07-01T12:00:00[Asia/Kolkata]", 5.5 * H),          # half-hour zone, no DST
    ("2013-07-01T12:00:00 UTC", 0 * H),
    ("2013-05-27T12:00:00-04:00[America/New_York]", -4 * H),  # offset and zone that agree
    ("2013-05-27T12:00:00[!America/New_York][u-ca=iso8601]", -4 * H),  # critical flag, ignored extension tag
])
def test_zone_offsets(text, offset):
    t = parse_time(text)
    assert t.utcoffset() == offset
    assert t.replace(tzinfo=None) == dt.datetime.fromisoformat(text[:19].replace(" ", "T"))  # wall time kept


def test_zone_and_offset_give_the_same_instant_and_sun():
    a = parse_time("2013-05-27T09:30:00 America/New_York")
    b = parse_time("2013-05-27T09:30:00-04:00")
    assert a == b and a.astimezone(dt.timezone.utc) == dt.datetime(2013, 5, 27, 13, 30, tzinfo=dt.timezone.utc)
    pa, pb = sun_position(a, 40.0, -75.0), sun_position(b, 40.0, -75.0)
    assert float(pa.zenith) == float(pb.zenith) and float(pa.azimuth) == float(pb.azimuth)


def test_clock_changes():
    # New York 2013: spring forward 10 March 02:00 -> 03:00, fall back 3 November 02:00 -> 01:00
    assert parse_time("2013-03-10T01:59:00[America/New_York]").utcoffset() == -5 * H
    assert parse_time("2013-03-10T03:00:00[America/New_York]").utcoffset() == -4 * H
    with pytest.raises(ValueError, match="does not exist"):
        parse_time("2013-03-10T02:30:00[America/New_York]")
    with pytest.raises(ValueError, match="happens twice"):
        parse_time("2013-11-03T01:30:00 America/New_York")
    # the offset chooses between the two 01:30s, an hour apart
    first = parse_time("2013-11-03T01:30:00-04:00[America/New_York]")
    second = parse_time("2013-11-03T01:30:00-05:00[America/New_York]")
    assert second.astimezone(dt.timezone.utc) - first.astimezone(dt.timezone.utc) == H
    with pytest.raises(ValueError, match="not America/New_York's"):
        parse_time("2013-05-27T12:00:00-05:00[America/New_York]")


@pytest.mark.parametrize("text", ["2013-05-27T12:00:00 Mars/Olympus_Mons", "2013-05-27T12:00:00[Not/AZone]",
                                  "2013-05-27T12:00:00[../../etc/passwd]"])
def test_unknown_zone(text):
    with pytest.raises(ValueError, match="unknown time zone"):
        parse_time(text)


def test_unknown_zone_cli_one_line_exit_2(tmp_path, capsys):
    rc = main(["render", "earth", "--out", str(tmp_path / "s.exr"), "--time", "2013-05-27T09:30:00 Mars/Olympus_Mons",
               "--location", "40,-75", "--size", "8"])
    err = capsys.readouterr().err
    assert rc == 2
    assert err.count("\n") == 1 and "--time" in err and "unknown time zone 'Mars/Olympus_Mons'" in err
    assert list(tmp_path.iterdir()) == []


def test_cli_help_names_zones(capsys):
    with pytest.raises(SystemExit):
        main(["render", "--help"])
    assert "America/New_York" in " ".join(capsys.readouterr().out.split())
