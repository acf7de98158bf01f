"""``skyfit fit`` and ``skyfit evaluate`` as plain functions (the CLI parses flags and reads the config).

Settings come from, in order of precedence: command-line flags, the config's
``fit:`` section, the defaults of :class:`FitSettings`. RESULT.json embeds the
atmosphere config and the model settings, so ``evaluate`` needs only it and DATA.
"""
from __future__ import annotations

import dataclasses
import time
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from .optimise import FitOptions, fit
from .data import Observation
from .parameters import NUISANCE, ORIENTATION, PARAMETERS, FitError, check_names, inside_bounds
from .losses import make_loss
from .problem import fit_settings, load_data, prepare
from .results import check_result_path, fitted_atmosphere_values, model_from_result, read_result, write_result
from .select import run_select
from ..resources import MAX_RUN_SECONDS, check


def run_fit(data: Sequence[str | Path], config: dict, out: str | Path, *, overrides: dict | None = None,
            config_source: str = "", kider_site: dict | None = None, plots: bool = True, progress: bool = False,
            laplace: bool = False, select: bool = False, device="cpu", force: bool = False) -> dict:
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
        device: where the fit runs (cpu, cuda, cuda:N; the observations and the atmosphere go there).
        select: choose the model by the ladder of :mod:`skyfit.fit.select` (docs/selection.md);
            RESULT.json then holds the chosen model and ``selection``.
        force: run even when the memory or time estimate says no (skyfit.resources).
    """
    t0 = time.perf_counter()
    out = check_result_path(out)
    if not isinstance(config, dict):
        raise FitError(f"config {config_source}: must be a mapping")
    if select:  # the model ladder (skyfit.fit.select) chooses the atmosphere's components
        return run_select(data, config, out, overrides=overrides, config_source=config_source, kider_site=kider_site,
                          plots=plots, progress=progress, laplace=laplace, device=device)
    prep = prepare(data, config, fit_settings(config.get("fit"), overrides, where=f"config {config_source}"),
                   kider_site=kider_site, device=device)
    problem = prep.fit_problem()
    s = prep.settings
    check(prep.estimate(evaluations=s.starts * (s.adam_steps + 2 * s.max_iter)), force=force, max_seconds=MAX_RUN_SECONDS,
          device=str(device), hint="reduce --max-samples, --view-samples, the --integrator's samples, --starts, --max-iter or --adam-steps, "
               "or add --force")
    res = solve(problem, s.options(progress))
    return write_result(problem, res, out, command="fit", settings=dataclasses.asdict(s), config=config,
                        config_source=config_source, base_dist=prep.base_dist, dtype=s.dtype, t0=t0, laplace=laplace,
                        plots=plots)


def solve(problem, options: FitOptions):
    """The fit ``skyfit fit`` runs on a prepared problem: :func:`skyfit.fit.optimise.fit`, or for
    ``multiple: bruneton_lagged`` :func:`skyfit.fit.photo.lagged_fit` (Bruneton's orders >= 2 as a factor, frozen per
    fit and refreshed at its result)."""
    if problem.model.lagged:
        from .photo import LAGGED_REFRESHES, lagged_fit

        return lagged_fit(problem, options, LAGGED_REFRESHES, bruneton=problem.model.factor_model())
    return fit(problem, options)


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


def _nuisance_for(res: dict, obs: Observation, name: str):
    """A fitted nuisance value for ``obs``: its own if it was fitted, else the mean over the fit's observations."""
    v = inside_bounds(name, res["parameters"].get(name))
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
                 kider_site: dict | None = None, progress: bool = False, refit: Sequence[str] | None = None,
                 device="cpu", force: bool = False) -> dict:
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
        model = model_from_result(res)
        loss = res.get("loss", {}).get("name", "squared") if isinstance(res.get("loss"), dict) else "squared"
        s = dataclasses.replace(s, loss=loss)
        make_loss(loss)
    except (TypeError, KeyError, ValueError) as e:
        raise FitError(f"{result_path}: malformed result ({e})".splitlines()[0]) from None
    observations = load_data(data, s, kider_site, None)
    try:
        prep = prepare(observations, res["config"], s, model=model, device=device)
    except ValueError as e:
        raise FitError(f"{result_path}: its config cannot be rebuilt: {e}") from None
    check(prep.estimate(evaluations=1 + (10 + 2 * 60 if refit_nuisance else 0), autograd=refit_nuisance,
                        what=f"evaluate with the renderer of {result_path}"),
          force=force, max_seconds=MAX_RUN_SECONDS, device=str(device), hint="add --force to run it anyway")
    dtype = s.torch_dtype
    # The atmosphere moves away from the config only in the parameters that were fitted or set in fit.initial.
    atm_values = fitted_atmosphere_values(res)
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
    problem = prep.problem(free, per, {**atm_values, **nuis_values})
    param = problem.param
    conv = None
    x = param.initial_vector(dtype, prep.base.device)
    if problem.model.lagged:  # the factor at the fitted atmosphere (and the sun geometry it sees)
        from .photo import freeze_tables

        freeze_tables(problem, x, problem.model.factor_model())
    if refit_nuisance:
        r = fit(problem, FitOptions(starts=1, adam_steps=10, max_iter=60, progress=progress))
        x, conv = r.x, r.convergence
        if problem.model.lagged:
            freeze_tables(problem, x, problem.model.factor_model())
    metrics = problem.metrics(x)
    phys = param.physical_dict(x)
    return {
        "rmse": metrics["rmse"], "rmse_units": metrics["rmse_units"], "delta_e": metrics["delta_e"],
        "n_samples": metrics["n_samples"], "loss": metrics["loss"], "per_observation": metrics["per_observation"],
        "refit_nuisance": refit_nuisance, "refitted": free, "nuisance": {n: phys[n] for n in ("exposure", *ORIENTATION)},
        "convergence": conv, "result": str(result_path), "data": [o.summary() for o in observations],
    }
