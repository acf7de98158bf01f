"""One camera from several sky photos: ``skyfit calibrate-camera`` as plain functions.

Each photo is fitted on its own (:func:`skyfit.fit.photo.fit_photo`: lens circle, sun, projection,
heading and tilt from the image and the computed sun, then the fit's camera nuisances), and the
per-photo cameras are combined into the one CAMERA.yaml that ``skyfit fit PHOTO --camera CAMERA.yaml``
reads (:func:`skyfit.fit.photo.read_camera`, :func:`skyfit.fit.photo.camera_from_dict`):

* **projection**: the one most photos chose; a tie goes to the smallest summed evidence (the angle
  between where each projection puts the detected sun's radius and the computed sun's zenith,
  ``projection_evidence`` of each fit, summed over the photos);
* **centre and radius** (``cx``, ``cy``, ``radius_px``): the median over all photos (the lens circle
  does not depend on the projection);
* **heading** (``up_azimuth_deg``): the circular median over the photos of the chosen projection;
  **tilt** (``tilt_deg``, toward East and North), **vignetting** and the white-balance **gains**: the
  median over those photos.

The file records each photo's own values (``photos:``) and, as comments, the spread of each combined
value (largest deviation from it and the median absolute deviation), so that a photo that disagrees
can be found. Angles in degrees, positions in the photos' pixels (x = column, y = row).
"""
from __future__ import annotations

import collections
import math
from pathlib import Path
from typing import Sequence

import numpy as np

from ..camera.autocal import CalibrationError
from ..camera.fisheye import FisheyeCamera
from ..io.atomic import write_text_atomic
from ..io.photo import read_photo
from .parameters import CAMERA_RESPONSE
from .photo import CAMERA_INFO_KEYS, CAMERA_KEYS, PhotoFitError, fit_photo, lens_camera

CAMERA_FILE_KEYS = ("projection", "size", "cx", "cy", "radius_px", "focal_px", "kb_coeffs", "nominal_projection", "lens_radial",
                    "up_azimuth_deg", "tilt_deg", "max_zenith_deg", "vignetting", "gain_red", "gain_blue", "saturation_red", "saturation_blue",
                    "convention",
                    "source", "photos")
"""The keys :func:`calibrate_camera` writes, in this order (all accepted by :func:`skyfit.fit.photo.read_camera`)."""


def circular_median_deg(angles: Sequence[float]) -> float:
    """The circular median of angles: the direction minimising the summed absolute angular distance. [deg]

    Candidates are the angles themselves and the midpoints between circularly neighbouring ones (for an even
    count every point of the arc between the two middle angles minimises the sum; its midpoint is returned).
    Fisher 1993, *Statistical analysis of circular data*, §2.3.2. Result in [0, 360).
    """
    a = np.mod(np.asarray(angles, np.float64), 360.0)
    if a.size == 0 or not np.isfinite(a).all():
        raise ValueError(f"circular median: need finite angles, got {list(np.atleast_1d(angles))}")
    s = np.sort(a)
    gap = np.mod(np.roll(s, -1) - s, 360.0)
    cands = np.concatenate([np.mod(s + gap / 2.0, 360.0), s])  # midpoints first: an even count's tie -> the middle
    cost = np.abs(_wrap180(a[None, :] - cands[:, None])).sum(1)
    best = cands[np.isclose(cost, cost.min(), rtol=0, atol=1e-9)]
    return float(best[0]) % 360.0


def _wrap180(d: np.ndarray) -> np.ndarray:
    """Angle differences into [-180, 180). [deg]"""
    return np.mod(np.asarray(d, np.float64) + 180.0, 360.0) - 180.0


def _spread(values: Sequence[float], centre: float, circular: bool = False) -> dict:
    """Largest |deviation| from ``centre`` and the median absolute deviation (both in the values' unit)."""
    d = np.asarray(values, np.float64) - centre
    d = np.abs(_wrap180(d) if circular else d)
    return {"max_abs_dev": float(d.max()), "mad": float(np.median(d))}


def _photo_entry(path, time: str, pf) -> dict:
    """One photo's own camera and fit quality, as written under ``photos:``."""
    cam = pf.camera
    meta = cam.to_metadata()
    res = pf.result
    rc = res["camera"]
    num = lambda v: None if v is None else float(v)  # noqa: E731
    return {
        "path": str(path), "time": str(time), "projection": cam.projection,
        "nominal_projection": rc.get("nominal_projection", cam.projection), "lens_radial": float(rc.get("lens_radial") or 0.0),
        **({"focal_px": float(meta["focal_px"]), "kb_coeffs": [float(v) for v in meta["kb_coeffs"]]}
           if cam.projection == "kannala_brandt" else {}),
        "cx": float(meta["cx"]), "cy": float(meta["cy"]), "radius_px": float(meta["radius_px"]),
        "up_azimuth_deg": float(meta["up_azimuth_deg"]), "tilt_deg": [float(v) for v in meta["tilt_deg"]],
        "max_zenith_deg": float(meta["max_zenith_deg"]),
        "vignetting": num(rc.get("vignetting")), "gain_red": num(rc.get("gain_red")), "gain_blue": num(rc.get("gain_blue")),
        "saturation_red": num(rc.get("saturation_red")), "saturation_blue": num(rc.get("saturation_blue")),
        "projection_evidence": {e["projection"]: num(e["sun_radius_error_deg"]) for e in rc.get("projection_evidence", [])},
        "sun_separation_deg": num(res["sun"].get("separation_deg")), "rmse_rel": num(res["metrics"].get("rmse_rel")),
        "loss": num(res["metrics"].get("loss")), "shape": [int(v) for v in res["photo"]["shape"]],
    }


def _nominal(entry: dict) -> str:
    """The projection a photo's fit chose (its camera is Kannala-Brandt when the fitted lens departs from it)."""
    return entry.get("nominal_projection") or entry["projection"]


def choose_projection(entries: list[dict]) -> tuple[str, str]:
    """The projection most photos chose (:func:`_nominal`); ties by the smallest summed sun-radius evidence. -> (name, why)."""
    votes = collections.Counter(_nominal(e) for e in entries)
    top = max(votes.values())
    tied = sorted(p for p, n in votes.items() if n == top)

    def evidence(p: str) -> float:
        vals = [e["projection_evidence"].get(p) for e in entries]
        return sum(v if v is not None else math.inf for v in vals)

    best = min(tied, key=lambda p: (evidence(p), p))
    why = f"{top} of {len(entries)} photo(s) chose it" + (
        f"; tie among {', '.join(tied)} broken by the summed sun-radius evidence "
        + ", ".join(f"{p} {evidence(p):.3g} deg" for p in tied) if len(tied) > 1 else "")
    return best, why


def combine_cameras(entries: list[dict]) -> tuple[dict, dict]:
    """Per-photo entries (:func:`calibrate_camera`'s ``photos``) -> (camera dict, spread per combined value)."""
    shapes = {tuple(e["shape"]) for e in entries}
    if len(shapes) > 1:
        sizes = ", ".join(f"{Path(e['path']).name} {e['shape'][1]}x{e['shape'][0]}" for e in entries)
        raise PhotoFitError(f"calibrate-camera: the photos differ in size ({sizes}); one camera takes one image size")
    h, w = next(iter(shapes))
    projection, why = choose_projection(entries)
    same = [e for e in entries if _nominal(e) == projection]
    med = lambda es, k: float(np.median([e[k] for e in es]))  # noqa: E731
    cam = {"projection": projection, "size": [h, w]}
    spread: dict = {}
    for k in ("cx", "cy", "radius_px"):
        cam[k] = med(entries, k)
        spread[k] = _spread([e[k] for e in entries], cam[k])
    cam["up_azimuth_deg"] = circular_median_deg([e["up_azimuth_deg"] for e in same])
    spread["up_azimuth_deg"] = _spread([e["up_azimuth_deg"] for e in same], cam["up_azimuth_deg"], circular=True)
    tilt = np.array([e["tilt_deg"] for e in same], np.float64)
    cam["tilt_deg"] = [float(v) for v in np.median(tilt, 0)]
    spread["tilt_deg"] = {"east": _spread(tilt[:, 0], cam["tilt_deg"][0]), "north": _spread(tilt[:, 1], cam["tilt_deg"][1])}
    cam["max_zenith_deg"] = med(same, "max_zenith_deg")
    for k in CAMERA_RESPONSE:
        vals = [e[k] for e in same if e.get(k) is not None]
        if vals:
            cam[k] = float(np.median(vals))
            spread[k] = _spread(vals, cam[k])
    ks = [float(e.get("lens_radial") or 0.0) for e in same]
    cam["lens_radial"] = float(np.median(ks))
    spread["lens_radial"] = _spread(ks, cam["lens_radial"])
    if cam["lens_radial"] != 0.0:  # the nominal projection through the median lens, as the Kannala-Brandt camera it is
        kb = lens_camera(camera_from_calibration(cam), cam["lens_radial"]).to_metadata()
        cam.update(nominal_projection=projection, projection="kannala_brandt", focal_px=kb["focal_px"],
                   kb_coeffs=[float(v) for v in kb["kb_coeffs"]])
    spread["projection"] = why
    return cam, spread


def calibrate_camera(photos: Sequence[str | Path], times: Sequence[str], location, config: dict, *, linear: bool = False,
                     response: str | None = None, overrides: dict | None = None, device="cpu", progress: bool = False,
                     fits: list | None = None) -> dict:
    """Fit each photo and combine their cameras into one CAMERA.yaml dict (module docstring); nothing is written.

    Args:
        photos: photo files or bracket folders of one camera at one image size.
        times: when each was taken, ISO 8601 with a UTC offset or a zone name, one per photo, in order.
        location: "LAT,LON[,ELEV]" or (lat, lon[, elev]) of every photo. [deg, deg, m]
        config: the atmosphere config dict (its ``fit:`` section sets the fits' settings).
        linear, response: how the photos' codes are decoded (:func:`skyfit.io.photo.read_photo`).
        overrides: FitSettings overrides of every fit.
        device: torch device of the fits.
        fits: if a list, each photo's :class:`skyfit.fit.photo.PhotoFit` is appended to it.

    Returns:
        The camera dict (keys of :data:`CAMERA_FILE_KEYS`; ``photos`` lists each photo's own values), with
        ``_spread`` (each combined value's spread over the photos; not written as a key, see :func:`camera_yaml`).

    Raises:
        PhotoFitError / PhotoError / CalibrationError (ValueErrors): one line naming the photo and the problem.
    """
    photos, times = list(photos), list(times)
    if not photos:
        raise PhotoFitError("calibrate-camera: give at least one photo")
    if len(times) != len(photos):
        raise PhotoFitError(f"calibrate-camera: {len(photos)} photo(s) but {len(times)} time(s); give one time per photo, in order")
    read = [read_photo(p, linear=linear, response=response) for p in photos]  # every photo before any fit: fail fast
    shapes = [ph.rgb.shape[:2] for ph in read]
    if len(set(shapes)) > 1:
        sizes = ", ".join(f"{Path(p).name} {w}x{h}" for p, (h, w) in zip(photos, shapes))
        raise PhotoFitError(f"calibrate-camera: the photos differ in size ({sizes}); one camera takes one image size")
    entries = []
    for path, ph, t in zip(photos, read, times):
        try:
            pf = fit_photo(ph, time=t, location=location, config=config, linear=linear, response=response,
                           overrides=overrides, laplace=False, progress=progress, device=device)
        except CalibrationError as e:  # the image tests' messages do not name the file
            msg = str(e)
            raise PhotoFitError(msg if str(path) in msg else f"photo {path}: {msg}") from None
        if fits is not None:
            fits.append(pf)
        entries.append(_photo_entry(path, t, pf))
    cam, spread = combine_cameras(entries)
    cam["convention"] = ("zenith at the optical axis, azimuth clockwise from North; tilt_deg = (toward East, toward North) "
                         "[deg]; up_azimuth_deg: azimuth of the image's up direction [deg]")
    cam["source"] = f"skyfit calibrate-camera from {len(entries)} photo(s)"
    cam["photos"] = entries
    unknown = set(cam) - set(CAMERA_KEYS) - set(CAMERA_INFO_KEYS)
    assert not unknown, unknown  # read_camera accepts every key written
    cam["_spread"] = spread
    return cam


def camera_from_calibration(cam: dict) -> FisheyeCamera:
    """The :class:`FisheyeCamera` of a calibration dict (the one ``--camera`` rebuilds from the file)."""
    meta = {k: v for k, v in cam.items() if k in ("projection", "size", "cx", "cy", "radius_px", "focal_px", "kb_coeffs",
                                                  "up_azimuth_deg", "tilt_deg", "max_zenith_deg")}
    h, w = cam["size"]
    meta["size"] = [h, w] if h != w else h
    return FisheyeCamera.from_metadata(meta)


def camera_yaml(cam: dict) -> str:
    """CAMERA.yaml's text: a comment header with how each value was combined and its spread, then the keys."""
    import yaml  # here: only writing a camera file needs it

    spread = cam.get("_spread") or {}
    lines = [f"# CAMERA.yaml: {cam.get('source', 'skyfit calibrate-camera')}",
             "# use: skyfit fit PHOTO --time T --location LAT,LON --camera THIS.yaml",
             "# combined: projection by vote; cx, cy, radius_px: median of all photos; up_azimuth_deg: circular median,",
             "#   tilt_deg, vignetting, gains: median of the photos of the chosen projection (skyfit/fit/photo_calibration.py)"]
    if "projection" in spread:
        lines.append(f"# projection {cam['projection']}: {spread['projection']}")
    lines.append("# spread over the photos (largest |deviation| from the combined value; median |deviation|):")
    for k, s in spread.items():
        if k == "projection":
            continue
        if k == "tilt_deg":
            for c in ("east", "north"):
                lines.append(f"#   tilt_deg {c}: max {s[c]['max_abs_dev']:.4g}, median {s[c]['mad']:.4g} deg")
        else:
            unit = {"cx": " px", "cy": " px", "radius_px": " px", "up_azimuth_deg": " deg"}.get(k, "")
            lines.append(f"#   {k}: max {s['max_abs_dev']:.4g}, median {s['mad']:.4g}{unit}")
    body = {k: cam[k] for k in CAMERA_FILE_KEYS if k in cam}
    text = yaml.safe_dump(body, sort_keys=False, default_flow_style=None, width=120)
    return "\n".join(lines) + "\n" + text


def write_camera(cam: dict, path: str | Path) -> Path:
    """Write a calibration dict as CAMERA.yaml, atomically (:func:`camera_yaml`); PhotoFitError unless .yaml/.yml."""
    path = Path(path)
    if path.suffix.lower() not in (".yaml", ".yml"):
        raise PhotoFitError(f"--out must name a .yaml file, got {path}")
    return write_text_atomic(path, camera_yaml(cam))


__all__ = ["CAMERA_FILE_KEYS", "calibrate_camera", "camera_from_calibration", "camera_yaml", "choose_projection",
           "circular_median_deg", "combine_cameras", "write_camera"]
