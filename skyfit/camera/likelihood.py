"""Photos against a model: the censored (Tobit) likelihood and the unknown exposure scale.

:func:`censored_gaussian_nll` scores a model against photo data whose pixels at the ends of the
code range are censored (Gaussian density for measured pixels, Gaussian tail probability for
censored ones); :func:`fit_exposure_scale` is the closed-form scale k with observed ~= k * model
(the exposure of an LDR photo is unknown). Both take plain tensors, e.g. the fields of a
:class:`skyfit.camera.photo_io.PhotoObservation`.
"""
from __future__ import annotations

import math

import torch
from torch import Tensor

def censored_gaussian_nll(
    model: Tensor,
    observed: Tensor,
    sigma: Tensor | float,
    censored_high: Tensor | None = None,
    censored_low: Tensor | None = None,
    *,
    clip_high: Tensor | float | None = None,
    clip_low: Tensor | float | None = None,
    mask: Tensor | None = None,
    reduction: str = "sum",
) -> Tensor:
    """Negative log-likelihood of data with Gaussian noise, censored at both ends (Tobit).

    Per element, with ``z = (observed - model) / sigma``:

    * measured: ``0.5 z^2 + log(sigma) + 0.5 log(2 pi)``;
    * censored high (true value + noise >= clip_high):
      ``-log(1 - Phi((clip_high - model)/sigma)) = -log_ndtr((model - clip_high)/sigma)``;
    * censored low (true value + noise <= clip_low): ``-log_ndtr((clip_low - model)/sigma)``.

    ``torch.special.log_ndtr`` is finite and smooth for any finite argument
    (about ``-x^2/2`` deep in the tail), so a clipped pixel whose model lies far
    below the clip still pulls it up with a finite gradient.

    Args:
        model: predicted values, shape (...). [data units]
        observed: measured values, broadcastable to ``model``. [data units]
        sigma: noise standard deviation, > 0, broadcastable. [data units]
        censored_high, censored_low: bool masks, broadcastable; not both at once.
        clip_high, clip_low: clip levels, broadcastable; default: ``observed``
            (a clipped value is the clip level). [data units]
        mask: bool, broadcastable; False elements contribute 0.
        reduction: ``'sum'``, ``'mean'`` (over the elements in ``mask``) or ``'none'``.

    Returns:
        Shape () for 'sum'/'mean', the broadcast shape for 'none'. [nat]
    """
    if reduction not in ("sum", "mean", "none"):
        raise ValueError(f"unknown reduction {reduction!r}; valid: sum, mean, none")
    sigma = torch.as_tensor(sigma, dtype=model.dtype, device=model.device)
    if not bool(torch.all(sigma > 0)):
        raise ValueError("censored_gaussian_nll: sigma must be > 0 everywhere")
    observed = torch.as_tensor(observed, dtype=model.dtype, device=model.device)
    z = (observed - model) / sigma
    nll = 0.5 * z**2 + torch.log(sigma) + 0.5 * math.log(2 * math.pi)
    if censored_high is not None and censored_low is not None and bool(torch.any(censored_high & censored_low)):
        raise ValueError("censored_gaussian_nll: an element is censored both high and low")
    if censored_high is not None:
        c = observed if clip_high is None else torch.as_tensor(clip_high, dtype=model.dtype, device=model.device)
        nll = torch.where(censored_high, -torch.special.log_ndtr((model - c) / sigma), nll)
    if censored_low is not None:
        c = observed if clip_low is None else torch.as_tensor(clip_low, dtype=model.dtype, device=model.device)
        nll = torch.where(censored_low, -torch.special.log_ndtr((c - model) / sigma), nll)
    if mask is not None:
        mask = torch.broadcast_to(mask, nll.shape)
        nll = torch.where(mask, nll, torch.zeros_like(nll))
    if reduction == "none":
        return nll
    if reduction == "sum":
        return nll.sum()
    n = nll.numel() if mask is None else int(mask.sum())
    return nll.sum() / max(n, 1)


EXPOSURE_FIT_METHODS = ("linear", "log")


def fit_exposure_scale(
    model_rgb: Tensor,
    observed_rgb: Tensor,
    mask: Tensor | None = None,
    *,
    weights: Tensor | None = None,
    method: str = "linear",
) -> Tensor:
    """Closed-form scale k with ``observed ~= k * model``: the unknown exposure of a photo.

    * ``'linear'``: weighted least squares in linear space,
      ``k = sum(w m o) / sum(w m^2)``; the maximum-likelihood scale for
      additive Gaussian noise of variance ``1 / w`` (pass ``w = 1 / variance``),
      unbiased for zero-mean noise. Use it by default.
    * ``'log'``: least squares of ``log o - log m``,
      ``k = exp(sum(w (log o - log m)) / sum(w))``; the ML scale for
      multiplicative (log-normal) noise. With additive noise it is biased by
      about ``-var / (2 o^2)`` in log k; it needs positive values.

    Censored pixels must be left out through ``mask``. Differentiable in both inputs.

    Args:
        model_rgb: model values, shape (..., 3) or any shape. [model units]
        observed_rgb: observed values, same shape. [data units]
        mask: bool, broadcastable (e.g. (H, W, 1) or (H, W, 3)); True = use.
        weights: non-negative weights, broadcastable. [1/data units^2]
        method: ``'linear'`` or ``'log'``.

    Returns:
        k, shape (). [data units / model units]
    """
    if method not in EXPOSURE_FIT_METHODS:
        raise ValueError(f"unknown exposure-fit method {method!r}; valid: {', '.join(EXPOSURE_FIT_METHODS)}")
    m, o = torch.broadcast_tensors(model_rgb, observed_rgb.to(model_rgb.dtype))
    w = torch.ones_like(m) if weights is None else torch.broadcast_to(weights.to(m.dtype), m.shape)
    if mask is not None:
        w = torch.where(torch.broadcast_to(mask, m.shape), w, torch.zeros_like(w))
    if method == "linear":
        den = (w * m * m).sum()
        if not bool(den > 0):
            raise ValueError("fit_exposure_scale: no pixel with weight > 0 and model != 0 in the mask")
        return (w * m * o).sum() / den
    used = w > 0
    if not bool(used.any()):
        raise ValueError("fit_exposure_scale: empty mask")
    if not bool(torch.all((m[used] > 0) & (o[used] > 0))):
        raise ValueError("fit_exposure_scale(method='log'): model and observed must be > 0 in the mask (mask out censored-low pixels)")
    one = torch.ones_like(m)
    d = torch.log(torch.where(used, o, one)) - torch.log(torch.where(used, m, one))
    return torch.exp((w * d).sum() / w.sum())



__all__ = ["EXPOSURE_FIT_METHODS", "censored_gaussian_nll", "fit_exposure_scale"]
