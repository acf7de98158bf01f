"""Bruneton & Neyret 2008 transmittance table (Sec. 4), in the Bruneton 2017 parametrisation.

Bruneton & Neyret 2008, Sec. 4, precompute the transmittance to the top of
the atmosphere, T(r, mu), in a 2D table and obtain the transmittance between
two points of a ray from the identity T(x, y) = T(x, v) / T(y, v). In
optical-depth terms (one table per exponential layer of scale height H)::

    C(r, mu) = int_0^{d(r, mu)} exp(-(r(s) - R_bottom) / H) ds,     d = distance to the top,

and the column of a segment from (r, mu) of length L ending at (r_d, mu_d) is
(Bruneton 2017 reference implementation, ``GetTransmittance``)::

    C(r, mu) - C(r_d, mu_d)          if the ray (r, mu) does not hit the ground,
    C(r_d, -mu_d) - C(r, -mu)        if it does (reversed directions, which do not),

clamped at >= 0 (the 2017 code clamps the transmittance ratio at <= 1).
Whether the ray hits the ground is decided from the segment's line
(``ray_hits_ground(r, mu)``, Bruneton 2017 ``RayIntersectsGround``), not from
where the segment ends: a segment that stops short of the ground on a
ground-bound ray still uses the reversed directions, whose rays reach the top.

The table is indexed as in the 2017 implementation (``GetTransmittanceTextureUvFromRMu``
and ``GetRMuFromTransmittanceTextureUv``): with H_a = sqrt(top^2 - bottom^2)
and rho = sqrt(r^2 - bottom^2),

    x_r  = rho / H_a,
    x_mu = (d - d_min) / (d_max - d_min),   d_min = top - r,  d_max = rho + H_a,

each mapped to a texture coordinate by ``GetTextureCoordFromUnitRange``
(u = 0.5 / n + x (1 - 1 / n)) and read with bilinear filtering (texel
centres at (i + 0.5) / n), so that texel i of an n-texel axis holds
x = i / (n - 1). x_mu = 1 is the ray tangent to the ground; the table covers
exactly the rays that do not hit the ground.

Expected error (docs/lut_chapman_fog.md, 256 x 64, Earth, H = 8 km / 1.2 km):
  * The table itself is exact to ~1e-12 (Gauss-Legendre; 64 nodes already
    converge, Bruneton's 500-sample trapezoid is as good); the error is the
    bilinear interpolation's, second order in the texel size.
  * A segment's column is a *difference* of two interpolated columns, so its
    error scales with the larger one, C_scale (the column to the top from the
    start, or from the ground point looking back): 4e-4 / 2.5e-3 of C_scale on
    the docs grid, up to 1e-2 / 4e-2 where the rows (uniform in rho) are far
    apart compared with H (0.6 H_Mie at 9 km, 1.9 km at the top; there the Mie
    column is < ~15 m). Median relative error of random segments: 6e-4 / 4e-3.
  * Relative to the segment's own column the error is unbounded for short
    segments and near the horizon and the ground (a 1 m vertical segment 1 m
    above the ground: 2.9 m of error), and the clamp at 0 can engage. This is
    the difference form's known weakness; it is reported, not hidden.
  * float32: radii are quantised to 0.5 m, which matters where the column
    changes fastest with r (horizontal rays just below the top): up to 0.13
    of C_scale there (~0.1 m).
  * The column is piecewise bilinear in (x_mu, x_r): its gradient with respect
    to r and mu is that of the interpolant (piecewise smooth, finite), not of
    the true column. With respect to the scale heights it is exact for the
    interpolated table (the table's derivative is integrated alongside it;
    first order only: no double backward).

Refusals: start or end radius outside [bottom, top] (beyond rounding), or
|mu| > 1, raise ValueError: the table does not cover them.
"""
from __future__ import annotations

import torch
from torch import Tensor
from torch.autograd.function import once_differentiable

from ..geometry import distance_to_top, ray_hits_ground, safe_sqrt
from ..quadrature import nodes_weights, validate_rule
from .base import ColumnFn, OpticalDepthIntegrator

TRANSMITTANCE_TEXTURE_WIDTH: int = 256
"""Texels along mu [1]. Bruneton 2017 reference implementation (constants.h)."""
TRANSMITTANCE_TEXTURE_HEIGHT: int = 64
"""Texels along r [1]. Bruneton 2017 reference implementation (constants.h)."""
TRANSMITTANCE_SAMPLES: int = 500
"""Samples of the column integral per texel [1]. Bruneton 2017 (ComputeOpticalLengthToTopAtmosphereBoundary, SAMPLE_COUNT)."""

_CHUNK_ELEMENTS = 1 << 21  # texels x samples per building block (bounds memory)


def texture_coord_from_unit_range(x: Tensor, size: int) -> Tensor:
    """Bruneton 2017 ``GetTextureCoordFromUnitRange``: [0, 1] -> texel-centre coordinates. [1]"""
    return 0.5 / size + x * (1.0 - 1.0 / size)


def unit_range_from_texture_coord(u: Tensor, size: int) -> Tensor:
    """Bruneton 2017 ``GetUnitRangeFromTextureCoord`` (inverse of :func:`texture_coord_from_unit_range`). [1]"""
    return (u - 0.5 / size) / (1.0 - 1.0 / size)


def transmittance_uv_from_r_mu(r: Tensor, mu: Tensor, bottom_radius: float, top_radius: float, mu_size: int, r_size: int) -> tuple[Tensor, Tensor]:
    """Bruneton 2017 ``GetTransmittanceTextureUvFromRMu``.

    Args:
        r: radius in [bottom, top], shape (...). [m]
        mu: view cosine, not hitting the ground, shape (...). [1]
        mu_size, r_size: texture width and height. [1]

    Returns:
        (u, v): texture coordinates along mu and r, shape (...). [1]
    """
    h_a = (top_radius * top_radius - bottom_radius * bottom_radius) ** 0.5
    rho = safe_sqrt((r - bottom_radius) * (r + bottom_radius))
    d = distance_to_top(r, mu, top_radius)
    d_min = top_radius - r
    d_max = rho + h_a
    x_mu = (d - d_min) / (d_max - d_min)
    x_r = rho / h_a
    return texture_coord_from_unit_range(x_mu, mu_size), texture_coord_from_unit_range(x_r, r_size)


def r_mu_from_transmittance_uv(u: Tensor, v: Tensor, bottom_radius: float, top_radius: float, mu_size: int, r_size: int) -> tuple[Tensor, Tensor, Tensor]:
    """Bruneton 2017 ``GetRMuFromTransmittanceTextureUv``, also returning the distance to the top.

    Returns:
        (r, mu, d): radius [m], cosine [1] and distance to the top [m], shape (...).
    """
    h_a = (top_radius * top_radius - bottom_radius * bottom_radius) ** 0.5
    x_mu = unit_range_from_texture_coord(u, mu_size)
    x_r = unit_range_from_texture_coord(v, r_size)
    rho = h_a * x_r
    r = torch.sqrt(rho * rho + bottom_radius * bottom_radius)
    d_min = top_radius - r
    d_max = rho + h_a
    d = d_min + x_mu * (d_max - d_min)
    zero = d == 0
    mu = (h_a * h_a - rho * rho - d * d) / (2.0 * r * torch.where(zero, torch.ones_like(d), d))
    mu = torch.where(zero, torch.ones_like(mu), torch.clamp(mu, -1.0, 1.0))
    return r, mu, d


def _integrate_table(r: Tensor, mu: Tensor, d: Tensor, x: Tensor, w: Tensor, H: Tensor, bottom_radius: float, with_derivative: bool) -> tuple[Tensor, Tensor | None]:
    """Column to the top and its derivative in H for each texel, by the rule (x, w) on [0, d].

    Args:
        r, mu, d: texel radius [m], cosine [1], distance to the top [m], shape (Nr, Nmu).
        x, w: rule nodes and weights on [0, 1], shape (M,).
        H: scale heights, shape (K,). [m]

    Returns:
        (C, dC/dH): shape (Nr, Nmu, K) each (the second None unless requested). [m], [1]
    """
    n_r, n_mu = r.shape
    step = max(1, _CHUNK_ELEMENTS // max(n_mu * x.shape[0], 1))
    cols, dcols = [], []
    for i in range(0, n_r, step):
        r_, mu_, d_ = (t[i : i + step].reshape(-1, 1) for t in (r, mu, d))
        s = d_ * x  # (n, M)
        # r(s) - R = ((r - R)(r + R) + 2 r mu s + s^2) / (r(s) + R): no cancellation near the ground.
        q = s * (2.0 * r_ * mu_ + s)
        rs = torch.sqrt(torch.clamp_min(r_ * r_ + q, 0.0))
        alt = ((r_ - bottom_radius) * (r_ + bottom_radius) + q) / (rs + bottom_radius)
        c_k, dc_k = [], []
        for k in range(H.shape[0]):
            dens = torch.exp(alt * (-1.0 / H[k]))  # (n, M)
            c_k.append(dens @ w)
            if with_derivative:
                dc_k.append((dens * alt) @ w / (H[k] * H[k]))
        cols.append(torch.stack(c_k, -1) * d_)
        if with_derivative:
            dcols.append(torch.stack(dc_k, -1) * d_)
    n_k = H.shape[0]
    table = torch.cat(cols, 0).reshape(n_r, n_mu, n_k)
    return table, (torch.cat(dcols, 0).reshape(n_r, n_mu, n_k) if with_derivative else None)


class _ColumnTable(torch.autograd.Function):
    """The table as a differentiable function of the scale heights (exact first derivative)."""

    @staticmethod
    def forward(ctx, H: Tensor, r: Tensor, mu: Tensor, d: Tensor, x: Tensor, w: Tensor, bottom_radius: float) -> Tensor:
        need = ctx.needs_input_grad[0]
        table, dtable = _integrate_table(r, mu, d, x, w, H, bottom_radius, need)
        if need:
            ctx.save_for_backward(dtable)
        return table

    @staticmethod
    @once_differentiable
    def backward(ctx, grad: Tensor):
        (dtable,) = ctx.saved_tensors
        return (grad * dtable).sum(dim=(0, 1)), None, None, None, None, None, None


def _bilinear(table: Tensor, u: Tensor, v: Tensor) -> Tensor:
    """GPU-style bilinear fetch with clamp-to-edge: texel centres at (i + 0.5) / n.

    Args:
        table: shape (Nr, Nmu, K).
        u, v: texture coordinates along mu and r, shape (...). [1]

    Returns:
        shape (..., K).
    """
    n_r, n_mu, _ = table.shape
    fu = torch.clamp(u * n_mu - 0.5, 0.0, n_mu - 1.0)  # continuous texel index; clamp = texture edge addressing
    fv = torch.clamp(v * n_r - 0.5, 0.0, n_r - 1.0)
    i0 = torch.clamp(torch.floor(fu.detach()), max=n_mu - 2).long()
    j0 = torch.clamp(torch.floor(fv.detach()), max=n_r - 2).long()
    tu = (fu - i0.to(fu.dtype)).unsqueeze(-1)
    tv = (fv - j0.to(fv.dtype)).unsqueeze(-1)
    c00 = table[j0, i0]
    c01 = table[j0, i0 + 1]
    c10 = table[j0 + 1, i0]
    c11 = table[j0 + 1, i0 + 1]
    return (1.0 - tv) * ((1.0 - tu) * c00 + tu * c01) + tv * ((1.0 - tu) * c10 + tu * c11)


class BrunetonLUTOpticalDepth(OpticalDepthIntegrator):
    """Bruneton & Neyret 2008 Sec. 4 column table with bilinear lookup (Bruneton 2017 indexing).

    Args:
        mu_size: texels along mu (256 in Bruneton 2017). [1]
        r_size: texels along r (64 in Bruneton 2017). [1]
        samples: nodes of the rule per texel (500 in Bruneton 2017). [1]
        rule: quadrature rule of the table (Bruneton 2017 uses the trapezoid;
            Gauss-Legendre, the default here, is exact to rounding with 500 nodes).
    """

    name = "bruneton_lut"

    def __init__(self, mu_size: int = TRANSMITTANCE_TEXTURE_WIDTH, r_size: int = TRANSMITTANCE_TEXTURE_HEIGHT, samples: int = TRANSMITTANCE_SAMPLES, rule: str = "gauss"):
        for nm, v in (("mu_size", mu_size), ("r_size", r_size)):
            if int(v) < 2:
                raise ValueError(f"{nm} must be >= 2 texels for bilinear lookup, got {v}")
        if int(samples) < 2:
            raise ValueError(f"samples must be >= 2, got {samples}")
        self.mu_size, self.r_size, self.samples = int(mu_size), int(r_size), int(samples)
        self.rule = validate_rule(rule)

    def table(self, scale_heights: Tensor, bottom_radius: float, top_radius: float) -> Tensor:
        """The column to the top at each texel, differentiable in the scale heights.

        Args:
            scale_heights: shape (K,). [m]
            bottom_radius, top_radius: [m]

        Returns:
            shape (r_size, mu_size, K); entry [j, i] is C(r, mu) at u = (i + 0.5) / mu_size,
            v = (j + 0.5) / r_size. [m]
        """
        if not 0.0 < bottom_radius < top_radius:
            raise ValueError(f"need 0 < bottom_radius < top_radius, got {bottom_radius}, {top_radius}")
        H = scale_heights
        if H.dim() != 1:
            raise ValueError(f"scale_heights must have shape (K,), got {tuple(H.shape)}")
        if bool((H.detach() <= 0).any()):
            raise ValueError("scale heights must be > 0")
        dt, dev = H.dtype, H.device
        u = (torch.arange(self.mu_size, dtype=dt, device=dev) + 0.5) / self.mu_size
        v = (torch.arange(self.r_size, dtype=dt, device=dev) + 0.5) / self.r_size
        vv, uu = torch.meshgrid(v, u, indexing="ij")
        r, mu, d = r_mu_from_transmittance_uv(uu, vv, bottom_radius, top_radius, self.mu_size, self.r_size)
        x, w = nodes_weights(self.rule, self.samples, dt, dev)
        return _ColumnTable.apply(H, r, mu, d, x, w, float(bottom_radius))

    def prepare(self, scale_heights: Tensor, bottom_radius: float, top_radius: float) -> ColumnFn:
        table = self.table(scale_heights, bottom_radius, top_radius)
        return lambda r, mu, length: self.lookup_column(table, r, mu, length, bottom_radius, top_radius)

    def column(self, r, mu, length, scale_heights, bottom_radius, top_radius) -> Tensor:
        """Builds the table and looks up once; use :meth:`prepare` to reuse the table."""
        return self.prepare(scale_heights, bottom_radius, top_radius)(r, mu, length)

    def column_to_top(self, table: Tensor, r: Tensor, mu: Tensor, bottom_radius: float, top_radius: float) -> Tensor:
        """C(r, mu) by bilinear lookup, for rays that do not hit the ground, shape (..., K). [m]"""
        u, v = transmittance_uv_from_r_mu(r, mu, bottom_radius, top_radius, self.mu_size, self.r_size)
        return _bilinear(table, u, v)

    def lookup_column(self, table: Tensor, r: Tensor, mu: Tensor, length: Tensor, bottom_radius: float, top_radius: float) -> Tensor:
        """Column of the segment from (r, mu) of the given length (Bruneton 2017 ``GetTransmittance``).

        Args:
            table: from :meth:`table`, shape (Nr, Nmu, K). [m]
            r: start radius in [bottom, top], shape (...). [m]
            mu: view cosine at the start, shape (...). [1]
            length: segment length >= 0, its end inside the atmosphere, shape (...). [m]

        Returns:
            shape (..., K). [m]
        """
        r, mu, length = torch.broadcast_tensors(r, mu, length)
        r_d = safe_sqrt(length * length + 2.0 * r * mu * length + r * r)
        # r_d = r + (2 r mu L + L^2) / (r_d + r): better than the square root alone in float32.
        den = r_d + r
        r_d = r + length * (2.0 * r * mu + length) / torch.where(den > 0, den, torch.ones_like(den))
        self._check(r, mu, r_d, bottom_radius, top_radius)
        # ClampRadius / ClampCosine of Bruneton 2017: only rounding is removed here (checked above).
        r = torch.clamp(r, bottom_radius, top_radius)
        mu = torch.clamp(mu, -1.0, 1.0)
        r_d = torch.clamp(r_d, bottom_radius, top_radius)
        mu_d = torch.clamp((r * mu + length) / r_d, -1.0, 1.0)
        ground = ray_hits_ground(r, mu, bottom_radius)
        a_r, a_mu = torch.where(ground, r_d, r), torch.where(ground, -mu_d, mu)
        b_r, b_mu = torch.where(ground, r, r_d), torch.where(ground, -mu, mu_d)
        col = self.column_to_top(table, a_r, a_mu, bottom_radius, top_radius) - self.column_to_top(table, b_r, b_mu, bottom_radius, top_radius)
        # Bruneton 2017 clamps T(x, y) <= 1; interpolation error can make short differences negative.
        return torch.clamp_min(col, 0.0)

    @staticmethod
    def _check(r: Tensor, mu: Tensor, r_d: Tensor, bottom_radius: float, top_radius: float) -> None:
        tol = max(1.0, 16.0 * torch.finfo(r.dtype).eps * top_radius)  # rounding of radii [m]
        with torch.no_grad():
            lo = torch.minimum(r, r_d).min() if r.numel() else None
            hi = torch.maximum(r, r_d).max() if r.numel() else None
            bad_mu = bool((mu.abs() > 1.0 + 1e-6).any()) if r.numel() else False
        if lo is not None and (float(lo) < bottom_radius - tol or float(hi) > top_radius + tol):
            raise ValueError(
                f"bruneton_lut: segment radii span [{float(lo):.6g}, {float(hi):.6g}] m, outside the table's "
                f"[bottom, top] = [{bottom_radius:.6g}, {top_radius:.6g}] m (the table covers the atmosphere only)"
            )
        if bad_mu:
            raise ValueError("bruneton_lut: |mu| > 1")

    def settings(self) -> dict:
        return {"name": self.name, "mu_size": self.mu_size, "r_size": self.r_size, "samples": self.samples, "rule": self.rule}
