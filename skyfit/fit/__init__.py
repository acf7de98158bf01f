"""Fitting an atmosphere to measured skies: parameters -> forward model -> loss -> optimiser.

Data flow (docs/fitting.md)::

    data.py        Observation: directions, sun, values (N, C), sigma, mask  (EXR fisheye, Kider capture)
    parameters.py  Parameterisation: unconstrained x <-> physical values -> Atmosphere
    model.py       SkyModel (renderer settings; orders > 1 plug in at SkyModel.renderer), FitProblem
    losses.py      Loss (linear / log / relative residual; squared / Huber / Cauchy), masks
    optimise.py    fit(): Adam warm start, L-BFGS (strong Wolfe), multi-start
    result.py      RESULT.json, evaluate, plots
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
