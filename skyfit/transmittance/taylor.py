"""Gałaj et al. 2021 Taylor-expansion optical depth (Sec. IV.F, eqs. 13, 14, 17).

A ray at distance d from the planet centre is parametrised by the signed
distance t from its closest point P_o (Gałaj 2021 eq. 10), so that the
altitude is h(t) = sqrt(d^2 + t^2) - R (eq. 11). Replacing h by its
expansion of order 1 + a about tau_b(d) = t_min + b (t_max - t_min) gives
the closed form of eq. 17 for G(t) = int_{t_min}^{t} exp(-h/H), and eqs. 13/14
combine G at both ends of the segment into its column. No loop, no table.

Safeguards beyond the paper (documented in docs/accuracy.md):
  * h'(tau_b) vanishes only for rays that graze the top of the atmosphere
    (d -> R_top), where the column is ~0; it is floored at 1e-9.
  * Far from tau_b the expansion can make h~ negative, and for tiny H the
    closed form then grows without bound (horizon rays with the Mie layer:
    Gałaj's a = b = 0.45 were fitted on Earth's layers). The result is
    therefore capped by the exact bound L * exp(-h_low / H), with h_low the
    lowest altitude on the segment, and the exponent by 60, so values and
    gradients stay finite. Where the cap is active the method is out of its
    regime; docs/accuracy.md reports the error there.
"""
from __future__ import annotations

import torch
from torch import Tensor

from ..geometry import safe_sqrt
from .base import ColumnFn, OpticalDepthIntegrator

TAYLOR_A_DEFAULT: float = 0.45
"""Gałaj 2021, Sec. VI.A.2: grid search over {0, 0.01, ..., 1}^2 for Earth. [1]"""
TAYLOR_B_DEFAULT: float = 0.45
"""Gałaj 2021, Sec. VI.A.2. [1]"""

_EXP_CAP = 60.0


def taylor_column(r: Tensor, mu: Tensor, length: Tensor, scale_heights: Tensor, bottom_radius: float, top_radius: float, a: Tensor, b: Tensor) -> Tensor:
    """Column along a segment by Gałaj 2021 eq. 17 combined with eqs. 13/14.

    Args:
        r: start radius, shape (...). [m]
        mu: view cosine at the start, shape (...). [1]
        length: segment length, shape (...). [m]
        scale_heights: shape (K,). [m]
        a, b: hyperparameters in [0, 1], shape () (0.45, 0.45 in the paper) or (K,), one per layer. [1]

    Returns:
        Column, shape (..., K). [m]
    """
    # No broadcast up front: per-ray quantities keep the shape of (r, mu), so a view ray
    # sampled at N lengths computes its line parameters once, not N times. Each value is
    # computed with the same operations as the broadcast form: in the out-of-regime cases
    # (grazing rays, where eq. 17 cancels) a reordering would change the rounding visibly.
    r, mu, length = (x.unsqueeze(-1) for x in (r, mu, length))
    H = scale_heights
    R = bottom_radius
    # Line parameters (Gałaj 2021 Fig. 2-4): distance d of the line from the centre,
    # signed position t0 of the start relative to the closest point P_o.
    d2 = r * r * (1.0 - mu) * (1.0 + mu)
    d2 = torch.clamp_min(d2, 0.0)
    t0 = r * mu
    t1 = t0 + length
    t_min = safe_sqrt(R * R - d2)  # eq. 12: sqrt(r^2 - d^2) for d < r, else 0
    t_max = safe_sqrt(top_radius * top_radius - d2)
    t_max = torch.maximum(t_max, t_min)
    tau = t_min + b * (t_max - t_min)
    rho = safe_sqrt(d2 + tau * tau)  # sqrt(d^2 + tau^2) > 0 unless d = tau = 0
    rho = torch.clamp_min(rho, 1.0)
    h_tau = rho - R
    hp = torch.clamp_min(tau / rho, 1e-9)  # h'(tau)
    hpp = d2 / rho**3  # h''(tau)

    def h_tilde(t: Tensor) -> Tensor:
        dt = t - tau
        return 0.5 * a * hpp * dt * dt + hp * dt + h_tau

    exp_min = torch.exp(torch.clamp_max(-h_tilde(t_min) / H, _EXP_CAP))
    H_hp = H / hp

    def F(t: Tensor) -> Tensor:
        """Signed antiderivative about P_o: eqs. 13 (ends on both sides) and 14 (same side)
        are both F(t1) - F(t0) with F(t) = sign(t) G(|t|), and eq. 17 for t >= t_min reads
        G(t) = H / h'(tau) (exp(-h~(t_min)/H) - exp(-h~(t)/H))."""
        tt = torch.maximum(t.abs(), t_min)
        g = H_hp * (exp_min - torch.exp(torch.clamp_max(-h_tilde(tt) / H, _EXP_CAP)))
        return torch.where(t < 0, -g, g)

    col = F(t1) - F(t0)
    # Exact bound: the density never exceeds its value at the segment's lowest point.
    t_low = torch.clamp(torch.zeros_like(t1), min=t0, max=t1)  # closest point to P_o on the segment
    h_low = safe_sqrt(d2 + t_low * t_low) - R
    bound = length * torch.exp(-torch.clamp_min(h_low, 0.0) / H)
    return torch.minimum(torch.clamp_min(col, 0.0), bound)


TAYLOR_MIN_SCALE_HEIGHT: float = 1000.0
"""Smallest scale height the Taylor method accepts [m]. Below it the capped expansion is off by
more than 10x for grazing rays (420x at 100 m, 4200x at 10 m; 7.2x at Earth's 1.2 km aerosol
layer, docs/stability.md, docs/accuracy.md), so it refuses instead of returning garbage."""


class TaylorOpticalDepth(OpticalDepthIntegrator):
    """Gałaj 2021 Taylor method with hyperparameters ``a``, ``b`` as tensors (fit-able).

    ``a`` and ``b`` are scalars (shape (), one pair for every layer, as in the
    paper) or one value per layer (shape (K,), in the order of the scale heights,
    e.g. from ``skyfit calibrate-integrator``'s ``taylor.per_layer``).
    """

    name = "taylor"

    def __init__(self, a: float | Tensor = TAYLOR_A_DEFAULT, b: float | Tensor = TAYLOR_B_DEFAULT):
        self.a = a
        self.b = b
        for nm, v in (("a", a), ("b", b)):
            vv = v.detach().cpu().double() if isinstance(v, Tensor) else torch.as_tensor(v, dtype=torch.float64)
            if vv.ndim > 1:
                raise ValueError(f"Taylor hyperparameter {nm} must be a scalar or one value per layer (shape (K,)), got shape {tuple(vv.shape)}")
            if not bool(((vv >= 0.0) & (vv <= 1.0)).all()):
                raise ValueError(f"Taylor hyperparameter {nm} must be in [0, 1], got {vv.tolist()}")

    def _hyperparameters(self, scale_heights: Tensor) -> tuple[Tensor, Tensor]:
        """a, b as tensors on the layers' dtype and device, after checking them and the layers' regime."""
        a = torch.as_tensor(self.a, dtype=scale_heights.dtype, device=scale_heights.device)
        b = torch.as_tensor(self.b, dtype=scale_heights.dtype, device=scale_heights.device)
        for nm, v in (("a", a), ("b", b)):
            if v.ndim == 1 and v.shape[0] != scale_heights.shape[-1]:
                raise ValueError(f"Taylor hyperparameter {nm} has {v.shape[0]} values, one per layer, but there are {scale_heights.shape[-1]} layers")
        with torch.no_grad():
            h_min = float(torch.as_tensor(scale_heights).min())
        if h_min < TAYLOR_MIN_SCALE_HEIGHT:
            raise ValueError(f"taylor: scale height H = {h_min:.4g} m is below its regime (H >= {TAYLOR_MIN_SCALE_HEIGHT:g} m; "
                             "the column is off by > 10x for grazing rays there); use chapman or a quadrature integrator")
        return a, b

    def column(self, r, mu, length, scale_heights, bottom_radius, top_radius) -> Tensor:
        a, b = self._hyperparameters(torch.as_tensor(scale_heights, dtype=r.dtype, device=r.device))
        return taylor_column(r, mu, length, scale_heights, bottom_radius, top_radius, a, b)

    def prepare(self, scale_heights: Tensor, bottom_radius: float, top_radius: float) -> ColumnFn:
        """The checks once per atmosphere, not once per chunk of rays (each is a host sync on a GPU)."""
        a, b = self._hyperparameters(scale_heights)

        def fn(r: Tensor, mu: Tensor, length: Tensor) -> Tensor:
            return taylor_column(r, mu, length, scale_heights, bottom_radius, top_radius, a.to(r.dtype), b.to(r.dtype))

        return fn

    def settings(self) -> dict:
        def f(v):
            v = v.detach() if isinstance(v, Tensor) else torch.as_tensor(v, dtype=torch.float64)
            return float(v) if v.ndim == 0 else [float(x) for x in v]

        return {"name": self.name, "a": f(self.a), "b": f(self.b)}
