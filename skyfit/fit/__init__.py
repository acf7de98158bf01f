"""Fitting an atmosphere to measured skies: parameters -> forward model -> loss -> optimiser / sampler.

Data flow (docs/fitting.md, docs/architecture.md)::

    data.py        Observation: directions, sun, values (N, C), sigma, mask  (EXR fisheye, Kider capture, arrays)
    parameters.py  the parameter table (range, unit, transform, default prior); Parameterisation: x <-> values
    model.py       SkyModel (renderer settings; orders > 1 plug in at SkyModel.renderer), FitProblem
    losses.py      Loss (linear / log / relative residual; squared / Huber / Cauchy), masks
    optimise.py    fit(): Adam warm start, L-BFGS (strong Wolfe), multi-start -> OptimiseResult
    problem.py     FitSettings and the one fit-problem builder (prepare -> Prepared.problem)
    results.py     RESULT.json: result_dict, write/read, result -> renderer and atmosphere
    run.py         skyfit fit / evaluate on files;  select.py  the model ladder (fit --select)
    laplace.py     Hessian covariance;  priors.py, posterior.py, chain.py, diagnostics.py,
                   sample_plots.py, sample.py, batched.py: skyfit sample (emcee)
    report.py      JSON and plots of fits
"""
from .data import DataError, Observation, expand_data_paths, load_observations, observation_from_exr, observation_from_kider
from .losses import LOSS_PRESETS, Loss, horizon_mask, make_loss, rho_cauchy, rho_huber, rho_squared, saturation_mask, sun_disc_mask
from .model import FitProblem, SkyModel, channel_matrix, observation_metrics
from .optimise import FitOptions, OptimiseResult, fit
from .parameters import (
    ATMOSPHERE_PARAMETERS,
    DEFAULT_PER_OBSERVATION,
    NUISANCE,
    PARAMETERS,
    FitError,
    Parameterisation,
    ParameterSpec,
)

__all__ = [
    "ATMOSPHERE_PARAMETERS",
    "DEFAULT_PER_OBSERVATION",
    "DataError",
    "FitError",
    "FitOptions",
    "FitProblem",
    "OptimiseResult",
    "LOSS_PRESETS",
    "Loss",
    "NUISANCE",
    "Observation",
    "PARAMETERS",
    "ParameterSpec",
    "Parameterisation",
    "SkyModel",
    "channel_matrix",
    "expand_data_paths",
    "fit",
    "horizon_mask",
    "load_observations",
    "make_loss",
    "observation_from_exr",
    "observation_from_kider",
    "observation_metrics",
    "rho_cauchy",
    "rho_huber",
    "rho_squared",
    "saturation_mask",
    "sun_disc_mask",
]
