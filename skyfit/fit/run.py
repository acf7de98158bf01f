"""``skyfit fit`` and ``skyfit evaluate`` as plain functions (the CLI parses flags and reads the config).

Settings come from, in order of precedence: command-line flags, the config's
``fit:`` section, the defaults of :class:`FitSettings`. RESULT.json embeds the
atmosphere config and the model settings, so ``evaluate`` needs only it and DATA.
"""
from __future__ import annotations

import copy
import dataclasses
import inspect
import json
import time
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import torch

from .data import (Observation, check_noise_model, expand_data_paths, noise_sigma, observation_from_exr,
                   observation_from_kider)
from .losses import make_loss
from .model import FitProblem, SkyModel
from .optimise import FitOptions, fit
from .parameters import NUISANCE, ORIENTATION, PARAMETERS, FitError, Parameterisation, check_names
from .report import dumps, plot_all, write_text_atomic

DEFAULT_FREE = ("rayleigh_scale", "mie_beta_550", "mie_scale_height", "mie_g", "exposure")
"""Free parameters when neither --free nor the config's fit.free says; Kider scans add sun_azimuth_offset."""
DEFAULT_RGB_WAVELENGTHS = "400:700:20"
"""Model grid for RGB data whose EXR header does not give the grid it was rendered on [nm]."""
RESULT_VERSION = 1
RUN_SECTIONS = ("fit", "sample")
"""Config sections that set up a run rather than the atmosphere (not passed to the atmosphere loader)."""


@dataclasses.dataclass
class FitSettings:
    """What ``skyfit fit`` does; each field may be set in the config's ``fit:`` section or by a flag.

    The renderer defaults differ from ``skyfit render``'s (taylor, trapezoid, 32): a fit turns
    model error into parameter bias: on a 1 % noise sky Taylor's optical depth biased the
    aerosol scale height by +145 %, a 32-sample trapezoid view integral by -23 %, while Chapman
    with a 16-node Gauss-Legendre view integral recovered it to 0.3-7 % at lower cost
    (docs/fitting.md, "Model error").
    """

    free: list[str] | None = None
    per_observation: list[str] | None = None
    initial: dict = dataclasses.field(default_factory=dict)
    loss: str = "squared"
    integrator: str = "chapman"
    orders: int = 1
    multiple: str = "hillaire"
    lut_size: list[int] = dataclasses.field(default_factory=lambda: [16, 16])
    lut_directions: int = 64
    lut_samples: int = 20
    table_sizes: list[int] | None = None
    view_samples: int = 16
    rule: str = "gauss"
    starts: int = 3
    seed: int = 0
    adam_steps: int = 10
    max_iter: int = 100
    grad_tol: float = 1e-7
    rel_tol: float = 1e-10
    wavelengths: str | None = None
    min_elevation_deg: float = 0.0
    sun_disc_deg: float = 2.0
    saturation: float | None = None
    max_samples: int | None = None
    sigma_relative: float = 0.01
    spectral_noise: list[float] | None = None
    bin_nm: float = 10.0
    per_sample_sun: bool = True
    dtype: str = "float64"
    select_sigma: str = "scaled"
    """``--select``: ``scaled`` (sigma known up to a common factor, profiled) or ``known`` (skyfit.fit.select)."""
    select_heldout: float = 0.2
    """``--select``: fraction of the samples held out of the ladder's fits and scored afterwards."""
    accuracy: str | None = None
    """``auto`` (= ``noise``: relative model error <= 1/3 of the data's median relative sigma), ``de=X`` or
    ``rel=X``: replaces integrator, view_samples, rule (and the multiple-scattering fields for orders >= 2)
    by the cheapest measured setting meeting it (:mod:`skyfit.render.auto`, docs/benchmarks.md)."""


FIT_SECTION_KEYS = frozenset(f.name for f in dataclasses.fields(FitSettings))


def fit_settings(section: dict | None, overrides: dict | None = None) -> FitSettings:
    """Merge the config's ``fit:`` section and flag overrides (None values are ignored)."""
    section = dict(section or {})
    if not isinstance(section, dict):
        raise FitError(f"config section 'fit' must be a mapping, got {section!r}")
    unknown = set(section) - FIT_SECTION_KEYS
    if unknown:
        raise FitError(f"unknown key(s) {sorted(unknown)} in config section 'fit'; known: {sorted(FIT_SECTION_KEYS)}")
    merged = {**section, **{k: v for k, v in (overrides or {}).items() if v is not None}}
    for key in ("free", "per_observation"):
        v = merged.get(key)
        if isinstance(v, str):
            merged[key] = [s.strip() for s in v.split(",") if s.strip()]
    s = FitSettings(**merged)
    if s.free is not None:
        check_names(s.free)
    if s.per_observation is not None:
        check_names(s.per_observation, "per-observation parameter")
    if not isinstance(s.initial, dict):
        raise FitError(f"fit.initial must map parameter names to values, got {s.initial!r}")
    check_names(list(s.initial), "parameter in fit.initial")
    if s.orders < 1:
        raise FitError(f"orders must be >= 1, got {s.orders}")
    if s.view_samples < 1:
        raise FitError(f"view_samples must be >= 1, got {s.view_samples}")
    if s.max_samples is not None and s.max_samples < 1:
        raise FitError(f"max_samples must be >= 1, got {s.max_samples}")
    if s.spectral_noise is not None and (not isinstance(s.spectral_noise, (list, tuple)) or len(s.spectral_noise) != 2):
        raise FitError(f"fit.spectral_noise must be [relative, absolute], got {s.spectral_noise!r}")
    if s.dtype not in ("float32", "float64"):
        raise FitError(f"dtype must be float32 or float64, got {s.dtype!r}")
    return s


def _integrator(spec: str | dict):
    from ..transmittance import integrator_class, make_integrator

    if isinstance(spec, dict):
        d = dict(spec)
        name = d.pop("name", None)
        if name is None:
            raise FitError("integrator settings lack a name")
        accepted = set(inspect.signature(integrator_class(name).__init__).parameters) - {"self"}
        return make_integrator(name, **{k: v for k, v in d.items() if k in accepted})
    from ..cli import parse_integrator

    return parse_integrator(str(spec))


def _load(data: Sequence[str | Path], s: FitSettings, kider_site: dict | None, max_samples: int | None) -> list[Observation]:
    dtype = torch.float64 if s.dtype == "float64" else torch.float32
    obs = []
    for kind, p in expand_data_paths(data):
        if kind == "exr":
            obs.append(observation_from_exr(
                p, sigma_relative=s.sigma_relative, min_elevation_deg=s.min_elevation_deg, sun_disc_deg=s.sun_disc_deg,
                saturation=s.saturation, max_samples=max_samples, dtype=dtype))
        else:
            o = observation_from_kider(p, bin_nm=s.bin_nm, per_sample_sun=s.per_sample_sun, dtype=dtype,
                                       **(kider_site or {}))
            obs.append(o if s.spectral_noise is None else with_noise_model(o, *s.spectral_noise))
    return obs


def with_noise_model(obs: Observation, relative: float, absolute: float) -> Observation:
    """``obs`` with sigma = hypot(relative x value, absolute) instead of its own.

    Kider et al.'s band averages carry the standard error of the spectrometer's samples
    (0.06 % median at noon), far below the instrument's calibration and pointing errors, so
    weighting by it makes a fit chase a few bright samples. ``fit.spectral_noise: [rel, abs]``
    states the instrument's error instead; ``[0, a]`` weights every element alike, which makes
    the loss the published score (unweighted RMSE). [1], [W/(m^2 sr nm)]
    """
    check_noise_model(relative, absolute, f"{obs.source}: fit.spectral_noise")
    meta = {**obs.metadata, "sigma_model": {"relative": relative, "absolute": absolute}}
    return dataclasses.replace(obs, sigma=noise_sigma(obs.values, relative, absolute), metadata=meta)


def model_wavelengths(observations: Sequence[Observation], wavelengths: str | None) -> np.ndarray:
    """The grid the atmosphere is built on: every spectral channel, plus a grid for RGB data."""
    from ..cli import parse_wavelengths

    grid: set[float] = set()
    rgb = [o for o in observations if o.kind == "rgb"]
    if rgb:
        if wavelengths is not None:
            grid |= set(parse_wavelengths(wavelengths).tolist())
        else:
            meta = next((o.metadata.get("model_wavelengths_nm") for o in rgb if o.metadata.get("model_wavelengths_nm")), None)
            grid |= set(float(v) for v in meta) if meta else set(parse_wavelengths(DEFAULT_RGB_WAVELENGTHS).tolist())
    for o in observations:
        if o.kind == "spectral":
            grid |= set(float(v) for v in o.wavelengths.cpu().tolist())
    return np.array(sorted(grid))


def _base_atmosphere(config: dict, lam: np.ndarray, observations: Sequence[Observation], dtype):
    """Base atmosphere from the config (without its ``fit`` and ``sample`` sections) and its Earth-Sun distance [AU]."""
    from ..atmosphere import atmosphere_from_config

    cfg = {k: v for k, v in copy.deepcopy(config).items() if k not in RUN_SECTIONS}
    sun = cfg.setdefault("sun", {}) or {}
    cfg["sun"] = sun
    bands = {o.band_nm for o in observations if o.kind == "spectral" and o.band_nm is not None}
    if "bandwidth_nm" not in sun and len(bands) == 1:
        sun["bandwidth_nm"] = bands.pop()  # the data's band average, on the solar spectrum too
    atm = atmosphere_from_config(cfg, lam, dtype=dtype)
    return atm, float(sun.get("distance_au", 1.0))


def _initial_values(s: FitSettings, observations: Sequence[Observation], free: Sequence[str], per: Sequence[str]) -> dict:
    init = dict(s.initial)
    if "sun_azimuth_offset" in free and "sun_azimuth_offset" not in init:
        guesses = [o.metadata.get("azimuth_offset_guess_rad", 0.0) for o in observations]
        if any(guesses):
            init["sun_azimuth_offset"] = guesses if "sun_azimuth_offset" in per else float(np.mean(guesses))
    return init


def _model(s: FitSettings) -> SkyModel:
    return SkyModel(_integrator(s.integrator), orders=s.orders, view_samples=s.view_samples, rule=s.rule,
                    multiple=s.multiple, lut_size=s.lut_size, lut_directions=s.lut_directions,
                    lut_samples=s.lut_samples, table_sizes=s.table_sizes)


def _resolve_accuracy(s: FitSettings, observations) -> tuple[FitSettings, SkyModel]:
    """``s.accuracy`` -> settings with the automatic renderer fields, and their model (skyfit.render.auto)."""
    from ..render.auto import fit_overrides

    try:
        over, _ = fit_overrides(s.accuracy, observations, orders=s.orders, dtype=s.dtype)
    except ValueError as e:
        raise FitError(f"accuracy {s.accuracy!r}: {e}") from None
    s = dataclasses.replace(s, **over)
    return s, _model(s)


def _model_from_result(res: dict) -> SkyModel:
    """The SkyModel a RESULT.json was fitted with (its ``integrator`` and ``model`` entries)."""
    m = res["model"]  # SkyModel.settings() wrote the multiple-scattering fields only for orders > 1
    kw = {k: m[k] for k in ("multiple", "lut_size", "lut_directions", "lut_samples", "table_sizes") if m.get(k) is not None}
    return SkyModel(_integrator(res["integrator"]), orders=int(m.get("orders", 1)),
                    view_samples=int(m.get("view_samples", 32)), rule=m.get("rule", "trapezoid"),
                    ground=bool(m.get("ground", True)), **kw)


def check_out_and_config(out: str | Path, config, config_source: str) -> Path:
    """FitError unless ``out`` names a .json file and ``config`` is a mapping; ``out`` as a Path."""
    out = Path(out)
    if out.suffix.lower() != ".json":
        raise FitError(f"--out must name a .json file, got {out}")
    if not isinstance(config, dict):
        raise FitError(f"config {config_source}: must be a mapping")
    return out


def run_fit(data: Sequence[str | Path], config: dict, out: str | Path, *, overrides: dict | None = None,
            config_source: str = "", kider_site: dict | None = None, plots: bool = True, progress: bool = False,
            laplace: bool = False, select: bool = False) -> dict:
    """Fit DATA, write RESULT.json (and plots beside it), return the result dict.

    Args:
        data: .exr files, Kider capture folders, or folders of either (a joint fit when several).
        config: the atmosphere config dict, optionally with a ``fit:`` section (:class:`FitSettings`).
        out: RESULT.json path.
        overrides: flag values overriding the config's ``fit`` section (None = not given).
        config_source: where the config came from (for the report).
        kider_site: latitude / longitude / elevation / utc_offset_hours for Kider folders.
        plots: write PNG plots next to ``out``.
        progress: tqdm progress bar on stderr.
        laplace: add ``result["laplace"]``: sigma and correlation of every free parameter from the
            Hessian at the fit (:func:`skyfit.fit.laplace.laplace_summary`, docs/uncertainty.md).
        select: choose the model by the ladder of :mod:`skyfit.fit.select` (docs/selection.md);
            RESULT.json then holds the chosen model and ``selection``.
    """
    t0 = time.perf_counter()
    out = check_out_and_config(out, config, config_source)
    if select:  # the model ladder (skyfit.fit.select) chooses the atmosphere's components
        from .select import run_select

        return run_select(data, config, out, overrides=overrides, config_source=config_source, kider_site=kider_site,
                          plots=plots, progress=progress, laplace=laplace)
    s = fit_settings(config.get("fit"), overrides)
    loss = make_loss(s.loss)
    model = _model(s)
    observations = _load(data, s, kider_site, s.max_samples)
    if s.accuracy:  # the cheapest measured renderer setting meeting it, for these observations' scenes
        s, model = _resolve_accuracy(s, observations)
    free = list(s.free) if s.free is not None else list(DEFAULT_FREE) + (
        ["sun_azimuth_offset"] if any("ring" in o.metadata for o in observations) else [])
    per = s.per_observation
    per_eff = per if per is not None else [n for n in NUISANCE if n != "noise_scale"]
    dtype = torch.float64 if s.dtype == "float64" else torch.float32
    lam = model_wavelengths(observations, s.wavelengths)
    base, base_dist = _base_atmosphere(config, lam, observations, dtype)
    param = Parameterisation(base, free, len(observations), per, _initial_values(s, observations, free, per_eff))
    problem = FitProblem(param, model, observations, loss, base_sun_distance_au=base_dist)
    options = FitOptions(starts=s.starts, seed=s.seed, adam_steps=s.adam_steps, max_iter=s.max_iter,
                         grad_tol=s.grad_tol, rel_tol=s.rel_tol, progress=progress)
    res = fit(problem, options)
    return write_result(problem, res, out, command="fit", settings=dataclasses.asdict(s), config=config,
                        config_source=config_source, base_dist=base_dist, dtype=s.dtype, t0=t0, laplace=laplace,
                        plots=plots)


def write_result(problem: FitProblem, res, out: Path, *, command: str, settings: dict, config: dict,
                 config_source: str, base_dist: float, dtype: str, t0: float, laplace: bool, plots: bool,
                 extra: dict | None = None) -> dict:
    """RESULT.json of a finished fit (CONTRACT.md), with the Laplace covariance and plots when asked; atomic."""
    out = Path(out)
    param, model = problem.param, problem.model
    metrics = problem.metrics(res.x)
    phys = param.to_physical(res.x)
    result = {
        "skyfit_result": RESULT_VERSION,
        "command": command,
        "parameters": res.parameters,
        "units": param.units(),
        "derived": param.derived(phys),
        "free": res.free,
        "per_observation": list(param.per_observation),
        "fitted_vector": {n: float(v) for n, v in zip(param.names, res.x.tolist())},
        "integrator": {**model.integrator.settings(), **model.settings()},
        "model": {**model.settings(), "wavelengths_nm": param.base.wavelengths.cpu().tolist(), "base_sun_distance_au": base_dist,
                  "dtype": dtype, "kinds": sorted({o.kind for o in problem.observations})},
        "loss": problem.loss.settings(),
        "metrics": metrics,
        "data": [o.summary() for o in problem.observations],
        "convergence": {**res.convergence, "starts": res.starts},
        **(extra or {}),
        "settings": settings,
        "config": {k: v for k, v in config.items() if k not in RUN_SECTIONS},
        "config_source": config_source,
        "seconds": time.perf_counter() - t0,
    }
    if laplace:
        from .laplace import laplace_summary

        result["laplace"] = laplace_summary(problem, res.x)
    if plots:
        with torch.no_grad():
            preds = problem.predict(res.x)
        result["plots"] = plot_all(problem.observations, preds, out.parent, out.stem)
    result["seconds"] = time.perf_counter() - t0
    write_text_atomic(out, dumps(result))
    return result


# -- evaluate -----------------------------------------------------------------------------------
REFIT_NUISANCE = ("exposure", "sun_azimuth_offset", "sun_zenith_offset")
"""What ``evaluate --refit-nuisance`` re-estimates on the target when the source fit freed no
orientation parameter: the calibration scale and the sun azimuth and zenith offsets; the
atmosphere stays fixed (:func:`refit_names`)."""


def refit_names(source_free) -> list[str]:
    """The nuisance parameters ``evaluate --refit-nuisance`` re-estimates for a fit that freed ``source_free``:
    the exposure and the orientation parameters (sun offsets, camera tilts) that fit modelled, or
    :data:`REFIT_NUISANCE` when it modelled none."""
    orientation = [n for n in ORIENTATION if n in set(source_free)]
    return ["exposure", *orientation] if orientation else list(REFIT_NUISANCE)


REQUIRED_RESULT_KEYS = ("parameters", "free", "integrator", "config", "model")


def read_result(path: str | Path) -> dict:
    """A RESULT.json written by :func:`run_fit`; FitError naming the file when it is not one."""
    p = Path(path)
    if not p.is_file():
        raise FitError(f"result file not found: {p}")
    try:
        res = json.loads(p.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise FitError(f"{p}: not a readable JSON result ({type(e).__name__}: {e})".splitlines()[0]) from None
    if not isinstance(res, dict):
        raise FitError(f"{p}: a RESULT.json must hold a JSON object")
    missing = [k for k in REQUIRED_RESULT_KEYS if k not in res]
    if missing:
        raise FitError(f"{p}: not a skyfit fit result (missing {', '.join(missing)})")
    if not isinstance(res["parameters"], dict) or not isinstance(res["config"], dict) or not isinstance(res["model"], dict):
        raise FitError(f"{p}: malformed result (parameters, config and model must be objects)")
    unknown = [k for k in res["parameters"] if k not in PARAMETERS]
    if unknown:
        raise FitError(f"{p}: unknown parameter(s) {unknown}")
    return res


def _nuisance_for(res: dict, obs: Observation, name: str):
    """A fitted nuisance value for ``obs``: its own if it was fitted, else the mean over the fit's observations."""
    v = res["parameters"].get(name)
    if v is None:
        return None
    if not isinstance(v, list):
        return float(v)
    for d, vi in zip(res.get("data", []), v):
        if isinstance(d, dict) and d.get("source") == obs.source:
            return float(vi)
    if name == "exposure":
        return float(np.exp(np.mean(np.log(v))))
    return float(np.mean(v))


def run_evaluate(result_path: str | Path, data: Sequence[str | Path], *, refit_nuisance: bool = False,
                 kider_site: dict | None = None, progress: bool = False, refit: Sequence[str] | None = None) -> dict:
    """How well a fitted atmosphere predicts DATA, with DATA's own sun position (CONTRACT.md).

    Without ``refit_nuisance`` the fitted exposure and offsets are used (the observation's own
    when it was among the fitted data, else their mean). With it, the atmosphere stays fixed
    while :func:`refit_names` (exposure and the orientation parameters the fit modelled: sun
    offsets, camera tilts) are re-estimated per observation; ``refit`` names them instead (an API
    option: e.g. exposure and sun azimuth only, as a reference that re-estimated just those).
    """
    res = read_result(result_path)
    try:
        s = fit_settings(res.get("settings"), None)
        s = dataclasses.replace(s, max_samples=None)  # evaluate every usable sample
        model = _model_from_result(res)
        loss = make_loss(res.get("loss", {}).get("name", "squared") if isinstance(res.get("loss"), dict) else "squared")
    except (TypeError, KeyError, ValueError) as e:
        raise FitError(f"{result_path}: malformed result ({e})".splitlines()[0]) from None
    observations = _load(data, s, kider_site, None)
    dtype = torch.float64 if s.dtype == "float64" else torch.float32
    lam = model_wavelengths(observations, s.wavelengths)
    try:
        base, base_dist = _base_atmosphere(res["config"], lam, observations, dtype)
    except ValueError as e:
        raise FitError(f"{result_path}: its config cannot be rebuilt: {e}") from None
    # The atmosphere moves away from the config only in the parameters that were fitted or set in fit.initial.
    fitted = set(res.get("free", [])) | set((res.get("settings") or {}).get("initial", {}) or {})
    atm_values = {n: v for n, v in res["parameters"].items() if not PARAMETERS[n].nuisance and n in fitted}
    nuis_values: dict[str, Any] = {}
    for n in NUISANCE:
        vals = [_nuisance_for(res, o, n) for o in observations]
        if all(v is not None for v in vals):
            nuis_values[n] = vals if n != "noise_scale" else vals[0]
    if refit is not None:
        bad = [n for n in check_names(refit, "refit parameter") if not PARAMETERS[n].nuisance or n == "noise_scale"]
        if bad:
            raise FitError(f"only exposure and orientation parameters can be refitted, not {bad}")
    free = (list(refit) if refit is not None else refit_names(res.get("free", []))) if refit_nuisance else []
    per = [n for n in NUISANCE if n != "noise_scale"]
    param = Parameterisation(base, free, len(observations), per, {**atm_values, **nuis_values})
    problem = FitProblem(param, model, observations, loss, base_sun_distance_au=base_dist)
    conv = None
    if refit_nuisance:
        r = fit(problem, FitOptions(starts=1, adam_steps=10, max_iter=60, progress=progress))
        x, conv = r.x, r.convergence
    else:
        x = param.initial_vector(dtype)
    metrics = problem.metrics(x)
    phys = param.physical_dict(x)
    return {
        "rmse": metrics["rmse"], "rmse_units": metrics["rmse_units"], "delta_e": metrics["delta_e"],
        "n_samples": metrics["n_samples"], "loss": metrics["loss"], "per_observation": metrics["per_observation"],
        "refit_nuisance": refit_nuisance, "refitted": free, "nuisance": {n: phys[n] for n in ("exposure", *ORIENTATION)},
        "convergence": conv, "result": str(result_path), "data": [o.summary() for o in observations],
    }
