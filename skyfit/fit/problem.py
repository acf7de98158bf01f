"""One way to build a fit problem: data + atmosphere config + settings -> :class:`~skyfit.fit.model.FitProblem`.

``skyfit fit``, ``fit --select``, ``sample``, ``evaluate``, the Python API (:func:`skyfit.fit`)
and batch jobs all go through :func:`prepare` (settings -> loss, renderer, observations,
model wavelengths, base atmosphere) and :meth:`Prepared.problem` (free set and values ->
problem). Settings come from, in order of precedence: explicit overrides (command-line flags
or keyword arguments), the config's ``fit:`` section, the defaults of :class:`FitSettings`.
"""
from __future__ import annotations

import copy
import dataclasses
from pathlib import Path
from typing import Sequence

import numpy as np
import torch

from ..atmosphere import Atmosphere, atmosphere_from_config
from ..resources import AUTOGRAD, BASE_MEMORY_BYTES, Estimate, single_scattering_estimate, tables_estimate
from ..atmosphere.wavelengths import DEFAULT_WAVELENGTHS, parse_wavelengths
from ..atmosphere.config import RUN_SECTIONS
from ..render.auto import fit_overrides
from ..scattering.multiple import ACCURATE_QUADRATURE
from ..transmittance import integrator_from_spec
from .budget import CLUSTERS, DISCREPANCY_DEFAULT, DISCREPANCY_MODELS, SIGMA_MODES
from .data import Observation, check_noise_model, expand_data_paths, noise_sigma, observation_from_exr, observation_from_kider
from .losses import Loss, make_loss
from .model import FitProblem, SkyModel, check_density_directions, check_ray_rule
from .optimise import METHODS, FitOptions
from .parameters import NUISANCE, FitError, Parameterisation, check_names

DEFAULT_FREE = ("rayleigh_scale", "mie_beta_550", "mie_scale_height", "mie_g", "exposure")
"""Free parameters when neither ``free`` nor the config's fit.free says; Kider scans add sun_azimuth_offset."""
DEFAULT_RGB_WAVELENGTHS = DEFAULT_WAVELENGTHS
"""Model grid for RGB data whose EXR header does not give the grid it was rendered on [nm]."""
"""Config sections that set up a run rather than the atmosphere (not passed to the atmosphere loader)."""
DTYPES = {"float32": torch.float32, "float64": torch.float64}


@dataclasses.dataclass
class FitSettings:
    """What a fit does; each field may be set in the config's ``fit:`` section, by a flag or a keyword.

    The renderer defaults differ from ``skyfit render``'s former ones (taylor, trapezoid, 32): a fit turns
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
    ray_rule: str = ACCURATE_QUADRATURE.ray_rule
    """Bruneton tables' view-ray rule: ``gauss`` (skyfit.scattering.multiple.ray_nodes; the default since session 20,
    as every Bruneton table skyfit builds for a render, a photo, the error budget or an export) or 2017's
    ``trapezoid``, which puts a hazy sky's orders >= 2 1.4-2.2x too high (docs/luts.md, "The view-ray rule of an
    exported LUT"). A RESULT.json without the key was fitted with ``trapezoid`` (SkyModel's default)."""
    density_directions: list[int] = dataclasses.field(default_factory=lambda: list(ACCURATE_QUADRATURE.density_directions))
    """Bruneton tables' incident directions (theta, phi[, zenith]) of the scattering density (SkyModel.density_directions;
    the two bands nearest the zenith split since session 20, :data:`skyfit.scattering.multiple.ACCURATE_QUADRATURE`)."""
    view_samples: int = 16
    rule: str = "gauss"
    starts: int = FitOptions.starts
    seed: int = FitOptions.seed
    adam_steps: int = FitOptions.adam_steps
    max_iter: int = FitOptions.max_iter
    grad_tol: float = FitOptions.grad_tol
    rel_tol: float = FitOptions.rel_tol
    optimiser: str = FitOptions.method
    """``auto`` (Levenberg-Marquardt for squared losses, else L-BFGS), ``lm`` or ``lbfgs`` (skyfit.fit.optimise)."""
    wavelengths: str | None = None
    min_elevation_deg: float = 0.0
    sun_mask_deg: float = 2.0
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
    sigma: str = "total"
    """``--laplace``'s sigma: ``total`` (noise + numerical model error + discrepancy floor, skyfit.fit.budget)
    or ``noise`` (the Hessian of the noise alone); docs/uncertainty.md, "Honest sigma under model error"."""
    sigma_reference: list[int] | None = None
    """The numerical term's reference for orders >= 2: Bruneton table sizes and orders [R, MU, MU_S, NU, ORDERS]
    (None: the trade study's 16, 64, 16, 8 with 6 orders, skyfit.fit.budget.REFERENCE_TABLES). MU_S is the whole axis's
    texel count (``sigma_reference_axis: whole``); a window over the fit's suns takes texels at most 2 deg apart."""
    sigma_reference_axis: str = "window"
    """The reference's Bruneton tables: ``window`` (spanning the fit's suns, skyfit.fit.budget.REFERENCE_SUN_WINDOW) or
    ``whole`` (2017's whole mu_s axis of MU_S texels, as budgets were measured before session 18)."""
    sigma_refits: int = 3
    """The numerical term: lagged refits with the reference (at most this many) where the Newton step is
    not linear (skyfit.fit.budget.NONLINEAR); 0: always the Newton step."""
    sigma_polish: int = 0
    """The numerical term: after the lagged refits, up to this many Levenberg-Marquardt steps on the reference itself
    (skyfit.fit.budget.reference_polish; P + 1 renders of the reference a step), where the refits stop short of the
    reference's optimum (a parameter pushed to its bound by the fit's renderer; docs/uncertainty.md). 0: none."""
    sigma_discrepancy: str = DISCREPANCY_DEFAULT
    """The discrepancy term's model: ``floor`` (a white relative error floor), ``sandwich`` (cluster-robust over
    sky regions) or ``larger`` (an upper bound of both); skyfit.fit.budget, docs/uncertainty.md."""
    sigma_clusters: int = CLUSTERS
    """The sandwich's target number of sky-region clusters per observation (skyfit.fit.budget.sky_clusters)."""
    sigma_phase: bool = True
    """The total sigma's phase term: with a one-term Henyey-Greenstein phase and g free, the spread of a two-term
    refit and its shift count as errors (skyfit.fit.budget.phase_expansion; one more fit); other phases get a note.
    On by default since session 20: without it the corrected estimate's g and AOD miss their coverage on skies with a
    backward lobe; with it the corrected estimate covers in every cell over 60 skies (docs/uncertainty.md, "The
    phase term"). False: the faster, narrower sigma of a fit that knows its aerosol is one-lobed."""
    ms_follow: bool = True
    """Photo fits: follow the multiple-scattering factor to first order in the aerosol optical depth between
    refreshes (one more table build per refresh; skyfit.fit.photo.aod_slope). False: hold it fixed, about half the
    builds, with the old bias low on hazy skies (docs/photos.md)."""
    accuracy: str | None = None
    """``auto`` (= ``noise``: relative model error <= 1/3 of the data's median relative sigma), ``de=X`` or
    ``rel=X``: replaces integrator, view_samples, rule (and the multiple-scattering fields for orders >= 2)
    by the cheapest measured setting meeting it (:mod:`skyfit.render.auto`, docs/benchmarks.md)."""

    @property
    def sun_disc_deg(self) -> float:
        """The old name of :attr:`sun_mask_deg` (read-only). [deg]"""
        return self.sun_mask_deg

    @property
    def torch_dtype(self) -> torch.dtype:
        return DTYPES[self.dtype]

    def options(self, progress: bool = False) -> FitOptions:
        """The optimiser's options of these settings."""
        return FitOptions(starts=self.starts, seed=self.seed, adam_steps=self.adam_steps, max_iter=self.max_iter,
                          grad_tol=self.grad_tol, rel_tol=self.rel_tol, progress=progress, method=self.optimiser)


FIT_SECTION_KEYS = frozenset(f.name for f in dataclasses.fields(FitSettings))
RENAMED_KEYS = {"sun_disc_deg": "sun_mask_deg"}
"""Old fit-setting names still read (configs, RESULT.json ``settings``) -> today's (the ``--sun-mask`` flag's)."""

_INF = float("inf")
SETTING_RANGES: dict[str, tuple[str, float, float, str]] = {
    # name: (kind, lo, hi, interval as "[]", "[)", "()" or "(]")
    "orders": ("int", 1, _INF, "[)"), "view_samples": ("int", 1, _INF, "[)"), "starts": ("int", 1, _INF, "[)"),
    "seed": ("int", 0, _INF, "[)"), "adam_steps": ("int", 0, _INF, "[)"), "max_iter": ("int", 1, _INF, "[)"),
    "lut_directions": ("int", 1, _INF, "[)"), "lut_samples": ("int", 1, _INF, "[)"), "max_samples": ("int", 1, _INF, "[)"),
    "grad_tol": ("float", 0, _INF, "()"), "rel_tol": ("float", 0, _INF, "()"),
    "min_elevation_deg": ("float", -90, 90, "[)"), "sun_mask_deg": ("float", 0, 180, "[)"),
    "saturation": ("float", 0, _INF, "()"), "sigma_relative": ("float", 0, _INF, "[)"),
    "bin_nm": ("float", 0, _INF, "()"), "select_heldout": ("float", 0, 1, "[)"), "sigma_refits": ("int", 0, _INF, "[)"),
    "sigma_polish": ("int", 0, _INF, "[)"),
    "sigma_clusters": ("int", 2, _INF, "[)"),
}
"""Type and range of the numeric fit settings, checked with the setting's name and where it came from
before any work (docs/reliability.md)."""
_CHOICES = {"multiple": ("hillaire", "bruneton", "bruneton_lagged"), "select_sigma": ("scaled", "known"), "dtype": tuple(DTYPES),
            "optimiser": METHODS,
            "sigma": SIGMA_MODES, "sigma_discrepancy": DISCREPANCY_MODELS}
_STRINGS = ("loss", "integrator", "rule", "wavelengths", "accuracy")


def coerce_setting(name: str, value, ranges: dict = SETTING_RANGES):
    """A numeric setting written as a string (PyYAML reads ``1e-7`` as one) as its number; anything else as is."""
    if name in ranges and isinstance(value, str):
        try:
            return int(value) if ranges[name][0] == "int" else float(value)
        except ValueError:
            return value
    return value


def check_setting(name: str, value, label: str, ranges: dict = SETTING_RANGES) -> None:
    """FitError ``'<label> must be ..., got <value>'`` unless ``value`` has the setting's type and range (None passes)."""
    if value is None:
        return
    if name in ranges:
        kind, lo, hi, brackets = ranges[name]
        is_int = isinstance(value, (int, np.integer)) and not isinstance(value, bool)
        is_num = is_int or (isinstance(value, (float, np.floating)) and kind == "float")
        if not is_num:
            raise FitError(f"{label} must be {'an integer' if kind == 'int' else 'a number'}, got {value!r}")
        v = float(value)
        ok = (lo <= v if brackets[0] == "[" else lo < v) and (v <= hi if brackets[1] == "]" else v < hi)
        if not ok or v != v:
            rng = (f">= {lo:g}" if brackets[0] == "[" else f"> {lo:g}") if hi == _INF else f"in {brackets[0]}{lo:g}, {hi:g}{brackets[1]}"
            raise FitError(f"{label} must be {rng}, got {value!r}")
    elif name in _CHOICES:
        if value not in _CHOICES[name]:
            raise FitError(f"{label} must be one of {', '.join(_CHOICES[name])}, got {value!r}")
    elif name in _STRINGS:
        if not isinstance(value, str):
            raise FitError(f"{label} must be a string, got {value!r}")
    elif name in ("per_sample_sun", "ms_follow", "sigma_phase") and not isinstance(value, bool):
        raise FitError(f"{label} must be true or false, got {value!r}")


def fit_settings(section: dict | None, overrides: dict | None = None, where: str = "") -> FitSettings:
    """Merge the config's ``fit:`` section and overrides (None values are ignored); FitError when invalid.

    ``where`` names the config in messages about its ``fit:`` section (e.g. ``config sky.yaml``).
    """
    if section is not None and not isinstance(section, dict):
        raise FitError(f"{where + ': ' if where else ''}config section 'fit' must be a mapping, got {section!r}")
    section = dict(section or {})
    overrides = {k: v for k, v in (overrides or {}).items() if v is not None}
    prefix = f"{where}: " if where else ""
    for place, d in (("in config section 'fit'", section), ("among the fit settings", overrides)):
        unknown = set(d) - FIT_SECTION_KEYS - set(RENAMED_KEYS)
        if unknown:
            raise FitError(f"{prefix if d is section else ''}unknown key(s) {sorted(unknown)} {place}; "
                           f"known: {sorted(FIT_SECTION_KEYS)}")
        both = [k for k in RENAMED_KEYS if k in d and RENAMED_KEYS[k] in d]
        if both:
            raise FitError(f"{prefix if d is section else ''}{both[0]} is the old name of {RENAMED_KEYS[both[0]]}; "
                           f"give only {RENAMED_KEYS[both[0]]}")
    key = lambda k: RENAMED_KEYS.get(k, k)  # noqa: E731  (checked under today's name, reported under the user's)
    section = {k: coerce_setting(key(k), v) for k, v in section.items()}
    overrides = {k: coerce_setting(key(k), v) for k, v in overrides.items()}
    for k, v in section.items():
        check_setting(key(k), v, f"{prefix}fit.{k}")
    for k, v in overrides.items():
        check_setting(key(k), v, k)
    section = {key(k): v for k, v in section.items()}
    overrides = {key(k): v for k, v in overrides.items()}
    merged = {**section, **overrides}
    for key in ("free", "per_observation"):
        v = merged.get(key)
        if isinstance(v, str):
            merged[key] = [s.strip() for s in v.split(",") if s.strip()]
        elif isinstance(v, tuple):
            merged[key] = list(v)
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
    if s.sigma_reference is not None and (not isinstance(s.sigma_reference, (list, tuple)) or len(s.sigma_reference) != 5
                                          or not all(isinstance(v, int) and v >= 2 for v in s.sigma_reference)):
        raise FitError(f"fit.sigma_reference must be [R, MU, MU_S, NU, ORDERS], integers >= 2, got {s.sigma_reference!r}")
    if s.sigma_reference_axis not in ("window", "whole"):
        raise FitError(f"fit.sigma_reference_axis must be window or whole, got {s.sigma_reference_axis!r}")
    if s.dtype not in DTYPES:
        raise FitError(f"dtype must be float32 or float64, got {s.dtype!r}")
    check_ray_rule(s.ray_rule, "fit.ray_rule")
    s.density_directions = list(check_density_directions(s.density_directions, "fit.density_directions"))
    return s


def make_model(s: FitSettings) -> SkyModel:
    """The renderer of a fit's settings (integrator spec, view integral, multiple scattering)."""
    return SkyModel(integrator_from_spec(s.integrator), orders=s.orders, view_samples=s.view_samples, rule=s.rule,
                    multiple=s.multiple, lut_size=s.lut_size, lut_directions=s.lut_directions,
                    lut_samples=s.lut_samples, table_sizes=s.table_sizes, ray_rule=s.ray_rule,
                    density_directions=tuple(s.density_directions))


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


def load_data(data: Sequence[str | Path], s: FitSettings, kider_site: dict | None = None,
              max_samples: int | None = None) -> list[Observation]:
    """Observations of DATA paths (.exr files, Kider capture folders, folders of either) with the settings' masks."""
    obs = []
    for kind, p in expand_data_paths(data):
        if kind == "exr":
            obs.append(observation_from_exr(
                p, sigma_relative=s.sigma_relative, min_elevation_deg=s.min_elevation_deg, sun_disc_deg=s.sun_mask_deg,
                saturation=s.saturation, max_samples=max_samples, dtype=s.torch_dtype))
        else:
            o = observation_from_kider(p, bin_nm=s.bin_nm, per_sample_sun=s.per_sample_sun, dtype=s.torch_dtype,
                                       **(kider_site or {}))
            obs.append(o if s.spectral_noise is None else with_noise_model(o, *s.spectral_noise))
    return obs


def model_wavelengths(observations: Sequence[Observation], wavelengths: str | None) -> np.ndarray:
    """The grid the atmosphere is built on: every spectral channel, plus a grid for RGB data [nm]."""
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


def atmosphere_config(config: dict) -> dict:
    """The config without its run sections (``fit``, ``sample``): what the atmosphere loader reads."""
    return {k: v for k, v in copy.deepcopy(config).items() if k not in RUN_SECTIONS}


def base_atmosphere(config: dict, lam: np.ndarray, observations: Sequence[Observation], dtype,
                    device="cpu") -> tuple[Atmosphere, float]:
    """Base atmosphere from the config (without its ``fit`` and ``sample`` sections) and its Earth-Sun distance [AU]."""
    cfg = atmosphere_config(config)
    sun = cfg.setdefault("sun", {}) or {}
    cfg["sun"] = sun
    bands = {o.band_nm for o in observations if o.kind == "spectral" and o.band_nm is not None}
    if "bandwidth_nm" not in sun and len(bands) == 1:
        sun["bandwidth_nm"] = bands.pop()  # the data's band average, on the solar spectrum too
    atm = atmosphere_from_config(cfg, lam, dtype=dtype, device=device)
    return atm, float(sun.get("distance_au", 1.0))


def default_free(observations: Sequence[Observation]) -> list[str]:
    """:data:`DEFAULT_FREE`, plus ``sun_azimuth_offset`` for scanner data (rings of samples)."""
    return list(DEFAULT_FREE) + (["sun_azimuth_offset"] if any("ring" in o.metadata for o in observations) else [])


def effective_per_observation(per: Sequence[str] | None) -> list[str]:
    """The per-observation nuisance names: ``per`` when given, else every nuisance but the noise scale."""
    return list(per) if per is not None else [n for n in NUISANCE if n != "noise_scale"]


def initial_values(s: FitSettings, observations: Sequence[Observation], free: Sequence[str],
                   per: Sequence[str] | None) -> dict:
    """``s.initial``, plus the scanner's ring-symmetry guess for a free ``sun_azimuth_offset``."""
    init = dict(s.initial)
    if "sun_azimuth_offset" in free and "sun_azimuth_offset" not in init:
        guesses = [o.metadata.get("azimuth_offset_guess_rad", 0.0) for o in observations]
        if any(guesses):
            init["sun_azimuth_offset"] = guesses if "sun_azimuth_offset" in effective_per_observation(per) \
                else float(np.mean(guesses))
    return init


def resolve_accuracy(s: FitSettings, observations: Sequence[Observation]) -> tuple[FitSettings, SkyModel]:
    """``s.accuracy`` -> settings with the automatic renderer fields, and their model (skyfit.render.auto)."""
    try:
        over, _ = fit_overrides(s.accuracy, observations, orders=s.orders, dtype=s.dtype)
    except ValueError as e:
        raise FitError(f"accuracy {s.accuracy!r}: {e}") from None
    s = dataclasses.replace(s, **over)
    return s, make_model(s)


@dataclasses.dataclass
class Prepared:
    """Everything of a fit but the free set: settings, loss, renderer, observations and the base atmosphere.

    Attributes:
        settings: the merged settings (renderer fields resolved when ``accuracy`` was set).
        loss, model: the loss and the renderer.
        observations: the data, in the settings' dtype.
        base: the config's atmosphere on the model wavelengths.
        base_dist: the config's Earth-Sun distance. [AU]
    """

    settings: FitSettings
    loss: Loss
    model: SkyModel
    observations: list[Observation]
    base: Atmosphere
    base_dist: float

    def problem(self, free: Sequence[str], per_observation: Sequence[str] | None = None,
                values: dict | None = None) -> FitProblem:
        """The fit problem with ``free`` parameters, starting at (or fixed to) ``values``."""
        param = Parameterisation(self.base, list(free), len(self.observations), per_observation, values or {})
        return FitProblem(param, self.model, self.observations, self.loss, base_sun_distance_au=self.base_dist)

    def estimate(self, *, evaluations: float = 1.0, batch: int = 1, autograd: bool = True, what: str = "fit") -> Estimate:
        """:func:`run_estimate` of this problem's renderer, data and atmosphere."""
        return run_estimate(self.model, self.observations, self.base, evaluations=evaluations, batch=batch,
                            autograd=autograd, what=what)

    def fit_problem(self) -> FitProblem:
        """The problem of the settings' own free set (:func:`default_free` when unset) and initial values."""
        s = self.settings
        free = list(s.free) if s.free is not None else default_free(self.observations)
        return self.problem(free, s.per_observation, initial_values(s, self.observations, free, s.per_observation))


def run_estimate(model: SkyModel, observations: Sequence[Observation], base: Atmosphere, *, evaluations: float = 1.0,
                 batch: int = 1, autograd: bool = True, what: str = "fit") -> Estimate:
    """Memory and time of ``evaluations`` loss evaluations of ``model`` on ``observations``, each of ``batch``
    parameter vectors at once (the sampler's half ensemble), differentiated when ``autograd`` (skyfit.resources)."""
    m = model
    rays = float(sum(o.n_samples for o in observations)) * batch
    n_w = int(base.wavelengths.numel())
    nbytes = torch.finfo(base.dtype).bits // 8
    device = str(base.device)
    est = single_scattering_estimate(rays, n_w, m.view_samples, m.integrator.settings(), dtype_bytes=nbytes,
                                     evaluations=evaluations, autograd=autograd, device=device, what=what)
    if m.orders > 1 and m.multiple in ("bruneton", "bruneton_lagged"):
        shape = tuple(m.table_sizes or m.REDUCED_TABLES)[4:]
        t = tables_estimate(shape, n_w, m.orders, dtype_bytes=nbytes, device=device)
        grow = AUTOGRAD if autograd and not m.lagged else 1.0
        if m.lagged:  # a few builds per fit (lagged_fit's refreshes), not one per evaluation
            evaluations = min(evaluations, 6.0)
        est = Estimate(what, max(est.memory_bytes, t.memory_bytes * grow * batch),
                       est.seconds + t.seconds * grow * batch * evaluations, f"{est.detail}; tables {t.detail}")
    elif m.orders > 1:  # Hillaire's LUT: directions x steps for each texel, per evaluation
        texels = float(m.lut_size[0] * m.lut_size[1] * m.lut_directions) * batch
        lut = single_scattering_estimate(texels, n_w, m.lut_samples, None, dtype_bytes=nbytes, evaluations=evaluations,
                                         autograd=autograd, device=device)
        est = Estimate(what, est.memory_bytes + lut.memory_bytes - BASE_MEMORY_BYTES, est.seconds + lut.seconds,
                       f"{est.detail}; LUT {m.lut_size[0]}x{m.lut_size[1]}x{m.lut_directions} directions")
    return est


def prepare(data: Sequence[str | Path | Observation], config: dict, s: FitSettings, *, kider_site: dict | None = None,
            model: SkyModel | None = None, orders: int | None = None, device="cpu") -> Prepared:
    """Settings + DATA + config -> :class:`Prepared` (loss and renderer are built before the data is read).

    Args:
        data: DATA paths (:func:`load_data`) or observations already in memory.
        config: the atmosphere config dict (its ``fit``/``sample`` sections are ignored here).
        s: the settings (:func:`fit_settings`).
        kider_site: latitude / longitude / elevation / utc_offset_hours for Kider folders.
        model: a renderer to use instead of the settings' (``evaluate``: the fit's); ``accuracy`` is then not resolved.
        orders: force the scattering orders (``fit --select`` starts from single scattering).
        device: where the observations and the atmosphere live.
    """
    if not isinstance(config, dict):
        raise FitError("config must be a mapping")
    loss = make_loss(s.loss)
    given_model = model is not None
    model = model if given_model else make_model(s)
    in_memory = len(data) > 0 and all(isinstance(d, Observation) for d in data)
    observations = list(data) if in_memory else load_data(data, s, kider_site, s.max_samples)
    observations = [o if o.values.dtype == s.torch_dtype and o.values.device == torch.device(device)
                    else o.to(dtype=s.torch_dtype, device=device) for o in observations]
    if s.accuracy and not given_model:  # the cheapest measured renderer setting meeting it, for these scenes
        s, model = resolve_accuracy(s, observations)
    if orders is not None:
        model = dataclasses.replace(model, orders=orders)
    lam = model_wavelengths(observations, s.wavelengths)
    base, base_dist = base_atmosphere(config, lam, observations, s.torch_dtype, device)
    return Prepared(s, loss, model, observations, base, base_dist)
