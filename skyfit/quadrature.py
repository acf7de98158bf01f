"""Fixed quadrature rules on [0, 1], shared by the optical-depth and scattering integrals."""
from __future__ import annotations

import functools

import numpy as np
import torch
from torch import Tensor

RULES = ("trapezoid", "midpoint", "simpson", "gauss")


def validate_rule(rule: str) -> str:
    if rule not in RULES:
        raise ValueError(f"unknown quadrature rule {rule!r}; valid: {', '.join(RULES)}")
    return rule


@functools.lru_cache(maxsize=256)
def _nodes_weights_np(rule: str, n: int) -> tuple[np.ndarray, np.ndarray]:
    validate_rule(rule)
    if n < 1 or (rule in ("trapezoid", "simpson") and n < 2):
        raise ValueError(f"{rule} needs at least {1 if rule in ('midpoint', 'gauss') else 2} samples, got {n}")
    if rule == "trapezoid":
        x = np.linspace(0.0, 1.0, n)
        w = np.full(n, 1.0 / (n - 1))
        w[[0, -1]] *= 0.5
    elif rule == "midpoint":
        x = (np.arange(n) + 0.5) / n
        w = np.full(n, 1.0 / n)
    elif rule == "simpson":
        if n % 2 == 0:
            n += 1  # composite Simpson needs an odd number of nodes
        n = max(n, 3)
        x = np.linspace(0.0, 1.0, n)
        w = np.ones(n)
        w[1:-1:2] = 4.0
        w[2:-1:2] = 2.0
        w /= 3.0 * (n - 1)
    else:  # gauss
        x, w = np.polynomial.legendre.leggauss(n)
        x = 0.5 * (x + 1.0)
        w = 0.5 * w
    return x, w


def nodes_weights(rule: str, n: int, dtype: torch.dtype, device) -> tuple[Tensor, Tensor]:
    """Nodes and weights of an ``n``-point rule on [0, 1] (Simpson rounds even n up to n + 1).

    Returns:
        (x, w): shapes (n,) each; ``sum(w * f(x))`` approximates ``int_0^1 f``.
    """
    x, w = _nodes_weights_np(rule, int(n))
    return torch.as_tensor(x, dtype=dtype, device=device), torch.as_tensor(w, dtype=dtype, device=device)
