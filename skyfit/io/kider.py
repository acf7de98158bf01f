"""Kider et al. 2014 clear-sky spectral radiance captures (one scan = one folder).

Kider, Knowlton, Newlin, Li, Greenberg, "A Framework for the Experimental
Comparison of Solar and Skydome Illumination", ACM TOG 33(6), 2014; data from
spectralskylight/sky-measurements-2014 (Apache-2.0). A capture folder
``<date>___<HH.MM.SS>`` holds 81 files
``<capture>_-_<index>____<azimuth>___<elevation>.asd.rad.txt``: a header line,
then ``wavelength<TAB>radiance`` rows, 350-2500 nm every 1 nm, in
W/(m^2 sr nm). The scanner starts at North on the lowest ring (elevation
12.1151°, 32 samples), turns a full circle, then turns back on the next ring
(33.749°, 24), and so on (53.3665°, 16; 71.9187°, 8) up to the zenith.

Conventions checked against the data of 2013-05-27 (tests/test_kider.py,
docs/data.md):

* The azimuth in the file names is counter-clockwise from North (as stated in
  Bruneton's evaluation code, clear-sky-models/atmosphere/measurement/
  measured_atmosphere.cc): read that way, the symmetry axis of rings 1 and 2
  lies 7-21° from the SPA sun azimuth in every capture; read clockwise it lies
  100-170° away in the 10 captures whose sun is > 40° from the North-South
  line (near it the two readings coincide). We convert to CONTRACT.md's clockwise
  azimuth: ``ours = (360 - file) mod 360``.
* The symmetry axis trails the computed sun azimuth by 7-21° (drifting through
  the day), as Bruneton found ("maybe a drift in the measuring instrument");
  ``symmetry_azimuth`` measures it per capture so that a fit can treat the
  instrument's azimuth offset as a nuisance parameter.
* Sample 0 (North, lowest ring) reads 0.63-0.98 (median 0.67; below 0.8 in
  13 of 15 captures) of the mean of its ring neighbours 1 and 31 in 360-720
  nm, with a deficit that grows with wavelength; samples 2-30 of that ring
  read 0.986-1.017 of their neighbours (medians over captures). ``repair_sample0=True`` (default) replaces it by
  the neighbours' mean, as Bruneton does, and records it in ``repaired``.

Timing: each ``irradiance/<Y.m.d.H.M.S>.txt`` pyranometer log beside the date
folder holds 81 ``W/m^2 timestamp`` lines, the first at the folder's time and
the rest ~4.3 s apart over 341-343 s: one per scanned sample. The capture's
``time`` is the scan's mid-time (first + (last - first) / 2), which halves
the worst sun-position error over the scan (the sun moves 1.1-3.6° in
azimuth during a scan); ``sample_times`` keeps every sample's own time, and
``sample_sun_zenith`` / ``sample_sun_azimuth`` the sun at each. Without a log
(13:30) the samples are spaced uniformly over the median scan duration of the
14 logs (342 s). ``time_reference="start"`` uses the folder time instead, as
Bruneton's published scores do.
"""
from __future__ import annotations

import dataclasses
import datetime as _dt
import math
import re
from pathlib import Path

import numpy as np

from skyfit.camera.sun import sun_position

__all__ = [
    "KIDER_LATITUDE_DEG",
    "KIDER_LONGITUDE_DEG",
    "KIDER_ELEVATION_M",
    "KIDER_UTC_OFFSET_HOURS",
    "KiderError",
    "KiderCapture",
    "load_kider_capture",
    "is_kider_capture_name",
    "symmetry_azimuth",
    "noise_sigma",
    "box_weights",
    "broken_samples",
    "ring_symmetry_azimuths",
]

KIDER_LATITUDE_DEG: float = 42.443449
"""Rhodes Hall roof, Cornell University [deg North]. shared/data/README.md."""
KIDER_LONGITUDE_DEG: float = -76.481962
"""[deg East]. shared/data/README.md."""
KIDER_ELEVATION_M: float = 250.0
"""About 250 m above sea level [m]. shared/data/README.md."""
KIDER_UTC_OFFSET_HOURS: float = -4.0
"""Folder and log times are Eastern Daylight Time [h]. shared/data/README.md."""

N_SAMPLES = 81
RING_SLICES = (slice(0, 32), slice(32, 56), slice(56, 72), slice(72, 80), slice(80, 81))
"""Sample indices of each ring, lowest first (the scan order)."""

SCAN_DURATION_S: float = 342.0
"""Median first-to-last time of the 14 irradiance logs of 2013-05-27 (341-343 s) [s]."""

WAVELENGTH_RANGE_NM = (350.0, 2500.0)

FIT_BAND_NM = (360.0, 720.0)
"""The band a sample must be positive in to be used: the published score's 360-720 nm, where the
clear sky's radiance is 0.01-0.6 W/(m^2 sr nm) [nm]."""
NEGATIVE_NOISE_FLOOR: float = 0.01
"""Negative values down to minus this are detector noise, kept [W/(m^2 sr nm)]: the captures of
2013-05-27 hold 13,500-16,400 negative values each, all in the water-vapour bands beyond 1350 nm
where the signal is ~0, the lowest -0.0034 (docs/reliability.md). A value below minus this, or
NaN/Inf anywhere, or a value <= 0 in :data:`FIT_BAND_NM`, marks the sample as broken: it is left
out and the reason recorded in ``KiderCapture.dropped``."""

_CAPTURE_RE = re.compile(r"^(\d{4})-(\d{2})-(\d{2})___(\d{2})\.(\d{2})\.(\d{2})$")
_FILE_RE = re.compile(r"^(?P<cap>.+)_-_(?P<idx>\d+)____(?P<az>[-+]?\d+(?:\.\d*)?)___(?P<el>[-+]?\d+(?:\.\d*)?)"
                      r"\.asd\.rad\.txt$")


class KiderError(ValueError):
    """A Kider capture folder or file that cannot be read."""


def is_kider_capture_name(name: str) -> bool:
    """True when ``name`` looks like ``YYYY-MM-DD___HH.MM.SS``."""
    return _CAPTURE_RE.match(name) is not None


# --------------------------------------------------------------------------
# Noise model
# --------------------------------------------------------------------------

def _relative_noise(wl: np.ndarray) -> np.ndarray:
    # 0.2 % per nm in 355-720 nm (shared/data/README.md, an upper bound: our
    # robust second-difference estimate there is 0.15-0.2 % and still contains
    # Fraunhofer structure); 0.5 % in 350-355 and 720-1000 nm (second
    # differences give 0.46-0.55 % median in 720-1000 nm); 1 % beyond 1000 nm
    # (0.3-0.8 % where the signal is not absorbed).
    rel = np.full(wl.shape, 0.01)
    rel[wl <= 1000] = 0.005
    rel[(wl >= 355) & (wl <= 720)] = 0.002
    return rel


def _absolute_noise(wl: np.ndarray) -> np.ndarray:
    # Floor from the absorbed bands where the signal is ~0: second differences
    # give 0.7e-5 (1350-1400 nm) to 2.3e-5 (1820-1940 nm) and 7.5e-5 beyond
    # 2400 nm [W/(m^2 sr nm)].
    return np.where(wl >= 2400, 1e-4, 2e-5)


def noise_sigma(wavelengths, radiance, sun_angle_deg, pointing_sigma_deg: float = 1.0):
    """Per-sample noise model of the Kider spectroradiometer.

    sigma_random^2 = (r(λ) L)^2 + a(λ)^2: instrument noise, independent from
    one nm to the next (r, a above, measured on 2013-05-27 except the
    README's 0.2 %); sigma_systematic = s(γ) L: the circumsolar gradient times
    a pointing error δ, fully correlated across wavelengths. For the inner
    aureole L ∝ γ^-2, so a pointing error δ changes L by 2δ/γ; the term is
    applied in full up to γ = 15° and tapered linearly to 0 at 30°.

    Args:
        wavelengths: shape (W,). [nm]
        radiance: shape (N, W). [W/(m^2 sr nm)]
        sun_angle_deg: angle between each view and the sun, shape (N,). [deg]
        pointing_sigma_deg: δ. [deg]

    Returns:
        (sigma_random, sigma_systematic), each shape (N, W). [W/(m^2 sr nm)]
    """
    wl = np.asarray(wavelengths, float)
    L = np.abs(np.asarray(radiance, float))
    gamma = np.maximum(np.asarray(sun_angle_deg, float), 1.0)
    rnd = np.hypot(_relative_noise(wl) * L, _absolute_noise(wl))
    taper = np.clip((30.0 - gamma) / 15.0, 0.0, 1.0)
    s = np.minimum(2.0 * pointing_sigma_deg / gamma, 1.0) * taper
    return rnd, s[:, None] * L


REPAIR_RELATIVE_SIGMA = 0.02
"""Interpolation error of a ring-0 sample from its two neighbours [1]: over
samples 2-30 of the 15 captures of 2013-05-27 (360-720 nm means),
|ln(sample / neighbours' mean)| has median 0.008 and 90th percentile 0.028."""


# --------------------------------------------------------------------------
# The capture
# --------------------------------------------------------------------------

@dataclasses.dataclass
class KiderCapture:
    """One scan of the sky: 81 directions x 2151 wavelengths.

    Attributes:
        path: the capture folder.
        name: its name, e.g. ``2013-05-27___09.30.00``.
        wavelengths: shape (W,), 350..2500. [nm]
        radiance: shape (81, W). [W/(m^2 sr nm)]
        sigma_random: per-nm independent noise, shape (81, W). [W/(m^2 sr nm)]
        sigma_systematic: wavelength-correlated uncertainty (near the sun,
            repaired samples), shape (81, W). [W/(m^2 sr nm)]
        index: sample index from the file names, shape (81,), 0..80.
        ring: 0 (lowest) .. 4 (zenith), shape (81,).
        view_zenith: shape (81,). [rad]
        view_azimuth: clockwise from North (CONTRACT.md), shape (81,). [rad]
        file_azimuth_deg: the azimuth as written in the file names
            (counter-clockwise from North), shape (81,). [deg]
        time: the instant the sun position refers to (see time_reference).
        start_time: the folder's time (scan start).
        sample_times: each sample's time, shape (81,) of aware datetimes.
        time_source: "irradiance log" or "nominal (no log)".
        time_reference: "mid" or "start".
        sun_zenith, sun_azimuth: sun at ``time`` (SPA, refracted). [rad]
        sample_sun_zenith, sample_sun_azimuth: sun at each sample's time,
            shape (81,). [rad]
        sun_distance_au: Earth-Sun distance. [AU]
        sun_angle: angle between each view and the sun at its time, shape (81,). [rad]
        latitude_deg, longitude_deg, elevation_m: the site.
        ghi: the pyranometer's global horizontal irradiance per sample, shape
            (81,), or None without a log. [W/m^2]
        valid: samples to use, shape (81,) bool: finite everywhere, positive
            in 360-720 nm, nowhere below -:data:`NEGATIVE_NOISE_FLOOR`, and at least
            ``min_sun_distance_deg`` from the sun.
        repaired: sample index -> what was done to it.
        dropped: sample index -> why its data is broken (NaN/Inf, values below the noise floor,
            <= 0 in 360-720 nm); these samples are not valid.
        notes: anything else worth knowing (e.g. why the log was ignored).
    """

    path: Path
    name: str
    wavelengths: np.ndarray
    radiance: np.ndarray
    sigma_random: np.ndarray
    sigma_systematic: np.ndarray
    index: np.ndarray
    ring: np.ndarray
    view_zenith: np.ndarray
    view_azimuth: np.ndarray
    file_azimuth_deg: np.ndarray
    time: _dt.datetime
    start_time: _dt.datetime
    sample_times: tuple
    time_source: str
    time_reference: str
    sun_zenith: float
    sun_azimuth: float
    sample_sun_zenith: np.ndarray
    sample_sun_azimuth: np.ndarray
    sun_distance_au: float
    sun_angle: np.ndarray
    latitude_deg: float
    longitude_deg: float
    elevation_m: float
    ghi: np.ndarray | None
    valid: np.ndarray
    repaired: dict
    notes: list
    dropped: dict = dataclasses.field(default_factory=dict)

    @property
    def sigma(self) -> np.ndarray:
        """Total per-nm uncertainty, shape (81, W). [W/(m^2 sr nm)]"""
        return np.hypot(self.sigma_random, self.sigma_systematic)

    def band_average(self, bin_nm: float = 10, lo: float = 360, hi: float = 720):
        """Box averages over bins [lo + k bin, lo + (k+1) bin] of the spectra.

        Each value is the exact mean over the bin of the piecewise-linear
        interpolant of the 1 nm samples (trapezoid weights: the two edge
        samples count half), the same box average that
        ``skyfit.atmosphere.solar.solar_irradiance(centres, bin_nm)`` applies to
        the solar table, so both sides can be compared: point samples carry
        Fraunhofer-line structure (shared/data/README.md). A linear spectrum
        averages to its value at the bin centre.

        Args:
            bin_nm: bin width; (hi - lo) must be a multiple of it. [nm]
            lo, hi: range, within 350-2500. [nm]

        Returns:
            centres (B,) [nm], radiance (81, B) [W/(m^2 sr nm)], sigma (81, B):
            the random part propagated with the weights (sqrt(sum w^2 s^2)),
            the systematic part averaged (fully correlated).
        """
        lo, hi, bin_nm = float(lo), float(hi), float(bin_nm)
        if not (bin_nm > 0 and WAVELENGTH_RANGE_NM[0] <= lo < hi <= WAVELENGTH_RANGE_NM[1]):
            raise KiderError(f"band_average: need 350 <= lo < hi <= 2500 nm and bin_nm > 0, got "
                             f"lo={lo}, hi={hi}, bin_nm={bin_nm}")
        n = (hi - lo) / bin_nm
        if abs(n - round(n)) > 1e-9:
            raise KiderError(f"band_average: (hi - lo) = {hi - lo} nm is not a multiple of bin_nm = {bin_nm}")
        edges = lo + bin_nm * np.arange(round(n) + 1)
        w = box_weights(self.wavelengths, edges)
        rad = self.radiance @ w
        rnd = np.sqrt(self.sigma_random**2 @ w**2)
        sys_ = self.sigma_systematic @ w
        return (edges[:-1] + edges[1:]) / 2, rad, np.hypot(rnd, sys_)


def box_weights(grid, edges) -> np.ndarray:
    """Weights W such that (values @ W)[k] is the mean over [edges[k], edges[k+1]]
    of the piecewise-linear interpolant of ``values`` sampled on ``grid``.

    Each sample's hat function (1 at its wavelength, 0 at its neighbours) is
    integrated in closed form over the bin.

    Args:
        grid: uniformly spaced sample wavelengths, shape (W,). [nm]
        edges: increasing bin edges within the grid, shape (B + 1,). [nm]

    Returns:
        shape (W, B); each column sums to 1.
    """
    grid = np.asarray(grid, float)
    edges = np.asarray(edges, float)
    h = float(grid[1] - grid[0])

    def ramp(x):  # integral of each hat from -inf to x, shape (W, len(x))
        u = np.clip((x[None, :] - grid[:, None]) / h, -1.0, 1.0)
        return h * np.where(u <= 0, 0.5 * (1 + u) ** 2, 1 - 0.5 * (1 - u) ** 2)

    cum = ramp(edges)
    return (cum[:, 1:] - cum[:, :-1]) / np.diff(edges)[None, :]


def _read_spectrum(path: Path) -> tuple[np.ndarray, np.ndarray]:
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as e:
        raise KiderError(f"cannot read Kider file {path}: {e}") from None
    lines = text.split("\n", 1)
    if len(lines) < 2:
        raise KiderError(f"Kider file {path} has no data rows")
    try:
        vals = np.array(lines[1].split(), dtype=float)
    except ValueError:
        raise KiderError(f"Kider file {path}: non-numeric data row") from None
    if vals.size == 0 or vals.size % 2:
        raise KiderError(f"Kider file {path}: rows are not 'wavelength<TAB>radiance' pairs")
    vals = vals.reshape(-1, 2)
    return vals[:, 0], vals[:, 1]


def _read_log(path: Path, utc_offset_hours: float):
    tz = _dt.timezone(_dt.timedelta(hours=utc_offset_hours))
    times, ghi = [], []
    for line in path.read_text().splitlines():
        parts = line.split()
        if not parts:
            continue
        if len(parts) != 2:
            raise ValueError(f"line {line!r} is not 'W/m^2 timestamp'")
        ghi.append(float(parts[0]))
        times.append(_dt.datetime.strptime(parts[1], "%Y.%m.%d.%H.%M.%S").replace(tzinfo=tz))
    return times, np.array(ghi)


def _unit(zenith, azimuth):
    return np.stack([np.sin(zenith) * np.sin(azimuth), np.sin(zenith) * np.cos(azimuth), np.cos(zenith)], -1)


def load_kider_capture(folder, *, latitude: float = KIDER_LATITUDE_DEG, longitude: float = KIDER_LONGITUDE_DEG,
                       elevation: float = KIDER_ELEVATION_M, utc_offset_hours: float = KIDER_UTC_OFFSET_HOURS,
                       irradiance_dir=None, time_reference: str = "mid", repair_sample0: bool = True,
                       pointing_sigma_deg: float = 1.0, min_sun_distance_deg: float = 0.0,
                       delta_t: float | None = None) -> KiderCapture:
    """Load one Kider capture folder.

    Args:
        folder: ``.../<date>/<date>___HH.MM.SS``.
        latitude, longitude, elevation: site [deg, deg East, m]; Kider's by default.
        utc_offset_hours: of the folder and log times (EDT, -4). [h]
        irradiance_dir: folder of pyranometer logs; default
            ``<folder>/../../irradiance``; a missing log means nominal timing.
        time_reference: "mid" (scan mid-time, default) or "start" (folder time).
        repair_sample0: replace sample 0 by the mean of samples 1 and 31.
        pointing_sigma_deg: pointing error of the near-sun noise term. [deg]
        min_sun_distance_deg: views closer to the sun are marked invalid. [deg]
        delta_t: TT - UT1 for the SPA; None for Espenak & Meeus. [s]

    Raises:
        KiderError: missing folder, wrong file count or names, malformed files.
    """
    folder = Path(folder)
    if time_reference not in ("mid", "start"):
        raise KiderError(f"time_reference must be 'mid' or 'start', got {time_reference!r}")
    if not folder.is_dir():
        raise KiderError(f"Kider capture folder not found: {folder}")
    m = _CAPTURE_RE.match(folder.name)
    if not m:
        raise KiderError(f"folder name {folder.name!r} is not a Kider capture (YYYY-MM-DD___HH.MM.SS): {folder}")
    tz = _dt.timezone(_dt.timedelta(hours=float(utc_offset_hours)))
    start = _dt.datetime(*map(int, m.groups()), tzinfo=tz)

    files = sorted(p for p in folder.iterdir() if p.name.endswith(".asd.rad.txt"))
    if len(files) != N_SAMPLES:
        raise KiderError(f"Kider capture {folder} holds {len(files)} .asd.rad.txt files, expected {N_SAMPLES}")
    entries = {}
    for p in files:
        fm = _FILE_RE.match(p.name)
        if not fm or fm["cap"] != folder.name:
            raise KiderError(f"unexpected Kider file name {p.name!r} in {folder}")
        idx = int(fm["idx"])
        if idx in entries:
            raise KiderError(f"Kider capture {folder}: sample index {idx} appears twice")
        entries[idx] = (float(fm["az"]), float(fm["el"]), p)
    if sorted(entries) != list(range(N_SAMPLES)):
        raise KiderError(f"Kider capture {folder}: sample indices are not 0..{N_SAMPLES - 1}")

    wl0 = None
    spectra = []
    for i in range(N_SAMPLES):
        wl, rad = _read_spectrum(entries[i][2])
        if wl0 is None:
            wl0 = wl
            expected = np.arange(WAVELENGTH_RANGE_NM[0], WAVELENGTH_RANGE_NM[1] + 1)
            if wl.shape != expected.shape or np.any(wl != expected):
                raise KiderError(f"Kider file {entries[i][2]}: wavelengths are not 350..2500 nm every 1 nm")
        elif wl.shape != wl0.shape or np.any(wl != wl0):
            raise KiderError(f"Kider file {entries[i][2]}: wavelength grid differs from sample 0's")
        spectra.append(rad)
    radiance = np.stack(spectra)
    file_az = np.array([entries[i][0] for i in range(N_SAMPLES)])
    file_el = np.array([entries[i][1] for i in range(N_SAMPLES)])
    if np.any((file_el < 0) | (file_el > 90)):
        raise KiderError(f"Kider capture {folder}: elevation outside 0..90 degrees in a file name")
    ring = np.zeros(N_SAMPLES, dtype=int)
    for r, sl in enumerate(RING_SLICES):
        ring[sl] = r
        if np.ptp(file_el[sl]) > 1e-6:
            raise KiderError(f"Kider capture {folder}: samples {sl.start}..{sl.stop - 1} are not on one ring")

    notes: list[str] = []
    # Sample times: the pyranometer log, else uniform over the nominal scan duration.
    log_dir = Path(irradiance_dir) if irradiance_dir is not None else folder.parent.parent / "irradiance"
    log_path = log_dir / (start.strftime("%Y.%m.%d.%H.%M.%S") + ".txt")
    sample_times, ghi, time_source = None, None, "nominal (no log)"
    if log_path.is_file():
        try:
            ts, g = _read_log(log_path, float(utc_offset_hours))
            if len(ts) != N_SAMPLES:
                raise ValueError(f"{len(ts)} entries, expected {N_SAMPLES}")
            if abs((ts[0] - start).total_seconds()) > 60 or any(b <= a for a, b in zip(ts, ts[1:])):
                raise ValueError("timestamps do not start at the folder time or do not increase")
            sample_times, ghi, time_source = ts, g, "irradiance log"
        except ValueError as e:
            notes.append(f"ignored irradiance log {log_path}: {e}")
    if sample_times is None:
        step = SCAN_DURATION_S / (N_SAMPLES - 1)
        sample_times = [start + _dt.timedelta(seconds=k * step) for k in range(N_SAMPLES)]
    mid = sample_times[0] + (sample_times[-1] - sample_times[0]) / 2
    when = mid if time_reference == "mid" else start

    site = dict(latitude=latitude, longitude=longitude, elevation=elevation, delta_t=delta_t)
    sun = sun_position(when, **site)
    sun_s = sun_position(np.array(sample_times, dtype=object), **site)

    view_zen = np.radians(90.0 - file_el)
    view_az = np.radians((360.0 - file_az) % 360.0)
    s_zen, s_az = np.radians(sun_s.zenith), np.radians(sun_s.azimuth)
    cosg = np.sum(_unit(view_zen, view_az) * _unit(s_zen, s_az), -1)
    sun_angle = np.arccos(np.clip(cosg, -1.0, 1.0))

    repaired = {}
    rnd, syst = noise_sigma(wl0, radiance, np.degrees(sun_angle), pointing_sigma_deg)
    if repair_sample0:
        left, right = 31, 1  # ring-0 neighbours of sample 0 (azimuths 348.75 and 11.25 in the names)
        band = (wl0 >= 360) & (wl0 <= 720)
        neigh = 0.5 * (radiance[left] + radiance[right])
        ratio = float(radiance[0, band].mean() / neigh[band].mean())
        radiance[0] = neigh
        rnd[0] = np.sqrt(0.25 * (rnd[left] ** 2 + rnd[right] ** 2))
        half_diff = 0.5 * np.abs(radiance[left] - radiance[right])
        syst[0] = np.hypot(np.hypot(half_diff, REPAIR_RELATIVE_SIGMA * np.abs(neigh)),
                           0.5 * (syst[left] + syst[right]))
        repaired[0] = (f"replaced by the mean of samples {left} and {right} (raw / neighbours' mean "
                       f"= {ratio:.3f} in 360-720 nm)")

    dropped = broken_samples(wl0, radiance, [entries[i][2].name for i in range(N_SAMPLES)])
    valid = np.array([i not in dropped for i in range(N_SAMPLES)]) & (np.degrees(sun_angle) >= float(min_sun_distance_deg))

    return KiderCapture(
        path=folder, name=folder.name, wavelengths=wl0, radiance=radiance, sigma_random=rnd,
        sigma_systematic=syst, index=np.arange(N_SAMPLES), ring=ring, view_zenith=view_zen,
        view_azimuth=view_az, file_azimuth_deg=file_az, time=when, start_time=start,
        sample_times=tuple(sample_times), time_source=time_source, time_reference=time_reference,
        sun_zenith=math.radians(float(sun.zenith)), sun_azimuth=math.radians(float(sun.azimuth)),
        sample_sun_zenith=s_zen, sample_sun_azimuth=s_az, sun_distance_au=float(sun.distance_au),
        sun_angle=sun_angle, latitude_deg=float(latitude), longitude_deg=float(longitude),
        elevation_m=float(elevation), ghi=ghi, valid=valid, repaired=repaired, notes=notes, dropped=dropped)


def broken_samples(wavelengths: np.ndarray, radiance: np.ndarray, names=None) -> dict[int, str]:
    """Samples whose spectrum is broken, with the reason: sample index -> one phrase.

    Broken (docs/reliability.md): a NaN or Inf anywhere; a value below -:data:`NEGATIVE_NOISE_FLOOR`
    anywhere; a value <= 0 in :data:`FIT_BAND_NM`. Negative values above the floor are detector
    noise where the sky is dark (the water-vapour bands) and leave the sample in use.

    Args:
        wavelengths: shape (W,). [nm]
        radiance: shape (N, W). [W/(m^2 sr nm)]
        names: the file of each sample, for the reasons (optional).
    """
    band = (wavelengths >= FIT_BAND_NM[0]) & (wavelengths <= FIT_BAND_NM[1])
    out: dict[int, str] = {}
    with np.errstate(invalid="ignore"):
        for i, row in enumerate(radiance):
            where = f"sample {i}" + (f" ({names[i]})" if names is not None else "")
            finite = np.isfinite(row)
            if not finite.all():
                out[i] = f"{where}: {int((~finite).sum())} NaN/Inf value(s)"
            elif (row < -NEGATIVE_NOISE_FLOOR).any():
                k = int(np.argmin(row))
                out[i] = (f"{where}: {row[k]:.3g} W/(m^2 sr nm) at {wavelengths[k]:g} nm, below the "
                          f"-{NEGATIVE_NOISE_FLOOR:g} noise floor")
            elif not (row[band] > 0).all():
                out[i] = (f"{where}: {int((row[band] <= 0).sum())} value(s) <= 0 in "
                          f"{FIT_BAND_NM[0]:g}-{FIT_BAND_NM[1]:g} nm")
    return out


# --------------------------------------------------------------------------
# Symmetry axis of the measured pattern
# --------------------------------------------------------------------------

def _trig_interp(phi_s: np.ndarray, v: np.ndarray, phi: np.ndarray) -> np.ndarray:
    """Trigonometric interpolant of N uniformly spaced samples, evaluated at phi [rad]."""
    n = len(v)
    c = np.fft.rfft(v) / n
    k = np.arange(len(c))
    w = np.where((k == 0) | ((n % 2 == 0) & (k == n // 2)), 1.0, 2.0)
    d = (np.asarray(phi)[..., None] - phi_s[0]) * k
    return (w * (c.real * np.cos(d) - c.imag * np.sin(d))).sum(-1)


def symmetry_azimuth(view_azimuth, values, step_deg: float = 0.05, window_deg: float = 60.0) -> float:
    """Azimuth of the symmetry axis of one ring of sky values, on the bright side.

    A clear sky over flat ground is symmetric about the sun's vertical plane.
    The ring (uniform azimuth sampling) is interpolated trigonometrically and
    the axis a minimising sum_i (v(φ_i) - v(2a - φ_i))^2 is searched within
    ``window_deg`` of the phase of the first harmonic (the bright side). As
    Bruneton's EstimateSunAzimuth, on one ring; pass log radiance so that the
    bright circumsolar region does not dominate.

    Args:
        view_azimuth: uniformly spaced ring azimuths (any order), shape (N,). [rad]
        values: shape (N,).
        step_deg: search step. [deg]
        window_deg: half-width of the search around the first harmonic. [deg]

    Returns:
        Axis azimuth in [0, 2π). [rad]
    """
    az = np.mod(np.asarray(view_azimuth, float), 2 * np.pi)
    v = np.asarray(values, float)
    order = np.argsort(az)
    az, v = az[order], v[order]
    spacing = np.diff(np.concatenate([az, az[:1] + 2 * np.pi]))
    if len(v) < 4 or np.ptp(spacing) > 1e-6:
        raise ValueError("symmetry_azimuth needs >= 4 uniformly spaced azimuths")
    phase = np.angle(np.sum((v - v.mean()) * np.exp(1j * az)))
    grid = phase + np.radians(np.arange(-window_deg, window_deg + step_deg / 2, step_deg))
    mirrored = _trig_interp(az, v, 2 * grid[:, None] - az[None, :])
    err = ((mirrored - v[None, :]) ** 2).sum(-1)
    return float(np.mod(grid[np.argmin(err)], 2 * np.pi))


def ring_symmetry_azimuths(capture: KiderCapture, rings=(1, 2), lo: float = 360, hi: float = 720) -> np.ndarray:
    """Symmetry-axis azimuth of each ring's log mean radiance over [lo, hi] nm.

    Returns:
        shape (len(rings),). [rad]
    """
    band = (capture.wavelengths >= lo) & (capture.wavelengths <= hi)
    mean = capture.radiance[:, band].mean(1)
    out = []
    for r in rings:
        sl = RING_SLICES[r]
        out.append(symmetry_azimuth(capture.view_azimuth[sl], np.log(np.maximum(mean[sl], 1e-12))))
    return np.array(out)
