"""Fit results in one place: the RESULT.json dict (CONTRACT.md), its reader and writer, and result -> model.

``skyfit fit`` writes what :func:`result_dict` builds; ``evaluate``, ``export-lut``,
``sample --init``, the demo and :func:`skyfit.load_result` read it back with
:func:`read_result` and rebuild the renderer (:func:`model_from_result`) and the
fitted atmosphere (:func:`atmosphere_from_result`) from it.
"""
from __future__ import annotations

import json
import math
import time
from pathlib import Path

import numpy as np
import torch

from ..atmosphere import Atmosphere
from ..transmittance import integrator_from_spec
from .budget import CLUSTERS, DISCREPANCY_DEFAULT, ReferenceModel, uncertainty
from .model import FitProblem, SkyModel, aerosol_log_depth
from .optimise import FitOptions, OptimiseResult
from .parameters import PARAMETERS, FitError, Parameterisation, inside_bounds
from .problem import RUN_SECTIONS, base_atmosphere
from .report import dumps, plot_all, write_text_atomic

RESULT_VERSION = 1
REQUIRED_RESULT_KEYS = ("parameters", "free", "integrator", "config", "model")


HILLAIRE_HAZE_AOD = 0.15
"""A fit whose model takes orders >= 2 from Hillaire's LUT (isotropic from the second order on) and whose fitted aerosol
optical depth at 550 nm reaches this gets a note in RESULT.json's ``notes``: against converged orders (the error
budget's reference, Gauss-Legendre view rays since session 19), Hillaire 32 x 12 on a 1.2 km HG aerosol (g 0.76, sun
at 30 deg, 550 nm, 5-90 deg elevation) is 2.9 % RMS off at AOD 0.03, 4.4 % at 0.1, 5.9 % at 0.2, 8.7 % at 0.3 and
16 % at 0.5 (docs/hillaire.md, "Hazy skies"). The note points to ``laplace.sigma`` and says what it is worth: on ten
hazy synthetic skies the total sigma with the phase term covered 0.60 / 0.86 at 68 / 95 %, the corrected estimate
0.49 / 0.70 (docs/uncertainty.md, "The hazy draw again"; until session 20 the note sent users to the corrected
values). It no longer sends the fit to ``--multiple bruneton_lagged``, whose factor a non-photo fit holds
between refreshes instead of following it in the aerosol: on four hazy synthetic skies that fit ended at 2.3-4.2x
Hillaire's loss with g 0.02-0.14 low and the ground albedo on its bound (docs/hillaire.md). [1]"""


def model_notes(problem: FitProblem, x: torch.Tensor) -> list[str]:
    """What the fitted values say about the fit's own model: a hazy sky fitted with Hillaire's multiple scattering
    (:data:`HILLAIRE_HAZE_AOD`); [] otherwise."""
    m = problem.model
    if m.orders < 2 or m.multiple != "hillaire":
        return []
    with torch.no_grad():
        atm = problem.param.atmosphere(problem.param.to_physical(x))
        log_depth = aerosol_log_depth(atm).reshape(-1).cpu().numpy()
        lam = atm.wavelengths.reshape(-1).cpu().numpy()
    aod = float(np.exp(np.interp(math.log(550.0), np.log(lam), log_depth)))  # log-log, held at the ends
    if not aod >= HILLAIRE_HAZE_AOD:
        return []
    return [f"the fitted aerosol optical depth is {aod:.3g} at 550 nm, a hazy sky, and the fit's multiple scattering is "
            "Hillaire's (isotropic from the second order on): 6-16 % RMS from converged orders at AOD 0.2-0.5 "
            "(docs/hillaire.md), which biases this fit; --laplace's total sigma (laplace.sigma) widens for it, but on "
            "synthetic hazy skies no error bar covered the truth as often as it says, and the corrected values "
            "(laplace.corrected) less often still (docs/uncertainty.md, \"The hazy draw again\")"]


def result_dict(problem: FitProblem, res: OptimiseResult, *, command: str, settings: dict, config: dict,
                config_source: str, base_dist: float, dtype: str, seconds: float, laplace: bool = False,
                extra: dict | None = None) -> dict:
    """RESULT.json's content for a finished fit (CONTRACT.md), with the Laplace covariance when asked: its
    ``sigma`` is the total of noise, numerical model error and discrepancy (of the model
    ``settings["sigma_discrepancy"]``) unless ``settings["sigma"]`` is ``"noise"`` (:func:`skyfit.fit.budget.uncertainty`)."""
    param, model = problem.param, problem.model
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
        "metrics": problem.metrics(res.x),
        "data": [o.summary() for o in problem.observations],
        "notes": model_notes(problem, res.x),
        "convergence": {**res.convergence, "starts": res.starts},
        **(extra or {}),
        "settings": settings,
        "config": {k: v for k, v in config.items() if k not in RUN_SECTIONS},
        "config_source": config_source,
        "seconds": seconds,
    }
    if laplace:
        ref = (settings or {}).get("sigma_reference")
        st = settings or {}
        window = (st.get("sigma_reference_axis") or "window") == "window"
        sizes = {} if ref is None else {"tables": tuple(ref[:4]), "orders": int(ref[4])}
        result["laplace"] = uncertainty(problem, res.x, sigma=st.get("sigma") or "total",
                                        reference=None if ref is None and window else ReferenceModel.of(
                                            problem.model, sun_window=window, **sizes),
                                        refits=int(st.get("sigma_refits", 0) or 0),
                                        polish=int(st.get("sigma_polish", 0) or 0),
                                        options=FitOptions(starts=1, adam_steps=0, max_iter=int(st.get("max_iter", 100))),
                                        discrepancy=st.get("sigma_discrepancy") or DISCREPANCY_DEFAULT,
                                        clusters=int(st.get("sigma_clusters") or CLUSTERS),
                                        expand=bool(st.get("sigma_phase", True)))
    return result


def write_result(problem: FitProblem, res: OptimiseResult, out: Path, *, command: str, settings: dict, config: dict,
                 config_source: str, base_dist: float, dtype: str, t0: float, laplace: bool, plots: bool,
                 extra: dict | None = None) -> dict:
    """RESULT.json of a finished fit written atomically to ``out`` (plots beside it when asked); the dict."""
    out = Path(out)
    result = result_dict(problem, res, command=command, settings=settings, config=config, config_source=config_source,
                         base_dist=base_dist, dtype=dtype, seconds=time.perf_counter() - t0, laplace=laplace, extra=extra)
    if plots:
        with torch.no_grad():
            preds = problem.predict(res.x)
        result["plots"] = plot_all(problem.observations, preds, out.parent, out.stem)
    result["seconds"] = time.perf_counter() - t0
    save_result(result, out)
    return result


def check_result_path(out: str | Path) -> Path:
    """``out`` as a Path; FitError unless it names a .json file."""
    out = Path(out)
    if out.suffix.lower() != ".json":
        raise FitError(f"--out must name a .json file, got {out}")
    return out


def save_result(result: dict, out: str | Path) -> None:
    """Write a result dict as RESULT.json, atomically (strict JSON: NaN becomes null)."""
    write_text_atomic(Path(out), dumps(result))


def check_result(res, where: str) -> dict:
    """``res`` when it is a skyfit fit result dict; FitError naming ``where`` otherwise."""
    if not isinstance(res, dict):
        raise FitError(f"{where}: a RESULT.json must hold a JSON object")
    version = res.get("skyfit_result", RESULT_VERSION)  # absent: written before the key existed
    if version != RESULT_VERSION:
        raise FitError(f"{where}: RESULT.json format version {version!r}; this skyfit reads version {RESULT_VERSION}")
    missing = [k for k in REQUIRED_RESULT_KEYS if k not in res]
    if missing:
        raise FitError(f"{where}: not a skyfit fit result (missing {', '.join(missing)})")
    if not isinstance(res["parameters"], dict) or not isinstance(res["config"], dict) or not isinstance(res["model"], dict):
        raise FitError(f"{where}: malformed result (parameters, config and model must be objects)")
    unknown = [k for k in res["parameters"] if k not in PARAMETERS]
    if unknown:
        raise FitError(f"{where}: unknown parameter(s) {unknown}")
    for key in ("free", "per_observation"):
        names = res.get(key, [])
        if not isinstance(names, list) or not all(isinstance(n, str) for n in names):
            raise FitError(f"{where}: {key} must be a list of parameter names, got {names!r}")
        bad = [n for n in names if n not in PARAMETERS]
        if bad:
            raise FitError(f"{where}: unknown parameter(s) {bad} in {key}")
    used = set(res.get("free", [])) | set(((res.get("settings") or {}) if isinstance(res.get("settings"), dict) else {})
                                          .get("initial", None) or {})
    for name, value in res["parameters"].items():
        _check_result_value(name, value, name in used, where)
    return res


def _check_result_value(name: str, value, used: bool, where: str) -> None:
    """FitError naming ``where`` and the parameter unless ``value`` is a finite number (a list for a
    per-observation one) in the parameter's physical range; the fit's open range when it is ``used``
    (free or set in fit.initial), as the fit itself requires."""
    spec = PARAMETERS[name]
    vals = value if isinstance(value, list) and spec.nuisance else [value]
    unit = "" if spec.unit == "1" else f" {spec.unit}"
    for v in vals:
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            shown = "null (NaN)" if v is None else repr(v)
            raise FitError(f"{where}: parameter {name} must be a number, got {shown}")
        if not math.isfinite(v):
            raise FitError(f"{where}: parameter {name} must be finite, got {v}")
        if spec.transform == "log":
            ok, rng = (v > 0, f"> 0{unit}") if spec.nuisance else (v >= 0, f">= 0{unit}")
        elif spec.transform == "loginterval":
            ok, rng = v > 0, f"> 0{unit}"
        elif spec.transform == "interval":
            ok, rng = spec.lo <= v <= spec.hi, f"in [{spec.lo:g}, {spec.hi:g}]{unit}"
        else:
            ok, rng = True, ""
        if not ok:
            raise FitError(f"{where}: parameter {name} = {v:g}{unit} is out of range (must be {rng})")
        if used and name != "ground_albedo_scale":  # its upper bound depends on the config's albedo
            try:
                spec.inverse(float(v))
            except FitError as e:
                raise FitError(f"{where}: parameter {e}") from None


def read_result(path: str | Path) -> dict:
    """A RESULT.json written by ``skyfit fit`` (or :meth:`skyfit.FitResult.save`); FitError naming the file otherwise."""
    p = Path(path)
    if p.is_dir():
        raise FitError(f"{p} is a folder, not a RESULT.json file")
    if not p.is_file():
        raise FitError(f"result file not found: {p}")
    try:
        res = json.loads(p.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise FitError(f"{p}: not a readable JSON result ({type(e).__name__}: {e})".splitlines()[0]) from None
    return check_result(res, str(p))


def model_from_result(res: dict) -> SkyModel:
    """The SkyModel a RESULT.json was fitted with (its ``integrator`` and ``model`` entries)."""
    m = res["model"]  # SkyModel.settings() wrote the multiple-scattering fields only for orders > 1
    kw = {k: m[k] for k in ("multiple", "lut_size", "lut_directions", "lut_samples", "table_sizes", "ray_rule",
                            "density_directions") if m.get(k) is not None}  # SkyModel makes the lists tuples
    return SkyModel(integrator_from_spec(res["integrator"]), orders=int(m.get("orders", 1)),
                    view_samples=int(m.get("view_samples", 32)), rule=m.get("rule", "trapezoid"),
                    ground=bool(m.get("ground", True)), **kw)


def fitted_atmosphere_values(res: dict) -> dict:
    """The atmosphere parameters a result moved away from its config: those fitted or set in ``fit.initial``."""
    fitted = set(res.get("free", [])) | set((res.get("settings") or {}).get("initial", {}) or {})
    # a value a fit left on a bound moves just inside it (inside_bounds), so that the result rebuilds
    return {n: inside_bounds(n, v) for n, v in res["parameters"].items() if not PARAMETERS[n].nuisance and n in fitted}


def atmosphere_from_result(res: dict, wavelengths_nm=None, dtype=torch.float64, device="cpu") -> Atmosphere:
    """The fitted atmosphere of a RESULT dict (from :func:`read_result`), on ``wavelengths_nm`` [nm]
    (default: the fit's model wavelengths).

    As ``skyfit evaluate`` rebuilds it: the result's config, moved only in the parameters that
    were fitted or set in ``fit.initial`` (nuisance parameters ignored).
    """
    lam = np.asarray(res["model"]["wavelengths_nm"] if wavelengths_nm is None else wavelengths_nm, float)
    base, _ = base_atmosphere(res["config"], lam, [], dtype, device)
    param = Parameterisation(base, [], 1, None, fitted_atmosphere_values(res))
    with torch.no_grad():
        return param.atmosphere(param.to_physical(param.initial_vector(dtype, device)))
