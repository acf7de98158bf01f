"""Losses between a model and measured sky values, and the masks that choose what counts.

A loss is a *residual* and a *rho* (Hampel et al. 1986; Triggs et al. 2000, "Bundle
adjustment", Sec. 3.3)::

    loss = mean over used elements of  w * rho(r / s) + log s

with r, per element (sample x channel), one of

==============  ================================================  =======================================
residual        r                                                 use
==============  ================================================  =======================================
``linear``      (m - o) / sigma                                   weighted least squares on radiance
``log``         (log m - log o) / (sigma / o)                     multiplicative errors (delta method)
``relative``    (m - o) / o                                       every element's relative error alike
==============  ================================================  =======================================

and rho one of

==============  ================================================  =======================================
rho             rho(r)                                            influence
==============  ================================================  =======================================
``squared``     r^2 / 2                                           Gaussian likelihood
``huber``       r^2 / 2 if |r| <= d, else d (|r| - d / 2)         linear beyond d (Huber 1964)
``cauchy``      (c^2 / 2) log(1 + (r / c)^2)                      redescending (Cauchy / Lorentzian)
==============  ================================================  =======================================

Default tuning constants give 95 % efficiency at the Gaussian: d = 1.345, c = 2.3849
(Holland & Welsch 1977). ``s`` is the fitted ``noise_scale`` (1 when not fitted): with
``squared`` and ``linear`` the loss is then the Gaussian negative log-likelihood per
element up to a constant. ``w`` are optional per-element weights. The ``relative``
residual does not use sigma (masks and weights still apply).

Data and model are (N, C): C spectral channels [W/(m^2 sr nm)] or RGB (linear sRGB,
CONTRACT.md); the model side is projected to the data's channels before the loss
(:mod:`skyfit.fit.model`).
"""
from __future__ import annotations

import dataclasses
import math

import torch
from torch import Tensor

RESIDUALS = ("linear", "log", "relative")
RHOS = ("squared", "huber", "cauchy")
HUBER_DELTA: float = 1.345
"""Huber threshold for 95 % Gaussian efficiency [1]. Holland & Welsch 1977."""
CAUCHY_C: float = 2.3849
"""Cauchy scale for 95 % Gaussian efficiency [1]. Holland & Welsch 1977."""

LOSS_PRESETS: dict[str, tuple[str, str]] = {
    "squared": ("linear", "squared"),
    "log": ("log", "squared"),
    "relative": ("relative", "squared"),
    "huber": ("linear", "huber"),
    "cauchy": ("linear", "cauchy"),
}
"""``--loss`` names -> (residual, rho); ``NAME:residual=log,delta=2`` changes either."""


def rho_squared(r: Tensor) -> Tensor:
    """r^2 / 2."""
    return 0.5 * r * r


def rho_huber(r: Tensor, delta: float = HUBER_DELTA) -> Tensor:
    """Huber 1964: quadratic inside |r| <= delta, linear outside (continuous value and slope)."""
    a = r.abs()
    return torch.where(a <= delta, 0.5 * r * r, delta * (a - 0.5 * delta))


def rho_cauchy(r: Tensor, c: float = CAUCHY_C) -> Tensor:
    """(c^2 / 2) log(1 + (r / c)^2)."""
    return 0.5 * c * c * torch.log1p((r / c) ** 2)


@dataclasses.dataclass(frozen=True)
class Loss:
    """A residual and a rho (module docstring).

    Attributes:
        residual: one of RESIDUALS.
        rho: one of RHOS.
        delta: tuning constant of huber / cauchy in units of r (default 1.345 / 2.3849).
    """

    residual: str = "linear"
    rho: str = "squared"
    delta: float | None = None

    def __post_init__(self):
        if self.residual not in RESIDUALS:
            raise ValueError(f"unknown loss residual {self.residual!r}; valid: {', '.join(RESIDUALS)}")
        if self.rho not in RHOS:
            raise ValueError(f"unknown loss rho {self.rho!r}; valid: {', '.join(RHOS)}")
        if self.delta is not None and not (0 < self.delta < math.inf):
            raise ValueError(f"loss delta must be > 0, got {self.delta}")

    @property
    def name(self) -> str:
        for k, v in LOSS_PRESETS.items():
            if v == (self.residual, self.rho) and self.delta is None:
                return k
        return f"{self.rho}:residual={self.residual}" + ("" if self.delta is None else f",delta={self.delta:g}")

    def settings(self) -> dict:
        d = {"name": self.name, "residual": self.residual, "rho": self.rho}
        if self.rho != "squared":
            d["delta"] = self.delta if self.delta is not None else (HUBER_DELTA if self.rho == "huber" else CAUCHY_C)
        return d

    def residuals(self, model: Tensor, observed: Tensor, sigma: Tensor | None = None) -> Tensor:
        """r per element (module table); ``sigma`` None means 1 (linear) or sigma/o = 1 (log)."""
        if self.residual == "linear":
            d = model - observed
            return d if sigma is None else d / sigma
        if self.residual == "log":
            d = torch.log(model) - torch.log(observed)
            return d if sigma is None else d * observed / sigma
        return (model - observed) / observed

    def rho_fn(self, r: Tensor) -> Tensor:
        if self.rho == "squared":
            return rho_squared(r)
        if self.rho == "huber":
            return rho_huber(r, HUBER_DELTA if self.delta is None else self.delta)
        return rho_cauchy(r, CAUCHY_C if self.delta is None else self.delta)

    def elementwise(self, model: Tensor, observed: Tensor, sigma: Tensor | None = None, mask: Tensor | None = None,
                    noise_scale: Tensor | float = 1.0) -> tuple[Tensor, Tensor]:
        """(rho(r / s) + log s per element with 0 where masked, the bool mask broadcast to (N, C)).

        Masked elements are replaced by harmless values before any log or division, so
        that neither the value nor the gradient sees NaN from them.
        """
        model, observed = torch.broadcast_tensors(model, observed.to(model.dtype))
        use = torch.ones_like(model, dtype=torch.bool) if mask is None else _broadcast_mask(mask, model.shape)
        if sigma is not None:
            sigma = torch.broadcast_to(sigma.to(model.dtype), model.shape)
            use = use & (sigma > 0) & torch.isfinite(sigma)
        use = use & torch.isfinite(observed)
        if self.residual in ("log", "relative"):
            use = use & (observed > 0)
        one = torch.ones_like(model)
        o = torch.where(use, observed, one)
        m = torch.where(use, model, one)
        if self.residual == "log":
            # the model must be positive where used: it is a sky radiance; a zero means a bug
            m = torch.where(m > 0, m, one)
        s_ = None if sigma is None else torch.where(use, sigma, one)
        s = torch.as_tensor(noise_scale, dtype=model.dtype, device=model.device)
        val = self.rho_fn(self.residuals(m, o, s_) / s) + torch.log(s)
        return torch.where(use, val, torch.zeros_like(val)), use

    def __call__(self, model: Tensor, observed: Tensor, sigma: Tensor | None = None, mask: Tensor | None = None,
                 noise_scale: Tensor | float = 1.0, weights: Tensor | None = None, reduction: str = "mean") -> Tensor:
        """The loss of ``model`` against ``observed``.

        Args:
            model, observed: shape (N, C) (or any common shape). [data units]
            sigma: per-element noise standard deviation, broadcastable; elements with
                sigma <= 0 or non-finite are left out. [data units]
            mask: bool, (N,) or (N, C) or broadcastable; True = use.
            noise_scale: s, shape () (> 0). [1]
            weights: non-negative per-element weights, broadcastable. [1]
            reduction: ``'mean'`` (over used elements), ``'sum'`` or ``'none'``.

        Returns:
            shape () for mean/sum, (N, C) for none.
        """
        if reduction not in ("mean", "sum", "none"):
            raise ValueError(f"unknown reduction {reduction!r}; valid: mean, sum, none")
        val, use = self.elementwise(model, observed, sigma, mask, noise_scale)
        if weights is not None:
            val = val * torch.broadcast_to(weights.to(val.dtype), val.shape)
        if reduction == "none":
            return val
        if reduction == "sum":
            return val.sum()
        return val.sum() / use.sum().clamp_min(1)


def _broadcast_mask(mask: Tensor, shape) -> Tensor:
    mask = mask.to(torch.bool)
    if mask.ndim == len(shape) - 1 and mask.shape == tuple(shape[:-1]):
        mask = mask.unsqueeze(-1)
    return torch.broadcast_to(mask, shape)


def make_loss(spec: str | Loss) -> Loss:
    """``NAME`` from :data:`LOSS_PRESETS`, optionally ``NAME:residual=log,delta=2.0``."""
    if isinstance(spec, Loss):
        return spec
    name, _, opts = str(spec).partition(":")
    name = name.strip()
    if name not in LOSS_PRESETS:
        raise ValueError(f"unknown loss {name!r}; valid: {', '.join(LOSS_PRESETS)} (optionally NAME:residual=...,delta=...)")
    residual, rho = LOSS_PRESETS[name]
    delta = None
    for item in filter(None, (o.strip() for o in opts.split(","))):
        key, eq, val = item.partition("=")
        if not eq:
            raise ValueError(f"loss option must be key=value, got {item!r}")
        if key == "residual":
            residual = val
        elif key == "delta":
            try:
                delta = float(val)
            except ValueError:
                raise ValueError(f"loss delta must be a number, got {val!r}") from None
        else:
            raise ValueError(f"unknown loss option {key!r}; valid: residual, delta")
    return Loss(residual=residual, rho=rho, delta=delta)


# -- masks --------------------------------------------------------------------------
def horizon_mask(directions: Tensor, min_elevation_deg: float = 0.0) -> Tensor:
    """True for views above ``min_elevation_deg`` (elevation = 90° - zenith angle), shape (N,).

    Args:
        directions: unit ENU vectors, shape (N, 3). [1]
    """
    return directions[..., 2] > math.sin(math.radians(min_elevation_deg))


def sun_disc_mask(directions: Tensor, sun: Tensor, radius_deg: float) -> Tensor:
    """True for views more than ``radius_deg`` from the sun, shape (N,).

    Args:
        directions: unit ENU vectors, shape (N, 3). [1]
        sun: unit ENU vector(s), shape (3,) or (N, 3). [1]
        radius_deg: half-angle of the excluded disc; 0 excludes nothing. [deg]
    """
    if radius_deg <= 0:
        return torch.ones(directions.shape[:-1], dtype=torch.bool, device=directions.device)
    return (directions * sun.to(directions.dtype)).sum(-1) < math.cos(math.radians(radius_deg))


def saturation_mask(values: Tensor, level: float | None) -> Tensor:
    """True for samples whose every channel is below ``level`` (None: all True), shape (N,)."""
    if level is None:
        return torch.ones(values.shape[:-1], dtype=torch.bool, device=values.device)
    return (values < level).all(-1)
