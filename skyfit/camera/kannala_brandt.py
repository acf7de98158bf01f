"""Kannala–Brandt polynomial fisheye model, valid at and beyond 90° from the optical axis.

Kannala & Brandt 2006, "A generic camera model and calibration method for
conventional, wide-angle, and fish-eye lenses", IEEE TPAMI 28(8) 1335–1340,
radially symmetric model with four coefficients, in the form OpenCV's fisheye
module and kornia use::

    r(theta) = f * P(theta),   P(theta) = theta + k1 theta^3 + k2 theta^5 + k3 theta^7 + k4 theta^9

with ``theta`` the angle from the optical axis [rad], ``r`` the image radius
[px] and ``f`` the focal length [px/rad].

kornia 0.9 (``kornia.geometry.camera.distortion_kannala_brandt``) evaluates
the same polynomial but takes points on the z = 1 plane, i.e.
``theta = atan(r_z1)``, so it cannot represent rays at or beyond 90°. Here
``theta = atan2(rho, z)`` (in :mod:`skyfit.camera.fisheye`) and the inverse
``theta(r)`` is a bracketed Newton solve whose gradient is the implicit-function
gradient ``d theta = -(dP - d rho) / P'(theta)``.

The model is one-to-one only where ``P`` increases; :func:`check_kb_monotone`
refuses coefficients whose ``P'`` has a root inside the field of view.
"""
from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor

KB_NEWTON_MAX_ITERATIONS: int = 200
"""Upper bound on the bracketed Newton iterations (bisection alone needs < 64 in float64)."""


def _coeffs(k: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    if k.shape[-1:] != (4,):
        raise ValueError(f"Kannala-Brandt coefficients must have shape (..., 4), got {tuple(k.shape)}")
    return k[..., 0], k[..., 1], k[..., 2], k[..., 3]


def kb_ratio(theta: Tensor, k: Tensor) -> Tensor:
    """``Q(theta) = P(theta) / theta = 1 + k1 theta^2 + k2 theta^4 + k3 theta^6 + k4 theta^8``.

    Args:
        theta: angle from the optical axis, shape (...). [rad]
        k: (k1, k2, k3, k4), shape (4,) or broadcastable (..., 4). [rad^-2, rad^-4, rad^-6, rad^-8]

    Returns:
        shape (...). [1] Smooth and even in theta, 1 at theta = 0.
    """
    k1, k2, k3, k4 = _coeffs(k)
    t2 = theta * theta
    return 1.0 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4)))


def kb_polynomial(theta: Tensor, k: Tensor) -> Tensor:
    """``P(theta) = theta + k1 theta^3 + k2 theta^5 + k3 theta^7 + k4 theta^9``: image radius over focal length.

    Args:
        theta: angle from the optical axis, shape (...). [rad]
        k: coefficients, shape (4,) or (..., 4).

    Returns:
        shape (...). [rad] (image radius [px] / focal length [px/rad])
    """
    return theta * kb_ratio(theta, k)


def kb_derivative(theta: Tensor, k: Tensor) -> Tensor:
    """``P'(theta) = 1 + 3 k1 theta^2 + 5 k2 theta^4 + 7 k3 theta^6 + 9 k4 theta^8``, shape (...). [1]"""
    k1, k2, k3, k4 = _coeffs(k)
    t2 = theta * theta
    return 1.0 + t2 * (3.0 * k1 + t2 * (5.0 * k2 + t2 * (7.0 * k3 + t2 * 9.0 * k4)))


def check_kb_monotone(k, theta_max: float) -> None:
    """Raise ``ValueError`` unless ``P`` increases strictly on [0, theta_max] (theta_max in rad).

    Exact: ``P'`` is a quartic in ``t = theta^2``; its real roots in (0, theta_max^2] come from
    ``numpy.roots``. ``P' > 0`` on [0, theta_max] implies ``P > 0`` on (0, theta_max].
    """
    kk = np.asarray(torch.as_tensor(k).detach().cpu().double().reshape(-1), dtype=np.float64)
    if kk.shape != (4,) or not np.all(np.isfinite(kk)):
        raise ValueError(f"Kannala-Brandt coefficients must be 4 finite numbers, got {kk.tolist()}")
    # P'(t) = 9 k4 t^4 + 7 k3 t^3 + 5 k2 t^2 + 3 k1 t + 1, highest power first for numpy.roots
    poly = np.array([9 * kk[3], 7 * kk[2], 5 * kk[1], 3 * kk[0], 1.0])
    nz = np.flatnonzero(poly)
    roots = np.roots(poly[nz[0]:]) if nz[0] < 4 else np.array([])
    t_max = theta_max * theta_max
    bad = [r.real for r in roots if abs(r.imag) <= 1e-9 * max(1.0, abs(r)) and 0.0 < r.real <= t_max * (1 + 1e-12)]
    if bad:
        theta = math.degrees(math.sqrt(min(bad)))
        raise ValueError(
            f"Kannala-Brandt coefficients {kk.tolist()} are not monotone: r(theta) stops increasing at "
            f"{theta:.2f} deg, inside the field of view ({math.degrees(theta_max):.2f} deg); lower --max-zenith"
        )


def kb_theta(rho: Tensor, k: Tensor, theta_max: float) -> Tensor:
    """Inverse of :func:`kb_polynomial`: the angle ``theta`` in [0, theta_max] with ``P(theta) = rho``.

    Bracketed Newton iterations (Newton steps that leave the bracket become
    bisections) run without autograd until the step is at rounding level; one
    last Newton step with autograd attaches the implicit-function gradient
    ``d theta = (d rho - dP/dk dk) / P'(theta)`` with respect to ``rho`` and ``k``.

    Args:
        rho: image radius over focal length, 0 <= rho <= P(theta_max), shape (...). [rad]
        k: coefficients, shape (4,) (same dtype and device as rho); P must increase on [0, theta_max]
            (see :func:`check_kb_monotone`).
        theta_max: upper end of the bracket. [rad]

    Returns:
        theta, shape (...). [rad]

    Raises:
        ValueError: rho outside [0, P(theta_max)] (beyond rounding).
        RuntimeError: no convergence (only possible for coefficients that are not monotone).
    """
    with torch.no_grad():
        r = rho.detach()
        kd = k.detach()
        hi_val = float(kb_polynomial(torch.tensor(theta_max, dtype=torch.float64), kd.double().cpu()))
        eps = torch.finfo(r.dtype).eps
        if r.numel() and (bool((r < 0).any()) or bool((r > hi_val * (1 + 16 * eps)).any())):
            raise ValueError(f"kb_theta: rho must lie in [0, P(theta_max) = {hi_val:.6g}], got [{float(r.min()):.6g}, {float(r.max()):.6g}]")
        lo = torch.zeros_like(r)
        hi = torch.full_like(r, theta_max)
        th = torch.minimum(r, hi)  # equidistant first guess
        tol = 4 * eps
        for _ in range(KB_NEWTON_MAX_ITERATIONS):
            res = kb_polynomial(th, kd) - r
            lo = torch.where(res <= 0, th, lo)
            hi = torch.where(res >= 0, th, hi)
            new = th - res / kb_derivative(th, kd)
            ok = (new >= lo) & (new <= hi) & torch.isfinite(new)
            new = torch.where(ok, new, 0.5 * (lo + hi))
            done = bool(((new - th).abs() <= tol * torch.clamp(th, min=1.0)).all())
            th = new
            if done:
                break
        else:
            raise RuntimeError("kb_theta: Newton iterations did not converge; are the coefficients monotone?")
        slope = kb_derivative(th, kd)
    # One Newton step with autograd: value unchanged to rounding, gradient = implicit-function gradient.
    return th - (kb_polynomial(th, k) - rho) / slope
