"""Observations in one common form, and loaders for fisheye EXR images and Kider captures.

An :class:`Observation` is what a fit sees of one measurement: N view directions
(unit ENU vectors), the sun (one direction, or one per sample when a scan takes
minutes), N x C measured values with their sigma, a mask, and where it came
from. C channels are spectral (``L<nm>``, W/(m^2 sr nm)) or ``R, G, B``
(linear sRGB of XYZ with 683 lm/W, CONTRACT.md).

Loaders raise :class:`DataError` (a ValueError) with one line naming the file.
"""
from __future__ import annotations

import dataclasses
import math
import re
import warnings
from pathlib import Path
from typing import Sequence

import numpy as np
import torch
from torch import Tensor

from ..camera import FisheyeCamera, parse_location, parse_time, sun_position
from ..camera.fisheye import zenith_azimuth_to_enu
from ..io import is_kider_capture_name, kider, read_exr
from .losses import horizon_mask, saturation_mask, sun_disc_mask


class DataError(ValueError):
    """Data that cannot be fitted: unreadable, missing metadata, NaN or negative values."""


class DataWarning(UserWarning):
    """Data used with something left out or suspect (broken Kider samples, clipped pixels): one line
    naming the file, what and why (docs/reliability.md); the CLI prints it as ``skyfit: warning: ...``."""


def check_noise_model(relative: float, absolute: float, where: str) -> None:
    """DataError naming ``where`` unless relative >= 0, absolute >= 0 and not both 0."""
    if not (relative >= 0 and absolute >= 0 and relative + absolute > 0):
        raise DataError(f"{where}: the noise model needs sigma_relative >= 0 and sigma_absolute >= 0, not both 0; "
                        f"got {relative}, {absolute}")


def noise_sigma(values: Tensor, relative: float, absolute: float) -> Tensor:
    """The noise model sigma = hypot(relative x value, absolute), shape of ``values``. [values' unit]"""
    return torch.sqrt((relative * values) ** 2 + absolute**2)


KINDS = ("spectral", "rgb")
SPECTRAL_UNITS = "W/(m^2 sr nm)"
RGB_UNITS = "linear sRGB of XYZ with 683 lm/W (Y in cd/m^2)"
_SPECTRAL_CHANNEL = re.compile(r"^L(\d+(?:\.\d*)?)$")


@dataclasses.dataclass
class Observation:
    """One measurement as data for a fit.

    Attributes:
        name: short label (file or folder name).
        source: the file or folder read.
        kind: ``'spectral'`` or ``'rgb'``.
        directions: unit view vectors, East-North-Up, shape (N, 3). [1]
        sun_zenith, sun_azimuth: the sun, shape () or (N,) (one per sample);
            azimuth clockwise from North. [rad]
        values: measured values, shape (N, C). [W/(m^2 sr nm) or linear sRGB]
        sigma: their standard deviation, shape (N, C), > 0. [same unit]
        mask: samples to use, shape (N,), bool.
        channels: channel names, length C (``L550`` ... or ``R, G, B``).
        wavelengths: channel wavelengths for spectral data, shape (C,); None for RGB. [nm]
        band_nm: width of the band each spectral value averages (None: point values). [nm]
        sun_distance_au: Earth-Sun distance at the time, when known. [AU]
        altitude_m: observer height above the ground. [m]
        time: ISO 8601 time of the sun position, when known.
        location: {"latitude_deg", "longitude_deg", "elevation_m"}, when known.
        metadata: anything else (image shape and pixel index of each sample for images,
            ring and index for Kider, the model wavelength grid an EXR was rendered on).
        image_radius: for image data, each sample's distance from the optical axis over the
            radius of the 90 deg circle, shape (N,) (the ``vignetting`` parameter acts on it);
            None for other data. [1]
        censored: per value, +1 where the value is only a lower bound (saturated), -1 where it is
            only an upper bound (black), 0 where measured, shape (N, C), int8; None: all measured.
            A model beyond the bound on the censored side costs nothing (:class:`~skyfit.fit.model.FitProblem`).
    """

    name: str
    source: str
    kind: str
    directions: Tensor
    sun_zenith: Tensor
    sun_azimuth: Tensor
    values: Tensor
    sigma: Tensor
    mask: Tensor
    channels: tuple[str, ...]
    wavelengths: Tensor | None = None
    band_nm: float | None = None
    sun_distance_au: float | None = None
    altitude_m: float = 0.0
    time: str | None = None
    location: dict | None = None
    metadata: dict = dataclasses.field(default_factory=dict)
    image_radius: Tensor | None = None
    censored: Tensor | None = None

    def __post_init__(self):
        where = f"observation {self.source}"
        if self.kind not in KINDS:
            raise DataError(f"{where}: kind must be one of {KINDS}, got {self.kind!r}")
        n = self.directions.shape[0]
        if self.directions.shape != (n, 3):
            raise DataError(f"{where}: directions must have shape (N, 3), got {tuple(self.directions.shape)}")
        c = len(self.channels)
        for name in ("values", "sigma"):
            if getattr(self, name).shape != (n, c):
                raise DataError(f"{where}: {name} must have shape ({n}, {c}), got {tuple(getattr(self, name).shape)}")
        if self.mask.shape != (n,) or self.mask.dtype != torch.bool:
            raise DataError(f"{where}: mask must be a bool tensor of shape ({n},)")
        for name in ("sun_zenith", "sun_azimuth"):
            t = getattr(self, name)
            if t.shape not in ((), (n,)):
                raise DataError(f"{where}: {name} must have shape () or ({n},), got {tuple(t.shape)}")
        if self.image_radius is not None and (self.image_radius.shape != (n,) or not bool(torch.isfinite(self.image_radius).all())):
            raise DataError(f"{where}: image_radius must be finite with shape ({n},)")
        if self.censored is not None and (self.censored.shape != (n, c) or self.censored.is_floating_point()):
            raise DataError(f"{where}: censored must be an integer tensor of shape ({n}, {c}) with values -1, 0, +1")
        if self.kind == "spectral":
            if self.wavelengths is None or self.wavelengths.shape != (c,):
                raise DataError(f"{where}: spectral data needs one wavelength per channel")
        m = self.mask
        if not bool(torch.isfinite(self.values[m]).all()):
            raise DataError(f"{where}: NaN or Inf among the used values")
        if bool((self.values[m] < 0).any()):
            raise DataError(f"{where}: negative values among the used samples")
        if not bool((self.sigma[m] > 0).all()) or not bool(torch.isfinite(self.sigma[m]).all()):
            raise DataError(f"{where}: sigma must be finite and > 0")
        if not bool(m.any()):
            raise DataError(f"{where}: no usable sample (all masked)")

    @property
    def n_samples(self) -> int:
        """Number of used samples (directions)."""
        return int(self.mask.sum())

    @property
    def sun(self) -> Tensor:
        """Unit vector(s) to the sun, shape (3,) or (N, 3). [1]"""
        return zenith_azimuth_to_enu(self.sun_zenith, self.sun_azimuth)

    @property
    def units(self) -> str:
        return SPECTRAL_UNITS if self.kind == "spectral" else RGB_UNITS

    def to(self, dtype=torch.float64, device="cpu") -> "Observation":
        kw = {}
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            if isinstance(v, Tensor) and v.is_floating_point():
                v = v.to(dtype=dtype, device=device)
            elif isinstance(v, Tensor):
                v = v.to(device=device)
            kw[f.name] = v
        return Observation(**kw)

    @classmethod
    def from_arrays(cls, radiance, view, sun=None, *, time: str | None = None, location=None, sigma=None,
                    sigma_relative: float = 0.01, sigma_absolute: float | None = None, wavelengths=None,
                    mask=None, min_elevation_deg: float = 0.0, sun_disc_deg: float = 2.0,
                    altitude_m: float = 0.0, name: str = "array", dtype=torch.float64) -> "Observation":
        """An observation from arrays in memory: an image and its camera, or values along view directions.

        Args:
            radiance: with a camera, an image of shape (H, W, C); with directions, shape (N, C).
                C = 3 is linear sRGB (``R, G, B``, CONTRACT.md) unless ``wavelengths`` are given;
                with ``wavelengths`` (shape (C,) [nm]) the channels are spectral radiance.
                [W/(m^2 sr nm) or linear sRGB of XYZ with 683 lm/W]
            view: a :class:`skyfit.camera.FisheyeCamera` (its field of view masks the image), or
                unit view vectors East-North-Up, shape (N, 3). [1]
            sun: ``(zenith_deg, azimuth_deg)`` (azimuth clockwise from North) [deg]; or None with
                ``time`` (ISO 8601 with UTC offset) and ``location`` ("LAT,LON[,ELEV]" or a tuple), by NREL SPA.
            sigma: standard deviation per value, shape of ``radiance``; None: the noise model
                hypot(sigma_relative x value, sigma_absolute), sigma_absolute defaulting to 1e-3 x the
                median used value.
            mask: bool, shape (H, W) or (N,): values to use (True = sky).
            min_elevation_deg, sun_disc_deg: horizon and sun masks, as for EXR images. [deg]
            altitude_m: observer height above the ground. [m]
            name: label in results.
            dtype: working dtype.

        Raises:
            DataError: shapes that do not fit, NaN/Inf or negative used values, no sun, nothing usable.
        """
        where = f"observation {name}"
        values = torch.as_tensor(np.asarray(radiance.detach().cpu() if isinstance(radiance, Tensor) else radiance,
                                            dtype=np.float64)).to(dtype)
        if values.ndim not in (2, 3):
            raise DataError(f"{where}: radiance must have shape (H, W, C) or (N, C), got {tuple(values.shape)}")
        C = values.shape[-1]
        if isinstance(view, FisheyeCamera):
            if values.ndim != 3 or tuple(values.shape[:2]) != tuple(view.shape):
                raise DataError(f"{where}: radiance of shape {tuple(values.shape)} does not fit the camera's image "
                                f"{tuple(view.shape)} (H, W, C)")
            vec, valid = view.pixel_vectors(dtype)
            vec, valid = vec.reshape(-1, 3), valid.reshape(-1)
            image_shape = list(view.shape)
            with torch.no_grad():  # each pixel's distance from the optical axis over the 90-degree radius (vignetting)
                xx, yy = view.pixel_grid(dtype)
                radius = (torch.hypot(xx - view.cx.to(dtype), yy - view.cy.to(dtype)) / view.r90.to(dtype)).reshape(-1)
        else:
            # on the CPU as every other argument (values and sigma are): prepare() moves the observation to the fit's device
            vec = torch.as_tensor(view.detach().cpu() if isinstance(view, torch.Tensor) else view, dtype=dtype)
            if values.ndim != 2 or vec.shape != (values.shape[0], 3):
                raise DataError(f"{where}: directions of shape {tuple(vec.shape)} do not fit radiance of shape "
                                f"{tuple(values.shape)}: need (N, 3) and (N, C)")
            valid = torch.isfinite(vec).all(-1)
            image_shape, radius = None, None
        values = values.reshape(-1, C)
        keep = valid.clone()
        if mask is not None:
            m = torch.as_tensor(np.asarray(mask, dtype=bool)).reshape(-1)
            if m.shape != keep.shape:
                raise DataError(f"{where}: mask has {m.numel()} entries for {keep.numel()} values")
            keep &= m
        dated: dict = {}
        if sun is None:
            if time is None or location is None:
                raise DataError(f"{where}: give the sun as (zenith_deg, azimuth_deg), or time and location")
            lat, lon, elev = parse_location(location) if isinstance(location, str) else (tuple(location) + (0.0,))[:3]
            when = parse_time(time)
            sp = sun_position(when, lat, lon, elev)
            sz_deg, sa_deg = float(sp.zenith), float(sp.azimuth)
            dated = {"time": when.isoformat(), "sun_distance_au": float(sp.distance_au),
                     "location": {"latitude_deg": float(lat), "longitude_deg": float(lon), "elevation_m": float(elev)}}
        else:
            try:
                sz_deg, sa_deg = (float(v) for v in sun)
            except (TypeError, ValueError):
                raise DataError(f"{where}: sun must be (zenith_deg, azimuth_deg), got {sun!r}") from None
        if not (math.isfinite(sz_deg) and math.isfinite(sa_deg)):
            raise DataError(f"{where}: sun position is not finite")
        if sz_deg > 90.0:
            raise DataError(f"{where}: the sun is below the horizon (zenith {sz_deg:.2f} deg); night skies are not fitted")
        sz, sa = torch.tensor(math.radians(sz_deg), dtype=dtype), torch.tensor(math.radians(sa_deg), dtype=dtype)
        safe = torch.where(keep[:, None], vec, torch.tensor([0.0, 0.0, 1.0], dtype=dtype))
        keep &= horizon_mask(safe, min_elevation_deg)
        keep &= sun_disc_mask(safe, zenith_azimuth_to_enu(sz, sa), sun_disc_deg)
        idx = torch.nonzero(keep).reshape(-1)
        if idx.numel() == 0:
            raise DataError(f"{where}: no usable value (field of view, mask, horizon and sun disc leave none)")
        vals = values[idx]
        if sigma is None:
            absolute = 1e-3 * float(vals.median()) if sigma_absolute is None else float(sigma_absolute)
            check_noise_model(sigma_relative, absolute, where)
            if absolute == 0:
                absolute = 1e-3 * float(vals[vals > 0].median()) if bool((vals > 0).any()) else 1e-12
            sig = noise_sigma(vals, sigma_relative, absolute)
            sigma_model = {"relative": sigma_relative, "absolute": absolute}
        else:
            s_all = torch.as_tensor(np.asarray(sigma.detach().cpu() if isinstance(sigma, Tensor) else sigma,
                                               dtype=np.float64)).to(dtype)
            if s_all.numel() != values.numel():
                raise DataError(f"{where}: sigma has shape {tuple(s_all.shape)}, radiance {tuple(values.shape)}")
            sig, sigma_model = s_all.reshape(-1, C)[idx], "given"
        if wavelengths is None:
            if C != 3:
                raise DataError(f"{where}: {C} channels without wavelengths; give wavelengths for spectral data")
            kind, channels, lam = "rgb", ("R", "G", "B"), None
        else:
            lam = torch.as_tensor(np.asarray(wavelengths.detach().cpu() if isinstance(wavelengths, torch.Tensor) else wavelengths,
                                             dtype=np.float64)).to(dtype).reshape(-1)
            if lam.numel() != C:
                raise DataError(f"{where}: {lam.numel()} wavelengths for {C} channels")
            kind, channels = "spectral", tuple(f"L{float(v):g}" for v in lam)
        meta = {"mask": {"used": int(idx.numel()), "min_elevation_deg": min_elevation_deg, "sun_disc_deg": sun_disc_deg},
                "sigma_model": sigma_model, "pixel_index": idx}
        if image_shape is not None:
            meta.update(image_shape=image_shape, camera=view.metadata())
        return cls(name=name, source=name, kind=kind, directions=vec[idx], sun_zenith=sz, sun_azimuth=sa, values=vals,
                   sigma=sig, mask=torch.ones(idx.numel(), dtype=torch.bool), channels=channels, wavelengths=lam,
                   sun_distance_au=dated.get("sun_distance_au"), altitude_m=float(altitude_m), time=dated.get("time"),
                   location=dated.get("location"), metadata=meta,
                   image_radius=None if radius is None else radius[idx].detach().clone())

    def summary(self) -> dict:
        """JSON-ready description for RESULT.json's ``data``."""
        def deg(t):
            t = torch.rad2deg(t.detach().cpu())
            return float(t) if t.ndim == 0 else {"mean": float(t.mean()), "min": float(t.min()), "max": float(t.max())}

        d = {
            "name": self.name, "source": self.source, "kind": self.kind, "channels": list(self.channels),
            "units": self.units, "n_samples": self.n_samples, "n_directions": int(self.directions.shape[0]),
            "sun_zenith_deg": deg(self.sun_zenith), "sun_azimuth_deg": deg(self.sun_azimuth),
            "sun_per_sample": self.sun_zenith.ndim == 1, "time": self.time, "location": self.location,
            "sun_distance_au": self.sun_distance_au, "altitude_m": self.altitude_m,
        }
        if self.wavelengths is not None:
            d["wavelengths_nm"] = [float(v) for v in self.wavelengths.cpu()]
            d["band_nm"] = self.band_nm
        for k in ("mask", "sigma_model", "subsample_step", "azimuth_offset_guess_rad", "notes"):
            if k in self.metadata:
                d[k] = self.metadata[k]
        return d


# -- EXR fisheye -------------------------------------------------------------------------
def observation_from_exr(
    path: str | Path,
    *,
    sigma_relative: float = 0.01,
    sigma_absolute: float | None = None,
    min_elevation_deg: float = 0.0,
    sun_disc_deg: float = 2.0,
    saturation: float | None = None,
    max_samples: int | None = None,
    dtype=torch.float64,
) -> Observation:
    """An observation from a fisheye OpenEXR with skyfit metadata (CONTRACT.md).

    Channels ``L<nm>`` (spectral radiance) are used when present, else ``R, G, B``.
    The camera comes from the header's ``camera`` entry
    (:meth:`skyfit.camera.FisheyeCamera.from_metadata`), the sun from ``sun``
    (``zenith_deg``, ``azimuth_deg``; ``time``, ``location``, ``distance_au`` when dated).
    A channel ``mask`` (1 = sky, 0 = obstacle) is honoured.

    Args:
        path: the .exr file.
        sigma_relative, sigma_absolute: noise model sigma = hypot(rel x value, abs) unless
            the header has ``noise: {sigma_relative, sigma_absolute}``; abs defaults to
            1e-3 x the median used value. [1], [data units]
        min_elevation_deg: horizon mask: pixels at lower elevation are not used. [deg]
        sun_disc_deg: pixels closer to the sun are not used (0: keep all). [deg]
        saturation: samples with a channel at or above this are not used. [data units]
        max_samples: keep every k-th usable pixel (raster order) so that at most this many remain.

    Raises:
        DataError / ExrError (ValueErrors) naming the file.
    """
    path = Path(path)
    chans, meta = read_exr(path)
    if "camera" not in meta:
        raise DataError(f"{path}: no camera metadata (the skyfit header's 'camera' entry); cannot map pixels to directions")
    try:
        cam = FisheyeCamera.from_metadata(meta["camera"])
    except ValueError as e:
        raise DataError(f"{path}: {e}") from None
    sun = meta.get("sun") or {}
    try:
        sz, sa = math.radians(float(sun["zenith_deg"])), math.radians(float(sun["azimuth_deg"]))
    except (KeyError, TypeError, ValueError):
        raise DataError(f"{path}: no sun position in the metadata (sun.zenith_deg, sun.azimuth_deg)") from None
    if not (math.isfinite(sz) and math.isfinite(sa)):
        raise DataError(f"{path}: sun position is not finite")
    if sz > math.pi / 2:
        raise DataError(f"{path}: the sun is below the horizon (zenith {math.degrees(sz):.2f} deg); night skies are not fitted")

    spectral = sorted(((float(m.group(1)), k) for k in chans if (m := _SPECTRAL_CHANNEL.match(k))), key=lambda t: t[0])
    if spectral:
        kind, names = "spectral", [k for _, k in spectral]
        wavelengths = torch.tensor([w for w, _ in spectral], dtype=dtype)
    elif all(k in chans for k in "RGB"):
        kind, names, wavelengths = "rgb", ["R", "G", "B"], None
    else:
        raise DataError(f"{path}: neither spectral L<nm> channels nor R, G, B (channels: {sorted(chans)})")
    shape = cam.shape
    for k in names + (["mask"] if "mask" in chans else []):
        if chans[k].shape != shape:
            raise DataError(f"{path}: channel {k} has shape {chans[k].shape}, the camera metadata says {shape}")

    view, valid = cam.pixel_vectors(dtype)
    view = view.reshape(-1, 3)
    valid = valid.reshape(-1)
    values = torch.from_numpy(np.stack([chans[k] for k in names], -1).reshape(-1, len(names)).astype(np.float64)).to(dtype)
    v_valid = values[valid]
    if not bool(torch.isfinite(v_valid).all()):
        bad = [names[c] for c in range(len(names)) if not bool(torch.isfinite(v_valid[:, c]).all())]
        raise DataError(f"{path}: NaN or Inf pixels in channel(s) {bad}")
    if bool((v_valid < 0).any()):
        bad = [names[c] for c in range(len(names)) if bool((v_valid[:, c] < 0).any())]
        raise DataError(f"{path}: negative pixels in channel(s) {bad}")

    keep = valid.clone()
    safe_view = torch.where(valid[:, None], view, torch.tensor([0.0, 0.0, 1.0], dtype=dtype))
    sun_vec = zenith_azimuth_to_enu(torch.tensor(sz, dtype=dtype), torch.tensor(sa, dtype=dtype))
    keep &= horizon_mask(safe_view, min_elevation_deg)
    keep &= sun_disc_mask(safe_view, sun_vec, sun_disc_deg)
    unsaturated = saturation_mask(values, saturation)
    n_saturated = int((keep & ~unsaturated).sum())
    if n_saturated:  # censored by the level the user gave: said, not silent (docs/reliability.md)
        warnings.warn(DataWarning(f"{path}: {n_saturated} pixel(s) at or above the saturation level {saturation:g} left out"),
                      stacklevel=2)
    keep &= unsaturated
    mask_note = {"field_of_view": int(valid.sum()), "min_elevation_deg": min_elevation_deg,
                 "sun_disc_deg": sun_disc_deg, "saturation": saturation}
    if "mask" in chans:
        obstacle = torch.from_numpy(chans["mask"].reshape(-1) > 0.5)
        keep &= obstacle
        mask_note["obstacles"] = int((~obstacle & valid).sum())
    idx = torch.nonzero(keep).reshape(-1)
    if idx.numel() == 0:
        raise DataError(f"{path}: no usable pixel (field of view, horizon, sun disc and saturation masks leave none)")
    check_image_values(path, values[idx], names, saturation)
    step = 1
    if max_samples is not None and idx.numel() > max_samples:
        step = math.ceil(idx.numel() / max_samples)
        idx = idx[::step]
    vals = values[idx]
    noise = meta.get("noise") if isinstance(meta.get("noise"), dict) else {}
    rel = float(noise.get("sigma_relative", sigma_relative))
    absolute = noise.get("sigma_absolute", sigma_absolute)
    absolute = 1e-3 * float(vals.median()) if absolute is None else float(absolute)
    check_noise_model(rel, absolute, str(path))
    if absolute == 0 and bool((vals == 0).any()):
        absolute = 1e-3 * float(vals[vals > 0].median()) if bool((vals > 0).any()) else 1e-12
    sigma = noise_sigma(vals, rel, absolute)
    loc = sun.get("location")
    return Observation(
        name=path.stem, source=str(path), kind=kind, directions=view[idx],
        sun_zenith=torch.tensor(sz, dtype=dtype), sun_azimuth=torch.tensor(sa, dtype=dtype),
        values=vals, sigma=sigma, mask=torch.ones(idx.numel(), dtype=torch.bool), channels=tuple(names),
        wavelengths=wavelengths, band_nm=None, sun_distance_au=float(sun["distance_au"]) if "distance_au" in sun else None,
        altitude_m=float(meta.get("observer_altitude_m", 0.0) or 0.0), time=sun.get("time"),
        location=loc if isinstance(loc, dict) else None,
        metadata={
            "image_shape": list(shape), "pixel_index": idx, "camera": meta["camera"], "mask": mask_note,
            "subsample_step": step, "sigma_model": {"relative": rel, "absolute": absolute},
            "model_wavelengths_nm": meta.get("wavelengths_nm"),
        },
    )


CLIPPED_FRACTION: float = 0.01
"""A channel whose maximum is shared by more than this fraction of the used pixels (and by 10 or
more) looks clipped: warned, with the advice to set ``fit.saturation`` (docs/reliability.md)."""


def check_image_values(path, values: Tensor, channels: Sequence[str], saturation: float | None = None) -> None:
    """The data policy for an image's used pixels (docs/reliability.md), beyond NaN/Inf and negatives.

    DataError when every used value is 0 (a black frame: nothing to fit). A DataWarning when a
    channel is 0 at every used pixel (a dead channel, or a band with no light, as a float32 render
    deep in the ozone band gives), when every used pixel has the same value in every channel (a
    flat test pattern: no sky has it, but it is a valid input) and when a channel's maximum is
    shared by many pixels (clipped highlights) and no saturation level was given.

    Args:
        path: the file, for messages.
        values: used pixels, shape (N, C). [data units]
        channels: channel names, length C.
        saturation: the saturation level in force (None: none given). [data units]
    """
    if values.numel() == 0:
        return
    if not bool((values != 0).any()):
        raise DataError(f"{path}: every used pixel is 0 in every channel (a black image: nothing to fit)")
    dead = [channels[c] for c in range(values.shape[1]) if not bool((values[:, c] != 0).any())]
    if dead:  # a dead channel, or no light at all (a float32 render deep in the ozone band): fitted as 0, said
        warnings.warn(DataWarning(f"{path}: channel(s) {dead} are 0 at every used pixel (no light, or a dead channel)"),
                      stacklevel=3)
    if values.shape[0] > 1 and bool((values == values[:1]).all()):
        warnings.warn(DataWarning(f"{path}: every used pixel has the same value in every channel ({values[0].tolist()}): "
                                  "a flat test pattern, not a sky?"), stacklevel=3)
        return
    if saturation is None and values.shape[0] >= 100:
        top = values.max(0).values
        at_top = (values == top).sum(0)
        clipped = [channels[c] for c in range(values.shape[1])
                   if int(at_top[c]) >= max(10, CLIPPED_FRACTION * values.shape[0])]
        if clipped:
            warnings.warn(DataWarning(f"{path}: channel(s) {clipped} reach their maximum at {int(at_top.max())} of "
                                      f"{values.shape[0]} used pixels (clipped?); set fit.saturation to leave them out"),
                          stacklevel=3)


# -- Kider captures ----------------------------------------------------------------------
def observation_from_kider(
    folder: str | Path,
    *,
    bin_nm: float = 10.0,
    lo_nm: float = 360.0,
    hi_nm: float = 720.0,
    per_sample_sun: bool = True,
    time_reference: str = "mid",
    min_sun_distance_deg: float = 0.0,
    latitude: float | None = None,
    longitude: float | None = None,
    elevation: float | None = None,
    utc_offset_hours: float | None = None,
    dtype=torch.float64,
) -> Observation:
    """An observation from a Kider et al. 2014 capture folder (docs/data.md).

    Spectra are box-averaged over ``bin_nm`` bins in [lo_nm, hi_nm]
    (:meth:`skyfit.io.KiderCapture.band_average`; the model's solar spectrum is
    the same box average). With ``per_sample_sun`` each sample carries the sun at
    its own scan time; else the capture's (mid-time) sun. The sun is the SPA's
    refracted position (0.02° above the geometric one at these zenith angles).
    ``metadata['azimuth_offset_guess_rad']`` is the mean offset of the rings'
    symmetry axes from the sun azimuth (:func:`skyfit.io.ring_symmetry_azimuths`),
    a starting point for ``sun_azimuth_offset``.
    """
    site = {}
    if latitude is not None:
        site["latitude"] = latitude
    if longitude is not None:
        site["longitude"] = longitude
    if elevation is not None:
        site["elevation"] = elevation
    if utc_offset_hours is not None:
        site["utc_offset_hours"] = utc_offset_hours
    cap = kider.load_kider_capture(folder, time_reference=time_reference, min_sun_distance_deg=min_sun_distance_deg, **site)
    if cap.dropped:  # broken spectra are left out, never silently (docs/reliability.md)
        reasons = "; ".join(cap.dropped[i] for i in sorted(cap.dropped))
        warnings.warn(DataWarning(f"{cap.path}: {len(cap.dropped)} of {kider.N_SAMPLES} samples left out as broken: {reasons}"),
                      stacklevel=2)
    centres, rad, sig = cap.band_average(bin_nm, lo_nm, hi_nm)
    T = lambda a: torch.as_tensor(np.asarray(a, float), dtype=dtype)  # noqa: E731
    directions = zenith_azimuth_to_enu(T(cap.view_zenith), T(cap.view_azimuth))
    if per_sample_sun:
        sz, sa = T(cap.sample_sun_zenith), T(cap.sample_sun_azimuth)
    else:
        sz, sa = T(cap.sun_zenith), T(cap.sun_azimuth)
    axes = kider.ring_symmetry_azimuths(cap)
    guess = float(np.angle(np.mean(np.exp(1j * (axes - cap.sun_azimuth)))))
    channels = tuple(f"L{c:g}" for c in centres)
    return Observation(
        name=cap.name, source=str(cap.path), kind="spectral", directions=directions, sun_zenith=sz, sun_azimuth=sa,
        values=T(rad), sigma=T(sig), mask=torch.as_tensor(cap.valid, dtype=torch.bool), channels=channels,
        wavelengths=T(centres), band_nm=float(bin_nm), sun_distance_au=cap.sun_distance_au, altitude_m=0.0,
        time=cap.time.isoformat(),
        location={"latitude_deg": cap.latitude_deg, "longitude_deg": cap.longitude_deg, "elevation_m": cap.elevation_m},
        metadata={
            "ring": torch.as_tensor(cap.ring), "index": torch.as_tensor(cap.index), "azimuth_offset_guess_rad": guess,
            "mask": {"valid": int(cap.valid.sum()), "min_sun_distance_deg": min_sun_distance_deg,
                     **({"broken": [cap.dropped[i] for i in sorted(cap.dropped)]} if cap.dropped else {})},
            "notes": list(cap.notes) + [f"sample {k}: {v}" for k, v in cap.repaired.items()],
            "time_source": cap.time_source,
        },
    )


# -- dispatch ------------------------------------------------------------------------------
def expand_data_paths(paths: Sequence[str | Path]) -> list[tuple[str, Path]]:
    """(kind, path) for each DATA argument: an .exr file, a Kider capture folder, or a folder of either."""
    out: list[tuple[str, Path]] = []
    for p in map(Path, paths):
        if p.is_file():
            out.append(("exr", p))
        elif p.is_dir() and is_kider_capture_name(p.name):
            out.append(("kider", p))
        elif p.is_dir():
            caps = sorted(q for q in p.iterdir() if q.is_dir() and is_kider_capture_name(q.name))
            exrs = sorted(q for q in p.iterdir() if q.is_file() and q.suffix.lower() == ".exr")
            if not caps and not exrs:
                raise DataError(f"{p}: a folder with neither Kider captures (YYYY-MM-DD___HH.MM.SS) nor .exr files")
            out += [("kider", q) for q in caps] + [("exr", q) for q in exrs]
        else:
            raise DataError(f"data not found: {p}")
    if not out:
        raise DataError("no data given")
    return out


def load_observations(paths: Sequence[str | Path], exr_options: dict | None = None,
                      kider_options: dict | None = None) -> list[Observation]:
    """Observations from DATA arguments (:func:`expand_data_paths`), with per-format options."""
    obs = []
    for kind, p in expand_data_paths(paths):
        if kind == "exr":
            obs.append(observation_from_exr(p, **(exr_options or {})))
        else:
            obs.append(observation_from_kider(p, **(kider_options or {})))
    return obs
