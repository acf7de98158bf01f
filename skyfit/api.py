"""The Python API: skyfit's jobs on tensors and objects in memory, no files needed (CONTRACT.md, "Python").

``skyfit.render``, ``skyfit.fit``, ``skyfit.sample`` and ``skyfit.export_luts`` are what the
command line runs; ``cli.py`` only parses flags and files and calls the same library functions.
Every function takes ``device`` ("cpu", "cuda", "cuda:1" or "auto") and follows the dtype of
what it is given.
"""
from __future__ import annotations

import dataclasses
import time as _time
from pathlib import Path
from typing import Sequence

import numpy as np
import torch
from torch import Tensor

from .atmosphere import DEFAULT_WAVELENGTHS, Atmosphere, atmosphere_from_config, parse_wavelengths, read_config
from .atmosphere import load_atmosphere as _load_atmosphere
from .camera import FisheyeCamera, parse_location, parse_time, sun_position
from .camera.fisheye import zenith_azimuth_to_enu
from .geometry import zenith_angle_deg
from .export import export_luts as _write_luts
from .fit.data import Observation
from .fit.model import SkyModel
from .fit.optimise import fit as _optimise
from .fit.problem import FitSettings, fit_settings, make_model, prepare
from .fit.results import (atmosphere_from_result, check_result, model_from_result, read_result, result_dict,
                          save_result)
from .render.auto import RENDER_DEFAULTS, choose, parse_accuracy, setting_fields
from .render.colour import spectral_to_xyz, tonemap_srgb8, xyz_to_linear_srgb
from .render.sky import render_vectors
from .scattering.bruneton_tables import TableSizes
from .scattering.multiple import ACCURATE_QUADRATURE, PrecomputedAtmosphere, precompute
from .transmittance import parse_integrator

ACCURATE = "rel=1e-4"
"""A strict ``accuracy``: the cheapest setting measured on the trade study's Earth scenes with relative RMS
radiance error <= 1e-4 x the margin of :mod:`skyfit.render.auto` (docs/benchmarks.md). It was
:func:`render`'s default until that missed 1 % per pixel in haze (2.5 % at 5° elevation, earth_hazy;
docs/accuracy.md, "Render defaults"); the default is now ``skyfit render``'s, RENDER_DEFAULTS."""


def resolve_device(device: str | torch.device = "cpu") -> torch.device:
    """``cpu``, ``cuda[:N]`` or ``auto`` (CUDA when present) -> torch.device; ValueError when unusable here."""
    name = str(device)
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        dev = torch.device(name)
    except (RuntimeError, TypeError):
        raise ValueError(f"unknown device {name!r}; use cpu, cuda, cuda:N or auto") from None
    if dev.type == "cuda":
        if not torch.cuda.is_available():
            raise ValueError(f"device {name}: CUDA is not available on this machine")
        if dev.index is not None and dev.index >= torch.cuda.device_count():
            raise ValueError(f"device {name}: this machine has {torch.cuda.device_count()} CUDA device(s)")
    elif dev.type != "cpu":
        raise ValueError(f"unknown device {name!r}; use cpu, cuda, cuda:N or auto")
    return dev


def load_atmosphere(config: str | Path | dict = "earth", wavelengths=DEFAULT_WAVELENGTHS, *,
                    dtype: torch.dtype = torch.float64, device: str = "cpu",
                    sun_distance_au: float | None = None) -> Atmosphere:
    """An :class:`Atmosphere` from a config on a wavelength grid.

    Args:
        config: a shipped name (``earth``: Bruneton 2017's defaults; ``earth_hazy``, ``mars``, ``kider``...),
            a YAML path, or the config as a dict.
        wavelengths: ``"START:STOP:STEP"``, a comma list, or a sequence, in nm.
        dtype, device: of every tensor of the atmosphere (``device="auto"``: CUDA when present).
        sun_distance_au: Earth-Sun distance that scales the solar irradiance (None: the config's). [AU]
    """
    lam = parse_wavelengths(wavelengths) if isinstance(wavelengths, str) else np.asarray(wavelengths, float)
    return _load_atmosphere(config, lam, dtype, resolve_device(device), sun_distance_au)


def sun_vector(sun=None, *, time: str | None = None, location=None, dtype=torch.float64, device="cpu") -> Tensor:
    """The unit vector to the sun (East-North-Up), shape (3,).

    Args:
        sun: ``(zenith_deg, azimuth_deg)`` (azimuth clockwise from North) [deg], or a unit vector (3,).
        time, location: instead of ``sun``: ISO 8601 time with UTC offset and "LAT,LON[,ELEV]"
            (or a tuple) -> NREL SPA; the geometric (airless) position, as ``skyfit render --time`` uses.
    """
    if sun is None:
        if time is None or location is None:
            raise ValueError("give sun=(zenith_deg, azimuth_deg) or time= and location=")
        lat, lon, elev = parse_location(location) if isinstance(location, str) else (tuple(location) + (0.0,))[:3]
        sp = sun_position(parse_time(time), lat, lon, elev)
        sun = (float(sp.zenith_geometric), float(sp.azimuth))
    elif time is not None:
        raise ValueError("give the sun either as sun= or by time= and location=, not both")
    s = torch.as_tensor(sun, dtype=dtype, device=device)
    if s.shape == (3,):
        return s / torch.linalg.vector_norm(s)
    if s.shape != (2,) or not bool(torch.isfinite(s).all()):
        raise ValueError(f"sun must be (zenith_deg, azimuth_deg) or a unit vector (3,), got {sun!r}")
    return zenith_azimuth_to_enu(torch.deg2rad(s[0]), torch.deg2rad(s[1]))


def render_model(accuracy: str | None = None, orders: int = 1, multiple: str = "bruneton",
                 sun_zenith_deg: float = 45.0, altitude_m: float = 0.0, dtype: str = "float64") -> SkyModel:
    """The renderer :func:`render` uses for ``accuracy`` (see there) on a scene (sun zenith, altitude)."""
    if accuracy is None and orders == 1:  # skyfit render's defaults: within 1 % per pixel above 5° elevation
        return SkyModel(parse_integrator(RENDER_DEFAULTS["integrator"]), view_samples=RENDER_DEFAULTS["view_samples"],
                        rule=RENDER_DEFAULTS["rule"], spacing=RENDER_DEFAULTS["spacing"])
    if accuracy is None and orders > 1:
        if multiple == "bruneton":
            # the reference: Bruneton 2017's table sizes with what converges a hazy sky's orders >= 2 (Gauss-Legendre
            # view rays, the density directions' zenith bands split, the mu_s axis for the one sun; docs/envmap.md)
            return SkyModel(make_model(FitSettings()).integrator, orders=orders, multiple="bruneton",
                            table_sizes=dataclasses.astuple(TableSizes()), sun_window=True,
                            ray_rule=ACCURATE_QUADRATURE.ray_rule, density_directions=ACCURATE_QUADRATURE.density_directions)
        return make_model(FitSettings(integrator="gauss:samples=16", view_samples=32, orders=orders,
                                      multiple="hillaire", lut_size=[32, 32], lut_directions=64, lut_samples=20))
    tol = parse_accuracy(accuracy or ACCURATE)
    choice = choose(tol, sun_zenith_deg, altitude_m, orders=orders, dtype=dtype)
    fields = setting_fields(choice.setting)
    return make_model(dataclasses.replace(FitSettings(), orders=max(orders, int(fields.pop("orders", orders))),
                                          **fields))


@dataclasses.dataclass
class Sky:
    """A rendered sky.

    Attributes:
        radiance: spectral radiance, shape (..., W): (H, W_img, W) for a camera (0 outside its
            field of view), (N, W) for directions. [W/(m^2 sr nm)]
        xyz: CIE 1931 XYZ with 683 lm/W (Y in cd/m^2), shape (..., 3).
        rgb: linear sRGB of ``xyz``, shape (..., 3).
        valid: where the camera sees sky, shape (...) (all True for directions).
        wavelengths: shape (W,). [nm]
        model: the renderer settings used (integrator, view samples, orders...).
    """

    radiance: Tensor
    xyz: Tensor
    rgb: Tensor
    valid: Tensor
    wavelengths: Tensor
    model: dict

    def srgb8(self, exposure: float | None = None) -> np.ndarray:
        """An 8-bit display image (tone map 1 - exp(-k L), then the sRGB curve), shape (..., 3), uint8."""
        return tonemap_srgb8(self.rgb.detach().cpu().numpy(), exposure)


def render(atmosphere: Atmosphere, view: FisheyeCamera | Tensor, sun=None, *, time: str | None = None, location=None,
           accuracy: str | None = None, orders: int = 1, multiple: str = "bruneton", altitude: float = 0.0,
           model: SkyModel | None = None, sun_disk: bool = False) -> Sky:
    """Render the sky of ``atmosphere`` seen by a fisheye camera or along view directions.

    Args:
        atmosphere: from :func:`load_atmosphere` (its dtype and device are used).
        view: a :class:`~skyfit.camera.FisheyeCamera`, or unit view vectors East-North-Up, shape (N, 3).
        sun: ``(zenith_deg, azimuth_deg)`` or a unit vector; or ``time=`` and ``location=`` (NREL SPA).
        accuracy: None (default, accurate: single scattering with ``skyfit render``'s defaults,
            :data:`skyfit.render.auto.RENDER_DEFAULTS`, every pixel above 5° elevation within 1 % of the
            converged radiance; multiple scattering with Bruneton's full tables), :data:`ACCURATE`,
            or ``"auto"`` (= ``de=1``, mean ΔE 1, fast), ``"de=X"`` or ``"rel=X"``: the cheapest measured
            setting meeting it (:mod:`skyfit.render.auto`, docs/benchmarks.md).
        orders: scattering orders (1 = single scattering).
        multiple: ``bruneton`` (full orders) or ``hillaire`` (Hillaire 2020's cheaper LUT) for orders >= 2.
        altitude: observer height above the ground. [m]
        model: an explicit renderer (:class:`skyfit.fit.model.SkyModel`) instead of ``accuracy``.
        sun_disk: add the attenuated solar disc (Bruneton tables only).

    Returns:
        :class:`Sky` (radiance, XYZ, linear sRGB, valid mask).
    """
    atm = atmosphere
    s = sun_vector(sun, time=time, location=location, dtype=atm.dtype, device=atm.device)
    zen = zenith_angle_deg(s)
    if model is None:
        model = render_model(accuracy, orders, multiple, zen, altitude, "float64" if atm.dtype == torch.float64 else "float32")
    if isinstance(view, FisheyeCamera):
        vec, valid = view.pixel_vectors(atm.dtype, atm.device)
    else:
        vec = torch.as_tensor(view, dtype=atm.dtype, device=atm.device)
        if vec.ndim != 2 or vec.shape[-1] != 3:
            raise ValueError(f"view must be a FisheyeCamera or unit vectors of shape (N, 3), got {tuple(vec.shape)}")
        valid = torch.isfinite(vec).all(-1)
    radiance = torch.zeros(*valid.shape, atm.wavelengths.shape[0], dtype=atm.dtype, device=atm.device)
    tables = model.sun_tables(atm, zen, altitude) if model.sun_window else None
    renderer = model.renderer(atm, altitude, tables=tables) if not sun_disk else _disk_renderer(model, atm, altitude, tables)
    radiance = radiance.index_put((valid,), renderer(vec[valid], s))
    xyz = spectral_to_xyz(radiance, atm.wavelengths)
    return Sky(radiance, xyz, xyz_to_linear_srgb(xyz), valid, atm.wavelengths,
               {**model.integrator.settings(), **model.settings()})


def _disk_renderer(model: SkyModel, atm: Atmosphere, altitude: float, tables=None):
    """The renderer with the attenuated solar disc: a Bruneton lookup option that SkyModel does not carry."""
    if model.orders == 1 or model.multiple != "bruneton":
        raise ValueError("sun_disk needs orders >= 2 with multiple='bruneton'")
    tables = model.tables(atm) if tables is None else tables
    return lambda d, s: render_vectors(atm, d, s, model.integrator, altitude, model.orders, tables=tables,
                                       multiple="bruneton", ground=model.ground, sun_disk=True)


def envmap(source: "FitResult | Atmosphere", sun=None, *, time: str | None = None, location=None, size: int = 512,
           layout: str = "latlong", sun_disk: bool = False, orders: int = 4, multiple: str = "bruneton",
           table_sizes=None, accuracy: str | None = None, altitude: float = 0.0, model: SkyModel | None = None,
           spectral: bool = True, tables=None):
    """An HDR environment map of a (fitted) sky: :class:`skyfit.export.envmap.EnvMap` (docs/envmap.md).

    Args:
        source: a :class:`FitResult` (its atmosphere on the fit's wavelengths) or an :class:`Atmosphere`.
        sun, time, location: as :func:`render`.
        size: lat-long height H (width 2H) or cube face edge, even. [px]
        layout: ``latlong`` (row 0 straight up, azimuth 0 = North at the left edge) or ``cubemap``.
        sun_disk: add the solar disc (energy-conserving at any resolution).
        orders, multiple, table_sizes, accuracy, altitude, model: the renderer, as :func:`render`
            (default: 4 orders of Bruneton's tables at 2017's sizes; ``table_sizes`` R,MU,MUS,NU).
        tables: ``model.tables(atmosphere)`` computed once, to reuse across maps of one atmosphere (the default
            renderer builds its tables for the map's sun, :meth:`SkyModel.sun_tables`: pass 2017's, built by
            ``model.tables``, to reuse them across suns).
    """
    from .export.envmap import render_envmap

    atm = source.atmosphere() if isinstance(source, FitResult) else source
    s = sun_vector(sun, time=time, location=location, dtype=atm.dtype, device=atm.device)
    zen = zenith_angle_deg(s)
    if model is None:
        model = render_model(accuracy, orders, multiple, zen, altitude, "float64" if atm.dtype == torch.float64 else "float32")
        if table_sizes is not None and model.orders > 1 and model.multiple == "bruneton":
            sizes = table_sizes if isinstance(table_sizes, TableSizes) else TableSizes.parse(table_sizes)
            model = dataclasses.replace(model, table_sizes=dataclasses.astuple(sizes))
    if tables is None and model.sun_window:
        tables = model.sun_tables(atm, zen, altitude)
    fn = model.renderer(atm, altitude, tables=tables)
    meta = {"renderer": {**model.integrator.settings(), **model.settings()}, "observer_altitude_m": altitude,
            "atmosphere": atm.summary()}
    return render_envmap(atm, s, lambda d: fn(d, s), size=size, layout=layout, sun_disk=sun_disk, spectral=spectral,
                         altitude=altitude, meta=meta)


# -- fitting ----------------------------------------------------------------------------------------
@dataclasses.dataclass
class FitResult:
    """A fit's outcome in memory: RESULT.json's content (:attr:`result`), and the problem to render again.

    Attributes:
        result: the RESULT dict (CONTRACT.md): parameters, free, metrics, convergence, data, settings, config.
        problem: the fit problem (None for a result read from a file).
        x: the fitted unconstrained vector, shape (P,) (None for a result read from a file).
    """

    result: dict
    problem: object | None = None
    x: Tensor | None = None

    @property
    def parameters(self) -> dict:
        """Every parameter's value (SI units; lists for per-observation ones)."""
        return self.result["parameters"]

    @property
    def free(self) -> list[str]:
        return list(self.result["free"])

    @property
    def sigma(self) -> dict | None:
        """Standard deviation of each free parameter (None unless fitted with ``laplace=True``): noise, numerical
        model error and discrepancy floor in quadrature, or the noise alone with ``sigma="noise"``
        (docs/uncertainty.md, "Honest sigma under model error"; the parts in ``result["laplace"]["budget"]``)."""
        return (self.result.get("laplace") or {}).get("sigma")

    @property
    def corrected(self) -> dict | None:
        """The estimate corrected for the fit's renderer (None unless fitted with ``laplace=True`` and the total
        sigma): ``values`` at the converged reference's optimum as the budget's refits find it, with ``sigma``,
        ``interval68``, ``interval95`` and ``derived``. On 60 synthetic skies from a richer model, fitted with a
        one-term Henyey-Greenstein phase and the phase term (its default there), these intervals covered the truth at
        68 / 95 % in every parameter, where :attr:`sigma` about the fitted values under-covers the albedo and beta at
        68 % (docs/uncertainty.md, "Which to read")."""
        return (self.result.get("laplace") or {}).get("corrected")

    @property
    def metrics(self) -> dict:
        """rmse, rmse_units, delta_e, loss, n_samples, per observation."""
        return self.result["metrics"]

    @property
    def model(self) -> SkyModel:
        """The renderer the fit used."""
        return model_from_result(self.result)

    def atmosphere(self, wavelengths=None, *, dtype: torch.dtype = torch.float64, device: str = "cpu") -> Atmosphere:
        """The fitted atmosphere on ``wavelengths`` [nm] (default: the fit's model grid)."""
        lam = parse_wavelengths(wavelengths) if isinstance(wavelengths, str) else wavelengths
        return atmosphere_from_result(self.result, lam, dtype, resolve_device(device))

    def predict(self) -> list[Tensor]:
        """The model's values for each fitted observation, shape (N_i, C_i) each (fits in memory only)."""
        if self.problem is None:
            raise ValueError("a result read from a file has no observations; render(...) it instead")
        with torch.no_grad():
            return self.problem.predict(self.x)

    def render(self, view, sun=None, **kw) -> Sky:
        """Render the fitted atmosphere with the fit's renderer (see :func:`render`; ``wavelengths`` optional)."""
        atm = self.atmosphere(kw.pop("wavelengths", None), device=kw.pop("device", "cpu"))
        kw.setdefault("model", None if "accuracy" in kw else self.model)
        return render(atm, view, sun, **kw)

    def save(self, path: str | Path) -> Path:
        """Write RESULT.json (atomically); :func:`load_result` reads it back."""
        save_result(self.result, path)
        return Path(path)

    def __repr__(self) -> str:
        m = self.metrics
        free = ", ".join(f"{n}={self.parameters[n]}" for n in self.free)
        return f"FitResult({free}; rmse {m['rmse']:.4g} {m['rmse_units']}, loss {m['loss']:.6g})"


def load_result(path: str | Path) -> FitResult:
    """A RESULT.json (``skyfit fit --out`` or :meth:`FitResult.save`) as a :class:`FitResult`."""
    return FitResult(read_result(path))


def _observations(observations) -> list:
    if isinstance(observations, (Observation, str, Path)):
        return [observations]
    return list(observations)


def fit(observations, config: str | Path | dict | Atmosphere = "earth", *, free: Sequence[str] | None = None,
        laplace: bool = False, progress: bool = False, device: str = "cpu", kider_site: dict | None = None,
        **settings) -> FitResult:
    """Fit an atmosphere to observations in memory (or DATA paths); nothing is written.

    Args:
        observations: an :class:`~skyfit.fit.data.Observation` (e.g. :meth:`Observation.from_arrays`), a
            list of them (one joint fit), or DATA paths (.exr, Kider capture folders).
        config: the atmosphere to start from: a shipped name, a YAML path, a dict (with an optional
            ``fit:`` section), or an :class:`Atmosphere` from :func:`load_atmosphere` (its config is used).
        free: the fitted parameters (docs/fitting.md); None: the config's ``fit.free`` or the default set.
        laplace: add the Laplace (Hessian) covariance with the error budget: :attr:`FitResult.sigma`.
        progress: a tqdm bar on stderr.
        device: cpu, cuda, cuda:N or auto.
        kider_site: latitude / longitude / elevation / utc_offset_hours for Kider folders.
        **settings: any field of :class:`skyfit.fit.problem.FitSettings` (loss, integrator, orders,
            accuracy, starts, max_iter, dtype, initial, per_observation, sigma, ...).
    """
    t0 = _time.perf_counter()
    cfg, source = _config_of(config)
    s = fit_settings(cfg.get("fit"), {**settings, "free": free})
    prep = prepare(_observations(observations), cfg, s, kider_site=kider_site, device=resolve_device(device))
    problem = prep.fit_problem()
    s = prep.settings
    res = _optimise(problem, s.options(progress))
    result = result_dict(problem, res, command="python", settings=dataclasses.asdict(s), config=cfg,
                         config_source=source, base_dist=prep.base_dist, dtype=s.dtype,
                         seconds=_time.perf_counter() - t0, laplace=laplace)
    result["seconds"] = _time.perf_counter() - t0
    return FitResult(result, problem, res.x)


@dataclasses.dataclass(repr=False)
class PhotoResult(FitResult):
    """A photo fit (:func:`fit_photo`): a :class:`FitResult` with the photo's camera, sun and aerosol.

    Attributes (besides FitResult's):
        camera: the fitted :class:`~skyfit.camera.FisheyeCamera` (projection, centre, radius, heading, tilt), in the
            photo's own pixels also where a large photo was fitted reduced (``result["photo"]["reduced"]``).
        photo_fit: the whole :class:`skyfit.fit.photo.PhotoFit` (scene, masks, blocks, model image; its scene, masks
            and blocks at the fitted size, ``photo_fit.scene.scale`` photo pixels per pixel).
    """

    camera: FisheyeCamera | None = None
    photo_fit: object | None = None

    @property
    def aerosol(self) -> dict:
        """aod_550, angstrom_alpha, g, rayleigh_scale and their Laplace sigma."""
        return self.result["aerosol"]

    @property
    def sun(self) -> dict:
        """model_px, detected_px, separation_deg (CONTRACT.md)."""
        return self.result["sun"]

    def save_report(self, path: str | Path) -> Path:
        """RESULT.png: photo, model, residual and mask side by side."""
        from .fit.photo import report_png

        return report_png(self.photo_fit, path)


def fit_photo(photo, *, time: str | None = None, location=None, config: str | Path | dict = "earth", camera=None, mask=None,
              exposures: Sequence[float] | None = None, linear: bool = False, response: str | None = None,
              free: Sequence[str] | None = None, laplace: bool = True, progress: bool = False, device: str = "cpu",
              **settings) -> PhotoResult:
    """Fit the atmosphere to a sky photo from its time and place alone; nothing is written.

    Args:
        photo: a JPEG/PNG/TIFF, camera RAW, Radiance .hdr or EXR path, a folder of one scene's bracketed
            exposures, or a :class:`skyfit.io.photo.LinearPhoto` in memory.
        time: ISO 8601 with its UTC offset (or a zone name); None: EXIF DateTimeOriginal with its OffsetTimeOriginal.
        location: "LAT,LON[,ELEV]" or (lat, lon[, elev]) [deg, deg, m]; None: the EXIF GPS position.
        config: the atmosphere to start from (a shipped name, a YAML path or a dict).
        camera: a FisheyeCamera, a CAMERA.yaml path or its dict; None: estimated from the image and the sun.
        mask: (H, W) bool, True = ignore, added to the automatic masks.
        exposures, linear, response: how to read the photo (:func:`skyfit.io.photo.read_photo`).
        free: the fitted parameters (default :data:`skyfit.fit.photo.PHOTO_FREE`).
        laplace: Laplace sigma of the fitted values (``result.aerosol["sigma"]``).
        **settings: any :class:`skyfit.fit.problem.FitSettings` field.
    """
    from .fit.photo import fit_photo as _fit_photo

    cfg, _ = read_config(config) if not isinstance(config, dict) else (config, "dict")
    overrides = {**settings, **({"free": list(free)} if free is not None else {})}
    pf = _fit_photo(photo, time=time, location=location, config=cfg, camera=camera, mask=mask, exposures=exposures,
                    linear=linear, response=response, overrides=overrides, laplace=laplace, progress=progress,
                    device=resolve_device(device))
    return PhotoResult(pf.result, pf.problem, pf.x, camera=pf.camera, photo_fit=pf)


def _config_of(config) -> tuple[dict, str]:
    """A config dict for ``fit``: an Atmosphere is accepted when it is exactly its config's atmosphere."""
    if not isinstance(config, Atmosphere):
        return read_config(config)
    cfg = getattr(config, "config", None)
    if cfg is None:
        raise ValueError("this Atmosphere has no config to rebuild it on the data's wavelengths; "
                         "pass the config (a name, a YAML path or a dict) instead")
    rebuilt = atmosphere_from_config(cfg, config.wavelengths.cpu().numpy(), config.dtype, config.device)
    changed = [f for f in config.tensor_fields() if not torch.equal(getattr(config, f), getattr(rebuilt, f))]
    if changed:
        raise ValueError(f"this Atmosphere differs from its config in {changed}; pass a config dict with those "
                         "values instead, so that the result can be rebuilt")
    return cfg, config.name


# -- uncertainty and export ----------------------------------------------------------------------------
def sample(fit_result: FitResult, *, walkers: int = 32, steps: int = 2000, seed: int = 0, priors: dict | None = None,
           checkpoint: str | Path | None = None, resume: bool = False, progress: bool = False,
           plots: bool = False) -> dict:
    """emcee posterior around a fit in memory (docs/uncertainty.md).

    Args:
        fit_result: from :func:`fit` (it carries its problem and optimum).
        walkers, steps, seed: the ensemble (walkers even and >= 2 x free parameters).
        priors: name -> {kind, lo, hi | mean, sd} replacing the default priors.
        checkpoint: a folder for chain.h5 (atomic checkpoints; ``resume`` continues it), summary and
            plots; None keeps the chain in memory and writes nothing.

    Returns:
        The summary: posterior median/percentiles/std per parameter, diagnostics (tau, acceptance,
        burn-in), Laplace comparison; ``chain_array`` (steps, walkers, P: unconstrained x) when kept in memory.
    """
    # emcee (through scipy.stats) takes ~1.5 s to import: only a sampling session pays for it.
    from .fit.priors import make_priors
    from .fit.sample import sample_posterior

    if fit_result.problem is None:
        raise ValueError("sample needs a FitResult from skyfit.fit (a result read from a file has no data)")
    problem = fit_result.problem
    lap = fit_result.result.get("laplace")
    return sample_posterior(problem, fit_result.x, checkpoint, walkers=walkers, steps=steps,
                            priors=make_priors(problem, priors or {}), seed=seed, resume=resume, progress=progress,
                            laplace=lap, plots=plots and checkpoint is not None)


def export_luts(source: FitResult | Atmosphere, out_dir: str | Path | None = None, *, orders: int = 4,
                table_sizes: TableSizes | Sequence[int] | None = None, wavelengths=None, format: str = "exr", rgb: bool = False,
                device: str = "cpu", layout: str = "skyfit", precision: str = "f32") -> PrecomputedAtmosphere:
    """Bruneton's precomputed tables of a fitted atmosphere (or any Atmosphere), written as LUTs when asked.

    Precomputed by :data:`~skyfit.scattering.multiple.ACCURATE_QUADRATURE` (Gauss-Legendre view rays; 2017's equal
    steps put a hazy sky's orders >= 2 too high, docs/luts.md "The view-ray rule of an exported LUT"), whatever the layout.

    Args:
        source: a :class:`FitResult` (its atmosphere on ``wavelengths``, default the fit's) or an Atmosphere.
        out_dir: a folder for the LUT files (docs/luts.md); None: only return the tables.
        orders: scattering orders in the tables.
        table_sizes: :class:`~skyfit.scattering.bruneton_tables.TableSizes`, or the scattering table's
            (R, MU, MU_S, NU) as ``skyfit export-lut --table-sizes`` takes them (default Bruneton 2017's).
        format, rgb: ``exr`` or ``npz``; linear sRGB channels instead of one per wavelength.
        layout, precision: ``skyfit`` (the files above) or ``bruneton2017`` (the RGB textures, .dat files and
            GLSL of an unmodified Bruneton 2017 shader, docs/luts.md; scattering textures in ``f16`` or ``f32``).
    """
    from .export import bruneton2017 as b17

    atm = source.atmosphere(wavelengths, device=device) if isinstance(source, FitResult) else source
    if table_sizes is not None and not isinstance(table_sizes, TableSizes):
        table_sizes = TableSizes.parse(table_sizes)
    if layout not in ("skyfit", "bruneton2017"):
        raise ValueError(f"unknown LUT layout {layout!r}; valid: skyfit, bruneton2017")
    kw = {} if layout == "skyfit" else {"mu_s_min": b17.skyfit_mu_s_min(b17.UPSTREAM_MU_S_MIN, atm.bottom_radius, atm.top_radius)}
    if layout == "bruneton2017":
        b17.check_precision(precision)  # before the precomputation
    with torch.no_grad():
        tables = precompute(atm, orders=orders, sizes=table_sizes or TableSizes(), quadrature=ACCURATE_QUADRATURE, **kw)
    if out_dir is not None and layout == "bruneton2017":
        atm_rgb = source.atmosphere(list(b17.LAMBDAS_RGB_NM), device=device) if isinstance(source, FitResult) else None
        b17.export_bruneton2017(tables, out_dir, precision=precision, atm_rgb=atm_rgb)
    elif out_dir is not None:
        _write_luts(tables, atm, out_dir, format=format, rgb=rgb)
    return tables


__all__ = ["ACCURATE", "FitResult", "Sky", "check_result", "envmap", "export_luts", "fit", "load_atmosphere", "load_result",
           "read_config", "render", "render_model", "resolve_device", "sample", "sun_vector"]
