"""A sky photo as a user has it -> the atmosphere behind it: camera from the image, masks, fit, report.

The path of ``skyfit fit PHOTO --time T --location LAT,LON[,ELEV]`` (CONTRACT.md, "Photos"),
as plain functions on in-memory objects:

1. **read** (:func:`skyfit.io.photo.read_photo`): JPEG/PNG/TIFF, RAW, ``.hdr``, EXR or a
   bracket folder -> one linear image with per-pixel variance and censoring;
2. **the sun** by NREL SPA from the time and place (:func:`skyfit.camera.sun_position`);
3. **the camera** (:mod:`skyfit.camera.autocal`, :func:`cameras_from_image`): the lens circle from
   the image, the sky's mirror axis (the sun's vertical), the sun's saturated core (or, in a saturated
   aureole, its place on that axis), one candidate camera per projection with the heading that puts
   the computed sun on the detected one, ranked by how well each projection puts it at the detected
   radius; projections the sun cannot tell apart (:func:`projection_decision`) are fitted briefly, the
   best two race for :data:`RACE_REFRESHES` refreshes on :data:`RACE_SAMPLES` blocks (one far behind is
   dropped there), the rest are converged and the lower loss wins; the short fits, the race and the two
   converging fits run side by side on a multi-core CPU (:mod:`skyfit.fit.side_by_side`); ``camera=``
   (a :class:`~skyfit.camera.FisheyeCamera` or CAMERA.yaml) skips this;
4. **what is not sky** (:mod:`skyfit.camera.masks`): outside the circle, below the horizon, the
   sun's disc and flare, horizon obstacles, the user's mask; saturated and black pixels are
   *censored* (bounds), not dropped;
5. **blocks**: the photo is averaged over square blocks (about :data:`TARGET_SAMPLES` of them
   inside the circle; a block with a masked pixel is left out), which keeps a fit's cost
   independent of the photo's size and averages away JPEG and demosaicing noise; the block
   image is itself a fisheye image of the same camera, scaled;
6. **fit** (:func:`skyfit.fit.problem.prepare`, the one fit-problem builder): the aerosol
   (``mie_aod_550``, ``mie_angstrom_alpha``, ``mie_g``) with the camera's nuisances (exposure,
   white-balance gains, vignetting, heading as ``sun_azimuth_offset``, tilt), robust (Cauchy)
   loss; then the pixels the first fit cannot explain (obstacles the image tests missed) are
   masked (:func:`skyfit.camera.masks.grow_outlier_mask`) and the fit is repeated;
7. **report**: RESULT.json's ``camera``, ``sun``, ``aerosol``, ``metrics.rmse_rel``, ``pixels``,
   and RESULT.png (photo, model, residual, mask).

Units: photo values are linear and relative (an unknown exposure scales them); angles in the
result in degrees, pixel positions in the photo's pixels, x = column, y = row (CONTRACT.md).
"""
from __future__ import annotations

import copy
import dataclasses
import math
import os
import time
from pathlib import Path
from typing import TYPE_CHECKING, Sequence

import numpy as np
import scipy.stats
import torch

from ..atmosphere.constants import PRESSURE_SCALE_HEIGHT_M
from ..camera.autocal import (SRGB_LUMA, CalibrationError, CameraGuess, Circle, SunDetection, cameras_from_sun,
                              detect_circle, detect_sun, symmetry_axis)
from ..camera.fisheye import CLASSICAL_PROJECTIONS, FisheyeCamera, theta_to_rho, zenith_azimuth_to_enu
from ..camera.icc import icc_sensitivities
from ..camera.masks import SUN_MASK_MAX_DEG, grow_outlier_mask, obstacle_mask, sun_mask
from ..camera.sun import parse_location, parse_time, sun_position
from ..geometry import zenith_angle_deg
from ..io.photo import LinearPhoto, block_view, exif_location, exif_stamps, read_photo, reduced_photo
from ..scattering.bruneton_tables import SUN_MARGIN_DEG, SUN_SPACING_DEG
from ..scattering.bruneton_tables import sun_window as sun_mu_s_window
from .data import Observation
from .model import FitProblem, aerosol_log_depth, applied_lens, lens_directions, sun_zenith_span, tilt_directions
from .optimise import CURVED_PRECISION_TOL, curved, resolved_method
from .optimise import fit as optimise
from .parameters import CAMERA_RESPONSE, NUISANCE
from .problem import fit_settings, make_model, prepare
from .side_by_side import in_child, side_by_side

if TYPE_CHECKING:
    from .model import SkyModel

TARGET_SAMPLES = 1000
"""About this many blocks inside the lens circle are fitted, whatever the photo's size."""
QUICK_SAMPLES = 400
"""Blocks of the short fits that choose among projections or starting headings."""
MS_REFRESHES = 6
"""At most this many fits with the multiple-scattering tables frozen and refreshed (:func:`lagged_fit`) in a photo
fit: from the default AOD 0.1 a hazy sky's 0.3 takes two trust-region steps (:data:`MS_AOD_TRUST`) and two or three
to settle."""
LAGGED_REFRESHES = 3
"""The same for ``multiple: bruneton_lagged`` in ``skyfit fit`` of other data (no :class:`PhotoProblem`: the factor
held fixed between refreshes, which stop when it changes by < 1 %)."""
PHOTO_FREE = ("mie_aod_550", "mie_angstrom_alpha", "mie_g", "exposure", "gain_red", "gain_blue", "saturation_red",
              "saturation_blue", "vignetting", "sun_azimuth_offset", "camera_tilt_north", "camera_tilt_east")
"""Free parameters of a photo fit: the aerosol and the camera's nuisances. Rayleigh's scale stays at the
config's (a photo of unknown exposure and white balance hardly separates it from the aerosol: add it with
``free=``); the aerosol's scale height stays at the config's (a ground photo sees the column, not its shape).
The lens's departure from the chosen projection (``lens_radial``) is not fitted to the sky alone, which trades it
against the aerosol: :func:`lens_from_sun` measures it from a compact sun between the passes, and a refit goes on from
there with it and the tilt free (:data:`LENS_WITH_TILT`)."""
CALIBRATED_FREE = ("mie_aod_550", "mie_angstrom_alpha", "mie_g", "exposure", "sun_azimuth_offset")
"""Free parameters when the camera is given (``camera=``): its geometry, gains, saturations and vignetting are
known (a file without ``saturation_red`` / ``saturation_blue`` holds them at 1, a colorimetric camera)."""
PHOTO_TABLES = (64, 32, 16, 8, 16, 128, 16, 8)
"""Bruneton table sizes of a photo fit's multiple-scattering factor (transmittance mu, r, irradiance mu_s, r,
scattering r, mu, mu_s, nu; since session 16 the scattering mu_s axis spans only the photo's sun, in the texels
:func:`sun_window` sets, instead of these 16 over 2017's axis), built on :data:`MS_WAVELENGTH_NODES` wavelengths, with Gauss-Legendre view rays (``ray_rule: gauss`` in
:data:`PHOTO_SETTINGS`). On a hazy sky (AOD 0.3, g 0.82, sun at 23 deg) 2017's 50-interval trapezoid along the view
ray put orders >= 2 1.43-2.18x above a converged reference (mu 128, 200 Gauss nodes, 32 x 64 density directions)
at every elevation; the same 51 nodes by Gauss-Legendre 1.01-1.05x away from the sun, 1.17x at the zenith (the
16 x 32 density directions) and, with 64 mu samples, 1.43-1.58x within 25 deg of the sun; 128 mu samples give
1.00-1.11x there (docs/multiple/hazy_convergence.json; ``scripts/ms_hazy_convergence.py``). A generator with those
converged tables (session 14, docs/photos.md "A generator with converged multiple scattering") showed what the 64
cost: hazy skies under a high sun fitted 12-43 % low in AOD (held-out case 0, AOD 0.39 at sun zenith 20 deg: -43 %
with mu 64, -3.7 % with 128). 128 mu samples cost a build 1.7-2x (the 16 x 32 density directions stay: 32 x 64 would
cost another ~2x for the zenith's 1.17x)."""
PHOTO_DENSITY = (16, 32, 2)
"""Incident directions of the scattering density in a photo fit's tables (``fit.density_directions``; theta, phi,
zenith bands split: :attr:`skyfit.scattering.multiple.Quadrature.density_zenith`): 2017's 16 x 32 with the two bands
nearest the zenith halved, 576 directions. With 2017's 512 a hazy sky's orders >= 2 (AOD 0.3, g 0.82, sun at 23 deg)
came out 16 % high at the zenith and 11 % high 30 deg from it towards the sun, where each view's forward peak sits at
the grid's pole; with the split bands every view of scripts/ms_hazy_convergence.py is within 1 % of the converged
tables with the sun at 23 deg, and the zenith within 1.1 % with the sun at 50 and 70 deg (the worst view there 3.1 and
3.6 % low, near the sun and the horizon, as with 32 x 32's 1.6 and 3.2 %), for 12 % more directions where 32 x 32
doubles them (docs/multiple_scattering.md, "The density directions' pole"; session 14 had measured seed-0 case 6,
AOD 0.30 at sun zenith 23 deg, at -15.6 % with 16 x 32 and -9.7 % with 32 x 64)."""
PHOTO_CLUSTERS = 24
"""Sky regions of a photo fit's discrepancy term (``fit.sigma_clusters``; :func:`skyfit.fit.budget.robust_sandwich_share`):
8 scattering-angle x 3 view-zenith bins of ~120 blocks each, twice the 12 free parameters of a photo fit (the
sandwich needs G - 1 >= P; its variances' relative spread is about sqrt(2 / (G - 1)), 0.3)."""
PHOTO_SETTINGS = {"loss": "cauchy", "orders": 4, "multiple": "bruneton", "table_sizes": list(PHOTO_TABLES), "ray_rule": "gauss",
                  "density_directions": list(PHOTO_DENSITY), "starts": 1, "adam_steps": 30, "max_iter": 80, "sigma_clusters": PHOTO_CLUSTERS,
                  "initial": {"mie_aod_550": 0.1, "mie_angstrom_alpha": 1.0, "mie_g": 0.7}, "sigma_phase": False}
"""Fit settings of a photo unless the config's ``fit:`` section or keywords say otherwise: a robust loss
(obstacles the masks miss); four orders of Bruneton's tables (:data:`PHOTO_TABLES`) frozen per fit around live single
scattering (:func:`lagged_fit`), since multiple scattering makes a third to a half of a hazy sky's radiance, and
Hillaire's isotropic approximation of it biased the aerosol (docs/photos.md). The phase term (``sigma_phase``, on for
other fits) stays off: its two-term refit holds the reference's factor where a photo follows its own, and it is not
measured on photos; a photo's sigma has the validation term (:data:`PHOTO_VALIDATION_SIGMA`) instead."""
SIGMA_RELATIVE = 0.03
"""Relative error of a block's value besides its measured variance: JPEG, demosaicing, the sensor's
non-linearity, the model's own error (docs/photos.md). [1]"""
PHOTO_VALIDATION_SIGMA = {"aod_550": ("relative", 0.088), "angstrom_alpha": ("absolute", 0.20), "g": ("absolute", 0.004)}
"""The photo path's expected error beyond the fit's own budget (a GUM Type B term, as MODIS and AERONET state an
expected error from validation): what the 20 synthetic photos of ``scripts/photo_study.py`` (published camera
sensitivities, Bayer, JPEG, flare, dome, vignetting, obstacles) put between the truth and the fit that no residual
shows, because the camera's gains, saturations, vignetting and exposure absorb it. Each value is the maximum-likelihood
s of e_i ~ N(0, sigma_i^2 + (s a_i)^2) over the 20 photos of seed 0 (a_i the fitted AOD for ``relative``, 1 for
``absolute``; 0.0878, 0.200, 0.0043), checked on the 20 of seed 1 (docs/photos.md, "Honest sigma of a photo"). Added in quadrature to
``aerosol.sigma``; ``aerosol.sigma_statistical`` is the budget's alone. (kind, value) [1]"""
SECOND_PASS_REFRESHES = 2
"""Fits of the second pass (outliers masked, from the first pass's values and tables): a second after a rebuild only
where the first moved an optical depth beyond :data:`MS_AOD_SETTLE`, so that the result is never a fit against a
factor the rebuilt one contradicts (synthetic held-out case 15 ended at loss 6.4 after one). [1]"""
OUTLIER_THRESHOLD = 0.25
"""A block whose relative residual after the first fit exceeds this is a candidate obstacle. [1]"""
OUTLIER_MAX_ELEVATION_DEG = 40.0
OUTLIER_SUN_DISTANCE_DEG = 30.0
"""Outliers of the first fit are masked below this elevation (obstacles on the horizon) or this far from the sun
(masts, dome reflections); nearer the sun and higher up a misfit is the model's (the aureole), and masking it
would throw away what measures the aerosol best. [deg]"""
OUTLIER_NOTE_FRACTION = 0.2
"""When the second pass masks more than this share of the sky the first fit used as outliers, the result says so in
a note: the rest carries the fit, and so much misfit is more than a missed obstacle (clouds, a camera the first fit
got wrong). Synthetic cases 2 and 4 with clouds over 15 % of their sky (docs/photos.md, "Clouds") stay under it (13 and
15 % of the used blocks); case 2 with clouds over 30 % of it, one on the sun's aureole, masked 47 %. [1]"""
SUN_NOTE_DEG = 2.0
"""When the fitted camera puts the sun further than this from its detection, the result says so in a note: twice
what the synthetic photos are asked (the sun within 1 deg), met on all 20 of them (docs/photos.md). [deg]"""


class PhotoFitError(ValueError):
    """A photo that cannot be fitted as given (one line naming the file and the problem)."""


@dataclasses.dataclass
class PhotoScene:
    """A photo made ready for a fit: linear data, the sun, the camera and what is not sky.

    Attributes:
        photo: the linear photo (:class:`skyfit.io.photo.LinearPhoto`).
        sun_zenith_deg, sun_azimuth_deg: by SPA at the photo's time and place. [deg]
        sun_distance_au: Earth-Sun distance. [AU]
        time: ISO 8601 with offset; location: {latitude_deg, longitude_deg, elevation_m}.
        camera: the camera (given, or the best guess from the image).
        candidates: the calibration's ranked guesses (empty when the camera was given).
        detected_sun: the sun's saturated core in the image, or None.
        circle: the detected lens circle (None when the camera was given).
        masks: (H, W) bool, True = not used: ``outside``, ``horizon``, ``sun``, ``obstacles``, ``user``.
        notes: what a user should know (estimated exposures, hidden sun, ...).
        seconds: time of each step so far. [s]
        scale: the photo as read has ``scale`` x ``scale`` pixels per pixel of ``photo``, the camera, the sun and
            the masks (a large photo is fitted reduced: :data:`PHOTO_MAX_SIDE`); RESULT.json gives pixels of the
            photo as read.
    """

    photo: LinearPhoto
    sun_zenith_deg: float
    sun_azimuth_deg: float
    sun_distance_au: float
    time: str
    location: dict
    camera: FisheyeCamera
    candidates: list
    detected_sun: object | None
    circle: object | None
    masks: dict
    notes: list
    seconds: dict
    scale: int = 1
    """Pixels of the photo as read per pixel of ``photo`` (:data:`PHOTO_MAX_SIDE`; 1: fitted at full size)."""
    mirror: bool = False
    """The photo was flipped left-right before anything else (a camera file's ``mirror: true``)."""
    sun_mask_max_deg: float | None = SUN_MASK_MAX_DEG
    """Largest radius of the sun's mask, as :func:`prepare_scene` was given it (kept for :func:`with_camera`). [deg]"""

    @property
    def excluded(self) -> np.ndarray:
        """(H, W) bool: masked for any reason."""
        out = np.zeros(self.photo.rgb.shape[:2], bool)
        for m in self.masks.values():
            out |= m
        return out


# -- camera files --------------------------------------------------------------------------------
CAMERA_KEYS = ("projection", "size", "width", "height", "cx", "cy", "radius_px", "focal_px", "kb_coeffs", "up_azimuth_deg",
               "tilt_deg", "max_zenith_deg", "vignetting", "gain_red", "gain_blue", "saturation_red",
               "saturation_blue", "spectral_sensitivities", "mirror")
CAMERA_INFO_KEYS = ("convention", "rotation", "model", "tilt_zenith_deg", "tilt_azimuth_deg", "source", "photos",
                    "nominal_projection", "lens_radial")
"""Keys a camera file may carry for the reader's information (the camera is the CAMERA_KEYS'; ``nominal_projection``
and ``lens_radial`` say which projection and lens departure its Kannala-Brandt polynomial writes)."""


def read_camera(path: str | Path) -> dict:
    """CAMERA.yaml (``skyfit calibrate-camera`` writes it) as a dict; ValueError naming the file and the problem.

    Keys: ``projection``, ``cx``, ``cy``, ``radius_px`` (classical) or ``focal_px`` + ``kb_coeffs``
    (kannala_brandt), optional ``up_azimuth_deg``, ``tilt_deg`` [deg], ``max_zenith_deg``, ``vignetting``
    (v of 1 + v r^2), ``gain_red``/``gain_blue``, ``saturation_red``/``saturation_blue``, and ``spectral_sensitivities`` (a CSV of wavelength [nm],
    R, G, B, relative to this file). ``size`` may be left out: the photo's is used. ``mirror: true``: the camera sees
    the sky mirrored (through a convex mirror, or an image flipped East-right); its photos are flipped left-right
    before anything else, and every pixel value of the file and of RESULT.json is of the flipped image. Without ``projection`` the file
    gives the camera's colour only (sensitivities, gains, saturations, vignetting) and the lens comes from the image
    (:func:`prepare_scene`). With ``spectral_sensitivities`` the saturations are 1 unless the file gives them: the
    curves render the camera's colour (those of its output, matrix and white balance included, where it is not raw).
    """
    import yaml

    p = Path(path)
    try:
        data = yaml.safe_load(p.read_text())
    except FileNotFoundError:
        raise PhotoFitError(f"camera file {p}: not found") from None
    except (OSError, yaml.YAMLError) as e:
        raise PhotoFitError(f"camera file {p}: cannot read it: {str(e).splitlines()[0]}") from None
    if not isinstance(data, dict):
        raise PhotoFitError(f"camera file {p}: expected a mapping of camera parameters")
    unknown = sorted(set(data) - set(CAMERA_KEYS) - set(CAMERA_INFO_KEYS))
    if unknown:
        raise PhotoFitError(f"camera file {p}: unknown key(s) {', '.join(unknown)}; valid: {', '.join(CAMERA_KEYS)}")
    if "spectral_sensitivities" in data and data["spectral_sensitivities"] is not None:
        data["spectral_sensitivities"] = str((p.parent / str(data["spectral_sensitivities"])).resolve())
        read_sensitivities(data["spectral_sensitivities"])  # a bad curves file is refused before any work
    if not isinstance(data.get("mirror", False), bool):
        raise PhotoFitError(f"camera file {p}: mirror must be true or false, got {data['mirror']!r}")
    data["_source"] = str(p)
    return data


def camera_from_dict(meta: dict, shape: tuple[int, int], photo: str | None = None) -> FisheyeCamera:
    """A :class:`FisheyeCamera` of a camera file's dict (or a photo fit's RESULT.json ``camera``) for a photo of
    ``shape`` (H, W); ``photo`` names it in the error of a camera made for another size."""
    m = {k: v for k, v in meta.items() if k in CAMERA_KEYS and k != "mirror"}
    h, w = shape
    size = m.get("size")
    if size is not None and tuple(np.atleast_1d(size).tolist()) not in ((h, w), (w,) if h == w else ()):
        hw = "x".join(str(int(v)) for v in (np.atleast_1d(size).tolist() * 2)[:2])
        what = f"camera file {meta['_source']}" if meta.get("_source") else "the camera (a photo fit's)"
        raise PhotoFitError(f"{what}: made for {hw} px images, the photo{' ' + str(photo) if photo else ''} is {h}x{w} px "
                            "(a camera is for one image size)")
    m["size"] = [h, w] if h != w else h
    try:
        return FisheyeCamera.from_metadata(m)
    except ValueError as e:
        raise PhotoFitError(f"camera file {meta.get('_source', '')}: {e}") from None


def read_sensitivities(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """A CSV of spectral sensitivities: wavelength [nm], R, G, B per row, or wavelength and one curve for a monochrome
    camera (a header line allowed) -> (K,), (K, 3) or (K, 1)."""
    p = Path(path)
    try:
        arr = np.genfromtxt(p, delimiter=",", comments="#", skip_header=0)
        if np.isnan(arr[0]).all():
            arr = arr[1:]
    except (OSError, ValueError) as e:
        raise PhotoFitError(f"spectral sensitivities {p}: cannot read: {e}") from None
    if arr.ndim != 2 or arr.shape[1] not in (2, 4) or arr.shape[0] < 3 or not np.isfinite(arr).all():
        raise PhotoFitError(f"spectral sensitivities {p}: need rows 'wavelength_nm,R,G,B' (or 'wavelength_nm,S' for a "
                            "monochrome camera; >= 3 rows, finite)")
    if not np.all(np.diff(arr[:, 0]) > 0):
        raise PhotoFitError(f"spectral sensitivities {p}: wavelengths must increase")
    # an output's curves (a camera's sensitivities through its colour matrix, as the CIE observer's through sRGB's)
    # may dip below 0; each channel must still respond to white light
    if not (np.trapezoid(arr[:, 1:], arr[:, 0], axis=0) > 0).all():
        raise PhotoFitError(f"spectral sensitivities {p}: each channel's integral over wavelength must be > 0")
    return arr[:, 0], arr[:, 1:]


MONO_HELD = ("gain_red", "gain_blue", "saturation_red", "saturation_blue", "mie_angstrom_alpha")
"""Not fitted to a monochrome photo: its one channel has no white balance or colour rendering, and one band cannot
measure the aerosol's spectral slope (the Angstrom exponent stays at the config's value unless ``free`` names it;
the AOD at 550 nm, which a panchromatic band centred near it measures, moves with it by a few per cent: docs/photos.md)."""


def check_sensitivities(curves: np.ndarray, mono: bool, path: str, source: str) -> None:
    """PhotoFitError unless a grey photo has one curve and a colour photo three."""
    if mono and curves.shape[1] != 1:
        raise PhotoFitError(f"photo {source}: a grey image, but the camera file's spectral sensitivities {path} have "
                            "three curves; give one, 'wavelength_nm,S'")
    if not mono and curves.shape[1] != 3:
        raise PhotoFitError(f"photo {source}: a colour image, but the camera file's spectral sensitivities {path} have "
                            "one curve (a monochrome camera's); give R, G and B")


def mono_response(camera_meta: dict | None, source: str) -> tuple[np.ndarray, np.ndarray]:
    """The spectral sensitivity of a monochrome photo's one channel, repeated for the three equal channels it is read
    as: the camera file's one curve, else the CIE 1931 photopic luminance 683 y-bar (a colorimetric grey, as a colour
    photo's default is linear sRGB of the CIE observer)."""
    if camera_meta and camera_meta.get("spectral_sensitivities"):
        wl, curves = read_sensitivities(camera_meta["spectral_sensitivities"])
        check_sensitivities(curves, True, camera_meta["spectral_sensitivities"], source)
    else:
        from ..render.colour import _cmfs

        wl, cmf = _cmfs()
        curves = 683.0 * cmf[:, 1:2]
    return wl, np.repeat(curves, 3, axis=1)


# -- the scene ------------------------------------------------------------------------------------
def time_and_place(source: str, time: str | None, location, fallback_location=None) -> tuple[str, object, list[str]]:
    """(time, location, notes): those given, else the photo's EXIF ones: DateTimeOriginal with its OffsetTimeOriginal
    (EXIF 2.31; a bracket's earliest frame) and the GPS position (:func:`skyfit.io.photo.exif_location`), else
    ``fallback_location`` (``evaluate``: the fit's own site); a note for each taken so. PhotoFitError (one line) for
    what is neither given nor in the file: a time without its UTC offset is not guessed."""
    notes: list[str] = []
    exists = bool(source) and os.path.exists(source)
    if time is None:
        stamps = exif_stamps(source) if exists else []
        if not stamps:
            raise PhotoFitError(f"photo {source}: no time: give --time (ISO 8601 with its UTC offset); the file's EXIF "
                                "has no DateTimeOriginal")
        when, offset = min(stamps, key=lambda st: st[0])
        if offset is None:
            raise PhotoFitError(f"photo {source}: its EXIF time {when.isoformat()} has no UTC offset (no "
                                f"OffsetTimeOriginal); give --time with one, e.g. {when.isoformat()}+02:00")
        time = when.isoformat() + offset
        notes.append(f"the time from EXIF: {time} (DateTimeOriginal and OffsetTimeOriginal; a camera's clock can be off: "
                     "check the sun's separation)")
    if location is None:
        loc = exif_location(source) if exists else None
        if loc is not None:
            lat, lon, alt = loc
            location = (lat, lon, 0.0 if alt is None else alt)
            notes.append(f"the location from EXIF GPS: {lat:.5f}, {lon:.5f}, "
                         + (f"{alt:.0f} m" if alt is not None else "no altitude (0 m taken)"))
        elif fallback_location is not None:
            location = fallback_location
            notes.append("the location of the fit (the photo has none in EXIF)")
        else:
            raise PhotoFitError(f"photo {source}: no place: give --location LAT,LON[,ELEV]; the file's EXIF has no GPS "
                                "position")
    return time, location, notes


def _luminance(rgb: np.ndarray) -> np.ndarray:
    return rgb @ SRGB_LUMA


def prepare_scene(photo: str | Path | LinearPhoto, *, time: str | None = None, location=None, camera: FisheyeCamera | dict | str | Path | None = None,
                  mask: np.ndarray | None = None, exposures: Sequence[float] | None = None, linear: bool = False,
                  response: str | None = None, projections: Sequence[str] = CLASSICAL_PROJECTIONS,
                  sun_mask_max_deg: float | None = SUN_MASK_MAX_DEG, site=None) -> PhotoScene:
    """Read the photo, place the sun, find the camera and the masks (steps 1-4 of the module docstring).

    Args:
        photo: a photo path (any format of :func:`skyfit.io.photo.read_photo`, or a bracket folder) or a read photo.
        time: ISO 8601 with a UTC offset or a zone name; None: the photo's EXIF (:func:`time_and_place`).
        location: "LAT,LON[,ELEV]" or (lat, lon[, elev]) [deg, deg, m]; None: the photo's EXIF GPS position.
        camera: a FisheyeCamera, a camera dict (:func:`read_camera`) or CAMERA.yaml; None: from the image.
        mask: (H, W) bool, True = ignore (the user's own).
        exposures, linear, response: for :func:`read_photo`.
        projections: the candidate projections when the camera is not given.
        sun_mask_max_deg: largest radius of the sun's mask (:func:`scene_masks`). [deg]
        site: the location when neither ``location`` nor the photo's EXIF gives one (``evaluate``: the fit's).

    Raises:
        PhotoFitError / PhotoError / CalibrationError (ValueErrors): one line naming the file and the problem.
    """
    seconds: dict = {}
    t0 = _now()
    time, location, where = time_and_place(photo.source if isinstance(photo, LinearPhoto) else str(photo), time, location,
                                           site)
    if not isinstance(photo, LinearPhoto):
        photo = read_photo(photo, linear=linear, exposures=exposures, response=response)
    src = photo.source
    H, W = photo.rgb.shape[:2]
    scale = reduction_factor((H, W))
    if mask is not None:
        mask = np.asarray(mask, bool)
        if mask.shape != (H, W):
            raise PhotoFitError(f"photo {src}: the mask is {mask.shape[0]}x{mask.shape[1]}, the photo {H}x{W}")
    if isinstance(camera, (str, Path)):
        camera = read_camera(camera)
    if isinstance(camera, dict) and camera.get("spectral_sensitivities"):  # refused before any work
        curves = read_sensitivities(camera["spectral_sensitivities"])[1]
        check_sensitivities(curves, bool(photo.meta.get("monochrome")), camera["spectral_sensitivities"], src)
    mirror = isinstance(camera, dict) and bool(camera.get("mirror"))
    if mirror:  # a mirrored view of the sky: flipped left-right it is a camera's looking up
        photo = mirrored_photo(photo)
        mask = None if mask is None else mask[:, ::-1].copy()
    if scale > 1:
        photo = reduced_photo(photo, scale)
        h, w = photo.rgb.shape[:2]
        if mask is not None:  # a block is ignored where any of its pixels is
            mask = block_view(mask, scale, h, w).any(2)
        photo.meta["notes"] = list(photo.meta.get("notes", [])) + [
            f"the {H}x{W} px photo is fitted at 1/{scale} of its size ({h}x{w} px of {scale}x{scale} px means; "
            f"skyfit.fit.photo.PHOTO_MAX_SIDE {PHOTO_MAX_SIDE}); RESULT.json's pixel positions are the photo's own"]
    seconds["read"] = _now() - t0
    h, w = photo.rgb.shape[:2]
    try:
        lat, lon, elev = parse_location(location) if isinstance(location, str) else (tuple(float(v) for v in location) + (0.0,))[:3]
        when = parse_time(time)
    except (TypeError, ValueError) as e:
        raise PhotoFitError(f"photo {src}: {e}") from None
    sp = sun_position(when, lat, lon, elev)
    sz, sa = float(sp.zenith), float(sp.azimuth)
    if sz >= 90.0:
        raise PhotoFitError(f"photo {src}: the sun is below the horizon at {when.isoformat()} (zenith {sz:.2f} deg); "
                            "night and twilight skies are not fitted")
    notes = list(photo.meta.get("notes", [])) + where
    t1 = _now()
    candidates, circle, detected = [], None, None
    inside_valid = photo.valid
    if mirror:
        notes.append("the camera is mirrored (its file's mirror: true): the photo is fitted flipped left-right, and "
                     "RESULT.json's pixel positions are of the flipped photo")
    if isinstance(camera, dict) and camera.get("projection") is None:  # a file of the camera's colour only
        notes.append(f"camera file {camera.get('_source', '')} gives no lens (no projection): the lens circle, projection "
                     "and heading from the image")
        camera = None
    try:
        if camera is None:
            circle, detected, candidates = cameras_from_image(photo, sz, sa, projections)
            cam = candidates[0].camera
            notes.extend(candidates[0].notes)
        else:
            cam = camera if isinstance(camera, FisheyeCamera) else camera_from_dict(camera, (H, W), src)
            if tuple(cam.shape) != (H, W):
                raise PhotoFitError(f"photo {src}: the camera is for {cam.height}x{cam.width} images, the photo is {H}x{W}")
            if scale > 1:
                cam = scaled_camera(cam, scale, (h, w))
            cxy = (float(cam.cx), float(cam.cy))
            axis = symmetry_axis(_luminance(np.where(np.isfinite(photo.rgb), photo.rgb, 0.0)), *cxy, float(cam.r90),
                                 photo.valid)
            detected = detect_sun(photo.darkest, photo.darkest_saturated, cam.valid_mask().numpy() & inside_valid,
                                  centre=cxy, axis_deg=axis)
        seconds["calibrate"] = _now() - t1
        if detected is None:
            notes.append("the sun is not seen in the photo (hidden or outside the view): the heading comes from the sky pattern")
        masks = scene_masks(photo, cam, detected, sz, sa, mask, sun_mask_max_deg)
    except CalibrationError as e:
        hint = ("; a lens whose image fills the frame has no circle to find: give it with --camera CAMERA.yaml "
                "(docs/photos.md)" if camera is None and "no fisheye circle found" in str(e) else "")
        raise PhotoFitError(f"photo {src}: {e}{hint}") from None
    if not bool((~_union(masks)).any()):
        raise PhotoFitError(f"photo {src}: no sky pixel left (the lens circle, horizon, sun and masks cover everything)")
    return PhotoScene(photo, sz, sa, float(sp.distance_au), when.isoformat(),
                      {"latitude_deg": float(lat), "longitude_deg": float(lon), "elevation_m": float(elev)},
                      cam, candidates, detected, circle, masks, notes, seconds, scale, mirror, sun_mask_max_deg)


PHOTO_MAX_SIDE = 1200
"""A photo whose longer side exceeds this is fitted reduced by the smallest integer factor that brings it within
(:func:`skyfit.io.photo.reduced_photo`: block means, censoring kept as bounds). The fit uses about
:data:`TARGET_SAMPLES` blocks whatever the size, and the calibration's and the masks' pixel scales (Canny's sigma,
RANSAC thresholds, the obstacles' texture window and morphology) were set on photos of 120-800 px; at full size a
3000 x 3000 photo took 5.3 GB and 78 s against 47 s for the same sky at 600 px, its masks alone 23 s
(docs/photos.md, "Large photos"). [px]"""


def mirrored_photo(photo: LinearPhoto) -> LinearPhoto:
    """``photo`` flipped left-right (every per-pixel field); ``meta["mirrored"]`` True."""
    flip = lambda a: np.ascontiguousarray(a[:, ::-1])  # noqa: E731
    return dataclasses.replace(photo, rgb=flip(photo.rgb), variance=flip(photo.variance),
                               censored_high=flip(photo.censored_high), censored_low=flip(photo.censored_low),
                               valid=flip(photo.valid), darkest=flip(photo.darkest),
                               darkest_saturated=flip(photo.darkest_saturated), meta={**photo.meta, "mirrored": True})


def reduction_factor(shape: tuple[int, int], max_side: int | None = None) -> int:
    """The integer factor :func:`prepare_scene` reduces a photo of ``shape`` (H, W) by to bring its longer side
    within ``max_side`` (None: :data:`PHOTO_MAX_SIDE`); 1: none. [1]"""
    return max(1, math.ceil(max(shape) / (PHOTO_MAX_SIDE if max_side is None else max_side)))


def cameras_from_image(photo: LinearPhoto, sun_zenith_deg: float, sun_azimuth_deg: float,
                       projections: Sequence[str] = CLASSICAL_PROJECTIONS
                       ) -> tuple[Circle, SunDetection | None, list[CameraGuess]]:
    """The camera from the image alone (:mod:`skyfit.camera.autocal`): the lens circle, the sky's symmetry axis, the
    sun, and one untilted camera per projection, best first (:func:`projection_decision` says which the sun cannot
    tell apart).

    Args:
        photo: the read photo.
        sun_zenith_deg, sun_azimuth_deg: the computed sun. [deg]
        projections: the candidate projections.

    Raises:
        CalibrationError: no circle found.
    """
    h, w = photo.rgb.shape[:2]
    lum = _luminance(np.where(np.isfinite(photo.rgb), photo.rgb, 0.0))
    circle = detect_circle(lum, photo.valid)
    inside = _disc(h, w, circle.cx, circle.cy, circle.radius) & photo.valid
    axis = symmetry_axis(lum, circle.cx, circle.cy, circle.radius, photo.valid)
    detected = detect_sun(photo.darkest, photo.darkest_saturated, inside, centre=(circle.cx, circle.cy),
                          axis_deg=axis)
    candidates = cameras_from_sun((h, w), circle, detected, sun_zenith_deg, sun_azimuth_deg,
                                  projections=tuple(projections))
    return circle, detected, candidates


def _now() -> float:
    return time.perf_counter()


def _disc(h: int, w: int, cx: float, cy: float, r: float) -> np.ndarray:
    yy, xx = np.mgrid[0:h, 0:w]
    return (xx - cx) ** 2 + (yy - cy) ** 2 <= r * r


def _union(masks: dict) -> np.ndarray:
    out = None
    for m in masks.values():
        out = m.copy() if out is None else out | m
    return out


def scene_masks(photo: LinearPhoto, cam: FisheyeCamera, detected, sun_zenith_deg: float, sun_azimuth_deg: float,
                user: np.ndarray | None = None, sun_mask_max_deg: float | None = SUN_MASK_MAX_DEG) -> dict:
    """(H, W) bool masks, True = not used: outside the lens, below the horizon, sun and flare, obstacles, user's.

    ``sun_mask_max_deg``: largest radius of the sun's mask (:data:`skyfit.camera.masks.SUN_MASK_MAX_DEG`: the
    saturated aureole beyond it is censored bounds on the aerosol; None: the whole saturated region + margin). [deg]
    """
    h, w = photo.rgb.shape[:2]
    with torch.no_grad():
        vec, valid = cam.pixel_vectors(torch.float64)
    valid = valid.numpy() & photo.valid
    up = np.where(valid, vec[..., 2].numpy(), -1.0)
    masks = {"outside": ~valid, "horizon": valid & (up <= math.sin(math.radians(2.0)))}
    masks["sun"] = sun_mask((h, w), detected, cam, sun_zenith_deg, sun_azimuth_deg, max_radius_deg=sun_mask_max_deg) & valid
    rgb = np.where(np.isfinite(photo.rgb), photo.rgb, 0.0)
    masks["obstacles"] = obstacle_mask(rgb, valid & ~masks["sun"], cam) & valid
    if user is not None:
        user = np.asarray(user, bool)
        if user.shape != (h, w):
            raise PhotoFitError(f"photo {photo.source}: the mask is {user.shape[0]}x{user.shape[1]}, the photo {h}x{w}")
        masks["user"] = user & valid
    return masks


def with_camera(scene: PhotoScene, cam: FisheyeCamera) -> PhotoScene:
    """The scene under another candidate camera, its masks made again for that camera (the user's kept); notes and
    candidates are the same lists."""
    return dataclasses.replace(scene, camera=cam, masks=scene_masks(scene.photo, cam, scene.detected_sun, scene.sun_zenith_deg,
                                                                    scene.sun_azimuth_deg, scene.masks.get("user"),
                                                                    scene.sun_mask_max_deg))


# -- blocks ---------------------------------------------------------------------------------------
@dataclasses.dataclass
class BlockImage:
    """The photo averaged over ``step`` x ``step`` blocks, and its camera.

    Attributes:
        step: block side. [px]
        camera: the fisheye camera of the block image (centre and radius scaled by 1/step).
        rgb: block means, (h, w, 3); variance: their variance, (h, w, 3).
        usable: (h, w) bool: every pixel of the block is sky and inside the view, none censored.
        censored: (h, w, 3) int8: +1 some pixel of the block saturated in that channel (its mean is a lower bound),
            -1 all black, else 0.
        sky: (h, w) bool: every pixel of the block is sky and inside the view (censored or not).
        candidate: (h, w) bool: inside the view, above the horizon, off the sun (obstacle tests aside).
    """

    step: int
    camera: FisheyeCamera
    rgb: np.ndarray
    variance: np.ndarray
    usable: np.ndarray
    censored: np.ndarray
    sky: np.ndarray
    candidate: np.ndarray


def scaled_camera(cam: FisheyeCamera, step: int, shape: tuple[int, int]) -> FisheyeCamera:
    """The camera of an image of ``step`` x ``step`` block means: block (i, j) covers pixels
    [i step, (i + 1) step), its centre at pixel (i step + (step - 1) / 2) of the photo."""
    return FisheyeCamera.from_metadata(rescaled_camera_meta(cam.to_metadata(), 1.0 / step, shape))


def pixel_at(x: float, scale: float) -> float:
    """Pixel coordinate ``x`` of an image in one with ``scale`` of its pixels per pixel, pixel centres kept:
    scale (x + 1/2) - 1/2 (1/step for blocks of step pixels, k for the photo of one reduced by k). [px]"""
    return scale * (float(x) + 0.5) - 0.5


def rescaled_camera_meta(meta: dict, scale: float, shape: tuple[int, int]) -> dict:
    """A camera's metadata (:meth:`FisheyeCamera.to_metadata`, or a photo fit's RESULT.json ``camera``, with its
    ``circle``) for an image of ``shape`` (H, W) with ``scale`` of its pixels per pixel: x -> scale (x + 1/2) - 1/2
    (pixel centres; ``scale`` 1/step gives :func:`scaled_camera`'s blocks, an integer the full photo of a reduced
    one), lengths times ``scale``."""
    out = dict(meta)
    h, w = shape
    out.update(size=[h, w] if h != w else h, width=w, height=h, cx=pixel_at(meta["cx"], scale), cy=pixel_at(meta["cy"], scale))
    for k in ("radius_px", "focal_px"):
        if meta.get(k) is not None:
            out[k] = scale * float(meta[k])
    if isinstance(meta.get("circle"), dict):
        c = dict(meta["circle"])
        c.update(cx=pixel_at(c["cx"], scale), cy=pixel_at(c["cy"], scale), radius=scale * float(c["radius"]),
                 residual_px=scale * float(c["residual_px"]))
        out["circle"] = c
    return out


def block_image(scene: PhotoScene, step: int | None = None, exclude: np.ndarray | None = None,
                target: int = TARGET_SAMPLES) -> BlockImage:
    """Average the photo over blocks of ``step`` px (None: about ``target`` blocks inside the circle)."""
    ph, cam = scene.photo, scene.camera
    H, W = ph.rgb.shape[:2]
    inside = ~scene.masks["outside"]
    if step is None:
        step = max(1, int(round(math.sqrt(float(inside.sum()) / target))))
    h, w = H // step, W // step
    if h < 4 or w < 4:
        raise PhotoFitError(f"photo {ph.source}: {H}x{W} px is too small to fit (blocks of {step} px)")
    excluded = scene.excluded if exclude is None else exclude
    sky_px = ~excluded
    cand_px = inside & ~scene.masks["horizon"] & ~scene.masks["sun"]
    rgb = np.where(np.isfinite(ph.rgb), ph.rgb, 0.0)
    hi = block_view(ph.censored_high, step, h, w)
    lo = block_view(ph.censored_low, step, h, w)
    any_cens = (hi | lo).any(-1)  # (h, w, n) pixel censored in some channel
    sky = block_view(sky_px, step, h, w).all(-1)
    cand = block_view(cand_px, step, h, w).all(-1)
    usable = sky & ~any_cens.any(-1)
    vals = block_view(rgb, step, h, w).mean(2)
    var = np.where(np.isfinite(ph.variance), ph.variance, 0.0)
    bvar = block_view(var, step, h, w).sum(2) / float(step * step) ** 2
    cens = np.zeros((h, w, 3), np.int8)
    # a channel with saturated pixels is a lower bound on the block's mean (its clipped pixels hold the clip level,
    # below their truth); one all black an upper bound; the ring of partly saturated blocks around a saturated
    # aureole is kept so, since just outside the saturation is where the photo measures the aerosol best
    hi_any, lo_any = hi.any(2), lo.any(2)
    cens[hi_any] = 1
    cens[lo.all(2)] = -1
    mixed = (hi_any & lo_any) | (lo_any & ~lo.all(2))  # both kinds, or partly black: neither bound holds
    bound = sky & ~usable & ~mixed.any(-1)
    usable_or_bound = usable | bound
    return BlockImage(step, scaled_camera(cam, step, (h, w)), vals, bvar, usable_or_bound, cens, sky, cand)


def block_observation(scene: PhotoScene, blocks: BlockImage, use: np.ndarray, *, sigma_relative: float = SIGMA_RELATIVE,
                      response: tuple[np.ndarray, np.ndarray] | None = None, name: str | None = None) -> Observation:
    """The blocks in ``use`` (h, w) bool as an RGB :class:`Observation` with the scene's sun, time and place.

    sigma per value = sqrt(block variance + (sigma_relative x value)^2), floored at 1e-4 of the median value;
    ``image_radius`` is each block's distance from the optical axis over the 90-degree radius.
    """
    cam = blocks.camera
    with torch.no_grad():
        vec, _ = cam.pixel_vectors(torch.float64)
    idx = np.flatnonzero(use.reshape(-1))
    if idx.size == 0:
        raise PhotoFitError(f"photo {scene.photo.source}: no sky block left to fit")
    vals = blocks.rgb.reshape(-1, 3)[idx]
    var = blocks.variance.reshape(-1, 3)[idx]
    floor = 1e-4 * float(np.median(vals[vals > 0])) if (vals > 0).any() else 1e-12
    sig = np.sqrt(var + (sigma_relative * vals) ** 2)
    sig = np.maximum(sig, floor)
    if scene.photo.meta.get("monochrome"):  # three equal channels, one measurement: each weighs a third
        sig = sig * math.sqrt(3.0)
    h, w = use.shape
    yy, xx = np.divmod(idx, w)
    r = np.hypot(xx - float(cam.cx), yy - float(cam.cy)) / float(cam.r90)
    meta = {"image_shape": [h, w], "block_px": blocks.step, "pixel_index": torch.as_tensor(idx), "camera": cam.to_metadata(),
            "sigma_model": {"relative": sigma_relative, "variance": "merged photo's, per block"},
            "mask": {"used": int(idx.size)}}
    if response is not None:
        meta["response"] = response
    sz, sa = (torch.tensor(math.radians(v), dtype=torch.float64) for v in (scene.sun_zenith_deg, scene.sun_azimuth_deg))
    return Observation(
        name=name or Path(scene.photo.source).name, source=scene.photo.source, kind="rgb",
        directions=vec.reshape(-1, 3)[torch.as_tensor(idx)].clone(), sun_zenith=sz, sun_azimuth=sa,
        values=torch.as_tensor(vals), sigma=torch.as_tensor(sig), mask=torch.ones(idx.size, dtype=torch.bool),
        channels=("R", "G", "B"), sun_distance_au=scene.sun_distance_au, time=scene.time, location=scene.location,
        metadata=meta, image_radius=torch.as_tensor(r), censored=torch.as_tensor(blocks.censored.reshape(-1, 3)[idx]))


# -- the fit ---------------------------------------------------------------------------------------
VIGNETTING_PRIOR = (-0.15, 0.15)
"""Prior of the fall-off v of the relative illumination 1 + v r^2 (r = 1 at 90 deg from the axis): Gaussian,
mean and sigma. Real circular fisheyes lose 0-1 EV at 90 deg (0-50 %; a lens does not brighten toward its rim),
so v in [-0.45, 0.15] at 2 sigma; without it an unknown exposure, white balance and vignetting let a single photo
trade the aerosol's horizon brightening for fall-off (synthetic case 6: v -0.55, AOD -62 %). [1]"""
GAIN_PRIOR_LOG_SIGMA = 0.15
"""Prior of the white-balance gains (red, blue over green) relative to linear sRGB of the CIE observer: log-normal
about 1 with this sigma. A camera on a daylight preset or auto white balance under a daylight sky renders a sunlit
grey near grey (the three published cameras of the synthetic generator on daylight: gains 0.87-1.08); the gains
otherwise trade against the aerosol's whitening of the sky, which a photo's colour measures. [1]"""

SATURATION_PRIOR_LOG_SIGMA = 0.45
"""Prior of the camera's red and blue contrast against luminance relative to colorimetry (``saturation_red``,
``saturation_blue``): log-normal about 1 with this sigma (0.4-2.5 at 2 sigma), the RMS of ln s over the two channels
of the three published cameras measured on sky-like spectra (D65 times lambda^-a, a = -0.5 ... 4.5) through their
sensitivities, daylight white balance and rawtoaces matrices (docs/photos.md, "A camera is not a colorimeter";
tests/test_photo_fit.py): red / blue 0.99 / 1.03 (Canon EOS 5D Mark II), 0.79 / 0.74 (Nikon D5100), 0.35 / 0.82
(Sigma SD Merrill, a Foveon sensor). Without a colour matrix (white-balanced camera RGB: a raw developed without it,
a machine-vision all-sky camera) the same cameras give 0.65 / 0.48, 0.67 / 0.41, 0.40 / 0.23, 1-3 sigma out: the fit
reaches them (synthetic cases 9 and 14: 0.34 / 0.28 and 0.58 / 0.43), but they count toward the prior strain
(:data:`PRIOR_STRAIN_LEVEL`). A sigma of 0.70, the RMS over all twelve, was measured over the 20 synthetic photos and
not kept: with it case 12's wrong basin (AOD -86 %) no longer strained the priors (docs/photos.md, "Fewer builds").
Picture styles move them further by choice. [1]"""


LENS_RADIAL_PRIOR_SIGMA = 0.03
"""Prior of ``lens_radial`` k (:func:`skyfit.fit.model.lens_directions`) when a photo fit frees it (``free=``):
Gaussian about 0 with this sigma. k = 0.03 moves a ray at 52 deg from the axis (the largest shift) by 2.6 deg: a
fisheye that departs from its nominal projection by a few per cent of the radius, as real ones do, and the
Kannala-Brandt lenses of the synthetic generator (k1 within +-0.05) seen as equidistant. [1]"""
LENS_RADIAL_PROJECTIONS = ("equidistant", "equisolid", "stereographic")
"""Projections whose lens departure is measured (:func:`lens_from_sun`) or freed: an orthographic lens's radius stops
growing at 90 deg, which no monotone Kannala-Brandt polynomial (the fitted camera of :func:`lens_camera`) follows."""
LENS_SUN_MIN_DEG = 0.75
"""The lens departure is measured only where the first pass leaves a compact sun this far from its detection in
angle from the axis: 2.5 x :data:`SUN_DATUM_SIGMA_DEG` (compact detections lie within 0.73 deg of the true sun on
the synthetic suite); below it the chosen projection stands. [deg]"""
LENS_MISS_SHARE = 0.5
"""A lens measured from the sun is kept where the refit with it lowers the loss and leaves the sun nearer its detection
than :data:`LENS_SUN_MIN_DEG`, or than this share of where the fit without it left the sun: on seed-0 synthetic case 19
(a Kannala-Brandt lens, the sun 3.0 deg from its detection without the lens) the refit halved the loss and brought the
sun to 1.24 deg, and the first rule alone dropped the lens (AOD +31 %; docs/photos.md, "The factor follows g"). [1]"""
LENS_LEVER_MIN = 1.0
"""The sun measures the lens only where the departure's lever theta ((pi/2)^2 - theta^2) (d theta / d k) is at least
this, the sun 25-75 deg from the axis: a compact datum (:data:`SUN_DATUM_SIGMA_DEG`) then fixes k to +-0.005. Near
the axis and near the 90-degree circle the departure vanishes, and a detection's error (or a tilt's share) would be
divided by almost nothing: on the synthetic suite a hazy single photo with the sun at 23 deg (lever 0.93) got
k = 0.023 and rays 3.5 deg off (the cut was set after that case). [rad]"""
LENS_RADIAL_MAX = 0.08
"""Largest |lens_radial| the sun may set (the generator's Kannala-Brandt k1 lie within 0.05). [1]"""
LENS_WITH_TILT = True
"""The refit that tries a lens measured from the sun (:func:`lens_from_sun`) starts from that lens and fits it with the
tilt (and the rest), the sun datum and :data:`LENS_RADIAL_PRIOR_SIGMA` holding it, instead of holding it. The sun
measures the lens at the first pass's tilt, which had taken a share of the lens's miss: seed-0 synthetic case 19 (a
Kannala-Brandt lens, k1 0.043, best law k 0.031, tilted 1.1 deg) measured k 0.046, and the refit with it held
tilted the camera to leave the sun 1.6 deg from its detection (rays 1.2 deg off); fitted from there, k 0.033, the sun
0.3 deg from its detection, rays 0.46 deg off (docs/photos.md, "The lens fitted with the tilt"). Free from the start
instead, without the sun's start, the sky traded the lens against the aerosol (docs/photos.md, "The lens measured
from the sun"). [bool]"""


def sun_separation_deg(problem: "PhotoProblem", x: torch.Tensor) -> float:
    """The angle between the detected sun (through the fitted lens and tilt) and the fitted sun at x, from the sun
    datum's penalty 0.5 (chord / sigma)^2 (:meth:`PhotoProblem.sun_penalty`); NaN without a datum. [deg]"""
    if problem.sun is None:
        return math.nan
    with torch.no_grad():
        pen = float(problem.sun_penalty(problem.param.to_physical(x)))
    chord = math.sqrt(2.0 * pen) * math.radians(problem.sun.sigma_deg)
    return math.degrees(2.0 * math.asin(min(chord / 2.0, 1.0)))


def lens_from_sun(problem: "PhotoProblem", x: torch.Tensor, projection: str) -> tuple[float | None, str]:
    """The lens departure k (``lens_radial``) that puts a compact detected sun, at the fitted tilt and heading, at
    the computed sun's angle from the optical axis: theta_s = theta_p + k theta_p ((pi/2)^2 - theta_p^2), theta_p the
    detected pixel's angle under the nominal projection and theta_s the fitted sun's in the camera frame (the
    tilt undone). One radial datum, one radial parameter: the sky pattern, which trades a lens against the aerosol
    (free in the fit, it moved two of the synthetic suite's lenses by 1.7-4 deg), has no say. None (with why) where
    the sun is extended or missing, the projection orthographic, or its
    radial miss below :data:`LENS_SUN_MIN_DEG`, or the sun where it hardly measures a lens (:data:`LENS_LEVER_MIN`)."""
    sun = problem.sun
    if sun is None or sun.sigma_deg > SUN_DATUM_SIGMA_DEG:
        return None, "no compact sun"
    if projection not in LENS_RADIAL_PROJECTIONS:
        return None, f"{projection} lens"
    with torch.no_grad():
        phys = problem.param.to_physical(x)
        # a handful of numbers: on the CPU whatever the problem's device (the sun datum lives there)
        tn, te = (phys[n].reshape(-1)[0].to(dtype=torch.float64, device="cpu") for n in ("camera_tilt_north", "camera_tilt_east"))
        s = problem.sun_vectors(phys, 0).reshape(-1, 3)[0].to(dtype=torch.float64, device="cpu")
        # the tilt undone: tilt_directions(I) has the rotated axes R e_j as rows, so it applied to s is R^T s
        c = tilt_directions(torch.eye(3, dtype=torch.float64), tn, te) @ s
        theta_s = float(torch.atan2(torch.hypot(c[0], c[1]), c[2]))
        d = sun.direction.to(dtype=torch.float64, device="cpu")
        theta_p = float(torch.atan2(torch.hypot(d[0], d[1]), d[2]))
    miss = math.degrees(theta_s - theta_p)
    lever = theta_p * ((math.pi / 2) ** 2 - theta_p**2)
    if lever < LENS_LEVER_MIN:
        return None, f"sun {math.degrees(theta_p):.1f} deg from the axis, where it hardly measures a lens"
    if abs(miss) < LENS_SUN_MIN_DEG:
        return None, f"sun within {abs(miss):.2f} deg of the projection"
    k = (theta_s - theta_p) / lever
    k = max(-LENS_RADIAL_MAX, min(LENS_RADIAL_MAX, k))
    return k, f"the sun {miss:+.2f} deg from the {projection} projection's angle"


PRIOR_STRAIN_LEVEL = 0.95
"""A photo fit whose camera nuisances (gains, saturations, vignetting) end with sum z^2 over their k priors above
chi^2_k's quantile at this level (11.07 for the five of a photo fit) is refitted from the other side of the aerosol's
range (:data:`PROBE_AOD`) and the lower loss kept: the nuisances took up what the aerosol should, the sign of a second
basin of the lagged fit (synthetic case 12, AOD 0.5: the first start ended at 0.065 with gains 1.48 / 0.56 and
vignetting -0.49, sum z^2 27, loss 0.245; from AOD 0.4, 0.48 with gains 0.88 / 1.00, loss 0.132). A prior predictive
check, not a prior: a probe costs a second fit where it triggers and can only lower the loss. The level was 0.99
with three priors; with the two saturations case 12 ended in the wrong basin at sum z^2 14.8 under chi^2_5's 99 %
point 15.09 (a Foveon's red saturation alone is 2.4 sigma from a colorimetric camera's), so it is 0.95: on a camera
that obeys the priors, one photo in twenty pays the probe. [1]"""
PROBE_REFRESHES = 3
"""A probe's refreshes before it is judged: one that ends above the first fit's loss is dropped there, one below it
goes on to :data:`MS_REFRESHES` in all. On the synthetic suite a losing probe (case 9: loss 0.41-1.2 against 0.126)
ran all six refreshes without settling, 70 s of a 185 s fit. [1]"""
PROBE_BLOCKS = True
"""A probe fits on the race's :data:`RACE_SAMPLES` blocks first, as the race does, and goes on over all the photo's blocks
only where it ends below the first fit's loss on those same blocks (:func:`loss_with_factor`; where the probe is below
that, below the first fit refitted there from its result too). Its fits are cheaper there, its builds as many: the losing
probe of seed-0 synthetic case 19 (a Kannala-Brandt bracket) took 21 s on 333 blocks where it took 33 s of the photo's
74 s over all of them, through the CLI on 2 threads (docs/photos.md, "A probe on the race's blocks"). False: over all
the blocks from the start."""
PROBE_HEADS_BACK = True
"""A probe (:data:`PRIOR_STRAIN_LEVEL`) whose first refresh on the race's blocks ends above the first fit's loss there
and as far toward the first fit's AOD as the trust region lets it (:func:`heads_back`) is dropped there: it is on its
way back to the first fit's basin, not in a second one. On the two synthetic suites of session 16 all seven probes did
so (0.05 -> 0.10 toward 0.24-0.46, 0.4 -> 0.2 toward 0.06-0.11, each loss 5-22x the first fit's there) and all seven
ended in the first fit's basin after their three refreshes (AOD within 5 % of the first fit's; where one was kept, a
1.6 % lower loss at an AOD 0.5 % from the first fit's), at 15-30 s a photo (session 17, docs/photos.md "A probe that heads back"). A second basin within one
trust step of the probe's start (a factor :data:`MS_AOD_TRUST` in AOD) still shows, as one beyond it on the far side.
False: every probe runs its :data:`PROBE_REFRESHES`."""
PROBE_AOD = (0.05, 0.4)
"""Starting AODs of that second fit: the hazy one when the first ended below their geometric mean, else the clear one."""
RUNNER_UP_RATIO = 2.0
"""The runner-up projection of the short fits is fitted in full, from the same start as the first (:func:`fit_scene`),
only where its short fit's loss is below this many times the best's: the race's own ratio (:data:`RACE_RATIO`), so that
the short fits drop only what a race would. It was 1.5 (docs/photos.md, "The factor follows g": then a runner-up cost a
whole second fit, and on the suites of then the runner-up won twice, at ratios 1.09 and 1.00). On session 16's suites
held-out case 15 (an AOD-0.5 bracket under a saturated aureole) ranked the true equidistant lens 1.58x the equisolid
one, was fitted as equisolid (rays 5 deg off) and probed (59 s); raced, equidistant wins at 0.058 against 0.426, AOD
-8.2 -> -1.1 %, in 49 s (session 17, docs/photos.md "A probe that heads back"; the threshold was moved after
seeing that held-out case). [1]"""


RACE_REFRESHES = 3
"""Where a runner-up projection is fitted in full (:data:`RUNNER_UP_RATIO`), both fits run this many lagged refreshes
from the same start and are compared (:func:`fit_scene`); where neither is dropped (:data:`RACE_RATIO`) each goes on
to :data:`MS_REFRESHES` in all. From the default AOD 0.1 two refreshes are trust-region steps (:data:`MS_AOD_TRUST`)
and tell little: held-out synthetic case 14 (AOD 0.50) after two, equisolid 0.52 against the true equidistant's 0.58,
after three 0.54 against 0.24 (converged 0.55 and 0.20); held-out case 0 (AOD 0.39) 3.32 / 3.09, then 2.04 / 0.60
(converged 0.95 and 0.09). [1]"""
RACE_RATIO = 2.0
"""A projection whose race fit (:data:`RACE_REFRESHES`) ends above this many times the other's loss is dropped there,
without its remaining refreshes, probe and lens. The closest converged pair of the synthetic suites needed its lens
to be told apart (held-out case 4: 0.278 against 0.295 without the lens, 0.169 with it; 0.278 / 0.274 after three
refreshes), which a drop would have cut short. [1]"""

RACE_SAMPLES = QUICK_SAMPLES
"""Blocks of the race's fits (:data:`RACE_REFRESHES`): the race only ranks the two projections, whose losses stand 2x
or more apart where one is dropped (:data:`RACE_RATIO`); the fit that goes on is carried over the photo's
:data:`TARGET_SAMPLES` blocks from where it stands. On held-out synthetic case 14 the race took 20 s instead of 26 s
per projection, the same projection dropped, the AOD 0.447 both ways (docs/photos.md, "The race side by side"). [1]"""


def heads_back(probe_aod: float, first_aod: float, aod: float, trust: float | None = None) -> bool:
    """Whether a probe started at ``probe_aod`` and now at ``aod`` after one refresh went as far as the trust region
    (:data:`MS_AOD_TRUST`, a factor in AOD) lets it toward the first fit's ``first_aod`` (:data:`PROBE_HEADS_BACK`)."""
    step = math.log(aod / probe_aod)
    back = math.log(first_aod / probe_aod)
    return step * back > 0.0 and abs(step) >= 0.99 * (MS_AOD_TRUST if trust is None else trust) and abs(back) > abs(step)


def camera_priors(free: Sequence[str]) -> dict:
    """The camera's priors for the free names among ``vignetting``, ``gain_red``, ``gain_blue``, ``lens_radial``:
    name -> (kind, mean, sigma), kind ``linear`` (on the value) or ``log`` (on its logarithm)."""
    table = {"vignetting": ("linear",) + VIGNETTING_PRIOR, "gain_red": ("log", 0.0, GAIN_PRIOR_LOG_SIGMA),
             "gain_blue": ("log", 0.0, GAIN_PRIOR_LOG_SIGMA), "saturation_red": ("log", 0.0, SATURATION_PRIOR_LOG_SIGMA),
             "saturation_blue": ("log", 0.0, SATURATION_PRIOR_LOG_SIGMA),
             "lens_radial": ("linear", 0.0, LENS_RADIAL_PRIOR_SIGMA)}
    return {n: table[n] for n in free if n in table}


SUN_DATUM_SIGMA_DEG = 0.3
"""Standard error of the sun's detected position as a datum of the fit when found as a compact saturated core or
an unsaturated peak: on the 20 synthetic photos such detections lie 0.02-0.73 deg from the true sun (docs/photos.md,
"The sun in a single photo"), the sun's own radius is 0.27 deg. [deg]"""


@dataclasses.dataclass(frozen=True)
class SunDatum:
    """The sun's detected image position as a measurement of the camera's orientation.

    Attributes:
        direction: the detected pixel's view direction under the scene's camera (the frame of the fit's
            view directions before the fitted tilt), shape (3,). [unit vector]
        sigma_deg: its standard error (:func:`sun_datum`). [deg]
    """

    direction: torch.Tensor
    sigma_deg: float


def sun_datum(cam: FisheyeCamera, det: SunDetection | None) -> SunDatum | None:
    """The detected sun as a datum of the fit: its direction under ``cam`` and its standard error.

    A compact core or a peak: :data:`SUN_DATUM_SIGMA_DEG`. A sun placed in a saturated aureole (``extended``)
    lies within ``radius_px`` of the detected point toward the zenith (:func:`skyfit.camera.autocal.detect_sun`):
    half the angle that span subtends, at least :data:`SUN_DATUM_SIGMA_DEG`. None without a detection.
    """
    if det is None:
        return None
    f64 = torch.float64
    with torch.no_grad():
        u = cam.pixel_to_direction(torch.tensor(det.x, dtype=f64), torch.tensor(det.y, dtype=f64))
        sigma = SUN_DATUM_SIGMA_DEG
        if det.extended and det.radius_px > 0:
            dx, dy = float(cam.cx) - det.x, float(cam.cy) - det.y
            norm = math.hypot(dx, dy)
            if norm > 0:
                step = min(det.radius_px, norm) / norm
                v = cam.pixel_to_direction(torch.tensor(det.x + dx * step, dtype=f64), torch.tensor(det.y + dy * step, dtype=f64))
                sigma = max(sigma, 0.5 * _angle_deg(u.numpy(), v.numpy()))
    return SunDatum(u, sigma)


class PhotoProblem(FitProblem):
    """A photo's :class:`FitProblem` with Gaussian priors on camera nuisances (:func:`camera_priors`) and the
    sun's detected position as a datum (:func:`sun_datum`).

    The objective (the mean loss per element) adds sum 0.5 ((f(v) - mean) / sigma)^2 / n_elements over the
    priors, f the identity or log: the negative log prior on the scale of the loss (which is a negative
    log-likelihood, Cauchy or squared), so the Laplace covariance is the posterior's. The sun datum adds
    0.5 (c / sigma)^2 / n_elements, c the chord between the detected pixel's view direction (tilted by the fitted
    tilt) and the fitted sun (its azimuth plus the fitted heading): the angle between them for small angles, and
    smooth at 0 where the angle's gradient is not. Without it the sky pattern alone places the camera, and a short
    fit can trade the heading and tilt against the aerosol and vignetting (docs/photos.md).
    """

    priors: dict = {}
    sun: SunDatum | None = None
    follow: bool = True
    """Follow the lagged multiple-scattering factor in the aerosol optical depth (:func:`follows_aod`)."""
    trust: tuple[float, float] | None = None
    """(ln tau_0, T): the lagged fit's trust region in the aerosol optical depth (:data:`MS_AOD_TRUST`), or None."""
    trust_g: tuple[float, float] | None = None
    """(g_0, T): the lagged fit's trust region in the aerosol asymmetry g (:data:`MS_G_TRUST`), or None."""

    @classmethod
    def of(cls, problem: FitProblem, priors: dict, sun: SunDatum | None = None) -> "PhotoProblem":
        """The same problem (shared observations, parameterisation and model) with ``priors`` and the sun datum."""
        out = cls.__new__(cls)
        out.__dict__.update(problem.__dict__)
        for n, (kind, _, sigma) in priors.items():
            if kind not in ("linear", "log") or not sigma > 0:
                raise ValueError(f"prior of {n}: kind must be linear or log and sigma > 0, got {kind!r}, {sigma}")
        if sun is not None and not sun.sigma_deg > 0:
            raise ValueError(f"sun datum: sigma must be > 0 deg, got {sun.sigma_deg}")
        out.priors = dict(priors)
        out.sun = sun
        return out

    def sun_penalty(self, phys: dict) -> torch.Tensor:
        """Negative log likelihood of the sun datum (up to a constant), shape (). [1]"""
        tn, te = phys["camera_tilt_north"], phys["camera_tilt_east"]
        if tn.ndim:
            tn, te = tn[0], te[0]
        d = self.sun.direction.to(dtype=tn.dtype, device=tn.device)
        k = applied_lens(self, phys, 0)
        if k is not None:
            d = lens_directions(d, k)  # the detected pixel seen through the fitted lens
        view = tilt_directions(d, tn, te)
        sun = self.sun_vectors(phys, 0)
        if sun.ndim == 2:
            sun = sun[0]
        chord = torch.linalg.vector_norm(view - sun)
        return 0.5 * (chord / math.radians(self.sun.sigma_deg)) ** 2

    def prior_penalty(self, phys: dict) -> torch.Tensor:
        """Negative log prior of the camera's nuisances (up to a constant), shape (). [1]"""
        total = None
        for n, (kind, mean, sigma) in self.priors.items():
            v = phys[n]
            z = ((torch.log(v) if kind == "log" else v) - mean) / sigma
            term = 0.5 * (z * z).sum()
            total = term if total is None else total + term
        return total

    def penalty(self, phys: dict) -> torch.Tensor:
        """The objective's part that is not the data's (the camera priors, the sun datum, the trust region), on the
        scale of the loss per element, shape ()."""
        out = torch.zeros((), dtype=phys["mie_aod_550"].dtype, device=phys["mie_aod_550"].device)
        if self.priors:
            out = out + self.prior_penalty(phys) / max(self.n_elements, 1)
        if self.sun is not None:
            out = out + self.sun_penalty(phys) / max(self.n_elements, 1)
        if self.trust is not None:
            excess = torch.relu((torch.log(phys["mie_aod_550"]) - self.trust[0]).abs() - self.trust[1])
            out = out + TRUST_WEIGHT * excess * excess
        if self.trust_g is not None:
            excess = torch.relu((phys["mie_g"] - self.trust_g[0]).abs() - self.trust_g[1])
            out = out + TRUST_WEIGHT * excess * excess
        return out

    def loss_from_predictions(self, preds, phys: dict) -> torch.Tensor:
        return super().loss_from_predictions(preds, phys) + self.penalty(phys)


@dataclasses.dataclass
class PhotoFit:
    """A photo fit's outcome: RESULT.json's content, the problem and vector, and the images of its report."""

    result: dict
    problem: object
    x: torch.Tensor
    scene: PhotoScene
    blocks: BlockImage
    used: np.ndarray
    model_rgb: np.ndarray
    camera: FisheyeCamera


def fitted_camera(cam: FisheyeCamera, azimuth_offset: float, tilt_north: float, tilt_east: float) -> FisheyeCamera:
    """The camera whose pixels see what the fit's camera + nuisances see, with the sun where SPA puts it.

    The fit rotates view directions by T = R_y(tilt_east) R_x(-tilt_north) (FitProblem.view_directions)
    and adds ``azimuth_offset`` to the sun's azimuth; the sky is symmetric about the zenith, so that is the
    same as the sun in place and views turned by the opposite azimuth: R = A(-offset) T R_cam. This returns
    the FisheyeCamera (same projection and intrinsics) with that rotation. [rad]
    """
    def rx(a):
        c, s = math.cos(a), math.sin(a)
        return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])

    def ry(a):
        c, s = math.cos(a), math.sin(a)
        return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])

    def add_azimuth(d):  # azimuth clockwise from North in ENU: +d turns (E, N) clockwise seen from above
        c, s = math.cos(d), math.sin(d)
        return np.array([[c, s, 0], [-s, c, 0], [0, 0, 1]])

    R = add_azimuth(-azimuth_offset) @ ry(tilt_east) @ rx(-tilt_north) @ cam.rotation(torch.float64).numpy()
    axis = R[:, 2]
    zen = zenith_angle_deg(axis)
    horiz = math.hypot(axis[0], axis[1])
    te, tn = (zen * axis[0] / horiz, zen * axis[1] / horiz) if horiz > 1e-15 else (0.0, 0.0)
    meta = cam.to_metadata()
    meta.update(tilt_deg=[te, tn], up_azimuth_deg=0.0)
    level = FisheyeCamera.from_metadata(meta)
    up0 = np.diag([-1.0, -1.0, 1.0])  # R_up at up azimuth 0: camera x West, y South, z Up (fisheye module)
    R_tilt = level.rotation(torch.float64).numpy() @ up0.T  # the tilt alone
    R_up = R_tilt.T @ R
    upw = R_up @ np.array([0.0, -1.0, 0.0])  # image up in the world, tilt removed
    meta["up_azimuth_deg"] = math.degrees(math.atan2(upw[0], upw[1])) % 360.0
    return FisheyeCamera.from_metadata(meta)


def photo_settings(config: dict, overrides: dict | None, calibrated: bool):
    """FitSettings of a photo fit: :data:`PHOTO_SETTINGS` under the config's ``fit:`` section and the overrides."""
    section = dict(config.get("fit") or {})
    base = {**PHOTO_SETTINGS, "free": list(CALIBRATED_FREE if calibrated else PHOTO_FREE)}
    merged = {**base, **section}
    return fit_settings(merged, overrides or {}, where="photo fit")


def _fixed_camera_values(meta: dict | None) -> dict:
    """The camera response values a camera file fixes: those it gives, and saturations of 1 where it gives spectral
    sensitivities without them (the curves render the camera's colour)."""
    out = {}
    for k in CAMERA_RESPONSE:
        if meta and meta.get(k) is not None:
            out[k] = float(meta[k])
    if meta and meta.get("spectral_sensitivities"):
        out = {"saturation_red": 1.0, "saturation_blue": 1.0, **out}
    return out


def ranked_projections(close: Sequence, scores: Sequence[float]):
    """The candidate with the lowest short-fit loss, and the runner-up to fit in full as well: the second lowest where
    its loss is below :data:`RUNNER_UP_RATIO` times the best's, else None (the short fits told them apart)."""
    k, k2 = (int(v) for v in np.argsort(scores)[:2])
    return close[k], (close[k2] if scores[k2] < RUNNER_UP_RATIO * scores[k] else None)


def projection_decision(candidates: Sequence, detected) -> list:
    """The candidate cameras the sun alone cannot tell apart, best first; one (the sun decides) or several.

    All of them when no sun was detected; else those whose score lies within their ``tolerance_deg`` of the
    best's (:func:`skyfit.camera.autocal.cameras_from_sun`: the tilt allowance, plus the radial extent of a
    sun found in a saturated aureole). :func:`fit_scene` fits each briefly and keeps the lowest loss.
    """
    if not candidates:
        return []
    if detected is None:
        return list(candidates)
    best = candidates[0]
    return [c for c in candidates if c is best or c.score - best.score < c.tolerance_deg]


def fit_scene(scene: PhotoScene, config: dict, *, overrides: dict | None = None, camera_meta: dict | None = None,
              laplace: bool = True, progress: bool = False, device="cpu", second_pass: bool = True,
              choose_projection: bool = True) -> PhotoFit:
    """Fit the atmosphere to a prepared scene (steps 5-7 of the module docstring); nothing is written."""
    t0 = _now()
    calibrated = not scene.candidates
    s = photo_settings(config, overrides, calibrated)
    fixed = _fixed_camera_values(camera_meta)
    free = [n for n in s.free if n not in fixed]
    mono = bool(scene.photo.meta.get("monochrome"))
    if mono:
        chosen = "free" in (config.get("fit") or {}) or "free" in (overrides or {})
        held = [n for n in free if n in MONO_HELD and (n != "mie_angstrom_alpha" or not chosen)]
        free = [n for n in free if n not in held]
        if "mie_angstrom_alpha" in held:
            alpha = s.initial.get("mie_angstrom_alpha", config.get("mie", {}).get("angstrom_alpha"))
            scene.notes.append(f"a monochrome photo: one band cannot measure the Angstrom exponent, held at {alpha:g} "
                               "(name it in the fit's free parameters to fit it)")
    # the Rayleigh optical depth of a site follows its surface pressure, exp(-elevation / 8434 m)
    site = {"rayleigh_scale": math.exp(-float(scene.location.get("elevation_m", 0.0)) / PRESSURE_SCALE_HEIGHT_M)}
    s = dataclasses.replace(s, free=free, initial={**site, **fixed, **s.initial})
    response = None
    if mono:
        response = mono_response(camera_meta, scene.photo.source)
    elif camera_meta and camera_meta.get("spectral_sensitivities"):
        response = read_sensitivities(camera_meta["spectral_sensitivities"])
        check_sensitivities(response[1], False, camera_meta["spectral_sensitivities"], scene.photo.source)
    elif (scene.photo.meta.get("icc") or {}).get("rgb_from_xyz") is not None:
        # a photo in another RGB space (Display P3, Adobe RGB): the CIE observer through its primaries
        response = icc_sensitivities(scene.photo.meta["icc"]["rgb_from_xyz"])
    timings = dict(scene.seconds)
    bar = StageBar(progress and not in_child(), second_pass)

    shared: dict = {}  # Bruneton tables at the starting atmosphere, shared by the short fits (camera-independent)
    masks_of = {id(scene.camera): scene.masks}

    def under(sc: PhotoScene, cam: FisheyeCamera) -> PhotoScene:
        """:func:`with_camera`, the masks made once per candidate camera: the short fits, the race and the choice each
        took them anew (1.2 s a camera on a 600 px photo, 6 s of seed-0 synthetic case 16's 64 s)."""
        if id(cam) not in masks_of:
            masks_of[id(cam)] = with_camera(sc, cam).masks
        return dataclasses.replace(sc, camera=cam, masks=dict(masks_of[id(cam)]))

    def problem_for(sc: PhotoScene, exclude=None, start=None, settings=s, target=TARGET_SAMPLES):
        """A fit of ``sc`` set up, nothing fitted: (blocks, prepared data, problem, options, Bruneton model or None)."""
        blocks = block_image(sc, exclude=exclude, target=target)
        obs = block_observation(sc, blocks, blocks.usable, sigma_relative=settings.sigma_relative
                                if "sigma_relative" in (overrides or {}) else SIGMA_RELATIVE, response=response)
        bruneton = None
        if settings.orders > 1 and settings.multiple == "bruneton":
            # live single scattering, Bruneton's orders >= 2 frozen per fit (lagged_fit)
            bruneton = make_model(settings)
            settings = dataclasses.replace(settings, orders=1)
        prep = prepare([obs], config, settings, device=device)
        free = [n for n in settings.free if n != "lens_radial" or sc.camera.projection in LENS_RADIAL_PROJECTIONS]
        problem = PhotoProblem.of(prep.problem(free, settings.per_observation, {**settings.initial, **(start or {})}),
                                  camera_priors(free), sun_datum(sc.camera, sc.detected_sun))
        problem.follow = settings.ms_follow
        options = settings.options(progress and not in_child())  # a side-by-side branch's child draws no bar
        if (problem.priors or problem.sun is not None) and getattr(options, "method", None) not in (None, "lbfgs"):
            # the priors and the sun datum live in the objective, not in residuals
            options = dataclasses.replace(options, method="lbfgs")
        return blocks, prep, problem, options, bruneton

    def run(sc: PhotoScene, exclude=None, start=None, settings=s, target=TARGET_SAMPLES, refreshes=MS_REFRESHES,
            tables=None, refresh_last=True, settle_first=None):
        blocks, prep, problem, options, bruneton = problem_for(sc, exclude, start, settings, target)
        res = lagged_fit(problem, options, refreshes, bruneton=bruneton, tables=tables, refresh_last=refresh_last,
                         settle_first=settle_first)
        if res.convergence.get("ms_runaway") and target == TARGET_SAMPLES:
            sc.notes.append(f"the multiple-scattering refreshes of a {sc.camera.projection} fit ran away (a loss over "
                            f"{MS_RUNAWAY:g}x the best refresh's); the refresh the model explains best with its factor rebuilt "
                            f"stands (loss {res.loss:.5g} there)")
        shared["builds"] = shared.get("builds", 0) + getattr(problem, "table_builds", 0)
        return blocks, prep, problem, res

    def branches(*work):
        """``fn(sc)`` for each ``(sc, fn)`` of ``work``, side by side where the machine allows
        (:func:`skyfit.fit.side_by_side.side_by_side`). Each runs on a copy of its scene with notes of its own, which
        are added to the scene's in order, as are its table builds: the result is the same whichever way they ran."""
        def branch(sc, fn):
            def call():
                mine, before = dataclasses.replace(sc, notes=[]), shared.get("builds", 0)
                out = fn(mine)
                builds, shared["builds"] = shared.get("builds", 0) - before, before
                return out, mine.notes, builds
            return call
        outs = side_by_side([branch(sc, fn) for sc, fn in work], device=device)
        for (sc, _), (_, notes, builds) in zip(work, outs):
            sc.notes.extend(notes)
            shared["builds"] = shared.get("builds", 0) + builds
        return [out for out, _, _ in outs]

    def promoted(sc: PhotoScene, cand) -> PhotoScene:
        """``sc`` (the scene under candidate ``cand``) with ``cand`` first among the candidates."""
        sc.candidates = [cand] + [c for c in scene.candidates if c is not cand]
        return sc

    quick = dataclasses.replace(s, max_iter=min(s.max_iter, 25), adam_steps=min(s.adam_steps, 15))

    def quick_losses(*tries) -> list[float]:
        """The losses of short fits of ``(scene, start)`` pairs, side by side (:func:`branches`); Bruneton's tables at
        the config's starting atmosphere (camera- and heading-independent) are built once, first, for all of them."""
        if "tables" not in shared:
            _, _, problem, _, bruneton = problem_for(tries[0][0], start=tries[0][1], settings=quick, target=QUICK_SAMPLES)
            if bruneton is not None:
                freeze_tables(problem, problem.param.initial_vector(problem.param.base.dtype, problem.param.base.device),
                              bruneton)
                shared["tables"] = problem.bruneton[1:]
                shared["builds"] = shared.get("builds", 0) + problem.table_builds
        return branches(*[(sc, lambda sc, st=st: run(sc, start=st, settings=quick, target=QUICK_SAMPLES, refreshes=1,
                                                     tables=shared.get("tables"), refresh_last=False)[3].loss)
                          for sc, st in tries])

    # the projection by evidence: candidates the sun alone cannot tell apart are fitted and scored by their loss
    runner_up = None
    if scene.candidates and choose_projection:
        best = scene.candidates[0]
        close = projection_decision(scene.candidates, scene.detected_sun)
        if len(close) > 1:
            bar.stage(f"short fits of {len(close)} projections")
            scores = quick_losses(*[(under(scene, c.camera), None) for c in close])
            scene.notes.append("projection chosen by the fit's loss among " + ", ".join(
                f"{c.projection} {v:.4g}" for c, v in zip(close, scores)))
            chosen, runner_up = ranked_projections(close, scores)
            if chosen is not best:
                scene = under(scene, chosen.camera)
            scene.candidates = [chosen] + [c for c in scene.candidates if c is not chosen]
    timings["projection"] = _now() - t0

    # heading from the sky pattern when the sun is not seen: several starting headings, the best loss wins
    start = None
    if scene.detected_sun is None and "sun_azimuth_offset" in s.free and not calibrated:
        degs = (0.0, 90.0, 180.0, 270.0)
        bar.stage("the heading from the sky pattern")
        losses = quick_losses(*[(scene, {"sun_azimuth_offset": math.radians(deg)}) for deg in degs])
        start = {"sun_azimuth_offset": math.radians(min(zip(losses, degs))[1])}
    def carried_on(sc: PhotoScene, fit, done: int, settle_first=None):
        """``fit``, stopped after ``done`` lagged refreshes (a winning strain probe, a race's fit), carried on from
        where it stands, with the tables it ended on, to :data:`MS_REFRESHES` refreshes in all."""
        start_c, last = _continuation(fit[2], fit[3].x, s.free)
        return run(sc, start=start_c, refreshes=MS_REFRESHES - done, tables=last, settle_first=settle_first,
                   settings=dataclasses.replace(s, adam_steps=0, starts=1))

    def raced_on(sc: PhotoScene, fit):
        """A race's fit (on :data:`RACE_SAMPLES` blocks, its last fit against tables built before it) carried on over
        the photo's blocks from where it stands; its first refit rebuilds the tables at its result."""
        return carried_on(sc, fit, min(RACE_REFRESHES, fit[3].convergence.get("ms_refreshes", RACE_REFRESHES)),
                          settle_first=False)

    def probed(sc: PhotoScene, fit):
        """``fit`` or, where its camera nuisances strained their priors (:data:`PRIOR_STRAIN_LEVEL`), the refit from
        the other side of the aerosol's range when that fits better."""
        blocks, prep, problem, res = fit
        if calibrated or not problem.priors or "mie_aod_550" not in s.free:
            return fit
        with torch.no_grad():
            strain = 2.0 * float(problem.prior_penalty(problem.param.to_physical(res.x)))
        limit = float(scipy.stats.chi2.ppf(PRIOR_STRAIN_LEVEL, len(problem.priors)))
        if strain <= limit:
            return fit
        # the camera took up what the aerosol should: a second basin, from the other side
        aod1 = float(problem.param.physical_dict(res.x)["mie_aod_550"])
        probe = PROBE_AOD[1] if aod1 < math.sqrt(PROBE_AOD[0] * PROBE_AOD[1]) else PROBE_AOD[0]
        start_p = {**(start or {}), "mie_aod_550": probe}
        head = (f"the camera's nuisances (gains, saturations, vignetting) of the {sc.camera.projection} fit strained their "
                f"priors (sum z^2 {strain:.1f} > {limit:.4g}): refitted from AOD {probe:g}, ")
        if PROBE_BLOCKS:
            # on the race's blocks first; over all the blocks only where it beats the first fit there
            fit_q = run(sc, start=start_p, refreshes=1, target=RACE_SAMPLES, refresh_last=False)
            first_q = loss_with_factor(problem, res.x, fit_q[2])
            aod_q = float(fit_q[2].param.physical_dict(fit_q[3].x)["mie_aod_550"])
            if PROBE_HEADS_BACK and fit_q[3].loss > first_q and heads_back(probe, aod1, aod_q):
                sc.notes.append(f"{head}on {int(fit_q[0].usable.sum())} blocks its first refresh went as far as the trust "
                                f"region lets it back toward the first fit's AOD {aod1:.4g} (to {aod_q:.4g}; loss "
                                f"{fit_q[3].loss:.5g} against {first_q:.5g} for the first fit there): not kept")
                return fit
            done = 1
            if PROBE_REFRESHES > 1:  # its other refreshes from there, tables built there first (as a refresh would)
                start_q, _ = _continuation(fit_q[2], fit_q[3].x, s.free)
                fit_q = run(sc, start=start_q, refreshes=PROBE_REFRESHES - 1, target=RACE_SAMPLES, refresh_last=False,
                            settings=dataclasses.replace(s, adam_steps=0, starts=1))
                done += fit_q[3].convergence.get("ms_refreshes", PROBE_REFRESHES - 1)
                first_q = loss_with_factor(problem, res.x, fit_q[2])
            if fit_q[3].loss < first_q:
                # before a fit over all the blocks: the first fit refitted on those blocks too (one fit from its result,
                # with its tables), as the probe was fitted to them (held-out case 16: 0.0753 refitted, 0.0878 as it
                # stood, the probe 0.0773, which then lost over all the blocks, 0.0863 against 0.0856)
                start_f, last_f = _continuation(problem, res.x, s.free)
                fit_f = run(sc, start=start_f, target=RACE_SAMPLES, refreshes=1, refresh_last=False, tables=last_f,
                            settings=dataclasses.replace(s, adam_steps=0, starts=1))
                first_q = min(first_q, fit_f[3].loss)
            head += (f"on {int(fit_q[0].usable.sum())} blocks loss {fit_q[3].loss:.5g} against {first_q:.5g} for the first "
                     "fit there")
            if not fit_q[3].loss < first_q:
                sc.notes.append(f"{head} (not kept)")
                return fit
            fit_p = carried_on(sc, fit_q, min(PROBE_REFRESHES, done), settle_first=False)
            head += "; over all the blocks "
        else:
            fit_p = run(sc, start=start_p, refreshes=PROBE_REFRESHES)
            if fit_p[3].loss < res.loss and fit_p[3].convergence.get("ms_refreshes", 0) >= PROBE_REFRESHES:
                # a probe that wins but has not settled goes on, from where it stands, with the tables it ended on
                fit_p = carried_on(sc, fit_p, PROBE_REFRESHES)
        better = fit_p[3].loss < res.loss
        sc.notes.append(f"{head}loss {fit_p[3].loss:.5g} against {res.loss:.5g} from the first start "
                        f"({'kept' if better else 'not kept'})")
        return fit_p if better else fit

    def with_lens(sc: PhotoScene, fit):
        """``fit`` and its lens departure: refitted from the lens the sun measures (:func:`lens_from_sun`), the lens
        free with the tilt under the sun datum (:data:`LENS_WITH_TILT`), where the same data then fit better and the
        sun comes nearer its detection (:data:`LENS_MISS_SHARE`), else as it was with None."""
        blocks, prep, problem, res = fit
        if calibrated or "lens_radial" in s.free:
            return fit, None
        measured, why = lens_from_sun(problem, res.x, sc.camera.projection)
        if measured is None:
            return fit, None
        start_l, last = _continuation(problem, res.x, s.free)
        start_l["lens_radial"] = measured
        s_l = dataclasses.replace(s, adam_steps=0, starts=1)
        if LENS_WITH_TILT:
            s_l = dataclasses.replace(s_l, free=[*s.free, "lens_radial"])
        fit_l = run(sc, start=start_l, settings=s_l, tables=last)
        lens = float(fit_l[2].param.physical_dict(fit_l[3].x)["lens_radial"]) if LENS_WITH_TILT else measured
        miss, before = sun_separation_deg(fit_l[2], fit_l[3].x), sun_separation_deg(problem, res.x)
        kept = fit_l[3].loss < res.loss and miss < max(LENS_SUN_MIN_DEG, LENS_MISS_SHARE * before)
        sc.notes.append(f"lens departure lens_radial {measured:+.4f} measured from {why} (skyfit.fit.photo.lens_from_sun)"
                        + (f", {lens:+.4f} fitted with the tilt from there" if LENS_WITH_TILT else "")
                        + f"; {'kept' if kept else 'not kept'}: loss {fit_l[3].loss:.5g} with it, {res.loss:.5g} "
                        f"without, the sun {miss:.2f} deg from its detection after the refit, {before:.2f} before")
        # the refit must also bring the sun near its detection: else the sky disagrees with that lens
        return (fit_l, lens) if kept else (fit, None)

    t1 = _now()
    bar.done()
    fit_r, lens = None, None
    if runner_up is None:
        bar.stage("fit")
        # the short fits' tables were built at the same starting atmosphere (the start moves only the heading)
        fit = probed(scene, run(scene, start=start, tables=shared.get("tables"), settle_first=False))
        timings["fit_pass1"] = _now() - t1
    else:
        # the short fits rank the projections from a far start (unconverged on hazy skies under a high sun: 3.6 against
        # 3.3 where converged fits end at 0.23 for the true lens and 0.85 for the other); the runner-up is fitted as
        # the first was, from the same start (from the first fit's values it stayed in that fit's basin: held-out
        # case 14, 2.19 against 1.54). Both race for RACE_REFRESHES refreshes on RACE_SAMPLES blocks, side by side; one
        # over RACE_RATIO times the other's loss is dropped there, the rest go on over all the blocks with their own
        # probe and lens (held-out case 4, a Kannala-Brandt lens: equidistant lost to equisolid at 0.295 against 0.278
        # without its lens and won at 0.169 with it), and the lower loss keeps its projection
        sc_r = under(scene, runner_up.camera)
        bar.stage(f"race of {scene.camera.projection} and {runner_up.projection}")

        def race(sc):
            return run(sc, start=start, tables=shared.get("tables"), settle_first=False, refreshes=RACE_REFRESHES,
                       target=RACE_SAMPLES, refresh_last=False)

        fit, fit_r = branches((scene, race), (sc_r, race))
        timings["race"] = _now() - t1
        la, lr = fit[3].loss, fit_r[3].loss
        t1 = _now()
        if max(la, lr) > RACE_RATIO * min(la, lr):
            (kept, lk), (dropped, ld) = sorted([(scene.camera.projection, la), (runner_up.projection, lr)], key=lambda v: v[1])
            scene.notes.append(f"after {RACE_REFRESHES} refreshes from the same start the {dropped} fit's loss {ld:.5g} "
                               f"is over {RACE_RATIO:g}x the {kept} fit's {lk:.5g}: {dropped} dropped")
            if lr < la:
                scene, fit = promoted(sc_r, runner_up), fit_r
            bar.stage(f"fit ({dropped} dropped)")
            fit, fit_r = probed(scene, raced_on(scene, fit)), None
        else:
            bar.stage(f"fits of {scene.camera.projection} and {runner_up.projection}")
            def converged(f):
                return lambda sc: with_lens(sc, probed(sc, raced_on(sc, f)))

            (fit, lens), (fit_r, lens_r) = branches((scene, converged(fit)), (sc_r, converged(fit_r)))
            better = fit_r[3].loss < fit[3].loss
            scene.notes.append(f"the runner-up projection {runner_up.projection} fitted from the same start: loss "
                               f"{fit_r[3].loss:.5g} against {fit[3].loss:.5g} for {scene.camera.projection} "
                               f"({runner_up.projection if better else scene.camera.projection} kept)")
            if better:
                scene, fit, lens = promoted(sc_r, runner_up), fit_r, lens_r
        timings["fit_pass1"] = _now() - t1
    if fit_r is None:
        bar.stage("lens")
        t_lens = _now()
        fit, lens = with_lens(scene, fit)
        timings["lens"] = _now() - t_lens
    blocks, prep, problem, res = fit
    bar.done()
    if second_pass:
        bar.stage("second pass")
        t2 = _now()
        rel = relative_residual_map(problem, res.x, blocks, scene)
        grown = grow_outlier_mask(_upsample(np.nan_to_num(rel, nan=0.0), blocks.step, scene.photo.rgb.shape[:2]),
                                  ~scene.excluded, scene.camera, threshold=OUTLIER_THRESHOLD)
        # obstacles stand on the horizon or far from the sun; a misfit of the aureole is the model's, not a mask's
        elevation, to_sun = _sky_angles(scene.camera, scene.sun_zenith_deg, scene.sun_azimuth_deg)
        grown &= (elevation < OUTLIER_MAX_ELEVATION_DEG) | (to_sun > OUTLIER_SUN_DISTANCE_DEG)
        if grown.any():
            scene.masks["outliers"] = grown & ~scene.excluded
            share = float(scene.masks["outliers"].sum()) / max(float((~scene.excluded | scene.masks["outliers"]).sum()), 1.0)
            if share > OUTLIER_NOTE_FRACTION:
                scene.notes.append(f"the second pass masked {share:.0%} of the sky the first fit used as outliers (|residual| > "
                                   f"{OUTLIER_THRESHOLD:.0%}): more than a missed obstacle (clouds? a camera the first fit got "
                                   "wrong?); the fit stands on the rest: check RESULT.png")
            start2, last = _continuation(problem, res.x, s.free)
            if lens is not None:
                start2["lens_radial"] = lens  # held at the first pass's value (not free)
            blocks, prep, problem, res = run(scene, start=start2, settings=dataclasses.replace(s, adam_steps=0, starts=1),
                                             refreshes=SECOND_PASS_REFRESHES, tables=last)
        timings["fit_pass2"] = _now() - t2
        bar.done()
    t3 = _now()
    bar.stage("report: Laplace and error budget" if laplace else "report")
    result = photo_result(scene, blocks, prep, problem, res, config, laplace=laplace)
    timings["report"] = _now() - t3
    bar.close()
    result["seconds_split"] = {k: round(v, 3) for k, v in timings.items()}
    result["convergence"]["ms_table_builds"] = shared.get("builds", 0)  # every Bruneton build of this photo's fits
    result["seconds"] = sum(timings.values())
    model_rgb = predict_blocks(problem, res.x, blocks, scene, blocks.sky | blocks.candidate)
    cam = camera_from_result(scene.camera, problem.param.physical_dict(res.x))
    if scene.scale > 1:  # the photo's own pixels, as RESULT.json's camera
        cam = FisheyeCamera.from_metadata(rescaled_camera_meta(cam.to_metadata(), float(scene.scale), tuple(result["photo"]["shape"])))
    return PhotoFit(result, problem, res.x, scene, blocks, blocks.usable, model_rgb, cam)


class StageBar:
    """One tqdm bar over a photo fit's stages (camera, fit, second pass, report) on stderr, the stage at work as its
    postfix: a photo's fit is a minute of short fits, races, table builds and fits from a known curvature, most of
    which draw no bar of their own (a fit's L-BFGS bar comes and goes beneath it). Off: every call does nothing."""

    def __init__(self, on: bool, second_pass: bool = True):
        self.bar = None
        if on:
            from tqdm import tqdm

            self.bar = tqdm(total=4 if second_pass else 3, desc="photo fit", unit="stage", leave=False,
                            bar_format="{desc}: {n_fmt}/{total_fmt} stages [{elapsed}] {postfix}")
            self.stage("camera")

    def stage(self, name: str) -> None:
        if self.bar is not None:
            self.bar.set_postfix_str(name)

    def done(self) -> None:
        if self.bar is not None:
            self.bar.update()

    def close(self) -> None:
        if self.bar is not None:
            self.bar.update(self.bar.total - self.bar.n)
            self.bar.close()
            self.bar = None


def _continuation(problem: FitProblem, x: torch.Tensor, free) -> tuple[dict, tuple | None]:
    """A refit's start from a fit at x: the free values there, and the fit's last Bruneton tables (no build before
    the refit's first fit) with the atmosphere they were built at (:attr:`frozen_at`'s free values other than the
    camera's nuisances), None without them. That is x after a rebuild, and one refresh earlier after a fit that
    settled without one (:data:`MS_SETTLED_REBUILD`): :func:`lagged_fit` starts the refit from the factor the fit
    ended on, looked up there and followed to x, as :func:`transfer_factor` does (taken as built at x, the factor
    was off by the followed slope times the AOD's last move)."""
    vals = problem.param.physical_dict(x)
    start = {n: v for n, v in vals.items() if n in free}
    b = getattr(problem, "bruneton", None)
    if b is None:
        return start, None
    at = getattr(problem, "frozen_at", None)
    built = problem.param.physical_dict(at) if at is not None else vals
    return start, (*b[1:], {n: built[n] for n in problem.param.free if n not in NUISANCE})


def _start_at(problem: FitProblem, x: torch.Tensor) -> None:
    """Make ``x`` the problem's starting point (its free values)."""
    from .parameters import PARAMETERS

    vals = problem.param.physical_dict(x)
    for n in problem.param.free:
        spec, v = PARAMETERS[n], vals[n]
        if spec.transform in ("interval", "loginterval"):  # a sigmoid that rounded to its bound: step back inside
            hi = problem.param._hi(n) or spec.hi
            eps = 1e-9 * (hi - spec.lo)
            v = [min(max(u, spec.lo + eps), hi - eps) for u in v] if isinstance(v, list) else min(max(v, spec.lo + eps), hi - eps)
        problem.param.set_value(n, v)


MS_WAVELENGTH_NODES = 6
"""Bruneton's tables of a photo fit are built on this many of the model's wavelengths (evenly spread, the ends
included) and the factor is interpolated linearly in wavelength between them. Against every wavelength, at the
fitted atmosphere of synthetic case 2 (the problem :func:`skyfit.fit_photo` ends with, 2 threads): 6 nodes put
the factor within 0.58 % rms (3.6 % at most) for a build of 4.0 s instead of 7.8 s; 5 nodes 1.0 % (6.5 %) in 3.0 s;
4 nodes 1.6 % (8.9 %) in 2.5 s (docs/photos.md, "Fewer builds"); case 6 with 6 nodes: 0.9 % rms, 3.7 % at most
(docs/photos.md, "Speed"). Six keep the factor's error under a third of :data:`SIGMA_RELATIVE` in rms. None: every
wavelength."""


MS_TABLE_DTYPE = torch.float32
"""Bruneton's tables of a photo fit's factor are built in this dtype and widened to the fit's (None: the fit's own).
Measured at the fitted atmospheres of synthetic cases 2, 6 and 0 (``PHOTO_TABLES``, 6 wavelengths, 2 threads, each
side by side in one run): builds of 2.7 / 2.1 / 1.8 s instead of 4.0 / 4.5 / 2.9 s, and the factor within 2.0e-4 /
8.3e-4 / 6.8e-5 of the float64 tables' at most (rms 7.8e-5 / 2.6e-4 / 1.6e-5): forty times under
:data:`FACTOR_TOL` (docs/photos.md, "Tables in float32"). The factor is a ratio of table lookups; float32's 1e-7
rounding over the tables' few hundred quadrature sums is what is left."""


def _widened(tables, atm):
    """``tables`` (a PrecomputedAtmosphere) with every tensor in ``atm``'s dtype and ``atm`` as its atmosphere."""
    change = {f.name: getattr(tables, f.name).to(atm.wavelengths.dtype) for f in dataclasses.fields(tables)
              if isinstance(getattr(tables, f.name), torch.Tensor)}
    return dataclasses.replace(tables, atm=atm, **change)


MS_ANCHOR = "live"
"""What the tables' multiple scattering is a factor on: ``live`` (1 + orders >= 2 of the tables / the fit's live
single scattering: the sky is live single scattering plus the tables' multiple part) or ``tables`` (all orders /
first order, both from the tables). Bruneton's single-scattering table differs from the live Chapman integral by
+6 % at the zenith to +29 % at 2-10 deg elevation (synthetic case 6, at every table size: its integration, not its
resolution); ``tables`` scales the multiple part by that ratio, ``live`` adds it as the tables give it."""


def wavelength_nodes(n_wavelengths: int, nodes: int | None = MS_WAVELENGTH_NODES) -> np.ndarray | None:
    """Indices of ``nodes`` wavelengths evenly spread over a grid of ``n_wavelengths``, the ends included;
    None when that would be every wavelength."""
    if nodes is None or nodes >= n_wavelengths:
        return None
    if nodes < 2:
        raise ValueError(f"wavelength nodes must be >= 2 (the ends of the grid), got {nodes}")
    return np.unique(np.round(np.linspace(0, n_wavelengths - 1, nodes)).astype(int))


def atmosphere_at(atm, index: np.ndarray):
    """The atmosphere on the wavelengths ``atm.wavelengths[index]`` (every spectral field sliced alike)."""
    n = int(atm.wavelengths.numel())
    idx = torch.as_tensor(index, dtype=torch.long, device=atm.device)
    changes = {}
    for f in atm.tensor_fields():
        v = getattr(atm, f)
        if isinstance(v, torch.Tensor) and v.ndim >= 1 and v.shape[0] == n and f != "ozone_layer_m":
            changes[f] = v.index_select(0, idx)
    return atm.replace(**changes)


def interpolation_matrix(wavelengths: torch.Tensor, index: np.ndarray) -> torch.Tensor:
    """(K, W) weights that carry values on ``wavelengths[index]`` (K nodes, increasing) to every wavelength
    (W) by linear interpolation in wavelength."""
    lam = wavelengths.detach()
    nodes = lam[torch.as_tensor(index, dtype=torch.long, device=lam.device)]
    k = torch.searchsorted(nodes, lam.contiguous()).clamp(1, len(index) - 1)
    lo, hi = nodes[k - 1], nodes[k]
    t = ((lam - lo) / (hi - lo)).clamp(0.0, 1.0)
    m = torch.zeros(len(index), lam.numel(), dtype=lam.dtype, device=lam.device)
    cols = torch.arange(lam.numel(), device=lam.device)
    m[k - 1, cols] += 1.0 - t
    m[k, cols] += t
    return m


MS_SUN_MARGIN_DEG = SUN_MARGIN_DEG
"""Bruneton's tables of a fit whose suns are fixed (no ``sun_zenith_offset`` free) span the suns' zenith angles and this
much beyond on either side (:func:`sun_window`), instead of 2017's whole axis from mu_s_min to 1. [deg]"""
MS_SUN_SPACING_DEG = SUN_SPACING_DEG
"""The largest spacing in sun zenith angle between the mu_s texels of :func:`sun_window`'s tables (six texels for one
sun). 2017's axis spends its texels near the horizon: with the photo fit's 16 (before session 16) a sun 20-35 deg from
the zenith lay between two texels 0.975 and 0.999 of the axis apart, and a hazy sky's orders >= 2 (AOD 0.3, g 0.82)
came out 2.28x the converged value at the zenith with the sun at 23 deg and 2.33x at 50 deg (64 texels: 1.59x and
1.005x). One sun's window of 6 texels is within 0.2 % of the reference (+-10 deg in 21 texels) at every view with the
sun at 23, 50, 70 and 80 deg, for 0.37-0.44x the CPU of 16 texels on 2017's axis (scripts/ms_sun_window.py,
docs/multiple/sun_window.json, docs/multiple_scattering.md "One sun's mu_s window"). [deg]"""


def sun_window(problem: FitProblem, x: torch.Tensor, texels: int) -> tuple[tuple[float, float] | None, int]:
    """The sun zenith cosines (lo, hi) and texel count of Bruneton tables for ``problem``'s suns at ``x``
    (:func:`skyfit.scattering.bruneton_tables.sun_window` with :data:`MS_SUN_MARGIN_DEG` and
    :data:`MS_SUN_SPACING_DEG`); ``(None, texels)`` (2017's axis of ``texels``) where
    :func:`~skyfit.fit.model.sun_zenith_span` has none (a fitted sun zenith offset moves the sun during a fit; an
    observer in space)."""
    span = sun_zenith_span(problem, x)
    if span is None:
        return None, texels
    return sun_mu_s_window(*span, texels, MS_SUN_MARGIN_DEG, MS_SUN_SPACING_DEG)


def freeze_tables(problem: FitProblem, x: torch.Tensor, bruneton: "SkyModel | None" = None,
                  wavelength_nodes_count: int | None = MS_WAVELENGTH_NODES) -> None:
    """Multiple scattering at ``x`` (no gradient), used until refreshed.

    With ``bruneton`` (a SkyModel with ``multiple="bruneton"``; the problem's own model renders single
    scattering): Bruneton's tables are precomputed for the atmosphere at ``x`` on ``wavelength_nodes_count``
    of its wavelengths (:data:`MS_WAVELENGTH_NODES`; None: all) and each observation's factor of multiple
    scattering (:func:`multiple_from_tables`) is held in ``problem.frozen_factor``. Otherwise the problem's own
    multiple-scattering tables (Hillaire's LUT) are frozen."""
    problem.frozen_tables = None
    if bruneton is not None:
        from ..scattering.bruneton_tables import TableSizes
        from ..scattering.multiple import precompute

        def build(*points: torch.Tensor) -> list:
            """[(tables, nodes)] at each of ``points``; two atmospheres that differ only per wavelength (the AOD's
            step) in one precomputation on their wavelengths side by side (:func:`joined_atmosphere`)."""
            with torch.no_grad():
                subs = []
                for at in points:
                    atm = problem.param.atmosphere(problem.param.to_physical(at))
                    nodes = wavelength_nodes(int(atm.wavelengths.numel()), wavelength_nodes_count)
                    subs.append(atm if nodes is None else atmosphere_at(atm, nodes))
                joint = joined_atmosphere(subs) if len(subs) > 1 and MS_JOINT_BUILD else None
                if len(subs) > 1 and joint is None:
                    return [build(at)[0] for at in points]
                atm = subs[0] if joint is None else joint
                narrow = MS_TABLE_DTYPE is not None and MS_TABLE_DTYPE != atm.wavelengths.dtype
                sizes = TableSizes(*(bruneton.table_sizes or bruneton.REDUCED_TABLES))
                mu_s_range, n_mu_s = sun_window(problem, points[0], sizes.scattering_mu_s)
                tables = precompute(atm.to(dtype=MS_TABLE_DTYPE) if narrow else atm, orders=bruneton.orders,
                                    sizes=dataclasses.replace(sizes, scattering_mu_s=n_mu_s), mu_s_range=mu_s_range,
                                    quadrature=bruneton.quadrature(), progress=False)
                parts = [tables] if joint is None else split_tables(tables, subs)
                if narrow:
                    parts = [_widened(t, sub) for t, sub in zip(parts, subs)]
            problem.table_builds = getattr(problem, "table_builds", 0) + len(points)
            return [(t, nodes) for t in parts]

        previous, old = problem.frozen_slope, getattr(problem, "bruneton", None)
        previous_g = problem.frozen_slope_g
        stepped = None
        if follows_aod(problem):
            log_depth = _log_depth(problem, x)
            reuse = (previous is not None and old is not None and len(old) > 3
                     and float((log_depth - previous[1]).abs().max()) < MS_SLOPE_REUSE)
            (tables, nodes), *more = build(x) if reuse else build(x, aod_stepped(problem, x))
            _freeze_factor(problem, x, tables, nodes)
            if reuse:
                # the optical depth hardly moved since the slope was built: keep it (one build instead of two)
                stepped = old[3]
                problem.frozen_slope = (previous[0], log_depth)
                problem.trust = (_log_aod(problem, x), MS_AOD_TRUST)
            else:
                stepped = more[0]
                follow_aod(problem, x, stepped, log_depth)
        else:
            (tables, nodes), = build(x)
            _freeze_factor(problem, x, tables, nodes)
        stepped_g = None
        if follows_g(problem):
            g = _g_at(problem, x)
            if previous_g is not None and old is not None and len(old) > 4 and abs(g - previous_g[1]) < MS_G_REUSE:
                # g hardly moved since its slope was built: keep the slope about the new g (one build less)
                stepped_g = old[4]
                problem.frozen_slope_g = (previous_g[0], g)
                problem.trust_g = (g, MS_G_TRUST)
            else:
                stepped_g = build(g_stepped(problem, x))[0]
                follow_g(problem, x, stepped_g)
        problem.bruneton = (bruneton, tables, nodes, stepped, stepped_g)
        return
    if problem.model.orders > 1:
        with torch.no_grad():
            problem.frozen_tables = problem.model.tables(problem.param.atmosphere(problem.param.to_physical(x)))


MS_JOINT_BUILD = True
"""A refresh's tables at the fit's result and at its AOD's step (:func:`aod_slope`) come from one precomputation on the
two atmospheres' wavelengths side by side (:func:`joined_atmosphere`): they differ only in each wavelength's aerosol
coefficients, so the build's geometry and Python overhead are spent once (1.6 s + 1.6 s -> 2.3 s on one thread, 6
nodes, ``PHOTO_TABLES``; every table equal to separate builds' but the irradiance's float32 rounding, 2e-7). False: two
builds."""


def joined_atmosphere(atms: Sequence) -> "Atmosphere | None":
    """One atmosphere on the wavelengths of ``atms`` one after the other, every per-wavelength field joined alike; None
    where they differ in anything else (a scale height, g, the phase), which no such join can carry."""
    first = atms[0]
    n = int(first.wavelengths.numel())
    if any(a.tensor_fields() != first.tensor_fields() or a.mie_phase != first.mie_phase or a.mie_profile != first.mie_profile
           or a.mie_refractive_index != first.mie_refractive_index or a.ozone_layer_m != first.ozone_layer_m
           or (a.bottom_radius, a.top_radius) != (first.bottom_radius, first.top_radius) for a in atms):
        return None
    changes = {}
    for f in first.tensor_fields():
        values = [getattr(a, f) for a in atms]
        if any(v.shape != values[0].shape for v in values):
            return None
        if values[0].ndim >= 1 and values[0].shape[0] == n:
            changes[f] = torch.cat(values)
        elif not all(torch.equal(v, values[0]) for v in values[1:]):
            return None
    return first.replace(**changes)


def split_tables(tables, atms: Sequence) -> list:
    """The tables of a :func:`joined_atmosphere` taken apart: one PrecomputedAtmosphere per atmosphere of ``atms``, each
    on its own wavelengths (the last axis of every spectral table; the transmittance's optical lengths are shared)."""
    out, start = [], 0
    for atm in atms:
        n = int(atm.wavelengths.numel())
        cut = {}
        for f in ("direct_irradiance", "irradiance", "single_rayleigh", "single_mie", "multiple"):
            v = getattr(tables, f)
            cut[f] = None if v is None else v[..., start:start + n].contiguous()
        for f in ("order_scattering", "order_irradiance"):
            v = getattr(tables, f)
            cut[f] = None if v is None else [t[..., start:start + n].contiguous() for t in v]
        out.append(dataclasses.replace(tables, atm=atm.to(dtype=tables.transmittance_columns.dtype), **cut))
        start += n
    return out


def _freeze_factor(problem: FitProblem, x: torch.Tensor, tables, nodes) -> None:
    """Freeze the factor of ``tables`` (on wavelength ``nodes``) at x, where they were built (:attr:`frozen_at`), its
    slopes and trust regions cleared (:func:`follow_aod`, :func:`follow_g` set them)."""
    problem.frozen_slope = problem.trust = problem.frozen_slope_g = problem.trust_g = None
    problem.frozen_factor = multiple_from_tables(problem, x, tables, nodes)
    problem.frozen_at = x.detach().clone()


MS_AOD_SLOPE = True
"""Follow the frozen multiple-scattering factor to first order in the aerosol optical depth (:func:`aod_slope`,
one more table build per refresh) instead of holding it fixed between refreshes."""
MS_AOD_STEP = 0.2
"""Relative step in the aerosol optical depth of :func:`aod_slope`'s second build. [1]"""
MS_AOD_TRUST = math.log(2.0)
"""Trust region of a fit with the factor followed to first order: the aerosol optical depth moves at most this far
in ln tau from where the tables were built before the next refresh (:attr:`PhotoProblem.trust`); a first-order
factor extrapolated from AOD 0.1 to 0.45 sent a hazy photo's fit astray. At convergence the bound is not active. [1]"""
MS_SLOPE_REUSE = 0.1
"""A refresh keeps the previous slope (:func:`aod_slope`) when no wavelength's ln tau moved more than this since it
was built. At 0.2 (docs/photos.md, "Fewer builds") the 20 synthetic photos took 174 builds instead of 190, but four
fits ended further from the truth (case 18 +8.4 -> +21.7 %, case 11 +6.5 -> +14.0 %, case 6 -7.4 -> -13.6 %, case 17
-11.0 -> -14.4 %): AOD within 15 % on 18 instead of 19. [1]"""
MS_AOD_SETTLE = 0.02
"""The refreshes of :func:`lagged_fit` with the factor followed in the optical depth also stop when a fit moves the
aerosol optical depth by less than this (relative), inside its trust region: a fifth of the 15 % asked of a photo's
AOD (issue 13), and what the factor's remaining change moves it by. [1]"""
MS_SETTLED_REBUILD = False
"""Rebuild the tables after a fit that settled the AOD (:data:`MS_AOD_SETTLE`) following a refresh. Off: the factor
that fit used, followed to first order in each wavelength's optical depth from tables built one refresh earlier,
stands for the model at its result. The fitted values are the same either way (the rebuild came after the fit);
only the metrics and the Laplace sigma see the rebuilt factor, which moved by 0.55 % on synthetic case 2, and it
cost one build of about 4 s in a 60 s fit (docs/photos.md, "Fewer builds"). The model
image of the report and the outlier map (:func:`predict_blocks`) take the last tables at the result without the
followed slope: off by what the AOD's last move (< 2 %) changes the multiple part, about 1 % of the radiance against
the outliers' 25 % (:data:`OUTLIER_THRESHOLD`). [bool]"""
TRUST_WEIGHT = 1.0e3
"""Weight of the trust region's penalty, w max(0, |ln tau - ln tau_0| - T)^2, on the scale of the loss per element."""


def follows_aod(problem: FitProblem) -> bool:
    """Whether a lagged fit follows the problem's factor in the aerosol optical depth: a photo's (:class:`PhotoProblem`,
    its ``follow``, the ``ms_follow`` setting) with ``mie_aod_550`` free, and :data:`MS_AOD_SLOPE`."""
    return (MS_AOD_SLOPE and isinstance(problem, PhotoProblem) and getattr(problem, "follow", True)
            and "mie_aod_550" in problem.param.free)


def aod_stepped(problem: FitProblem, x: torch.Tensor) -> torch.Tensor:
    """``x`` with the aerosol optical depth times 1 + :data:`MS_AOD_STEP` (where :func:`aod_slope` builds again)."""
    vals = problem.param.free_dict(x)
    vals["mie_aod_550"] = float(vals["mie_aod_550"]) * (1.0 + MS_AOD_STEP)
    return problem.param.to_unconstrained(vals, x.dtype, x.device)


def _log_aod(problem: FitProblem, x: torch.Tensor) -> float:
    """ln of the aerosol optical depth at 550 nm at ``x`` (the trust region's coordinate). [1]"""
    return math.log(float(problem.param.free_dict(x)["mie_aod_550"]))


def _log_depth(problem: FitProblem, x: torch.Tensor) -> torch.Tensor:
    """ln of the aerosol optical depth at each model wavelength at ``x``, shape (W,) (the slope's coordinate). [1]"""
    with torch.no_grad():
        return aerosol_log_depth(problem.param.atmosphere(problem.param.to_physical(x)))


def follow_aod(problem: FitProblem, x: torch.Tensor, stepped, log_depth: torch.Tensor) -> None:
    """Set the problem's :attr:`frozen_slope` from the tables ``stepped`` = (tables, nodes) built at
    :func:`aod_stepped` (x), and its trust region (:data:`MS_AOD_TRUST`) around x's optical depth;
    ``log_depth`` is :func:`_log_depth` (x)."""
    problem.frozen_slope = aod_slope(problem, x, problem.frozen_factor, stepped, log_depth)
    problem.trust = (_log_aod(problem, x), MS_AOD_TRUST)


MS_G_SLOPE = True
"""Follow the frozen multiple-scattering factor to first order in the aerosol asymmetry g as well (:func:`g_slope`,
one more table build per refresh where g moved). Held in g, a fit that moved g between refreshes met a factor rebuilt
up to 52 % away (held-out synthetic case 10: g 0.78 -> 0.87, AOD +38 %; docs/photos.md, "The factor follows g")."""
MS_G_STEP = 0.04
"""Step in g of :func:`g_slope`'s build (toward 0: g - 0.04 for g > 0). [1]"""
MS_G_TRUST = 0.05
"""Trust region of a fit with the factor followed in g: g moves at most this far from where the tables were built
before the next refresh (the first-order factor's range). At convergence the bound is not active. [1]"""
MS_G_REUSE = 0.01
"""A refresh keeps the previous g slope when g moved less than this since it was built. [1]"""
MS_G_SETTLE = 0.01
"""With the factor followed in g, a fit settles (:data:`MS_AOD_SETTLE`) only if g also moved less than this. [1]"""


def follows_g(problem: FitProblem) -> bool:
    """Whether a lagged fit follows the problem's factor in the aerosol asymmetry g: as :func:`follows_aod`, with
    ``mie_g`` free, and :data:`MS_G_SLOPE`."""
    return (MS_G_SLOPE and isinstance(problem, PhotoProblem) and getattr(problem, "follow", True)
            and "mie_g" in problem.param.free)


def _g_at(problem: FitProblem, x: torch.Tensor) -> float:
    """The aerosol asymmetry g at ``x``. [1]"""
    return float(problem.param.free_dict(x)["mie_g"])


def g_stepped(problem: FitProblem, x: torch.Tensor) -> torch.Tensor:
    """``x`` with g moved :data:`MS_G_STEP` toward 0 (where :func:`g_slope` builds again)."""
    vals = problem.param.free_dict(x)
    g = float(vals["mie_g"])
    vals["mie_g"] = g - MS_G_STEP if g > 0 else g + MS_G_STEP
    return problem.param.to_unconstrained(vals, x.dtype, x.device)


def follow_g(problem: FitProblem, x: torch.Tensor, stepped) -> None:
    """Set the problem's :attr:`frozen_slope_g` from the tables ``stepped`` = (tables, nodes) built at
    :func:`g_stepped` (x), and its trust region in g (:data:`MS_G_TRUST`)."""
    problem.frozen_slope_g = g_slope(problem, x, problem.frozen_factor, stepped)
    problem.trust_g = (_g_at(problem, x), MS_G_TRUST)


def g_slope(problem: FitProblem, x: torch.Tensor, factor: list[torch.Tensor], stepped) -> tuple[list[torch.Tensor], float]:
    """The derivative D_g of ln(F - 1), F the multiple-over-single factor, in the aerosol asymmetry g, per sample and
    wavelength, from ``factor`` (built at x) and the tables ``stepped`` = (tables, nodes) built at :func:`g_stepped`
    (x): (D_g, g at x). :meth:`FitProblem.frozen_factor_at` applies it. [1]

    Why: F - 1 is the tables' multiple scattering over the live single scattering. Raising g brightens the aureole's
    single scattering and dims the rest, and the multiple part follows more slowly (it is a smoothed sky), so F - 1
    falls near the sun and rises away from it. Held fixed, that is hidden from the fit, which then moved g (and with it
    the AOD) from refresh to refresh."""
    x1 = g_stepped(problem, x)
    factor1 = multiple_from_tables(problem, x1, *stepped, follow_geometry=False)
    step = _g_at(problem, x1) - _g_at(problem, x)
    # at most x3 per step (tables' noise aside)
    return ([d.clamp(-math.log(3.0), math.log(3.0)) / step for d in share_log_ratios(factor, factor1)],
            _g_at(problem, x))


def aod_slope(problem: FitProblem, x: torch.Tensor, factor: list[torch.Tensor], stepped,
              log_depth: torch.Tensor) -> tuple[list[torch.Tensor], torch.Tensor]:
    """The logarithmic derivative D of the multiple-over-single ratio F - 1 in the aerosol optical depth, per sample
    and wavelength, from ``factor`` (built at x) and the tables ``stepped`` = (tables, nodes) built with every
    wavelength's aerosol optical depth times 1 + :data:`MS_AOD_STEP` (:func:`aod_stepped`):
    (D, ``log_depth``, ln tau(lambda) at x, shape (W,)). [1]

    Why: with F held fixed between refreshes a fit sees multiple scattering grow with the aerosol only as fast as
    single scattering, while in a hazy sky the multiple share itself grows with tau (it is a third to a half of
    the radiance at AOD 0.3); the fit's optimum with F frozen is then not the optimum of the model (a lagged fixed
    point), and on synthetic hazy photos the refreshes crept upward from a low aerosol without settling
    (docs/photos.md, "The lagged factor"). :meth:`FitProblem.frozen_factor_at` applies it."""
    factor1 = multiple_from_tables(problem, aod_stepped(problem, x), *stepped, follow_geometry=False)  # its live anchor ignores any frozen factor
    step = math.log1p(MS_AOD_STEP)
    # a power law in tau within physical bounds (noise of the tables aside)
    return [(d / step).clamp(-3.0, 3.0) for d in share_log_ratios(factor, factor1)], log_depth


def share_log_ratios(factor: list[torch.Tensor], factor1: list[torch.Tensor]) -> list[torch.Tensor]:
    """ln((F_1 - 1) / (F - 1)) per observation, sample and wavelength, between two multiple-scattering factors (the
    change of the multiple share over a stepped build: :func:`aod_slope`, :func:`g_slope`); 0 where either share is not
    positive. [1]"""
    out = []
    for f0, f1 in zip(factor, factor1):
        a, b = f0 - 1.0, f1 - 1.0
        ok = (a > 1e-9) & (b > 1e-9)
        out.append(torch.where(ok, torch.log(torch.where(ok, b, torch.ones_like(b)) / torch.where(ok, a, torch.ones_like(a))),
                               torch.zeros_like(a)))
    return out


@dataclasses.dataclass(eq=False)
class TableFactor:
    """Each observation's factor of multiple scattering from Bruneton ``tables`` at a view and sun geometry, with the
    anchors :func:`multiple_from_tables` fixed where it first looked them up: differentiable in the geometry. A class
    rather than a closure so that a fit's state pickles (a side-by-side branch sends it back,
    :mod:`skyfit.fit.side_by_side`)."""

    problem: FitProblem
    tables: object
    atm: object  # the atmosphere the tables were looked up in (its geometry), and ``sub`` on the tables' wavelengths
    sub: object
    interp: torch.Tensor | None
    anchors: list

    def lookup(self, ph: dict, i: int) -> tuple[torch.Tensor, torch.Tensor]:
        """The tables' (all orders, first order) at observation i's geometry under ``ph``, each (N_i, W_nodes)."""
        from ..scattering.multiple import sky_radiance
        from ..scattering.single import ray_parameters

        problem = self.problem
        o = problem.observations[i]
        sun = problem.sun_vectors(ph, i)
        r, mu, mu_s, nu = ray_parameters(self.atm, problem.view_directions(ph, i), sun[o.mask] if sun.ndim == 2 else sun,
                                         o.altitude_m)
        return (sky_radiance(self.tables, self.sub, r, mu, mu_s, nu, below_mu_s_min="clamp"),
                sky_radiance(self.tables, self.sub, r, mu, mu_s, nu, orders=1, below_mu_s_min="clamp"))

    def factor(self, every: torch.Tensor, first: torch.Tensor, i: int) -> torch.Tensor:
        """1 + (every - first) / first x observation i's anchor, on the model's wavelengths, (N_i, W)."""
        ok, anchor = self.anchors[i]
        f = 1.0 + torch.where(ok, (every - first) / torch.where(ok, first, torch.ones_like(first)),
                              torch.zeros_like(first)) * anchor
        return f if self.interp is None else f @ self.interp

    def __call__(self, ph: dict, i: int) -> torch.Tensor:
        """Observation i's factor at the geometry of ``ph`` (the same tables and anchor): differentiable in it."""
        return self.factor(*self.lookup(ph, i), i)


def multiple_from_tables(problem: FitProblem, x: torch.Tensor, tables, nodes: np.ndarray | None = None,
                         follow_geometry: bool = True) -> list[torch.Tensor]:
    """Each observation's factor of multiple scattering from Bruneton ``tables``, (N_i, W): all orders over the
    first, both looked up in the same tables so that their error in single scattering cancels. [1]

    ``nodes``: the tables are on ``atm.wavelengths[nodes]`` (:func:`wavelength_nodes`); the factor is interpolated
    linearly in wavelength to every model wavelength.

    A factor rather than the added radiance: multiple scattering grows with the scattering much as single
    scattering does, so the ratio moves little while a fit moves the aerosol; the added radiance held fixed made
    the refreshes oscillate (on a hazy synthetic photo the aerosol went 0.41 -> 0.24 -> 1.27 -> 0.82)."""
    out, anchors = [], []
    with torch.no_grad():
        phys = problem.param.to_physical(x)
        atm = problem.param.atmosphere(phys)
        sub = atm if nodes is None else atmosphere_at(atm, nodes)
        interp = None if nodes is None else interpolation_matrix(atm.wavelengths, nodes)
        live = None
        if MS_ANCHOR == "live":  # the problem's own single scattering at x (no factor), per observation (N_i, W)
            held, problem.frozen_factor = problem.frozen_factor, None
            try:
                live = [sp / sc for sp, sc in zip(problem.spectra(phys, atm), problem.solar_scale)]
            finally:
                problem.frozen_factor = held

        follow = TableFactor(problem, tables, atm, sub, interp, anchors)
        for i, o in enumerate(problem.observations):
            every, first = follow.lookup(phys, i)
            # f = 1 + (every - first) / first * anchor: anchor = first / live single where the live single scattering
            # anchors the factor (the tables' error in single scattering then cancels at x), else 1 (every / first)
            ok = first > 1e-12 * first.abs().max()
            if MS_ANCHOR == "live":
                single = live[i] if nodes is None else live[i][:, torch.as_tensor(nodes, device=live[i].device)]
                ok = ok & (single > 1e-12 * single.abs().max())
                anchor = torch.where(ok, first / torch.where(ok, single, torch.ones_like(single)), torch.zeros_like(single))
            else:
                anchor = ok.to(first.dtype)
            anchors.append((ok, anchor))
            out.append(follow.factor(every, first, i))

    if follow_geometry:  # the problem's factor from now on (not a stepped one's, :func:`aod_slope`)
        moving = any(n in problem.param.free for n in GEOMETRY_NAMES)
        problem.frozen_follow = (out, follow) if moving and MS_FOLLOW_GEOMETRY else None
    return out


GEOMETRY_NAMES = ("sun_azimuth_offset", "sun_zenith_offset", "camera_tilt_north", "camera_tilt_east", "lens_radial")
"""Fitted values that move a sample's view or sun geometry (heading, sun zenith offset, tilt, lens)."""
MS_FOLLOW_GEOMETRY = True
"""Whether a frozen multiple-scattering factor follows the fitted geometry (:meth:`FitProblem.frozen_factor_at`)."""


FACTOR_TOL = 0.01
"""The refreshes of :func:`lagged_fit` stop when the multiple-scattering factor rebuilt at a fit's result differs
from the one that fit used by less than this anywhere (largest relative change over samples and wavelengths): a
third of :data:`SIGMA_RELATIVE`, a block's relative error. [1]"""


def factor_change(old: list[torch.Tensor] | None, new: list[torch.Tensor] | None) -> float:
    """Largest relative change between two lists of multiple-scattering factors (inf when either is missing). [1]"""
    if not old or not new:
        return math.inf
    return max(float((n / o - 1.0).abs().max()) for o, n in zip(old, new))


def lagged_fit(problem: FitProblem, options, refreshes: int = MS_REFRESHES, tol: float = 1e-3,
               bruneton: "SkyModel | None" = None, *, factor_tol: float = FACTOR_TOL, tables=None,
               refresh_last: bool = True, settle_first: bool | None = None):
    """Fit with multiple scattering frozen, refreshed at each fit's result until the values settle.

    Single scattering, the scattering coefficients and the transmittances stay live and differentiable; the
    multiple-scattering part follows the parameters from one fit to the next (a lagged fixed point). Two kinds:

    * ``bruneton`` given: the factor all orders / first order from Bruneton's tables at the last fit's
      atmosphere, per sample and wavelength, on the live single scattering (:func:`freeze_tables`). Photo fits use it: Hillaire's approximation (isotropic phase from the second
      order on) misses the forward-peaked second order of a hazy sky: at AOD 0.3, g 0.82, sun 23 deg from the
      zenith it gives half of Bruneton's radiance at the zenith and at the horizon (docs/photos.md), which
      biased the aerosol of synthetic photos by -40 to -80 %.
    * else the problem's own tables (Hillaire's Psi_ms: sigma_s(y) Psi_ms(h, mu_s) E_sun keeps sigma_s live).

    A photo's factor is moreover followed to first order in each wavelength's aerosol optical depth between
    refreshes (:func:`aod_slope`, one more build; :meth:`FitProblem.frozen_factor_at`), inside a trust region of
    the AOD (:data:`MS_AOD_TRUST`): held fixed, the factor hid how the multiple share grows with the aerosol, and the
    refreshes of hazy synthetic photos crept up from a low AOD without settling (from the truth they ran away);
    and in the aerosol asymmetry g (:func:`g_slope`, one more build, trust region :data:`MS_G_TRUST`).

    Rebuilding and differentiating the tables per evaluation would cost several times a single-scattering
    evaluation of a photo's blocks. The refreshes stop when a fit moves no unconstrained value by more than
    ``tol``, or when the factor rebuilt at its result differs from the one it used by less than ``factor_tol``
    (:data:`FACTOR_TOL`; the fit would not move), or (factor followed) when the AOD moved by less than
    :data:`MS_AOD_SETTLE` — never while the fit ends on its trust region's bound — or after ``refreshes`` fits. The factor is left at the final
    values, so metrics and Laplace see the fitted model (the Laplace Hessian omits the multiple part's own
    dependence on the parameters, but for a followed factor's first-order term in the aerosol optical depth). ``tables``: Bruneton tables ``(tables, wavelength nodes)`` already built near
    the starting point (a second pass starting at the first's result), used for the first fit instead of a build;
    with the AOD-stepped and g-stepped tables when they were built. ``settle_first``: whether the first fit may settle
    without a rebuild (default: where ``tables`` are given; False for tables built at a config's starting
    atmosphere, whose fit moves g and alpha before any refresh). ``refresh_last=False`` skips the build after the last fit (short fits scored by their loss alone).
    """
    x = problem.param.initial_vector(problem.param.base.dtype, problem.param.base.device)
    if bruneton is not None and tables is not None:
        stepped = tables[2] if len(tables) > 2 else None
        stepped_g = tables[3] if len(tables) > 3 else None
        problem.bruneton = (bruneton, tables[0], tables[1], stepped, stepped_g)
        # the tables' own atmosphere (_continuation) with the start's camera: the factor is looked up where they
        # were built and followed from there, as the fit that handed them on followed it
        built = {n: v for n, v in (tables[4] if len(tables) > 4 else {}).items() if n in problem.param.free}
        xb = problem.param.to_unconstrained({**problem.param.free_dict(x), **built}, x.dtype, x.device) if built else x
        _freeze_factor(problem, xb, tables[0], tables[1])
        if stepped is not None and follows_aod(problem):
            follow_aod(problem, xb, stepped, _log_depth(problem, xb))
        if stepped_g is not None and follows_g(problem):
            follow_g(problem, xb, stepped_g)
    else:
        freeze_tables(problem, x, bruneton)
    _start_at(problem, problem.profile_exposure(x))
    res, k, change, best, rebuilt, exhausted = None, 0, math.inf, None, None, False
    curvature, curved_fits = None, 0
    # a fit carried on from another's result with its tables (a race's fit over all the blocks, a second pass, a lens
    # refit) starts near its optimum, as every refresh after the first does
    carried = tables is not None and options.adam_steps == 0 and options.starts == 1
    # Levenberg-Marquardt (a squared loss under "auto") builds its Gauss-Newton curvature itself
    lbfgs = resolved_method(problem, options) == "lbfgs"
    for k in range(max(1, refreshes)):
        res = None
        if (k > 0 or carried) and lbfgs and LAGGED_CURVED and curvature is not False:
            # a fit that starts near its optimum (a refresh's, the factor rebuilt at the last result): BFGS from the
            # Hessian taken once at the first such start (:func:`skyfit.fit.optimise.curved`), L-BFGS where it does
            # not converge
            if curvature is None:
                curvature = _curvature(problem, x)
            if curvature is not False:
                res = curved(problem, x, curvature, precision_tol=CURVED_PRECISION_TOL)
                curved_fits += res is not None
        if res is None:
            res = optimise(problem, options)
        if best is None or res.loss < best[0]:
            best = (res.loss, res, {a: getattr(problem, a, None) for a in _FROZEN_STATE})
        elif res.loss > MS_RUNAWAY * (rebuilt or best)[0]:
            # the refreshes run away: the model with its factor rebuilt at the last result explains the data this much
            # worse than it did at an earlier one (a fit ends at or below the loss it starts from, the rebuilt one);
            # that earlier fit stands, with its rebuilt factor (MS_RUNAWAY). Without a rebuild, the lowest fit loss
            loss, stood, state = rebuilt or best
            for a, v in state.items():
                setattr(problem, a, v)
            res = dataclasses.replace(stood, loss=loss, convergence={**stood.convergence, "ms_runaway": True})
            change = math.nan
            break
        moved = float((res.x - x).abs().max())
        aod_moved = (abs(problem.param.free_dict(res.x)["mie_aod_550"] / problem.param.free_dict(x)["mie_aod_550"] - 1.0)
                     if "mie_aod_550" in problem.param.free else math.inf)
        trust_g = getattr(problem, "trust_g", None)
        g_moved = abs(_g_at(problem, res.x) - _g_at(problem, x)) if trust_g is not None else 0.0
        x = res.x.detach()
        if not refresh_last and k == max(1, refreshes) - 1:
            break
        trust = getattr(problem, "trust", None)  # a PhotoProblem's
        at_trust_bound = ((trust is not None and abs(_log_aod(problem, x) - trust[0]) > 0.99 * trust[1])
                          or (trust_g is not None and abs(_g_at(problem, x) - trust_g[0]) > 0.99 * trust_g[1]))
        settled = trust is not None and aod_moved < MS_AOD_SETTLE and g_moved < MS_G_SETTLE and not at_trust_bound
        if settled and (k > 0 or (tables is not None if settle_first is None else settle_first)) and not MS_SETTLED_REBUILD:
            # the factor the fit followed to first order in the optical depth is the model at x to within what the
            # AOD's last move changes it by: no rebuild. Not on a first fit from fresh tables, whose other values
            # (g, alpha) moved without a refresh yet.
            change = math.nan
            break
        used = problem.frozen_factor
        if used is not None and (problem.frozen_slope is not None or problem.frozen_slope_g is not None):  # the factor the fit ended on
            with torch.no_grad():
                ph = problem.param.to_physical(x)
                used = [problem.frozen_factor_at(problem.param.atmosphere(ph), i, ph) for i in range(len(used))]
        freeze_tables(problem, x, bruneton)
        if problem.model.orders == 1 and bruneton is None:
            break
        change = factor_change(used, problem.frozen_factor)
        if bruneton is not None:
            with torch.no_grad():  # the loss at x of the model with the factor rebuilt there
                loss_x = float(problem.objective(x))
            if rebuilt is None or loss_x < rebuilt[0]:
                rebuilt = (loss_x, res, {a: getattr(problem, a, None) for a in _FROZEN_STATE})
        if ((k > 0 and moved < tol) or change < factor_tol or settled) and not at_trust_bound:
            break
        _start_at(problem, x)
        options = dataclasses.replace(options, adam_steps=0, starts=1)  # near the optimum: L-BFGS alone
    else:
        exhausted = True
    res.convergence["ms_refreshes"] = k + 1
    res.convergence["ms_curved_fits"] = curved_fits  # refreshes fitted from a known curvature (the rest by L-BFGS)
    res.convergence["ms_exhausted"] = exhausted  # the refreshes ran out (no stop by settling or a runaway)
    res.convergence["ms_factor_change"] = change
    res.convergence["ms_table_builds"] = getattr(problem, "table_builds", 0)
    return res


LAGGED_CURVED = True
"""A lagged fit's refreshes after its first, and every fit of one carried on from another's result with its tables, are
fitted from the Hessian taken at the first such fit's start (:func:`skyfit.fit.optimise.curved`), where that converges,
when they would be fitted by L-BFGS (a photo's: its priors live in the objective); L-BFGS from no curvature took
50-100 evaluations a fit (docs/photos.md, "Fits that start from a known curvature"). Levenberg-Marquardt builds its own
Gauss-Newton curvature. False: every fit by the options' optimiser."""


def _curvature(problem: FitProblem, x: torch.Tensor) -> torch.Tensor | bool:
    """The inverse Hessian of n_elements x the objective at x (P, P); for a robust loss the Gauss-Newton one in IRLS
    weights (:func:`skyfit.fit.budget.robust_hessian`): the exact one of a redescending rho is not positive definite
    where outliers sit off the optimum, as at a refresh's start (seed-0 synthetic case 2, min eigenvalue -3.5e4).
    False where it is not positive definite."""
    from .budget import prediction_jacobian, robust_hessian
    from .laplace import covariance_from_hessian, hessian_nll

    try:
        if problem.loss.rho == "squared":
            cov, pd, _ = covariance_from_hessian(hessian_nll(problem, x))
        else:
            cov, pd, _ = covariance_from_hessian(robust_hessian(problem, x, prediction_jacobian(problem, x)))
    except (ValueError, RuntimeError):  # a Hessian that is not finite (FitError is a ValueError)
        return False
    return cov.to(dtype=x.dtype) if pd else False


MS_RUNAWAY = 1.5
"""A lagged refresh whose fit ends above this many times the lowest rebuilt loss so far stops the refreshes: each
rebuild's loss at the fit it follows, the model with the factor rebuilt there (a fit starts from the last one and ends
at or below it). The fit with that lowest rebuilt loss stands, with its rebuilt factor. A fit's own loss is no measure:
the lowest is often one against a factor extrapolated far from its tables, which the model there does not reach
(held-out synthetic case 5, a Foveon bracket at AOD 0.30: fits 0.447, 0.134, 0.176, 0.203 at AOD 0.20, 0.34, 0.28,
0.29, and the 0.134 was against tables built at 0.20. Measured against it the 0.203 stopped the refreshes, the 0.134
stood, and the second pass went on from it with those tables taken for tables built at 0.34: AOD +11.4 %, the
report's model 11 % rms from the photo; docs/photos.md, "The runner-up with its lens"). Without a rebuild (the
first fit) the lowest fit loss is the measure. The rule was set when the factor followed the optical depth and the
geometry but not yet g: on a hazy photo (held-out synthetic case 14, AOD 0.5) g crept 0.73 -> 0.94 over the
refreshes while the loss rose 0.44 -> 1.54 (docs/photos.md, "The factor turns with the camera"). [1]"""
_FROZEN_STATE = ("frozen_factor", "frozen_slope", "frozen_slope_g", "frozen_follow", "bruneton", "trust", "trust_g",
                 "frozen_tables", "frozen_at")
"""What a lagged fit's refresh replaces on the problem (the state a fit was fitted against)."""


def _sky_angles(cam: FisheyeCamera, zenith_deg: float, azimuth_deg: float) -> tuple[np.ndarray, np.ndarray]:
    """Every pixel's elevation (-90 outside the field of view) and angle to the sun (0 outside), (H, W) each. [deg]"""
    with torch.no_grad():
        vec, valid = cam.pixel_vectors(torch.float64)
        sun = zenith_azimuth_to_enu(torch.tensor(math.radians(zenith_deg), dtype=torch.float64),
                                    torch.tensor(math.radians(azimuth_deg), dtype=torch.float64))
    v, ok = np.nan_to_num(vec.numpy()), valid.numpy()
    elevation = np.where(ok, np.degrees(np.arcsin(np.clip(v[..., 2], -1, 1))), -90.0)
    to_sun = np.where(ok, np.degrees(np.arccos(np.clip(np.where(ok, v @ sun.numpy(), 1.0), -1, 1))), 0.0)
    return elevation, to_sun


def _upsample(a: np.ndarray, step: int, shape: tuple[int, int]) -> np.ndarray:
    """Block values back on the photo's pixels (nearest block; the ragged right/bottom edge repeats the last)."""
    H, W = shape
    big = np.repeat(np.repeat(a, step, 0), step, 1)
    out = np.zeros((H, W) + a.shape[2:], a.dtype)
    hh, ww = min(H, big.shape[0]), min(W, big.shape[1])
    out[:hh, :ww] = big[:hh, :ww]
    return out


def loss_with_factor(problem: FitProblem, x: torch.Tensor, other: FitProblem) -> float:
    """The objective of ``other`` (a fit of the same parameters on other blocks: a probe's on the race's) at ``x`` with
    the multiple-scattering factor and trust regions ``problem``'s fit ended on there (:func:`transfer_factor`); ``other``
    itself is left as it was. [1]"""
    o = copy.copy(other)
    for a in _FROZEN_STATE:
        setattr(o, a, None)
    o.frozen_tables = getattr(problem, "frozen_tables", None)
    o.trust, o.trust_g = getattr(problem, "trust", None), getattr(problem, "trust_g", None)
    if getattr(problem, "bruneton", None) is not None:
        o.bruneton = problem.bruneton
        transfer_factor(problem, o, x)
    with torch.no_grad():
        return float(o.objective(x))


def transfer_factor(problem: FitProblem, other: FitProblem, x: torch.Tensor) -> None:
    """Give ``other`` (the same parameters, other samples) the multiple-scattering factor ``problem``'s fit used at x:
    the same tables, looked up where they were built (:attr:`frozen_at`) and followed from there to first order in
    the optical depth and g as the fit followed them. The factor looked up at x alone, without the slopes, is the
    tables' at the build's aerosol: after a runaway of the refreshes (:data:`MS_RUNAWAY`) the fit that stands lay 0.54 in
    ln tau from its tables (held-out synthetic case 5), and the outlier map of the second pass, made with that
    factor, masked 36 % of the sky. [1]"""
    _, tables, nodes = problem.bruneton[:3]
    x0 = getattr(problem, "frozen_at", None)
    slope, slope_g = problem.frozen_slope, problem.frozen_slope_g
    if x0 is None or (slope is None and slope_g is None):
        other.frozen_factor = multiple_from_tables(other, x, tables, nodes)
        return
    other.frozen_factor = multiple_from_tables(other, x0, tables, nodes)
    if slope is not None and problem.bruneton[3] is not None:
        other.frozen_slope = aod_slope(other, x0, other.frozen_factor, problem.bruneton[3], slope[1])
    if slope_g is not None and len(problem.bruneton) > 4 and problem.bruneton[4] is not None:
        other.frozen_slope_g = g_slope(other, x0, other.frozen_factor, problem.bruneton[4])


def predict_blocks(problem, x: torch.Tensor, blocks: BlockImage, scene: PhotoScene, where: np.ndarray) -> np.ndarray:
    """The fitted model (with the camera's nuisances) on every block in ``where``, (h, w, 3); NaN elsewhere."""
    fitted = problem.observations[0]
    obs = block_observation(scene, blocks, where, response=fitted.metadata.get("response"))
    other = FitProblem(problem.param, problem.model, [obs], problem.loss, base_sun_distance_au=base_sun_distance(problem))
    other.frozen_tables = problem.frozen_tables
    if getattr(problem, "bruneton", None) is not None:
        transfer_factor(problem, other, x)
    with torch.no_grad():
        pred = other.predict(x)[0].cpu().numpy()
    out = np.full(blocks.rgb.shape, np.nan)
    out.reshape(-1, 3)[np.flatnonzero(where.reshape(-1))] = pred
    return out


def base_sun_distance(problem: FitProblem) -> float:
    """The Earth-Sun distance the problem's solar spectrum is for (undoing its per-observation scale). [AU]"""
    o = problem.observations[0]
    return 1.0 if o.sun_distance_au is None else o.sun_distance_au * math.sqrt(problem.solar_scale[0])


def relative_residual_map(problem, x: torch.Tensor, blocks: BlockImage, scene: PhotoScene) -> np.ndarray:
    """(model - photo) / photo in luminance on every candidate block (h, w); NaN where none or censored."""
    where = blocks.candidate & ~(blocks.censored != 0).any(-1)
    model = predict_blocks(problem, x, blocks, scene, where)
    lm, lp = _luminance(np.nan_to_num(model)), _luminance(blocks.rgb)
    rel = np.where(where & (lp > 0), (lm - lp) / np.where(lp > 0, lp, 1.0), np.nan)
    return rel


def lens_camera(cam: FisheyeCamera, k: float, nodes: int = 200) -> FisheyeCamera:
    """The Kannala-Brandt camera whose pixels see what ``cam`` (an untilted classical projection) sees through
    ``lens_radial`` k (:func:`skyfit.fit.model.lens_directions`): r = f (theta + k1 theta^3 + ... + k4 theta^9)
    (Kannala & Brandt 2006, eq. 6) fitted by linear least squares to the radius r(theta) of ``nodes`` angles
    up to the camera's field; ``cam`` itself when k = 0. Centre, heading and 90-degree circle are kept."""
    if k == 0.0 or cam.projection == "kannala_brandt":
        return cam
    top = math.radians(cam.max_zenith_deg)
    tp = torch.linspace(0.0, top, nodes, dtype=torch.float64)
    theta = tp + k * tp * ((math.pi / 2) ** 2 - tp * tp)  # the ray's true angle at the pixel of nominal angle tp
    r = float(cam.r90) * theta_to_rho(tp, cam.projection)
    A = torch.stack([theta ** (2 * j + 1) for j in range(5)], -1)
    c = torch.linalg.lstsq(A, r[:, None]).solution[:, 0]
    f = float(c[0])
    meta = cam.to_metadata()
    meta.update(projection="kannala_brandt", focal_px=f, kb_coeffs=[float(v) / f for v in c[1:]], radius_px=None,
                nominal_projection=cam.projection, lens_radial=k)
    return FisheyeCamera.from_metadata(meta)


def camera_from_result(cam: FisheyeCamera, values: dict) -> FisheyeCamera:
    """The photo's camera with the fitted heading and tilt (:func:`fitted_camera`), through the fitted lens
    (:func:`lens_camera`) when ``lens_radial`` is not 0."""
    g = lambda n: float(values.get(n, 0.0)) if not isinstance(values.get(n), list) else float(values[n][0])  # noqa: E731
    return fitted_camera(lens_camera(cam, g("lens_radial")), g("sun_azimuth_offset"), g("camera_tilt_north"),
                         g("camera_tilt_east"))


def _angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    return math.degrees(math.atan2(float(np.linalg.norm(np.cross(a, b))), float(np.dot(a, b))))


SUN_REGISTRATION_MIN_IOU = 0.7
"""The fitted model's saturated region stands in for the detected sun only where, registered, it overlaps the photo's
by at least this (intersection over union): elsewhere its shape is not the photo's (a flare or a sun disc the model
lacks, an aureole the fit misses) and the detector's point stays. On the synthetic suite's single photos the
registered overlap was 0.79-0.98 (docs/photos.md, "The sun: registered, not only detected"). [1]"""
SUN_REGISTRATION_REACH = 0.25
"""The model's saturated region stands for the sun only where the model's own sun lies in it or within this fraction
of its equivalent radius (sqrt(area / pi)) of it (1.5 px at least). A large aureole whose tip stops short of the sun
is the photo's aureole without the sun's disc and flare, which add a bump at its tip (synthetic case 8: 5.1 px
short of a region of radius 52 px, 0.10); a region that lies beside the sun is a bright horizon the model puts where
the photo has a compact core of disc and flare (case 4: 4.7 px from a region of radius 7 px, 0.67; registered,
it would have moved the sun 12.6 px). On the other single photos of the suite the model's region holds its sun
(gaps under 0.5 px). [1]"""
SUN_REGISTRATION_MIN_CONTRAST = 0.25
"""The model's saturated region stands for the sun only where the model's brightest value in it is at least this much
over its faintest (:attr:`SunRegistration.contrast`): a flatter region is drawn by the weak gradients of a broad
aureole (the airmass toward the horizon, vignetting), not by the sun, and lies where they put it. On the synthetic
suites' 20 single photos (docs/photos.md, "A flat aureole registers nothing") the region was that flat where the photo's
saturated region is a compact sun disc with its flare (radius 6.5-7.2 px, contrast 0.005-0.019), and registering it
moved the sun 3.3-11.5 px off (held-out case 18: 7.3 px, 2.7 deg, where the centroid was 0.2 px from the truth);
seed-0 case 14 (0.16) 3.5 px against the centroid's 1.5; every region at 0.34 or more registered the sun nearer the
truth than the centroid, or within 0.3 px of it. [1]"""
SUN_REGISTRATION_BLOCKS = 5000
"""The model is rendered on at most this many blocks over the saturated region's window and interpolated in log
radiance to the photo's pixels (its aureole varies over several pixels; 1 s on one core for a 600 x 600 photo)."""


@dataclasses.dataclass
class SunRegistration:
    """The sun where the photo's saturated region lies under the fitted model's (:func:`register_sun`).

    Attributes:
        x, y: the registered sun, image convention: the fitted model's sun moved by ``shift``. [px]
        shift: (dx, dy) that best overlays the model's saturated region on the photo's. [px]
        iou: their overlap (intersection over union) at ``shift``. [1]
        pixels: saturated pixels of the photo's region (the model's region has as many). [px]
        step: block side the model was rendered on before interpolation. [px]
        covers_sun: the model's saturated region reaches its own sun (:data:`SUN_REGISTRATION_REACH`). Where it
            does not, the model's brightest pixels lie elsewhere (a bright horizon beside a compact core of sun disc
            and flare, which the model lacks) and the overlay says nothing about the sun.
        contrast: the model's brightest over its faintest value in its saturated region, less 1. [1]
    """

    x: float
    y: float
    shift: tuple[float, float]
    iou: float
    pixels: int
    step: int
    covers_sun: bool = True
    contrast: float = math.nan

    @property
    def used(self) -> bool:
        """Whether the registered sun stands for the detection: the model's region reaches its sun, is not flat
        (:data:`SUN_REGISTRATION_MIN_CONTRAST`) and overlaps the photo's by :data:`SUN_REGISTRATION_MIN_IOU`."""
        return (self.covers_sun and self.iou >= SUN_REGISTRATION_MIN_IOU
                and not self.contrast < SUN_REGISTRATION_MIN_CONTRAST)


def register_sun(scene: PhotoScene, problem, x: torch.Tensor, model_px: Sequence[float],
                 max_blocks: int = SUN_REGISTRATION_BLOCKS) -> SunRegistration | None:
    """Where the photo's saturated sun region says the sun is, under the fitted model's shape of that region.

    A saturated core's centroid (:func:`skyfit.camera.autocal.detect_sun`) lies off the sun wherever the aureole is
    not symmetric about it, and the aureole is not: it brightens toward the horizon, the projection stretches it,
    the horizon's glow merges with it (12.7 px, 4.6 deg, on a synthetic single photo with the sun 13 deg up, where
    the fitted camera put the sun 1.5 px from the truth). So the fitted model (camera nuisances included) is
    rendered over the region's window (:data:`SUN_REGISTRATION_BLOCKS` blocks, log-linear interpolation to pixels;
    obstacles and user-masked pixels excluded as the photo's dark obstacles are), its brightest pixels, as many as
    the photo's saturated ones in the window, are its saturated region, and the shift that overlays it best on the
    photo's region is found by cross-correlation (``scipy.signal.fftconvolve`` of the two masks, the peak refined
    by a parabola per axis). The registered sun is the model's sun moved by that shift. Least squares on the
    whole region's outline instead of one centroid; it uses the model's shape, not its position, which is what the
    comparison tests: the fit's censored bounds only push the model above a saturated block, never pull it down
    to the outline, and most of the outline lies inside the sun's mask.

    Returns None without a saturated detection, where the window holds no saturated pixel or the model no value.
    """
    import scipy.ndimage
    import scipy.signal
    import skimage.measure

    det = scene.detected_sun
    if det is None or not det.saturated:
        return None
    ph = scene.photo
    H, W = ph.rgb.shape[:2]
    valid = ~scene.masks["outside"]
    allowed = valid.copy()
    for k in ("obstacles", "user"):
        if k in scene.masks:
            allowed &= ~scene.masks[k]
    sat = ph.darkest_saturated & valid
    lab = skimage.measure.label(sat, connectivity=2)
    yy, xx = np.ogrid[:H, :W]
    near = (xx - det.x) ** 2 + (yy - det.y) ** 2 <= (det.radius_px + 3.0) ** 2
    ids = np.unique(lab[near & sat])
    region = np.isin(lab, ids[ids > 0])
    if not region.any():
        return None
    ys, xs = np.nonzero(region)
    pad = 0.25 * max(np.ptp(ys), np.ptp(xs)) + 10.0
    y0, y1 = max(0, int(ys.min() - pad)), min(H, int(ys.max() + pad) + 1)
    x0, x1 = max(0, int(xs.min() - pad)), min(W, int(xs.max() + pad) + 1)
    win = np.zeros((H, W), bool)
    win[y0:y1, x0:x1] = True
    photo_sat = sat & win
    n_sat = int(photo_sat.sum())
    step = max(1, math.ceil(math.sqrt((y1 - y0) * (x1 - x0) / max_blocks)))
    blocks = block_image(scene, step=step)
    h, w = blocks.rgb.shape[:2]
    with torch.no_grad():
        _, bvalid = blocks.camera.pixel_vectors(torch.float64)
    where = np.zeros((h, w), bool)
    where[max(0, y0 // step - 1): y1 // step + 2, max(0, x0 // step - 1): x1 // step + 2] = True
    where &= bvalid.cpu().numpy()
    if not where.any():
        return None
    model = predict_blocks(problem, x, blocks, scene, where)
    peak = np.where(where, np.nan_to_num(model, nan=0.0, posinf=0.0).max(-1), 0.0)  # the brightest channel saturates first
    good = where & (peak > 0)
    lm = np.log(np.where(good, peak, 1.0))
    if not good.any():
        return None
    # nearest-block fill so that the interpolation has neighbours at the window's and the circle's edges
    _, (iy, ix) = scipy.ndimage.distance_transform_edt(~good, return_indices=True)
    lm = lm[iy, ix]
    gy, gx = np.meshgrid((np.arange(y0, y1) - (step - 1) / 2.0) / step, (np.arange(x0, x1) - (step - 1) / 2.0) / step,
                         indexing="ij")
    full = np.full((H, W), -np.inf)
    full[y0:y1, x0:x1] = scipy.ndimage.map_coordinates(lm, [gy, gx], order=1, mode="nearest")
    full = np.where(allowed & win, full, -np.inf)
    fin = np.isfinite(full)
    n_fin = int(fin.sum())
    if n_fin < 3 or n_sat < 3:
        return None
    n = min(n_sat, n_fin)
    model_sat = fin & (full >= np.partition(full[fin], n_fin - n)[n_fin - n])
    a = photo_sat[y0:y1, x0:x1].astype(np.float64)
    b = model_sat[y0:y1, x0:x1].astype(np.float64)
    c = scipy.signal.fftconvolve(a, b[::-1, ::-1], mode="same")  # overlap in pixels at each shift
    iy0, ix0 = np.unravel_index(int(np.argmax(c)), c.shape)

    def vertex(m: float, z: float, p: float) -> float:
        d = m - 2.0 * z + p
        return 0.0 if d >= 0 else 0.5 * (m - p) / d

    sy = iy0 - c.shape[0] // 2 + (vertex(c[iy0 - 1, ix0], c[iy0, ix0], c[iy0 + 1, ix0]) if 0 < iy0 < c.shape[0] - 1 else 0.0)
    sx = ix0 - c.shape[1] // 2 + (vertex(c[iy0, ix0 - 1], c[iy0, ix0], c[iy0, ix0 + 1]) if 0 < ix0 < c.shape[1] - 1 else 0.0)
    moved = scipy.ndimage.shift(model_sat.astype(np.float64), (sy, sx), order=1) > 0.5
    iou = float((moved & photo_sat).sum() / max(1, (moved | photo_sat).sum()))
    mx, my = float(model_px[0]), float(model_px[1])
    ys_m, xs_m = np.nonzero(model_sat)
    gap = float(np.sqrt(np.min((xs_m - mx) ** 2 + (ys_m - my) ** 2)))  # from the model's sun to its region [px]
    covers = gap <= max(1.5, SUN_REGISTRATION_REACH * math.sqrt(n / math.pi))
    inner = full[model_sat]
    contrast = float(math.expm1(inner.max() - inner.min()))
    return SunRegistration(mx + float(sx), my + float(sy), (float(sx), float(sy)), iou, n_sat, step, covers, contrast)


def photo_result(scene: PhotoScene, blocks: BlockImage, prep, problem, res, config: dict, *, laplace: bool) -> dict:
    """RESULT.json of a photo fit: the common keys (:func:`skyfit.fit.results.result_dict`) and the photo's own."""
    from .results import result_dict

    s = prep.settings
    result = result_dict(problem, res, command="fit", settings=dataclasses.asdict(s), config=config,
                         config_source=str(config.get("name", "")), base_dist=prep.base_dist, dtype=s.dtype, seconds=0.0,
                         laplace=laplace)
    if getattr(problem, "bruneton", None) is not None:  # live single scattering + Bruneton's orders, frozen per fit
        ms = problem.bruneton[0]
        # the factor's tables as SkyModel.settings() writes them (orders, table sizes, ray rule, density directions)
        full = {k: v for k, v in ms.settings().items() if k in ("orders", "multiple", "table_sizes", "ray_rule", "density_directions")}
        result["settings"].update(orders=ms.orders, multiple="bruneton")
        result["model"].update(full, multiple_frozen="orders >= 2 from Bruneton's tables, refreshed per fit (fit.photo.lagged_fit)")
        result["integrator"].update(full)
    vals = problem.param.physical_dict(res.x)
    cam = camera_from_result(scene.camera, vals)
    sun_dir = zenith_azimuth_to_enu(torch.tensor(math.radians(scene.sun_zenith_deg), dtype=torch.float64),
                                    torch.tensor(math.radians(scene.sun_azimuth_deg), dtype=torch.float64))
    with torch.no_grad():
        mx, my = cam.direction_to_pixel(sun_dir)
    model_px = [float(mx), float(my)]
    det = scene.detected_sun

    def separation(px: float, py: float) -> float:
        with torch.no_grad():
            d = cam.pixel_to_direction(torch.tensor(px, dtype=torch.float64), torch.tensor(py, dtype=torch.float64))
        return _angle_deg(d.numpy(), sun_dir.numpy())

    detected_px, sep, centroid, reg, by = None, None, None, None, None
    if det is not None:
        centroid = {"px": [float(det.x), float(det.y)], "separation_deg": separation(det.x, det.y)}
        detected_px, sep, by = centroid["px"], centroid["separation_deg"], "centroid"
        reg = register_sun(scene, problem, res.x, model_px)
        if reg is not None and reg.used:
            detected_px, sep, by = [reg.x, reg.y], separation(reg.x, reg.y), "registration"
    sig = (result.get("laplace") or {}).get("sigma") or {}
    pred = problem.predict(res.x)[0].detach()
    obs = problem.observations[0]
    v = obs.values[obs.mask]
    measured = (obs.censored[obs.mask] == 0) & (v > 0)
    pc = problem.censor(pred, 0)
    rel = ((pc - v) / torch.where(v > 0, v, torch.ones_like(v)))[measured]
    step2 = blocks.step ** 2
    excluded = scene.excluded
    inside = ~scene.masks["outside"]
    censored_px = (scene.photo.censored_high | scene.photo.censored_low).any(-1) & inside & ~excluded
    cam_meta = cam.to_metadata()
    cam_meta.update(source="given" if not scene.candidates else "estimated from the image and the sun",
                    **{k: vals.get(k) for k in CAMERA_RESPONSE})
    if "lens_radial" in problem.param.free or vals.get("lens_radial"):
        cam_meta.update(nominal_projection=scene.camera.projection, lens_radial=vals["lens_radial"])
    if scene.circle is not None:
        cam_meta["circle"] = dataclasses.asdict(scene.circle)
    if scene.mirror:
        cam_meta["mirror"] = True
    if scene.candidates:
        cam_meta["projection_evidence"] = [{"projection": c.projection, "sun_radius_error_deg": c.score,
                                            "tolerance_deg": c.tolerance_deg} for c in scene.candidates]
    result["camera"] = cam_meta
    result["sun"] = {"zenith_deg": scene.sun_zenith_deg, "azimuth_deg": scene.sun_azimuth_deg, "model_px": model_px,
                     "detected_px": detected_px, "separation_deg": sep,
                     "detected_kind": None if det is None else ("saturated aureole" if det.extended
                                                               else "saturated core" if det.saturated else "peak"),
                     "detected_radius_px": None if det is None else float(det.radius_px),
                     "detected_by": by,
                     "centroid_px": None if centroid is None else centroid["px"],
                     "centroid_separation_deg": None if centroid is None else centroid["separation_deg"],
                     "registration": None if reg is None else {
                         "shift_px": list(reg.shift), "iou": reg.iou, "pixels": reg.pixels, "step_px": reg.step,
                         "covers_sun": reg.covers_sun, "contrast": reg.contrast, "used": reg.used}}
    result["aerosol"] = aerosol_summary(vals, sig, problem.param.free)
    result["metrics"]["rmse_rel"] = float(torch.sqrt((rel ** 2).mean())) if rel.numel() else None
    result["pixels"] = {"used": int(blocks.usable.sum()) * step2, "masked": int((excluded & inside).sum()),
                        "censored": int(censored_px.sum()), "block_px": blocks.step,
                        "masked_by": {k: int((m & inside).sum()) for k, m in scene.masks.items() if k != "outside"}}
    result["photo"] = {k: v for k, v in scene.photo.meta.items()}
    result["photo"]["shape"] = list(scene.photo.rgb.shape[:2])
    result["notes"] = list(scene.notes)
    if sep is not None and sep > SUN_NOTE_DEG:
        result["notes"].append(f"the fitted camera puts the sun {sep:.1f} deg from where the photo shows it (over "
                               f"{SUN_NOTE_DEG:g} deg): the camera or the detection is off (a cloud over the sun, a wrong "
                               "projection); check RESULT.png")
    result["time"], result["location"] = scene.time, scene.location
    return _in_photo_pixels(result, scene.scale)


def aerosol_summary(vals: dict, sig: dict, free) -> dict:
    """RESULT.json's ``aerosol`` of a photo fit: the values; ``sigma_statistical``, the error budget's sigma (noise,
    numerical, discrepancy: :mod:`skyfit.fit.budget`; None where the Laplace has none); ``sigma_validation``, the photo
    path's expected error (:data:`PHOTO_VALIDATION_SIGMA`) of each fitted value; ``sigma``, the two in quadrature (None
    where the statistical one is None)."""
    names = (("aod_550", "mie_aod_550"), ("angstrom_alpha", "mie_angstrom_alpha"), ("g", "mie_g"), ("rayleigh_scale", "rayleigh_scale"))
    out = {k: vals[n] for k, n in names}
    stat = {k: sig.get(n) for k, n in names}
    valid = {}
    for k, n in names:
        if k in PHOTO_VALIDATION_SIGMA and n in free:
            kind, v = PHOTO_VALIDATION_SIGMA[k]
            valid[k] = v * abs(float(vals[n])) if kind == "relative" else v
    out["sigma"] = {k: (None if s is None else math.hypot(s, valid.get(k, 0.0))) for k, s in stat.items()}
    out["sigma_statistical"] = stat
    out["sigma_validation"] = valid
    return out


def _in_photo_pixels(result: dict, scale: int) -> dict:
    """A photo fit's RESULT.json with the pixels of a reduced photo (:attr:`PhotoScene.scale`) turned into the photo's
    own: the camera and its circle (:func:`rescaled_camera_meta`), the sun's positions and radius, the registration's
    shift and step, the pixel counts (each reduced pixel stands for scale^2) and ``photo.shape``; ``photo.reduced``
    says by what. Unchanged for ``scale`` 1."""
    if scale == 1:
        return result
    at = lambda p: None if p is None else [pixel_at(v, scale) for v in p]  # noqa: E731
    shape = result["photo"]["reduced"]["original_shape"]
    result["camera"] = rescaled_camera_meta(result["camera"], float(scale), tuple(shape))
    sun = result["sun"]
    sun.update(model_px=at(sun["model_px"]), detected_px=at(sun["detected_px"]), centroid_px=at(sun.get("centroid_px")))
    if sun.get("detected_radius_px") is not None:
        sun["detected_radius_px"] = scale * sun["detected_radius_px"]
    if sun.get("registration"):
        reg = sun["registration"]
        reg.update(shift_px=[scale * v for v in reg["shift_px"]], step_px=scale * reg["step_px"], pixels=scale ** 2 * reg["pixels"])
    px = result["pixels"]
    for k in ("used", "masked", "censored"):
        px[k] *= scale ** 2
    px["block_px"] *= scale
    px["masked_by"] = {k: v * scale ** 2 for k, v in px["masked_by"].items()}
    result["photo"]["shape"] = list(shape)
    return result


def fit_photo(photo, *, time: str | None = None, location=None, config: dict, camera=None, mask=None, exposures=None, linear: bool = False,
              response: str | None = None, overrides: dict | None = None, laplace: bool = True, progress: bool = False,
              device="cpu") -> PhotoFit:
    """Steps 1-7 on one photo (see the module docstring); nothing is written. ValueErrors name the file."""
    camera_meta = None
    if isinstance(camera, (str, Path)):
        camera_meta = read_camera(camera)
        camera = camera_meta
    elif isinstance(camera, dict):
        camera_meta = camera
    scene = prepare_scene(photo, time=time, location=location, camera=camera, mask=mask, exposures=exposures,
                          linear=linear, response=response)
    return fit_scene(scene, copy.deepcopy(config), overrides=overrides, camera_meta=camera_meta, laplace=laplace,
                     progress=progress, device=device)


def report_png(pf: PhotoFit, path: str | Path) -> Path:
    """RESULT.png: photo, model, relative residual and mask side by side (atomic write)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ..io.atomic import atomic_path

    b = pf.blocks
    sky = b.sky | b.candidate
    lum = _luminance(np.nan_to_num(b.rgb))
    white = float(np.percentile(lum[sky], 99)) if sky.any() else 1.0
    tone = lambda a: np.clip(np.nan_to_num(a) / max(white, 1e-30), 0, 1) ** (1 / 2.2)  # noqa: E731
    rel = np.where(sky, (_luminance(np.nan_to_num(pf.model_rgb)) - lum) / np.where(lum > 0, lum, 1.0), np.nan)
    used = np.zeros(b.usable.shape + (3,))
    used[..., 1] = b.usable
    used[..., 0] = (b.censored != 0).any(-1) & b.sky
    used[..., 2] = b.candidate & ~b.sky
    fig, ax = plt.subplots(1, 4, figsize=(16, 4.4))
    ax[0].imshow(tone(b.rgb))
    ax[0].set_title("photo (linear, tone-mapped)")
    ax[1].imshow(tone(np.where(sky[..., None], pf.model_rgb, 0.0)))
    ax[1].set_title("model (fitted camera)")
    im = ax[2].imshow(rel, cmap="RdBu_r", vmin=-0.3, vmax=0.3)
    fig.colorbar(im, ax=ax[2], fraction=0.046, label="(model - photo) / photo")
    ax[2].set_title(f"residual, rms {pf.result['metrics'].get('rmse_rel') or float('nan'):.3f}")
    ax[3].imshow(used)
    ax[3].set_title("used (green), censored (red), masked (blue)")
    sun = pf.result["sun"]
    per = b.step * pf.scene.scale  # pixels of the photo as read per block
    on = lambda p: ([pixel_at(p[0], 1.0 / per)], [pixel_at(p[1], 1.0 / per)])  # noqa: E731
    for a in ax:
        a.set_axis_off()
        a.plot(*on(sun["model_px"]), "y+", ms=12)
        if sun["detected_px"]:
            a.plot(*on(sun["detected_px"]), "mx", ms=8)
        if sun.get("centroid_px") and sun["centroid_px"] != sun["detected_px"]:
            a.plot(*on(sun["centroid_px"]), "c.", ms=6)
    fig.suptitle(f"{Path(pf.scene.photo.source).name}: AOD550 {pf.result['aerosol']['aod_550']:.3f}, "
                 f"alpha {pf.result['aerosol']['angstrom_alpha']:.2f}, g {pf.result['aerosol']['g']:.2f}")
    fig.tight_layout()
    path = Path(path)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=90)
    plt.close(fig)
    return path


__all__ = [
    "BlockImage", "CALIBRATED_FREE", "SUN_DATUM_SIGMA_DEG", "SunDatum", "sun_datum", "GAIN_PRIOR_LOG_SIGMA", "PHOTO_FREE", "PhotoProblem", "VIGNETTING_PRIOR", "camera_priors", "PHOTO_SETTINGS", "PhotoFit", "PhotoFitError", "PhotoScene",
    "block_image", "block_observation", "camera_from_dict", "camera_from_result", "fit_photo", "fit_scene",
    "fitted_camera", "prepare_scene", "read_camera", "read_sensitivities", "report_png", "scaled_camera", "scene_masks",
]


# -- files in, files out (the CLI's calls) ----------------------------------------------------------
def read_mask(path: str | Path, shape: tuple[int, int]) -> np.ndarray:
    """A user's mask image (PNG/TIFF/JPEG; non-zero = ignore) as (H, W) bool; PhotoFitError naming the file."""
    import skimage.io  # here: 1 s to import, only a mask file needs it

    p = Path(path)
    if not p.is_file():
        raise PhotoFitError(f"mask {p}: not found")
    try:
        m = np.asarray(skimage.io.imread(p))
    except Exception as e:  # noqa: BLE001 - reader errors vary by plugin
        raise PhotoFitError(f"mask {p}: cannot read it: {str(e).splitlines()[0] if str(e) else type(e).__name__}") from None
    if m.ndim == 3:
        m = m[..., :3].max(-1) if m.shape[-1] in (3, 4) else m.max(-1)
    if m.shape != tuple(shape):
        raise PhotoFitError(f"mask {p}: {m.shape[0]}x{m.shape[1]} px, the photo is {shape[0]}x{shape[1]}")
    return m != 0


def run_photo_fit(photo: str | Path, config: dict, out: str | Path, *, time: str | None = None, location=None, camera=None, mask=None,
                  exposures=None, linear: bool = False, response: str | None = None, overrides: dict | None = None,
                  plots: bool = True, progress: bool = False, laplace: bool = True, device="cpu") -> dict:
    """``skyfit fit PHOTO``: fit, then write RESULT.png and RESULT.json (each atomically; nothing on failure)."""
    from .results import check_result_path, save_result

    out = check_result_path(out)
    user_mask = None
    if mask is not None:
        ph = read_photo(photo, linear=linear, exposures=exposures, response=response)
        user_mask = read_mask(mask, ph.rgb.shape[:2])
        photo = ph
    pf = fit_photo(photo, time=time, location=location, config=config, camera=camera, mask=user_mask, exposures=exposures,
                   linear=linear, response=response, overrides=overrides, laplace=laplace, progress=progress, device=device)
    png = out.with_suffix(".png")
    if plots:
        report_png(pf, png)
        pf.result["plots"] = [str(png)]
    try:
        save_result(pf.result, out)
    except BaseException:
        if plots:  # no RESULT.png without its RESULT.json
            png.unlink(missing_ok=True)
        raise
    return pf.result


def evaluate_photo(result: dict, photo, *, time: str | None = None, location=None, refit: Sequence[str] = ("exposure",), device="cpu",
                   progress: bool = False) -> dict:
    """Score another photo of the same camera with a photo fit's atmosphere and camera.

    The atmosphere and the camera (heading, tilt, vignetting, gains, saturations) stay as fitted; only ``refit``
    (default the exposure, which differs from photo to photo) is fitted on the new photo.
    Returns rmse_rel (relative RMS over the used blocks), rmse, delta_e, the pixels, the sun's placement.
    """
    if "camera" not in result or "aerosol" not in result:
        source = photo.source if isinstance(photo, LinearPhoto) else photo
        raise PhotoFitError(f"photo {source}: evaluate needs the RESULT.json of a photo fit (this one has no fitted camera)")
    cam = dict(result["camera"])
    params = {k: v for k, v in result["parameters"].items() if not isinstance(v, list)}
    fixed_atm = {k: v for k, v in params.items() if k in ("rayleigh_scale", "rayleigh_scale_height", "mie_aod_550",
                                                           "mie_angstrom_alpha", "mie_ssa", "mie_scale_height", "mie_g",
                                                           "ground_albedo", "ozone_column")}
    config = dict(result["config"])
    settings = dict(result.get("settings") or {})
    keep = ("loss", "integrator", "orders", "multiple", "lut_size", "lut_directions", "lut_samples", "view_samples", "rule",
            "wavelengths", "dtype")
    overrides = {k: settings[k] for k in keep if k in settings}
    overrides.update(free=list(refit), initial=fixed_atm)
    site = result.get("location") or {}
    site = tuple(site[k] for k in ("latitude_deg", "longitude_deg", "elevation_m")) if "latitude_deg" in site else None
    scene = prepare_scene(photo, time=time, location=location, camera=cam, site=site)
    was_mono, is_mono = bool((result.get("photo") or {}).get("monochrome")), bool(scene.photo.meta.get("monochrome"))
    if was_mono != is_mono:
        kind = lambda m: "grey (monochrome)" if m else "colour"  # noqa: E731
        raise PhotoFitError(f"photo {scene.photo.source}: a {kind(is_mono)} image, but the fit was of a {kind(was_mono)} "
                            "camera's photo; evaluate takes another photo of the same camera")
    pf = fit_scene(scene, config, overrides=overrides, camera_meta=cam, laplace=False, progress=progress, device=device,
                   second_pass=False, choose_projection=False)
    r = pf.result
    return {"rmse_rel": r["metrics"]["rmse_rel"], "rmse": r["metrics"]["rmse"], "rmse_units": r["metrics"]["rmse_units"],
            "delta_e": r["metrics"]["delta_e"], "n_samples": r["metrics"]["n_samples"], "refitted": list(refit),
            "nuisance": {n: r["parameters"][n] for n in refit}, "sun": r["sun"], "pixels": r["pixels"],
            "photo": r["photo"].get("format"), "time": r["time"], "location": r["location"], "notes": r["notes"],
            "seconds": r["seconds"]}
