"""Realistic synthetic all-sky photos with known truth, to test the photo fit end to end.

The photo fit ("fit the atmosphere to real sky photos, end to end, from time and place
alone") must cope with what a real camera does to the sky. This generator makes such
photos *not* through the fit's own forward path:

* **sky**: Bruneton & Neyret 2008 multiple scattering (``orders=4``, the reference method of
  :func:`skyfit.render`) on finer tables and a finer spectral grid (380-760 nm every 20 nm)
  than a fit uses (:attr:`skyfit.fit.model.SkyModel.REDUCED_TABLES`, 400-700 nm), rendered once
  per atmosphere and sun on a camera-independent (view zenith, azimuth from the sun) grid and
  cached (:func:`sky_grid`), then sampled per pixel;
* **scene**: a skyline of textured obstacles (trees with ragged tops, blocky buildings, a
  mountain ridge with aerial perspective, a mast) lit by the sky and the sun, with published
  reflectance spectra (ColorChecker foliage, dark skin, neutrals); the ground below the horizon
  when the camera leans; the sun as its attenuated irradiance spread by a glare PSF (a blurred
  disc plus a few-degree halo with a power-law tail), sometimes a lens ghost on the line through
  the sun and the image centre and a dome's inner reflection ring near the rim;
* **camera**: a fisheye (five projections, off-centre image circle, heading, small tilt),
  polynomial vignetting, a published camera's RGB spectral sensitivities
  (colour-science: Nikon D5100 and Sigma SD Merrill from NPL, Canon EOS 5D Mark II from
  RAW to ACES), photon shot noise, read noise, full-well clipping and 14-bit quantisation
  (:func:`skyfit.camera.sensor.synthesize_photo`), an RGGB Bayer mosaic demosaiced with kornia
  (not for the Foveon Sigma), white balance (daylight gains for D65, or grey world), a 3x3
  colour matrix to sRGB (rawtoaces IDT to ACES2065-1, then ACES -> sRGB with CAT02), or camera
  RGB left as it is, sRGB encoding, 8-bit JPEG at quality 80-95 with or without the exposure
  time in EXIF;
* **brackets**: 3-7 frames with a fixed nominal step of 1-2 EV (in 1/3 stops) and the actual
  exposures jittered by a few per cent around the nominal ones (EXIF holds the nominal time
  or nothing); the shortest frame leaves the sun unsaturated, all others saturate it.

Each case writes its own folder: ``photo.jpg`` (or ``bracket/frame_00.jpg`` ...),
``mask_truth.png`` (0 sky, 255 obstacle or ground, 64 outside the lens's field),
``truth.json`` (everything the fit should recover or is not told; see :func:`make_case`)
and ``truth_arrays.npz`` (the skyline, the noiseless CIE linear sRGB of the sky alone and
the fraction of each pixel's signal that is sky, for diagnosis).

Units of the photo: 8-bit sRGB-encoded codes. ``srgb_decode(code / 255)`` is linear in the
sensor's raw signal (before clipping) with an unknown scale: truth.json's
``frames[i].linear_over_cie_rgb`` gives, per channel, the least-squares factor between that
linear value (vignetting divided out) and skyfit's CIE linear sRGB (Y in cd/m^2) of the same
sky, and ``colour_mismatch_rel`` how far the camera's colours are from CIE's.

Cost (one core, ``OMP_NUM_THREADS=1``, on the shared 2-core machine; the spread is the machine's
load): the Bruneton tables of :data:`TIGHT_TABLES` for 20 wavelengths plus the 373 x 361 grid take
11-25 s of CPU (up to 30 s when 7 jobs shared the 2 cores); a whole 600 x 600 case took 13-28 s,
a 600 x 800 one 27 s, a 300 x 300 bracket of 6-7 frames 11.5-25 s; a second case of the same
atmosphere (another sun, another camera: the tables are cached) 2.6 s. The full 2017 tables
(256 x 64, 64 x 16, 32 x 128 x 32 x 8) took 99 s of CPU and more, the 10 nm grid on
:data:`TIGHT_TABLES` 69 s: over the minute a case may take. Those figures are of scattering mu 64 and 2017's 16 x 32
density directions; with mu 128 and 32 x 64 (the defaults since session 14) a build for 20 wavelengths takes 20 s
on two threads instead of 8 s, and ``make_suite(n=20, size=600, bracket_size=300)`` (one process per suite, two
suites at once on the 2 cores) took 30-45 s for the first case of each atmosphere instead of 9-16 s, 1-2 s for the
second, 361 s a suite instead of 127 s. Since session 16 the tables are built for each case's sun (:attr:`SynthSettings.sun_window`),
so a second case of the same atmosphere under another sun builds its own: both suites, made at once beside a third
single-threaded job, took about 10 min each.

How far from the reference (the full 2017 tables, same 20 wavelengths, 1° x 2° grid up to the
horizon, AOD 0.15): :data:`TIGHT_TABLES` differ by a median 2.8 % (95th percentile 11 %) of the
radiance with the sun at 30° zenith and 0.5 % (1.9 %) at 70°; a fit's reduced tables by 9.7 % (33 %)
and 6.9 % (30 %). So the photos carry physics the fit's own forward model lacks, as real skies do.

What real photos can still do that this generator does not
-----------------------------------------------------------
* clouds, contrails, haze layers and horizontal gradients of the aerosol (the atmosphere
  here is horizontally uniform, one exponential Mie layer of the ``earth`` config);
* atmospheric refraction of the sun and of the sky near the horizon (the geometric sun
  position is used for both the sky and the disc: at 80° zenith the apparent sun is 0.1° higher);
* polarisation-dependent dome or lens transmission, non-uniform dome transmission, dirt,
  water drops and scratches on the dome, condensation;
* chromatic aberration, lateral colour at the rim, a PSF that changes across the field,
  diffraction spikes of the aperture blades, sensor blooming and smear columns;
* rolling shutter, motion between bracket frames (moving clouds, trees in the wind),
  camera auto-white-balance changing between frames (one white balance serves the bracket);
* a raw pipeline's tone curve, highlight recovery, local tone mapping, denoising,
  sharpening, lens-profile vignetting correction, HDR merging inside the phone;
* dark current and hot pixels, fixed-pattern noise, black-level offsets, non-linear sensor
  response near full well, compression artefacts of HEIF;
* obstacles that are lit by the true local radiance field (here: a simple sky-plus-sun model),
  specular windows, moving birds, light pollution and the moon;
* sensitivities of cameras other than the three bundled with colour-science.
"""
from __future__ import annotations

import collections
import dataclasses
import datetime as _dt
import hashlib
import json
import math
import os
import time
from fractions import Fraction
from pathlib import Path

import numpy as np
import torch
from kornia.color import CFA, raw_to_rgb, rgb_to_raw
from PIL import Image, TiffImagePlugin
from torch import Tensor

from ..api import load_atmosphere
from ..atmosphere import Atmosphere
from ..camera.fisheye import PROJECTIONS, FisheyeCamera, zenith_azimuth_to_enu
from ..camera.sensor import spectral_response_matrix, synthesize_photo, vignetting_map
from ..camera.srgb import srgb_encode
from ..camera.sun import sun_position
from ..export.envmap import sun_transmittance
from ..fit.model import SkyModel
from ..fit.parameters import Parameterisation
from ..fit.problem import FitSettings, make_model
from ..render.colour import spectral_to_xyz, xyz_to_linear_srgb

__all__ = [
    "CAMERA_SENSITIVITIES",
    "SynthSettings",
    "SkyGrid",
    "make_atmosphere",
    "find_time_for_zenith",
    "sky_grid",
    "camera_sensitivities",
    "colour_pipeline",
    "make_skyline",
    "make_case",
    "make_suite",
    "suite_plan",
]

SCHEMA = "skyfit.photo_synth/1"

CAMERA_SENSITIVITIES = {
    # name: (source in colour-science, Bayer mosaic or not, EXIF make, EXIF model)
    "Nikon 5100 (NPL)": ("colour.MSDS_CAMERA_SENSITIVITIES['Nikon 5100 (NPL)'] (Darrodi et al. 2015, NPL)",
                         True, "NIKON CORPORATION", "NIKON D5100"),
    "Sigma SDMerill (NPL)": ("colour.MSDS_CAMERA_SENSITIVITIES['Sigma SDMerill (NPL)'] (Darrodi et al. 2015, NPL)",
                             False, "SIGMA", "SIGMA SD1 Merrill"),
    "Canon EOS 5D Mark II (rawtoaces)": ("colour/characterisation/datasets/rawtoaces/"
                                        "CANON_EOS_5DMark_II_RGB_Sensitivities.csv (AMPAS rawtoaces)",
                                        True, "Canon", "Canon EOS 5D Mark II"),
}
"""Published camera RGB sensitivities shipped with colour-science: (source, Bayer?, EXIF make, model).
The Sigma is a Foveon (stacked) sensor: every pixel measures all three channels, no mosaic."""

TIGHT_TABLES = (256, 64, 32, 8, 16, 128, 16, 8)
"""Bruneton table sizes of the generator: transmittance 256 x 64 (2017's), irradiance 32 x 8,
scattering 16 x 128 x 16 x 8 (r, mu, mu_s, nu) -- twice a fit's reduced tables
(:attr:`SkyModel.REDUCED_TABLES` = 64 x 16, 32 x 8, 8 x 32 x 8 x 4) in every scattering axis, and a photo fit's mu
since session 14 (:data:`skyfit.fit.photo.PHOTO_TABLES`; 64 before): with 64 mu samples a hazy sky's orders >= 2
within 25 deg of the sun are 1.43-1.58x a converged reference's, with 128 1.02-1.11x
(docs/multiple/hazy_convergence.json); with :attr:`SynthSettings.density_directions` 32 x 64 too, within 0.4 %. With
Gauss-Legendre view rays (:attr:`SynthSettings.ray_rule`): 2017's trapezoid put a hazy sky's orders >= 2 1.4-2.2x
too high (docs/photos.md, "The view ray's rule")."""


@dataclasses.dataclass(frozen=True)
class SynthSettings:
    """How the sky is rendered (the part that is cached) and sampled.

    Attributes:
        wavelengths: spectral grid of the render, ``START:STOP:STEP``. [nm]
        orders: scattering orders (4: Bruneton multiple scattering; 1: single scattering, for tests).
        table_sizes: Bruneton table sizes (8 integers, :class:`~skyfit.scattering.bruneton_tables.TableSizes`).
        ray_rule: the tables' view-ray rule (:attr:`skyfit.scattering.multiple.Quadrature.ray_rule`).
        density_directions: (theta, phi) incident directions of the tables' scattering density, Delta J
            (:attr:`skyfit.scattering.multiple.Quadrature.density_theta`): 32 x 64, twice 2017's 16 x 32 in each,
            which a photo fit keeps by default; 16 x 32 put a hazy sky's orders >= 2 at the zenith 1.17x a converged
            reference's, 32 x 64 1.01x (docs/multiple/hazy_convergence.json).
        sun_window: (margin in degrees, texels): the tables' mu_s axis spans the sun's zenith angle +- margin in that many
            texels (:func:`skyfit.scattering.multiple.precompute`'s ``mu_s_range``; it replaces ``table_sizes``' mu_s):
            10 deg and 16 texels, 1.3 deg apart, where a photo fit's are 5 deg and 2 deg
            (:data:`skyfit.fit.photo.MS_SUN_MARGIN_DEG`). None: 2017's axis, whose 16 texels put a hazy sky's orders
            >= 2 at the zenith 2.3x the converged value with the sun at 50 deg (docs/multiple_scattering.md, "One sun's
            mu_s window"); the suites before session 16 were made with it.
        zenith_step_deg, azimuth_step_deg: spacing of the sky grid in view zenith and azimuth from
            the sun's vertical plane; pixels interpolate it bilinearly. [deg]
        max_zenith_deg: the grid's largest view zenith (a tilted camera sees a little below the horizon). [deg]
        cache_dir: a folder for rendered sky grids (.npz) shared between runs; None: memory only.
    """

    wavelengths: str = "380:760:20"
    orders: int = 4
    table_sizes: tuple[int, ...] = TIGHT_TABLES
    ray_rule: str = "gauss"
    density_directions: tuple[int, int] = (32, 64)
    sun_window: tuple[float, int] | None = (10.0, 16)
    zenith_step_deg: float = 0.25
    azimuth_step_deg: float = 0.5
    max_zenith_deg: float = 93.0
    cache_dir: str | None = None

    def key(self) -> dict:
        return {"wavelengths": self.wavelengths, "orders": self.orders, "table_sizes": list(self.table_sizes),
                "zenith_step_deg": self.zenith_step_deg, "azimuth_step_deg": self.azimuth_step_deg,
                "max_zenith_deg": self.max_zenith_deg, "ray_rule": self.ray_rule,
                "density_directions": list(self.density_directions),
                **({"sun_window": list(self.sun_window)} if self.sun_window is not None else {})}


TEST_SETTINGS = SynthSettings(wavelengths="380:760:40", orders=1, zenith_step_deg=1.0, azimuth_step_deg=2.0)
"""Cheap settings for unit tests: single scattering, 40 nm steps, a 1° x 2° grid."""


# --------------------------------------------------------------------------- atmosphere and sun


def make_atmosphere(values: dict, wavelengths: str = "380:760:20", config: str = "earth",
                    sun_distance_au: float | None = None) -> Atmosphere:
    """The ``config`` atmosphere with fit parameters set to ``values``, as a fit would build it.

    The same path as :func:`skyfit.fit.results.atmosphere_from_result`: a
    :class:`~skyfit.fit.parameters.Parameterisation` with no free parameter and ``values`` as fixed
    overrides, so ``mie_aod_550`` means beta_550 x H_M of the config's Mie layer, ``mie_angstrom_alpha``
    the power law of its extinction, ``rayleigh_scale`` a factor on its Rayleigh coefficients.

    Args:
        values: {name: value} of :data:`skyfit.fit.parameters.PARAMETERS` (SI units).
        wavelengths: spectral grid. [nm]
        config: a shipped config name or a YAML path.
        sun_distance_au: Earth-Sun distance scaling the solar irradiance (None: the config's). [AU]
    """
    base = load_atmosphere(config, wavelengths, sun_distance_au=sun_distance_au)
    param = Parameterisation(base, [], 1, None, dict(values))
    with torch.no_grad():
        return param.atmosphere(param.to_physical(param.initial_vector(base.dtype, base.device)))


def _utc_offset_for(longitude: float) -> int:
    """A plausible civil UTC offset for a longitude: the nearest whole hour of solar time. [h]"""
    return int(max(-12, min(14, round(longitude / 15.0))))


def find_time_for_zenith(zenith_deg: float, rng: np.random.Generator, *, afternoon: bool | None = None,
                         latitude: float | None = None, longitude: float | None = None,
                         elevation: float | None = None, year_range=(2016, 2025)) -> dict:
    """A time and place where NREL's SPA puts the sun at the geometric zenith ``zenith_deg``.

    Draws a date, a longitude (with the whole-hour civil offset of its solar time), an elevation and a
    latitude from which the sun reaches ``zenith_deg`` that day, then searches the local day with SPA
    (1-minute scan, then bisection) for the morning or afternoon crossing and rounds it to the second.

    Args:
        zenith_deg: wanted geometric (airless) topocentric zenith, in (0, 90). [deg]
        rng: the random source.
        afternoon: which crossing (None: random).
        latitude, longitude, elevation: fix the site (latitude must let the sun reach the zenith). [deg, deg, m]

    Returns:
        dict with ``time`` (ISO 8601 with UTC offset, whole seconds), ``latitude``, ``longitude``,
        ``elevation``, ``utc_offset_hours``, ``sun`` (SPA at that time: ``zenith_deg`` geometric,
        ``zenith_apparent_deg``, ``azimuth_deg``, ``distance_au``).
    """
    if not 0 < zenith_deg < 90:
        raise ValueError(f"sun zenith must be in (0, 90) deg, got {zenith_deg}")
    for _ in range(50):
        year = int(rng.integers(year_range[0], year_range[1] + 1))
        date = _dt.date(year, 1, 1) + _dt.timedelta(days=int(rng.integers(0, 365)))
        lon = float(rng.uniform(-179.0, 179.0)) if longitude is None else float(longitude)
        elev = float(rng.uniform(0.0, 1000.0)) if elevation is None else float(elevation)
        off = _utc_offset_for(lon)
        tz = _dt.timezone(_dt.timedelta(hours=off))
        doy = date.timetuple().tm_yday
        decl = 23.44 * math.sin(2 * math.pi * (284 + doy) / 365.0)  # Cooper 1969, to pick a latitude only
        if latitude is None:
            lo, hi = max(-65.0, decl - (zenith_deg - 3.0)), min(65.0, decl + (zenith_deg - 3.0))
            if lo >= hi:
                continue
            lat = float(rng.uniform(lo, hi))
        else:
            lat = float(latitude)
        start = _dt.datetime(date.year, date.month, date.day, tzinfo=tz) - _dt.timedelta(hours=2)
        minutes = np.arange(0, 28 * 60, 1.0)
        times = [start + _dt.timedelta(minutes=float(m)) for m in minutes]
        zen = sun_position(times, lat, lon, elev, refraction=False).zenith_geometric
        f = zen - zenith_deg
        cross = np.nonzero(np.sign(f[:-1]) != np.sign(f[1:]))[0]
        # crossings of the local day (04:00-20:00 local around the date's noon)
        cross = [i for i in cross if 2 * 60 <= i < 26 * 60]
        rising = [i for i in cross if f[i] > 0]  # zenith decreasing: morning
        setting = [i for i in cross if f[i] < 0]
        pick_pm = bool(rng.integers(0, 2)) if afternoon is None else afternoon
        cands = setting if pick_pm else rising
        if not cands:
            if latitude is not None:
                raise ValueError(f"the sun does not reach zenith {zenith_deg} deg at latitude {lat} on {date}")
            continue
        i = cands[0]
        a, b = 0.0, 60.0  # seconds after times[i]
        fa = f[i]
        for _ in range(40):
            m = 0.5 * (a + b)
            fm = float(sun_position(times[i] + _dt.timedelta(seconds=m), lat, lon, elev, refraction=False)
                       .zenith_geometric) - zenith_deg
            if np.sign(fm) == np.sign(fa):
                a, fa = m, fm
            else:
                b = m
        t = (times[i] + _dt.timedelta(seconds=0.5 * (a + b)))
        t = t.replace(microsecond=0) + _dt.timedelta(seconds=1 if t.microsecond >= 500_000 else 0)
        sp = sun_position(t, lat, lon, elev)
        return {
            "time": t.isoformat(timespec="seconds"),
            "latitude": lat, "longitude": lon, "elevation": elev, "utc_offset_hours": off,
            "sun": {"zenith_deg": float(sp.zenith_geometric), "zenith_apparent_deg": float(sp.zenith),
                    "azimuth_deg": float(sp.azimuth), "distance_au": float(sp.distance_au)},
        }
    raise ValueError(f"no site found where the sun reaches zenith {zenith_deg} deg")


# --------------------------------------------------------------------------- the sky (cached)


@dataclasses.dataclass
class SkyGrid:
    """Spectral sky radiance on a (view zenith, azimuth from the sun) grid, and the direct sun.

    Attributes:
        radiance: shape (N_zenith, N_azimuth, W); row i is zenith ``i * zenith_step``, column j the
            azimuth ``j * azimuth_step`` away from the sun's (the sky is symmetric about the sun's
            vertical plane). [W/(m^2 sr nm)]
        zenith_step_deg, azimuth_step_deg: grid spacing. [deg]
        sun_irradiance: direct solar spectral irradiance at the ground on a plane normal to the sun
            (extraterrestrial x transmittance), shape (W,). [W/(m^2 nm)]
        wavelengths: shape (W,). [nm]
        sun_zenith_deg: the sun's geometric zenith. [deg]
        seconds: CPU seconds of the render (tables + lookups) when it was made. [s]
        info: renderer settings.
    """

    radiance: Tensor
    zenith_step_deg: float
    azimuth_step_deg: float
    sun_irradiance: Tensor
    wavelengths: Tensor
    sun_zenith_deg: float
    seconds: float
    info: dict

    def sample(self, zenith_deg: Tensor, dazimuth_deg: Tensor) -> Tensor:
        """Bilinear radiance at view zenith and |azimuth - sun azimuth| in [0, 180], shape (...) -> (..., W)."""
        nz, na, w = self.radiance.shape
        img = self.radiance.permute(2, 0, 1).unsqueeze(0)  # (1, W, Nz, Na)
        gx = dazimuth_deg / (self.azimuth_step_deg * (na - 1)) * 2 - 1
        gy = zenith_deg / (self.zenith_step_deg * (nz - 1)) * 2 - 1
        grid = torch.stack([gx, gy], -1).reshape(1, -1, 1, 2).to(img.dtype)
        out = torch.nn.functional.grid_sample(img, grid, mode="bilinear", padding_mode="border", align_corners=True)
        return out[0, :, :, 0].T.reshape(*zenith_deg.shape, w)


_SKY_CACHE: "collections.OrderedDict[str, SkyGrid]" = collections.OrderedDict()
_TABLE_CACHE: "collections.OrderedDict[str, object]" = collections.OrderedDict()


def _cache_key(*parts) -> str:
    return hashlib.sha1(json.dumps(parts, sort_keys=True, default=str).encode()).hexdigest()[:20]


def sky_grid(atmosphere_values: dict, sun_zenith_deg: float, settings: SynthSettings = SynthSettings(),
             sun_distance_au: float = 1.0, config: str = "earth") -> SkyGrid:
    """The rendered spectral sky of an atmosphere and a sun zenith, from the cache when already made.

    Multiple scattering uses Bruneton's tables (:class:`~skyfit.fit.model.SkyModel` with
    ``multiple='bruneton'``, ``settings.table_sizes``), which hold every sun zenith: they are cached
    per atmosphere too, so a second sun costs only the lookups. Keys hold the values and the
    settings; ``settings.cache_dir`` adds a disk cache.

    Args:
        atmosphere_values: fit parameters of the atmosphere (:func:`make_atmosphere`).
        sun_zenith_deg: geometric sun zenith. [deg]
        settings: render settings.
        sun_distance_au: Earth-Sun distance. [AU]
        config: the base config.
    """
    akey = _cache_key(config, atmosphere_values, sun_distance_au, settings.wavelengths)
    key = _cache_key(akey, round(float(sun_zenith_deg), 9), settings.key())
    if key in _SKY_CACHE:
        _SKY_CACHE.move_to_end(key)
        return _SKY_CACHE[key]
    path = Path(settings.cache_dir) / f"sky_{key}.npz" if settings.cache_dir else None
    if path is not None and path.exists():
        z = np.load(path, allow_pickle=False)
        grid = SkyGrid(torch.from_numpy(z["radiance"]), float(z["zenith_step"]), float(z["azimuth_step"]),
                       torch.from_numpy(z["sun_irradiance"]), torch.from_numpy(z["wavelengths"]),
                       float(sun_zenith_deg), float(z["seconds"]), json.loads(str(z["info"])))
    else:
        grid = _render_grid(atmosphere_values, sun_zenith_deg, settings, sun_distance_au, config, akey)
        if path is not None:
            path.parent.mkdir(parents=True, exist_ok=True)
            tmp = path.with_suffix(".tmp.npz")
            np.savez(tmp, radiance=grid.radiance.numpy(), zenith_step=grid.zenith_step_deg,
                     azimuth_step=grid.azimuth_step_deg, sun_irradiance=grid.sun_irradiance.numpy(),
                     wavelengths=grid.wavelengths.numpy(), seconds=grid.seconds, info=json.dumps(grid.info))
            os.replace(tmp, path)
    _SKY_CACHE[key] = grid
    while len(_SKY_CACHE) > 8:
        _SKY_CACHE.popitem(last=False)
    return grid


def _render_grid(values: dict, sun_zenith_deg: float, s: SynthSettings, sun_distance_au: float, config: str,
                 akey: str) -> SkyGrid:
    t0 = time.process_time()
    atm = make_atmosphere(values, s.wavelengths, config, sun_distance_au)
    integ = make_model(FitSettings()).integrator
    if s.orders > 1:
        window = None if s.sun_window is None else (float(s.sun_window[0]), int(s.sun_window[1]))
        model = SkyModel(integ, orders=s.orders, multiple="bruneton", table_sizes=tuple(s.table_sizes), ray_rule=s.ray_rule,
                         density_directions=tuple(s.density_directions), sun_window=window is not None)
        tkey = _cache_key(akey, s.orders, list(s.table_sizes), s.ray_rule, list(s.density_directions),
                          *(() if window is None else (window, float(sun_zenith_deg))))  # tables of one sun
        if tkey not in _TABLE_CACHE:
            with torch.no_grad():
                _TABLE_CACHE[tkey] = (model.tables(atm) if window is None else
                                      model.sun_tables(atm, sun_zenith_deg, margin_deg=window[0], texels=window[1]))
            while len(_TABLE_CACHE) > 2:
                _TABLE_CACHE.popitem(last=False)
        tables = _TABLE_CACHE[tkey]
    else:
        model, tables = SkyModel(integ, orders=1, view_samples=64), None
    nz = int(round(s.max_zenith_deg / s.zenith_step_deg)) + 1
    na = int(round(180.0 / s.azimuth_step_deg)) + 1
    zen = torch.deg2rad(torch.arange(nz, dtype=torch.float64) * s.zenith_step_deg)
    daz = torch.deg2rad(torch.arange(na, dtype=torch.float64) * s.azimuth_step_deg)
    zz, aa = torch.meshgrid(zen, daz, indexing="ij")
    dirs = zenith_azimuth_to_enu(zz, aa).reshape(-1, 3)
    sun = zenith_azimuth_to_enu(torch.tensor(math.radians(sun_zenith_deg), dtype=torch.float64),
                                torch.tensor(0.0, dtype=torch.float64))
    with torch.no_grad():
        render = model.renderer(atm, 0.0, tables=tables) if tables is not None else model.renderer(atm, 0.0)
        rad = torch.cat([render(dirs[i:i + 20000], sun) for i in range(0, dirs.shape[0], 20000)])
        t_sun = sun_transmittance(atm, atm.bottom_radius, sun.reshape(1, 3))[0]
    radiance = rad.reshape(nz, na, -1).clamp(min=0.0)
    info = {"method": "bruneton" if s.orders > 1 else "single", "orders": s.orders,
            "table_sizes": list(s.table_sizes) if s.orders > 1 else None,
            "density_directions": list(s.density_directions) if s.orders > 1 else None, "ray_rule": s.ray_rule,
            "sun_window": list(s.sun_window) if s.orders > 1 and s.sun_window is not None else None,
            **model.integrator.settings(),
            "wavelengths_nm": [float(v) for v in atm.wavelengths.tolist()]}
    return SkyGrid(radiance, s.zenith_step_deg, s.azimuth_step_deg, (atm.solar_irradiance * t_sun).detach(),
                   atm.wavelengths.detach(), float(sun_zenith_deg), time.process_time() - t0, info)


# --------------------------------------------------------------------------- camera colour


def _msds(name: str):
    import colour  # heavy optional dependency of the tools layer only
    if name == "Canon EOS 5D Mark II (rawtoaces)":
        from colour.characterisation import RGB_CameraSensitivities
        from colour.characterisation.aces_it import ROOT_RESOURCES_RAWTOACES
        from colour.colorimetry import sds_and_msds_to_msds
        from colour.io import read_sds_from_csv_file
        path = os.path.join(ROOT_RESOURCES_RAWTOACES, "CANON_EOS_5DMark_II_RGB_Sensitivities.csv")
        return RGB_CameraSensitivities(sds_and_msds_to_msds(read_sds_from_csv_file(path).values()))
    if name not in CAMERA_SENSITIVITIES:
        raise ValueError(f"unknown camera {name!r}; valid: {', '.join(CAMERA_SENSITIVITIES)}")
    return colour.MSDS_CAMERA_SENSITIVITIES[name]


def camera_sensitivities(name: str) -> tuple[np.ndarray, np.ndarray]:
    """A camera's RGB spectral sensitivities from colour-science, the green peak scaled to 1.

    Returns:
        (wavelengths (K,) [nm], sensitivities (K, 3) [1], columns R, G, B, non-negative).
    """
    m = _msds(name)
    wl = np.asarray(m.wavelengths, float)
    v = np.clip(np.asarray(m.values, float), 0.0, None)
    return wl, v / v[:, 1].max()


_PIPELINES: dict = {}


def colour_pipeline(name: str) -> dict:
    """Daylight white balance and the camera RGB -> linear sRGB matrix of a camera, as its raw pipeline would.

    colour-science's :func:`colour.matrix_idt` (AMPAS rawtoaces' method: white-balance multipliers for
    the illuminant, then a 3x3 matrix fitted on 190 training reflectances) for CIE D65 gives the matrix
    to ACES2065-1; :func:`colour.matrix_RGB_to_RGB` (CAT02) takes ACES to linear sRGB.

    Returns:
        {"daylight_gains": (3,), "matrix": (3, 3) white-balanced camera RGB -> linear sRGB}.
    """
    if name not in _PIPELINES:
        import colour  # heavy: imported when used
        m_idt, rgb_w = colour.matrix_idt(_msds(name), colour.SDS_ILLUMINANTS["D65"])
        a = colour.matrix_RGB_to_RGB(colour.RGB_COLOURSPACES["ACES2065-1"], colour.RGB_COLOURSPACES["sRGB"], "CAT02")
        m = a @ m_idt
        m = m / (m @ np.ones(3))[:, None]  # a white-balanced neutral stays neutral: rows sum to 1
        _PIPELINES[name] = {"daylight_gains": np.asarray(rgb_w, float), "matrix": m}
    return _PIPELINES[name]


def colour_rendering(name: str, slopes: np.ndarray = np.linspace(-0.5, 4.5, 11), output: str = "srgb") -> dict:
    """How a published camera renders sky-like spectra against CIE colorimetry (docs/photos.md, "A camera is not a
    colorimeter"; ``scripts/camera_colour.py``).

    Spectra D65 x (lambda / 550 nm)^-a for each a in ``slopes`` (4: a clear zenith, 0: white haze) go through the
    camera's sensitivities, its daylight white balance and rawtoaces matrix (:func:`colour_pipeline`; ``output``
    ``camera_rgb``: no matrix, the white-balanced camera RGB that a fifth of the generator's photos carry) and through
    CIE 1931 -> linear sRGB. Three models of the difference are fitted by least squares on log chromaticity (ln R/G,
    ln B/G): gains only; gains and one saturation s; gains and red / blue saturations (Y + s (c - Y) about sRGB's
    luminance, as :meth:`skyfit.fit.model.FitProblem.predict_unscaled` applies them).

    Returns:
        ``slopes``; ``relative`` (len(slopes), 3): the camera's R/G, 1, B/G over CIE's, each relative to white (a = 0);
        ``rms_gains``, ``rms_one``, ``rms_two``: the fits' rms in log chromaticity; ``s`` (one saturation);
        ``s_red``, ``s_blue``. [1]
    """
    if output not in ("srgb", "camera_rgb"):
        raise ValueError(f"output must be srgb or camera_rgb, got {output!r}")
    import colour  # heavy: imported when used
    from scipy.optimize import least_squares

    from ..render.colour import srgb_luminance_weights, xyz_to_srgb_matrix

    shape = colour.SpectralShape(400, 700, 5)
    lam = np.arange(400.0, 701.0, 5.0)
    d65 = colour.SDS_ILLUMINANTS["D65"].copy().align(shape).values
    cmf = colour.MSDS_CMFS["CIE 1931 2 Degree Standard Observer"].copy().align(shape).values
    to_srgb = np.asarray(xyz_to_srgb_matrix())
    y_w = srgb_luminance_weights()
    slopes = np.asarray(slopes, float)
    spectra = np.stack([d65 * (lam / 550.0) ** -a for a in slopes])
    base = spectra @ (cmf @ to_srgb.T)
    wl, sens = camera_sensitivities(name)
    s_i = np.stack([np.interp(lam, wl, sens[:, c]) for c in range(3)], 1)
    pipe = colour_pipeline(name)
    cam = (spectra @ s_i) * pipe["daylight_gains"] / pipe["daylight_gains"][1]
    if output == "srgb":
        cam = cam @ pipe["matrix"].T
    target = np.log(cam / cam[:, 1:2])[:, [0, 2]]
    y = (base @ y_w)[:, None]

    def resid(q):
        out = (y + np.array([q[2], 1.0, q[3]]) * (base - y)) * np.array([np.exp(q[0]), 1.0, np.exp(q[1])])
        return (np.log(out / out[:, 1:2])[:, [0, 2]] - target).ravel()

    rms = lambda r: float(np.sqrt(np.mean(r.fun**2)))  # noqa: E731
    gains = least_squares(lambda q: resid(np.r_[q, 1.0, 1.0]), [0.0, 0.0])
    one = least_squares(lambda q: resid(np.r_[q[:2], q[2], q[2]]), [0.0, 0.0, 1.0])
    two = least_squares(resid, [0.0, 0.0, 1.0, 1.0])
    white = int(np.argmin(np.abs(slopes)))
    rel = (cam / cam[white]) / (base / base[white])
    return {"slopes": slopes, "relative": rel / rel[:, 1:2], "rms_gains": rms(gains), "rms_one": rms(one),
            "rms_two": rms(two), "s": float(one.x[2]), "s_red": float(two.x[2]), "s_blue": float(two.x[3])}


@dataclasses.dataclass(frozen=True)
class _Material:
    name: str
    patch: str  # ColorChecker N Ohta patch with the reflectance spectrum
    scale: float  # multiplies the patch's reflectance


_MATERIALS = {
    "foliage": _Material("foliage", "foliage", 0.8),
    "bark": _Material("bark", "dark skin", 0.7),
    "brick": _Material("brick", "dark skin", 1.0),
    "concrete": _Material("concrete", "neutral 5 (.70 D)", 1.0),
    "dark_grey": _Material("dark_grey", "neutral 3.5 (1.05 D)", 1.0),
    "rock": _Material("rock", "neutral 3.5 (1.05 D)", 1.2),
    "metal": _Material("metal", "black 2 (1.5 D)", 1.5),
    "ground": _Material("ground", "dark skin", 0.8),
}


def _reflectance(material: str, wavelengths: np.ndarray) -> np.ndarray:
    """Reflectance of a material on ``wavelengths`` [nm], from colour-science's ColorChecker spectra, shape (W,). [1]"""
    import colour  # heavy: imported when used
    mat = _MATERIALS[material]
    sd = colour.SDS_COLOURCHECKERS["ColorChecker N Ohta"][mat.patch]
    return mat.scale * np.interp(wavelengths, sd.wavelengths, sd.values)


# --------------------------------------------------------------------------- obstacles


def make_skyline(rng: np.random.Generator, horizon_fraction: float, *, sun_azimuth_deg: float | None = None,
                 sun_elevation_deg: float | None = None, max_elevation_deg: float = 15.0,
                 step_deg: float = 0.1) -> dict:
    """A skyline: obstacle elevation per azimuth, and the object (segment) holding each azimuth.

    Objects are placed in 1-3 clusters until they cover about ``horizon_fraction`` of the horizon:
    trees (rounded crowns with ragged tops), blocky buildings (flat roofs, steps), a mountain ridge
    (a fractal profile, seen through haze) and sometimes a mast (a thin line). Elevations are
    clipped to ``max_elevation_deg``; near the sun's azimuth the skyline is kept 3° below the sun
    so that the sun stays visible.

    Returns:
        dict: ``azimuth_deg`` (N,), ``elevation_deg`` (N,) [deg, 0 = no obstacle], ``segment`` (N,)
        int (-1 = none), ``segments`` (list of dicts: kind, material, azimuth range, height, haze),
        ``fraction`` (share of the horizon covered).
    """
    az = np.arange(0.0, 360.0, step_deg)
    n = az.size
    elev = np.zeros(n)
    seg = np.full(n, -1, int)
    segments: list[dict] = []

    def put(kind: str, start: float, prof: np.ndarray, material: str, haze: float = 0.0) -> None:
        idx = (int(round(start / step_deg)) + np.arange(prof.size)) % n
        k = len(segments)
        higher = prof > elev[idx]
        elev[idx] = np.where(higher, prof, elev[idx])
        seg[idx] = np.where(higher & (prof > 0), k, seg[idx])
        segments.append({"kind": kind, "material": material, "azimuth_start_deg": float(start % 360.0),
                         "azimuth_end_deg": float((start + prof.size * step_deg) % 360.0),
                         "max_elevation_deg": float(min(prof.max(), max_elevation_deg)), "haze": haze})

    def ragged(m: int, scale: float) -> np.ndarray:
        """1-D correlated noise of m samples with unit spread (smoothed white noise)."""
        from skimage.filters import gaussian  # scikit-image, imported when used (a slow import)
        x = gaussian(rng.normal(size=m), sigma=scale, mode="wrap", preserve_range=True)
        return x / (x.std() + 1e-12)

    def cluster(pos: float, end: float) -> None:
        while pos < end - 1.0:
            kind = str(rng.choice(["trees", "trees", "building", "ridge"]))
            width = float(min(end - pos, {"trees": rng.uniform(4, 25), "building": rng.uniform(5, 20),
                                          "ridge": rng.uniform(20, 60)}[kind]))
            m = max(int(width / step_deg), 2)
            x = np.linspace(0, 1, m)
            if kind == "trees":
                prof = np.zeros(m)
                n_tree = max(1, int(width / rng.uniform(2, 5)))
                for c0 in np.linspace(0.1, 0.9, n_tree) + rng.uniform(-0.05, 0.05, n_tree):
                    h, w = rng.uniform(4, 14), rng.uniform(0.1, 0.3)
                    prof = np.maximum(prof, h * np.sqrt(np.clip(1 - ((x - c0) / w) ** 2, 0, None)))
                prof = np.where(prof > 0, prof + 0.6 * ragged(m, 1.5) + 0.3 * ragged(m, 0.5), 0)
                material, haze = str(rng.choice(["foliage", "foliage", "bark"])), 0.0
            elif kind == "building":
                prof = np.full(m, rng.uniform(3, 12))
                for _ in range(int(rng.integers(0, 3))):  # roof steps and annexes
                    a, b = np.sort(rng.integers(0, m, 2))
                    prof[a:b] = rng.uniform(2, 12)
                material, haze = str(rng.choice(["brick", "concrete", "dark_grey"])), 0.0
            else:
                base = rng.uniform(2, 8) * np.sin(np.pi * x) ** 0.5
                prof = base + sum(rng.uniform(0.3, 1.2) / k * np.sin(2 * np.pi * k * x + rng.uniform(0, 6.3))
                                  for k in range(1, 9)) + 0.15 * ragged(m, 2.0)
                prof = np.maximum(prof, 0.5)
                material, haze = str(rng.choice(["rock", "foliage"])), float(rng.uniform(0.2, 0.6))
            put(kind, pos, np.clip(prof, 0, max_elevation_deg), material, haze)
            pos += width

    def covered() -> float:
        e = np.clip(elev, 0.0, max_elevation_deg)
        if sun_azimuth_deg is not None and sun_elevation_deg is not None:
            e = np.where(near_sun, np.minimum(e, max(0.0, sun_elevation_deg - 3.0)), e)
        return float((e > 0).mean())

    near_sun = (np.abs((az - (sun_azimuth_deg or 0.0) + 180.0) % 360.0 - 180.0) < 12.0)
    total = horizon_fraction * 360.0
    if total > 0:
        n_clusters = int(rng.integers(1, 4))
        shares = rng.dirichlet(np.ones(n_clusters)) * total
        for start, share in zip(rng.uniform(0, 360, n_clusters), shares):
            cluster(float(start), float(start + share))
        for _ in range(20):  # gaps, overlaps and the sun's gap leave less than asked: add until near it
            missing = horizon_fraction - covered()
            if missing < 0.02:
                break
            start = float(rng.uniform(0, 360))
            cluster(start, start + max(missing * 360.0, 3.0))
        if rng.random() < 0.5:  # a mast
            m = max(int(rng.uniform(0.3, 0.8) / step_deg), 2)
            put("mast", float(rng.uniform(0, 360)), np.full(m, rng.uniform(9, max_elevation_deg)), "metal")
    elev = np.clip(elev, 0.0, max_elevation_deg)
    if sun_azimuth_deg is not None and sun_elevation_deg is not None:
        elev[near_sun] = np.minimum(elev[near_sun], max(0.0, sun_elevation_deg - 3.0))
    return {"azimuth_deg": az, "elevation_deg": elev, "segment": np.where(elev > 0, seg, -1),
            "segments": segments, "fraction": float((elev > 0).mean())}


# --------------------------------------------------------------------------- case drawing


def _draw_camera(rng: np.random.Generator, shape: tuple[int, int], projection: str) -> FisheyeCamera:
    h, w = shape
    s = min(h, w)
    r90 = float(rng.uniform(0.40, 0.48)) * s
    # centre offset up to 5 % of each side, kept so that the whole circle stays on the sensor
    mx = max(0.0, min(0.05 * w, (w - 1) / 2.0 - r90 - 1.0))
    my = max(0.0, min(0.05 * h, (h - 1) / 2.0 - r90 - 1.0))
    cx = (w - 1) / 2.0 + float(rng.uniform(-mx, mx))
    cy = (h - 1) / 2.0 + float(rng.uniform(-my, my))
    tilt_mag, tilt_dir = float(rng.uniform(0, 2.0)), float(rng.uniform(0, 2 * math.pi))
    kw = dict(size=(h, w) if h != w else h, projection=projection, cx=cx, cy=cy, radius=r90,
              up_azimuth_deg=float(rng.uniform(0, 360)),
              tilt_deg=(tilt_mag * math.sin(tilt_dir), tilt_mag * math.cos(tilt_dir)))
    if projection == "kannala_brandt":
        kw["kb_coeffs"] = (float(rng.uniform(-0.05, 0.05)), float(rng.uniform(-0.01, 0.01)), 0.0, 0.0)
    return FisheyeCamera(**kw)


_MARKED = (8000, 6400, 5000, 4000, 3200, 2500, 2000, 1600, 1250, 1000, 800, 640, 500, 400, 320, 250, 200, 160,
           125, 100, 80, 60, 50, 40, 30, 25, 20, 15, 13, 10, 8, 6, 5, 4)
"""Shutter times a camera marks and writes in EXIF, 1/8000 s ... 1/4 s in 1/3 stops (denominators)."""


def _marked_time(t: float) -> float:
    """The marked 1/3-stop shutter time nearest (in stops) to a nominal time ``t``, as EXIF holds it. [s]"""
    marks = np.array([1.0 / d for d in _MARKED] + [0.3, 0.4, 0.5, 0.6, 0.8, 1.0, 1.3, 1.6, 2.0, 2.5, 3.2, 4.0])
    return float(marks[int(np.argmin(np.abs(np.log2(marks) - math.log2(t))))])


def _exif_bytes(make: str, model: str, local_time: _dt.datetime, exposure_s: float | None, quality: int) -> bytes:
    exif = Image.Exif()
    exif[0x010F] = make
    exif[0x0110] = model
    exif[0x0131] = "skyfit photo_synth"
    stamp = local_time.strftime("%Y:%m:%d %H:%M:%S")
    exif[0x0132] = stamp
    ifd = exif.get_ifd(0x8769)
    ifd[0x9003] = stamp  # DateTimeOriginal
    off = local_time.utcoffset()
    hours, rem = divmod(int(off.total_seconds()), 3600)
    ifd[0x9011] = f"{'+' if off.total_seconds() >= 0 else '-'}{abs(hours):02d}:{abs(rem) // 60:02d}"  # OffsetTimeOriginal
    ifd[0x829D] = TiffImagePlugin.IFDRational(8, 1)  # FNumber
    ifd[0x8827] = 100  # ISO
    if exposure_s is not None:
        fr = Fraction(exposure_s).limit_denominator(100000)
        ifd[0x829A] = TiffImagePlugin.IFDRational(fr.numerator, fr.denominator)
    return exif.tobytes()


def _ring(x: Tensor, y: Tensor, cx: float, cy: float, r: float, rho0: float, width: float) -> Tensor:
    rho = torch.hypot(x - cx, y - cy) / r
    return torch.exp(-0.5 * ((rho - rho0) / width) ** 2)


def make_case(seed: int, out_dir: str | Path, *, size: int | tuple[int, int] = 600, bracket: bool = False,
              projection: str | None = None, aod_550: float | None = None, angstrom_alpha: float | None = None,
              mie_g: float | None = None, rayleigh_scale: float | None = None, sun_zenith_deg: float | None = None,
              camera: str | None = None, horizon_fraction: float | None = None, n_frames: int | None = None,
              exposure_ev: float | None = None, elevation_m: float | None = None,
              settings: SynthSettings = SynthSettings(), time_and_place: dict | None = None,
              save_arrays: bool = True) -> dict:
    """Write one synthetic all-sky photo (or bracket) with its truth into ``out_dir``; return the truth.

    Every choice not given is drawn from ``seed`` (same seed and arguments: same files, bit for bit):
    AOD 550 log-uniform in [0.05, 0.5], Ångström alpha in [0.5, 1.8], g in [0.6, 0.85], the Rayleigh
    scale of the site's pressure (exp(-elevation / 8434 m)), sun zenith in [20, 80]°, a projection, a
    camera, the skyline (about a third of the horizon, sometimes 3-20 %), flare, ghost and dome ring,
    vignetting (0-30 % at the rim), sensor noise, white balance, colour matrix, JPEG quality, EXIF.

    Args:
        seed: the case's random seed.
        out_dir: the case's folder (created).
        size: image side, or (height, width) of a non-square sensor (even numbers). [px]
        bracket: write ``bracket/frame_NN.jpg`` (3-7 frames, exposures increasing) instead of ``photo.jpg``.
        projection: one of :data:`skyfit.camera.fisheye.PROJECTIONS` (None: random).
        aod_550, angstrom_alpha, mie_g, rayleigh_scale: atmosphere truth (None: random). [1]
        sun_zenith_deg: geometric sun zenith (None: random in [20, 80]). [deg]
        camera: a key of :data:`CAMERA_SENSITIVITIES` (None: random).
        horizon_fraction: share of the horizon behind obstacles (None: random; 0: no obstacles). [1]
        n_frames: bracket frames (None: random 3-7, raised when the sun needs more range).
        exposure_ev: exposure compensation of the metered exposure (None: random in [-1.5, 0.7]). [EV]
        elevation_m: the site's elevation (None: random in [0, 1000]). [m]
        settings: the sky render settings (:data:`TEST_SETTINGS` for fast tests).
        time_and_place: reuse :func:`find_time_for_zenith`'s dict (its sun zenith wins over ``sun_zenith_deg``).
        save_arrays: also write ``truth_arrays.npz``.

    Returns:
        The truth dict written to ``truth.json`` (schema ``skyfit.photo_synth/1``).
    """
    t_start, cpu_start = time.perf_counter(), time.process_time()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    shape = (int(size), int(size)) if isinstance(size, (int, np.integer)) else (int(size[0]), int(size[1]))
    if shape[0] % 2 or shape[1] % 2 or min(shape) < 32:
        raise ValueError(f"image size must be even and >= 32 px (a Bayer mosaic has 2x2 cells), got {shape}")
    projection = projection or str(rng.choice(PROJECTIONS))
    camera_name = camera or str(rng.choice(list(CAMERA_SENSITIVITIES)))

    # ---- time, place, sun
    zenith = float(rng.uniform(20.0, 80.0)) if sun_zenith_deg is None else float(sun_zenith_deg)
    tp = time_and_place or find_time_for_zenith(zenith, rng, elevation=elevation_m)
    sun_info = tp["sun"]
    zenith = sun_info["zenith_deg"] if time_and_place is not None else zenith
    local_time = _dt.datetime.fromisoformat(tp["time"])

    # ---- atmosphere
    values = {
        "mie_aod_550": float(math.exp(rng.uniform(math.log(0.05), math.log(0.5)))) if aod_550 is None else float(aod_550),
        "mie_angstrom_alpha": float(rng.uniform(0.5, 1.8)) if angstrom_alpha is None else float(angstrom_alpha),
        "mie_g": float(rng.uniform(0.6, 0.85)) if mie_g is None else float(mie_g),
        # barometric: the Rayleigh optical depth follows the site's pressure (scale height of pressure 8434 m)
        "rayleigh_scale": float(math.exp(-tp["elevation"] / 8434.0)) if rayleigh_scale is None else float(rayleigh_scale),
    }
    grid = sky_grid(values, sun_info["zenith_deg"], settings)  # at 1 AU: shared by every date
    d2 = 1.0 / sun_info["distance_au"] ** 2  # radiance is linear in the solar irradiance
    lam = grid.wavelengths

    # ---- camera geometry and pixel directions
    cam = _draw_camera(rng, shape, projection)
    h, w = shape
    vec, valid = cam.pixel_vectors(torch.float64)
    vz = torch.where(valid[..., None], vec, torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64))
    zen_px = torch.rad2deg(torch.acos(vz[..., 2].clamp(-1, 1)))
    az_px = torch.rad2deg(torch.atan2(vz[..., 0], vz[..., 1])) % 360.0
    daz = (az_px - sun_info["azimuth_deg"] + 180.0) % 360.0 - 180.0
    sky = d2 * grid.sample(zen_px, daz.abs())  # (H, W, W_l)
    sky = torch.where(valid[..., None], sky, torch.zeros_like(sky))
    sun_vec = zenith_azimuth_to_enu(torch.tensor(math.radians(sun_info["zenith_deg"]), dtype=torch.float64),
                                    torch.tensor(math.radians(sun_info["azimuth_deg"]), dtype=torch.float64))
    sx, sy = (float(v) for v in cam.direction_to_pixel(sun_vec))
    xs, ys = cam.pixel_grid(torch.float64)
    r90 = float(cam.r90)
    deg_per_px = 90.0 / r90  # at the centre of an equidistant lens; sizes below are set in these units
    i550 = int(torch.argmin((lam - 550.0).abs()))
    sky_med = float(sky[..., i550][valid & (zen_px < 85)].median())

    # ---- obstacles (2 x 2 sub-pixel coverage) and the ground a leaning camera sees
    if horizon_fraction is None:
        horizon_fraction = float(rng.uniform(0.25, 0.4)) if rng.random() < 0.7 else float(rng.uniform(0.03, 0.2))
    sky_line = make_skyline(rng, horizon_fraction, sun_azimuth_deg=sun_info["azimuth_deg"],
                            sun_elevation_deg=90.0 - sun_info["zenith_deg"])
    step = sky_line["azimuth_deg"][1] - sky_line["azimuth_deg"][0]
    prof = torch.from_numpy(sky_line["elevation_deg"])
    segid = torch.from_numpy(sky_line["segment"])
    cover = torch.zeros(h, w, dtype=torch.float64)
    ground = torch.zeros(h, w, dtype=torch.float64)
    for ox in (-0.25, 0.25):
        for oy in (-0.25, 0.25):
            v = cam.pixel_to_direction(xs + ox, ys + oy)
            ok = torch.isfinite(v).all(-1)
            v = torch.where(ok[..., None], v, torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64))
            el = torch.rad2deg(torch.asin(v[..., 2].clamp(-1, 1)))
            a = torch.rad2deg(torch.atan2(v[..., 0], v[..., 1])) % 360.0
            k = torch.round(a / step).long() % prof.numel()
            cover += 0.25 * (ok & (el >= 0) & (el < prof[k])).double()
            ground += 0.25 * (ok & (el < 0)).double()
    el_px = 90.0 - zen_px
    k_px = torch.round(az_px / step).long() % prof.numel()
    seg_px = segid[k_px]
    occluded = cover + ground  # fraction of each pixel not sky

    from skimage.filters import gaussian  # scikit-image, imported when used (a slow import): texture fields
    tex_fine = torch.from_numpy(gaussian(rng.normal(size=shape), sigma=0.8 * w / 600 + 0.3))
    tex_coarse = torch.from_numpy(gaussian(rng.normal(size=shape), sigma=4.0 * w / 600 + 0.5))
    tex_fine, tex_coarse = tex_fine / tex_fine.std(), tex_coarse / tex_coarse.std()
    horizon_sky = d2 * grid.sample(torch.full_like(az_px, 85.0), daz.abs())  # light that reaches a facade
    e_sun = d2 * grid.sun_irradiance
    sun_el = math.radians(90.0 - sun_info["zenith_deg"])
    # a facade seen at azimuth a faces a + 180: direct sun on it by the cosine of incidence
    cos_inc = (math.cos(sun_el) * torch.cos(torch.deg2rad(az_px + 180.0 - sun_info["azimuth_deg"]))).clamp(min=0)
    obst = torch.zeros_like(sky)
    lam_np = lam.numpy()
    kinds = [s["kind"] for s in sky_line["segments"]]
    lit = {"trees": 0.25, "building": 0.6, "ridge": 0.5, "mast": 0.3}
    texture_strength = {"trees": 0.55, "building": 0.15, "ridge": 0.35, "mast": 0.1}
    for k_seg, s in enumerate(sky_line["segments"]):
        where = (seg_px == k_seg) & (cover > 0)
        if not bool(where.any()):
            continue
        rho = torch.from_numpy(_reflectance(s["material"], lam_np))
        tex = torch.exp(texture_strength[s["kind"]] * (0.7 * tex_fine + 0.5 * tex_coarse))[where]
        shade = (0.35 + 0.3 * (el_px[where] / 15.0).clamp(0, 1))[:, None]  # darker toward the foot
        illum = shade * horizon_sky[where] + (lit[s["kind"]] / math.pi) * cos_inc[where][:, None] * e_sun
        rad = rho * illum * tex[:, None]
        if s["haze"] > 0:  # aerial perspective: a distant ridge takes the colour of the horizon sky
            rad = (1 - s["haze"]) * rad + s["haze"] * horizon_sky[where]
        obst[where] = rad
    # pixels whose covering segment is not the one at their centre (edges): darkest material
    fallback = (cover > 0) & (obst.sum(-1) == 0)
    obst[fallback] = 0.3 * torch.from_numpy(_reflectance("dark_grey", lam_np)) * horizon_sky[fallback]
    ground_rad = (0.4 * torch.from_numpy(_reflectance("ground", lam_np)) * horizon_sky
                  * torch.exp(0.4 * tex_fine)[..., None])
    scene = (1 - occluded)[..., None] * sky + cover[..., None] * obst + ground[..., None] * ground_rad

    # ---- the sun through the lens: blurred disc + halo (a glare PSF over angle psi from the sun)
    psi = 2 * torch.asin((vz - sun_vec).norm(dim=-1).clamp(max=2.0) / 2)  # accurate near 0 [rad]
    blur = math.radians(float(rng.uniform(0.8, 1.6)) * deg_per_px)
    sigma_core = math.sqrt(blur ** 2 + (math.radians(0.2666) / 2) ** 2)  # disc variance alpha^2/4 per axis
    psi0 = math.radians(float(rng.uniform(0.5, 2.0)))
    p_tail = float(rng.uniform(2.5, 3.5))
    f_halo = float(math.exp(rng.uniform(math.log(0.003), math.log(0.02))))
    tt = np.linspace(0, math.pi, 200001)
    z_halo = float(np.trapezoid((1 + (tt / psi0) ** 2) ** (-p_tail / 2) * 2 * math.pi * np.sin(tt), tt))
    psf = ((1 - f_halo) * torch.exp(-0.5 * (psi / sigma_core) ** 2) / (2 * math.pi * sigma_core ** 2)
           + f_halo * (1 + (psi / psi0) ** 2) ** (-p_tail / 2) / z_halo)  # [1/sr]
    psf = torch.where(valid, psf, torch.zeros_like(psf))
    flare = psf[..., None] * e_sun
    flare_truth = {"core_sigma_deg": math.degrees(sigma_core), "lens_blur_deg": math.degrees(blur),
                   "halo_fraction": f_halo, "halo_psi0_deg": math.degrees(psi0), "halo_power": p_tail,
                   "model": "radiance += E_sun(lambda) [(1-f) exp(-psi^2/2 s^2)/(2 pi s^2) + f (1+(psi/psi0)^2)^(-p/2)/Z]"}
    extras = torch.zeros_like(sky)
    ghost_truth = None
    if rng.random() < 0.5:
        kappa = float(rng.uniform(0.3, 0.9))
        gx, gy = float(cam.cx) - kappa * (sx - float(cam.cx)), float(cam.cy) - kappa * (sy - float(cam.cy))
        g_sigma = float(rng.uniform(1.5, 4.0)) * w / 600 + 0.7
        lam0 = float(rng.uniform(450, 650))
        tint = 1 + 0.6 * torch.cos(2 * math.pi * (lam - lam0) / 300.0)
        peak = float(rng.uniform(0.5, 2.5)) * sky_med
        blob = torch.exp(-0.5 * ((xs - gx) ** 2 + (ys - gy) ** 2) / g_sigma ** 2)
        extras += blob[..., None] * (peak * e_sun * tint / float(e_sun[i550] * tint[i550]))
        ghost_truth = {"x": gx, "y": gy, "sigma_px": g_sigma, "kappa": kappa, "peak_over_sky_median_550": peak / sky_med,
                       "tint_peak_nm": lam0}
    ring_truth = None
    if rng.random() < 0.4:
        rho0, width = float(rng.uniform(0.90, 0.97)), float(rng.uniform(0.008, 0.02))
        amp = float(rng.uniform(0.02, 0.08))
        side = 1 + 0.6 * torch.cos(torch.atan2(ys - float(cam.cy), xs - float(cam.cx))
                                   - math.atan2(sy - float(cam.cy), sx - float(cam.cx)))
        mean_sky = sky[valid].mean(0)
        extras += (amp * _ring(xs, ys, float(cam.cx), float(cam.cy), r90, rho0, width) * side)[..., None] * mean_sky
        ring_truth = {"rho": rho0, "width_rho": width, "amplitude_over_mean_sky": amp,
                      "model": "radiance += a exp(-((r/R90 - rho)/width)^2/2) (1 + 0.6 cos(angle to the sun's side)) mean sky"}
    extras = torch.where(valid[..., None], extras, torch.zeros_like(extras))
    total = scene + flare + extras

    # ---- sensor
    rw, sens = camera_sensitivities(camera_name)
    source, bayer, make, model_name = CAMERA_SENSITIVITIES[camera_name]
    response = (torch.from_numpy(rw), torch.from_numpy(sens))
    m_resp = spectral_response_matrix(lam, response[1], response[0])  # (W_l, 3)
    drop = float(rng.uniform(0.0, 0.3))
    wv = float(rng.uniform(0.3, 0.9))
    v_coeffs = [1.0, 0.0, -drop * wv, 0.0, -drop * (1 - wv)]
    # the polynomial holds inside the image circle; beyond it (black anyway) it keeps its rim value
    vig = vignetting_map(lambda rho: sum(c * rho.clamp(max=1.0) ** k for k, c in enumerate(v_coeffs)), shape, cam)
    full_well = float(rng.uniform(15000, 40000))
    read_noise = float(rng.uniform(2.0, 6.0))
    bit_depth = 14
    max_dn = 2 ** bit_depth - 1
    signal = total @ m_resp  # (H, W, 3) noiseless camera signal
    lit_sig = vig[..., None] * signal
    sky_signal = scene @ m_resp
    # metering: the green median over the image circle lands at 18 % of full scale, with an exposure
    # compensation (sky photographers often underexpose to keep the highlights)
    g_med = float(lit_sig[..., 1][valid].median())
    ev_comp = float(rng.uniform(-1.5, 0.7))
    ev_comp = ev_comp if exposure_ev is None else float(exposure_ev)
    e_meter = 0.18 * 2 ** ev_comp * full_well / g_med
    peak = float(lit_sig.amax())
    e_sun_ok = float(rng.uniform(0.5, 0.85)) * full_well / peak  # sun peak below the full well
    exif_on = bool(rng.random() < 0.6)
    ev_step = None
    if bracket:
        need = math.log2(e_meter / e_sun_ok)  # EV from the sun-safe frame to the metered one
        n = int(rng.integers(3, 8)) if n_frames is None else int(n_frames)
        ev_step = float(np.clip(round(3 * need / max(n - 1, 1) + rng.uniform(-0.5, 0.5)) / 3.0, 1.0, 2.0))
        if n_frames is None:
            while n < 7 and ev_step * (n - 1) < need:
                n += 1
        nominal_rel = [2.0 ** (ev_step * k) for k in range(n)]
        jitter = [float(1 + rng.uniform(-0.04, 0.04)) for _ in range(n)]
        exposures = [e_sun_ok]  # the shortest frame; the others follow their true times below
    else:
        nominal_rel, jitter = [1.0], [float(1 + rng.uniform(-0.04, 0.04))]
        exposures = [e_meter]
    # seconds: nominal times are exact 1/3 stops 2^(-k/3) s (a camera's clock), EXIF writes the marked value
    # (1/125 for 2^-7 = 1/128); the actual exposure is nominal x jitter. K (e- per signal per second, the
    # aperture and sensitivity) is whatever makes the first frame's nominal time a plausible one.
    k0 = int(rng.integers(30, 40)) if bracket else int(rng.integers(21, 37))  # 1/1000-1/8000 s; 1/128-1/4096 s
    t_nominal = [2.0 ** (-k0 / 3.0) * r for r in nominal_rel]
    t_true = [t * j for t, j in zip(t_nominal, jitter)]
    exposures = [exposures[0] * tt / t_true[0] for tt in t_true]
    t_exif = [_marked_time(t) for t in t_nominal]

    # white balance and colour matrix
    wb_method = "daylight" if rng.random() < 0.6 else "grey_world"
    pipe = colour_pipeline(camera_name)
    ref_e = exposures[len(exposures) // 2]
    if wb_method == "daylight":
        gains = pipe["daylight_gains"] / pipe["daylight_gains"][1]
    else:
        ref = (ref_e * lit_sig / full_well).clamp(max=1.0)
        use = valid & (ref < 0.95).all(-1)
        mean = ref[use].mean(0).numpy()
        gains = mean[1] / mean
    output_space = "srgb" if rng.random() < 0.8 else "camera_rgb"
    matrix = pipe["matrix"] if output_space == "srgb" else np.eye(3)
    quality = int(rng.integers(80, 96))
    subsampling = int(rng.choice([0, 2]))  # PIL: 0 = 4:4:4, 2 = 4:2:0
    gains_t = torch.as_tensor(gains, dtype=torch.float64)
    mat_t = torch.as_tensor(matrix, dtype=torch.float64)

    cie_sky = xyz_to_linear_srgb(spectral_to_xyz(scene, lam))  # skyfit's units, sky and obstacles
    pure_sky = valid & (occluded == 0)
    psf_share = (flare + extras)[..., i550] / total[..., i550].clamp(min=1e-30)
    frames = []
    frame_dir = out / "bracket" if bracket else out
    frame_dir.mkdir(parents=True, exist_ok=True)
    gen = torch.Generator().manual_seed(int(seed) * 1009 + 17)
    for i, e in enumerate(exposures):
        photo = synthesize_photo(total, lam, camera=cam, camera_response=response, exposure=e,
                                 full_well=full_well, read_noise=read_noise, vignetting=vig, bit_depth=bit_depth,
                                 noise="poisson", generator=gen, output="raw")
        x = (photo.image / max_dn).clamp(0, 1).permute(2, 0, 1).unsqueeze(0)  # (1, 3, H, W) raw, 0..1
        clipped = photo.saturated.to(x.dtype).permute(2, 0, 1).unsqueeze(0)  # raw sites at the full well
        if bayer:  # RGGB mosaic (kornia's CFA.BG), white balance on the mosaic, clip, demosaic
            mosaic = rgb_to_raw(x * gains_t[None, :, None, None], CFA.BG)
            rgb = raw_to_rgb(mosaic.clamp(0, 1), CFA.BG)
            clip_share = raw_to_rgb(rgb_to_raw(clipped, CFA.BG), CFA.BG).amax(1, keepdim=True).clamp(0, 1)
        else:  # Foveon: three values per pixel
            rgb = (x * gains_t[None, :, None, None]).clamp(0, 1)
            clip_share = clipped.amax(1, keepdim=True)
        # highlight handling as camera JPEG engines do: where a raw channel clipped, go to white rather
        # than show the false colour of the unclipped channels
        rgb = rgb + clip_share * (1 - rgb)
        lin = torch.einsum("ij,bjhw->bihw", mat_t, rgb).clamp(0, 1)[0].permute(1, 2, 0)
        lin = torch.where(valid[..., None], lin, torch.zeros_like(lin))
        code = torch.round(255 * srgb_encode(lin)).clamp(0, 255).to(torch.uint8).numpy()
        name = f"frame_{i:02d}.jpg" if bracket else "photo.jpg"
        exif = _exif_bytes(make, model_name, local_time, t_exif[i] if exif_on else None, quality)
        Image.fromarray(code).save(frame_dir / name, quality=quality, subsampling=subsampling, exif=exif)
        # noiseless linear output over CIE linear sRGB, on unclipped sky pixels (vignetting divided out)
        clean = (mat_t @ (gains_t * (e * sky_signal * (1.0 / full_well))).unsqueeze(-1)).squeeze(-1)
        ok = pure_sky & (clean * vig[..., None] < 0.95).all(-1) & (clean > 1e-4).all(-1) & (psf_share < 0.01)
        if bool(ok.sum() > 10):
            c, r_ = clean[ok], cie_sky[ok]
            k_c = (c * r_).sum(0) / (r_ * r_).sum(0).clamp(min=1e-300)
            mis = float(((c - k_c * r_).norm(dim=-1) / (k_c * r_).norm(dim=-1)).median())
            k_list = [float(v) for v in k_c]
        else:
            k_list, mis = None, None
        sat = photo.saturated.any(-1) & valid
        sun_sat = bool(((lit_sig.amax(-1) * e) >= full_well).any())
        frames.append({
            "file": str((frame_dir / name).relative_to(out)),
            "exposure_electrons_per_signal": e,
            "relative_exposure": e / exposures[0],
            "exposure_time_s_true": t_true[i],
            "exposure_time_s_nominal": t_nominal[i],
            "exposure_time_s_exif": t_exif[i] if exif_on else None,
            "exposure_time_exif_written": exif_on,
            "saturated_fraction_of_circle": float(sat.sum() / valid.sum()),
            "sun_saturated": sun_sat,
            "linear_over_cie_rgb": k_list,
            "colour_mismatch_rel": mis,
        })

    # ---- masks and truth
    mask = np.zeros(shape, np.uint8)
    mask[(occluded > 0).numpy()] = 255
    mask[~valid.numpy()] = 64
    Image.fromarray(mask).save(out / "mask_truth.png")
    if save_arrays:
        np.savez_compressed(out / "truth_arrays.npz",
                            skyline_azimuth_deg=sky_line["azimuth_deg"].astype(np.float32),
                            skyline_elevation_deg=sky_line["elevation_deg"].astype(np.float32),
                            obstacle_coverage=cover.numpy().astype(np.float16),
                            ground_coverage=ground.numpy().astype(np.float16),
                            sky_cie_linear_srgb=cie_sky.numpy().astype(np.float32),
                            flare_share_550=psf_share.numpy().astype(np.float16),
                            vignetting=vig.numpy().astype(np.float32))
    cam_meta = cam.to_metadata()
    cx0, cy0 = (w - 1) / 2.0, (h - 1) / 2.0
    truth = {
        "schema": SCHEMA,
        "seed": int(seed),
        "photo": "bracket/" if bracket else "photo.jpg",
        "frames": frames,
        "time": tp["time"],
        "location": f"{tp['latitude']:.6f},{tp['longitude']:.6f},{tp['elevation']:.1f}",
        "latitude_deg": tp["latitude"], "longitude_deg": tp["longitude"], "elevation_m": tp["elevation"],
        "utc_offset_hours": tp["utc_offset_hours"],
        "sun": {**sun_info, "asked_zenith_deg": zenith, "model_px": [sx, sy],
                "position": "NREL SPA topocentric; zenith_deg is geometric (no refraction), as skyfit.render uses; "
                            "the sky and the sun's disc are both rendered at it"},
        "atmosphere": {
            "config": "earth",
            "parameters": values,
            "how": "skyfit.load_atmosphere('earth', wavelengths, sun_distance_au=1), then "
                   "skyfit.fit.parameters.Parameterisation(base, free=[], values=parameters).atmosphere(...) "
                   "(as skyfit.fit.results.atmosphere_from_result); rayleigh_scale = exp(-elevation_m / 8434 m), "
                   "the site's pressure ratio, unless given; radiance and sun then scaled by "
                   "(1 AU / sun.distance_au)^2",
            "sun_distance_au": sun_info["distance_au"],
        },
        "camera": {**cam_meta, "centre_offset_px": [float(cam.cx) - cx0, float(cam.cy) - cy0],
                   "r90_px": r90, "tilt_magnitude_deg": float(cam.tilt_deg.norm())},
        "vignetting": {"model": "V = sum_k c_k rho^k, rho = distance from (cx, cy) / radius_px (clamped at 1)",
                       "coeffs": v_coeffs, "rim_value": 1.0 - drop},
        "sensor": {
            "name": camera_name, "sensitivities_source": source, "exif_make": make, "exif_model": model_name,
            "mosaic": "RGGB Bayer, kornia.color.raw_to_rgb(CFA.BG) demosaicing" if bayer else "none (Foveon)",
            "full_well_e": full_well, "read_noise_e": read_noise, "bit_depth": bit_depth,
            "noise": "Poisson shot noise + Gaussian read noise, quantised to 14-bit DN (skyfit.camera.sensor)",
            "white_balance": {"method": wb_method, "gains_rgb": [float(v) for v in gains],
                              "applied": "to the raw mosaic before demosaicing, then clipped at full scale"},
            "output_space": output_space,
            "colour_matrix": [[float(v) for v in row] for row in matrix],
            "colour_matrix_how": ("colour.matrix_idt(camera, D65) to ACES2065-1, then ACES -> sRGB (CAT02), rows "
                                  "normalised to sum 1" if output_space == "srgb" else "identity: white-balanced camera RGB"),
            "encoding": "sRGB (IEC 61966-2-1), 8 bit, no tone curve",
            "jpeg_quality": quality, "jpeg_subsampling": "4:4:4" if subsampling == 0 else "4:2:0",
            "exif_exposure_time": exif_on,
            "metering": {"rule": "green median of the image circle at 18 % of full scale x 2^compensation",
                         "compensation_ev": ev_comp},
        },
        "bracket": {"frames": len(exposures), "ev_step_nominal": ev_step,
                    "ratio_jitter": jitter,
                    "sun_unsaturated_frames": [i for i, f in enumerate(frames) if not f["sun_saturated"]]}
        if bracket else None,
        "obstacles": {
            "mask_file": "mask_truth.png",
            "mask_values": {"0": "sky", "255": "obstacle or ground (any part of the pixel)", "64": "outside the lens's field"},
            "horizon_fraction_asked": horizon_fraction,
            "horizon_fraction": sky_line["fraction"],
            "max_elevation_deg": float(sky_line["elevation_deg"].max()),
            "segments": sky_line["segments"],
            "kinds": sorted(set(kinds)),
            "skyline": "truth_arrays.npz: skyline_azimuth_deg, skyline_elevation_deg",
            "pixels": int((occluded > 0).sum()),
        },
        "flare": flare_truth,
        "ghost": ghost_truth,
        "dome_ring": ring_truth,
        "photo_scale": "8-bit sRGB codes; srgb_decode(code/255) = M (wb * raw / full scale), raw = exposure * "
                       "vignetting * camera signal (+ noise), camera signal = integral of L(lambda) S_c(lambda) dlambda "
                       "with L in W/(m^2 sr nm) and S the sensitivities (green peak 1); frames[i].linear_over_cie_rgb "
                       "relates it to skyfit's CIE linear sRGB",
        "generator": {
            "module": "skyfit.tools.photo_synth", "settings": settings.key(), "sky": grid.info,
            "sky_render_cpu_s": grid.seconds,
            "case_cpu_s": time.process_time() - cpu_start, "case_wall_s": time.perf_counter() - t_start,
            "torch": torch.__version__,
        },
    }
    (out / "truth.json").write_text(json.dumps(truth, indent=1))
    return truth


def suite_plan(n: int = 10, seed: int = 0, *, size: int = 600, bracket_size: int = 300, share_sky: bool = True,
               non_square_every: int = 4) -> list[dict]:
    """The :func:`make_case` keyword arguments of each case of :func:`make_suite` (no rendering).

    Case i uses projection ``PROJECTIONS[i % 5]`` and is a bracket when ``(i // 5 + i % 5) % 2 == 1`` (ten
    cases cover every projection with and without a bracket); AOD 550 and sun zenith are stratified
    (log-spaced 0.05-0.5 and evenly 20-80° in a seeded order). With ``share_sky`` pairs of cases share an
    atmosphere and the site's elevation (not the sun), so the Bruneton tables are computed once for both.
    Every ``non_square_every``-th single photo has a 3:4 sensor (height ``size``).
    """
    rng = np.random.default_rng(seed)
    n_atm = (n + 1) // 2 if share_sky else n
    aods = np.exp(np.linspace(math.log(0.05), math.log(0.5), max(n_atm, 1)))[rng.permutation(max(n_atm, 1))]
    zeniths = np.linspace(20.0, 80.0, max(n, 1))[rng.permutation(max(n, 1))]
    plan = []
    singles = 0
    for i in range(n):
        bracket = (i // len(PROJECTIONS) + i % len(PROJECTIONS)) % 2 == 1
        a = i // 2 if share_sky else i
        arng = np.random.default_rng([seed, a])
        kw = {"seed": int(seed) * 1000 + i, "projection": PROJECTIONS[i % len(PROJECTIONS)], "bracket": bracket,
              "aod_550": float(aods[a]), "angstrom_alpha": float(arng.uniform(0.5, 1.8)),
              "mie_g": float(arng.uniform(0.6, 0.85)), "elevation_m": float(arng.uniform(0.0, 1000.0)),
              "sun_zenith_deg": float(zeniths[i])}
        if bracket:
            kw["size"] = bracket_size
        else:
            singles += 1
            square = not (non_square_every and singles % non_square_every == 0)
            kw["size"] = size if square else (size, (size * 4 // 3) // 2 * 2)
        plan.append(kw)
    return plan


def make_suite(out_dir: str | Path, n: int = 10, seed: int = 0, *, size: int = 600, bracket_size: int = 300,
               settings: SynthSettings = SynthSettings(), share_sky: bool = True, non_square_every: int = 4,
               progress=None) -> list[dict]:
    """``n`` cases in ``out_dir/case_NNN`` spread over the five projections, with and without brackets.

    The spread is :func:`suite_plan`'s: every projection with and without a bracket in each ten cases,
    AOD 550 log-spaced over 0.05-0.5, sun zenith over 20-80°, a 3:4 sensor every few single photos;
    pairs of cases share an atmosphere (``share_sky``) so that one Bruneton precomputation serves both.

    Returns:
        The truth dicts, also summarised in ``out_dir/suite.json``.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    truths = []
    for i, kw in enumerate(suite_plan(n, seed, size=size, bracket_size=bracket_size, share_sky=share_sky,
                                      non_square_every=non_square_every)):
        kw = dict(kw)
        t0 = time.perf_counter()
        truth = make_case(kw.pop("seed"), out / f"case_{i:03d}", settings=settings, **kw)
        truths.append(truth)
        if progress:
            progress(f"case_{i:03d}: {kw['projection']}, {'bracket' if kw['bracket'] else 'single'}, "
                     f"AOD {kw['aod_550']:.3f}, sun zenith {truth['sun']['zenith_deg']:.2f}, "
                     f"{time.perf_counter() - t0:.1f} s")
    summary = [{"case": f"case_{i:03d}", "projection": t["camera"]["projection"], "bracket": t["bracket"] is not None,
                "mie_aod_550": t["atmosphere"]["parameters"]["mie_aod_550"], "sun_zenith_deg": t["sun"]["zenith_deg"],
                "time": t["time"], "location": t["location"], "case_wall_s": t["generator"]["case_wall_s"]}
               for i, t in enumerate(truths)]
    (out / "suite.json").write_text(json.dumps({"schema": SCHEMA, "seed": seed, "cases": summary}, indent=1))
    return truths
