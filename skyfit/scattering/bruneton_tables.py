"""Table layout, parametrisation and interpolation of Bruneton's precomputed atmosphere.

The mappings between physical parameters and table coordinates are those of
Bruneton's 2017 reference implementation (ebruneton/precomputed_atmospheric_
scattering, ``functions.glsl``), which refine Bruneton & Neyret 2008, Sec. 4:

- transmittance, ``GetTransmittanceTextureUvFromRMu``: x_r = rho / H and
  x_mu = (d - d_min) / (d_max - d_min) with d the distance to the top of the
  atmosphere, d_min = r_top - r, d_max = rho + H (rho the distance to the
  horizon, H that for an observer on the ground);
- scattering, ``GetScatteringTextureUvwzFromRMuMuSNu``: the same x_r; for mu a
  *discontinuous* mapping at the horizon (2008, Sec. 4 "S is discontinuous at
  the horizon"): rays that hit the ground fill the lower half of the mu axis
  (x from the ground distance, nadir next to the middle, horizon at index 0),
  the others the upper half (zenith next to the middle, horizon at the last
  index), so that interpolation never mixes the two; for mu_s the generic
  mapping with the configurable limit mu_s_min (-0.2 in 2017); nu linear;
- irradiance, ``GetIrradianceTextureUvFromRMuS``: affine in r and mu_s.

Texel centres: a GPU texture of n texels sampled at u = (i + 0.5) / n; 2017's
``GetTextureCoordFromUnitRange`` puts x = 0 and x = 1 on the first and last
texel centres, so a unit-range value x lands on the continuous texel index
x (n - 1). We store tables as plain arrays indexed by texel and interpolate
multilinearly in that index, clamping to the edge texels as GL's
CLAMP_TO_EDGE does: this reproduces the GPU lookup (2017's nu axis, which is
not texel-centred, also maps to x (n - 1)). The 4D scattering table is a 5D
array (r, mu, mu_s, nu, W) interpolated quadrilinearly (16 corners), instead
of 2017's 3D texture with nu and mu_s packed along x and a manual lerp in nu;
the result is the same.

All lookups follow the dtype and device of their inputs; the indices and
weights depend on geometry only, so gradients flow to the table values
(which carry all dependence on the atmosphere's parameters) exactly.
"""
from __future__ import annotations

from collections.abc import Sequence

import dataclasses
import math

import torch
from torch import Tensor

from ..atmosphere import Atmosphere
from ..geometry import distance_to_bottom, distance_to_top, safe_sqrt

MU_S_MIN_DEFAULT: float = -0.2
"""Lowest sun zenith cosine covered by the scattering tables [1]. Bruneton 2017 (demo.cc,
max_sun_zenith_angle = 102 deg; -0.2 in the model's default)."""


@dataclasses.dataclass(frozen=True)
class TableSizes:
    """Texel counts of the precomputed tables (Bruneton 2017 defaults; 2008 Sec. 6).

    Attributes:
        transmittance_mu, transmittance_r: 256 x 64.
        irradiance_mu_s, irradiance_r: 64 x 16.
        scattering_r, scattering_mu, scattering_mu_s, scattering_nu: 32 x 128 x 32 x 8;
            ``scattering_mu`` must be even (two halves, see the module docstring).
    """

    transmittance_mu: int = 256
    transmittance_r: int = 64
    irradiance_mu_s: int = 64
    irradiance_r: int = 16
    scattering_r: int = 32
    scattering_mu: int = 128
    scattering_mu_s: int = 32
    scattering_nu: int = 8

    def __post_init__(self) -> None:
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            if not isinstance(v, int) or v < 2:
                raise ValueError(f"TableSizes.{f.name} must be an integer >= 2, got {v!r}")
        if self.scattering_mu % 2 or self.scattering_mu < 4:
            raise ValueError(f"TableSizes.scattering_mu must be even and >= 4 (two halves), got {self.scattering_mu}")

    @classmethod
    def parse(cls, spec: "str | Sequence[int]") -> "TableSizes":
        """The scattering table's ``R,MU,MUS,NU`` (a string or 4 integers) with 2017's other sizes; ValueError otherwise."""
        try:
            r, mu, mu_s, nu = (int(v) for v in (spec.split(",") if isinstance(spec, str) else spec))
        except (TypeError, ValueError):
            raise ValueError(f"table sizes must be R,MU,MUS,NU integers, got {spec!r}") from None
        return cls(scattering_r=r, scattering_mu=mu, scattering_mu_s=mu_s, scattering_nu=nu)

    @property
    def scattering_shape(self) -> tuple[int, int, int, int]:
        return (self.scattering_r, self.scattering_mu, self.scattering_mu_s, self.scattering_nu)

    @property
    def scattering_texels(self) -> int:
        return math.prod(self.scattering_shape)


# ----------------------------------------------------------------------------------------
# Extinction rows (the density profiles are in skyfit.atmosphere.profiles)


def extinction_matrix3(atm: Atmosphere) -> Tensor:
    """Rows (Rayleigh scattering, Mie extinction, ozone absorption), shape (3, W). [1/m]

    ``optical depth = columns (..., 3) @ this``; ozone row is 0 when ``atm.ozone_absorption`` is None.
    """
    oz = atm.ozone_absorption if atm.ozone_absorption is not None else torch.zeros_like(atm.rayleigh_scattering)
    return torch.stack([atm.rayleigh_scattering, atm.mie_extinction, oz])


# ----------------------------------------------------------------------------------------
# Parametrisations (forward: physical -> continuous texel index; inverse: texel -> physical)


def _horizon_distances(r: Tensor, bottom: float, top: float) -> tuple[Tensor, float]:
    """(rho, H): distance to the horizon from r, and from the ground to the top. [m]"""
    H = math.sqrt(top * top - bottom * bottom)
    rho = safe_sqrt((r - bottom) * (r + bottom))
    return rho, H


def transmittance_index(r: Tensor, mu: Tensor, bottom: float, top: float, sizes: TableSizes) -> tuple[Tensor, Tensor]:
    """Continuous texel indices (i_r, i_mu) of (r, mu) (2017 GetTransmittanceTextureUvFromRMu).

    Args:
        r: shape (...), in [bottom, top]. [m]
        mu: shape (...), for rays that do not hit the ground. [1]
    """
    rho, H = _horizon_distances(r, bottom, top)
    d = distance_to_top(r, mu, top)
    d_min = top - r
    d_max = rho + H
    x_mu = (d - d_min) / (d_max - d_min)
    x_r = rho / H
    return x_r * (sizes.transmittance_r - 1), x_mu * (sizes.transmittance_mu - 1)


def transmittance_texel_params(bottom: float, top: float, sizes: TableSizes, dtype, device) -> tuple[Tensor, Tensor]:
    """(r, mu) at the transmittance texel centres, shapes (n_r, n_mu) (2017 GetRMuFromTransmittanceTextureUv)."""
    x_r = torch.linspace(0.0, 1.0, sizes.transmittance_r, dtype=dtype, device=device)[:, None]
    x_mu = torch.linspace(0.0, 1.0, sizes.transmittance_mu, dtype=dtype, device=device)[None, :]
    H = math.sqrt(top * top - bottom * bottom)
    rho = H * x_r
    r = torch.sqrt(rho * rho + bottom * bottom)
    d_min = top - r
    d_max = rho + H
    d = d_min + x_mu * (d_max - d_min)
    safe_d = torch.where(d > 0, d, torch.ones_like(d))
    mu = torch.where(d > 0, (H * H - rho * rho - d * d) / (2.0 * r * safe_d), torch.ones_like(d))
    r, mu = torch.broadcast_tensors(r, torch.clamp(mu, -1.0, 1.0))
    return r.contiguous(), mu.contiguous()


def mu_s_unit(mu_s: Tensor, bottom: float, top: float, mu_s_min: float) -> Tensor:
    """Unit-range coordinate of the sun zenith cosine (2017 GetScatteringTextureUvwzFromRMuMuSNu).

    Values below ``mu_s_min`` map to 0 (the mapping's own max(., 0)).
    """
    H = math.sqrt(top * top - bottom * bottom)
    d = distance_to_top(torch.full_like(mu_s, bottom), mu_s, top)
    d_min = top - bottom
    d_max = H
    a = (d - d_min) / (d_max - d_min)
    A = -2.0 * mu_s_min * bottom / (d_max - d_min)
    return torch.clamp_min(1.0 - a / A, 0.0) / (1.0 + a)


def mu_s_from_unit(x: Tensor, bottom: float, top: float, mu_s_min: float) -> Tensor:
    """Inverse of :func:`mu_s_unit` (2017 GetRMuMuSNuFromScatteringTextureUvwz). [1]"""
    H = math.sqrt(top * top - bottom * bottom)
    d_min = top - bottom
    d_max = H
    A = -2.0 * mu_s_min * bottom / (d_max - d_min)
    a = (A - x * A) / (1.0 + x * A)
    d = d_min + torch.clamp_max(a, A) * (d_max - d_min)
    safe_d = torch.where(d > 0, d, torch.ones_like(d))
    mu_s = torch.where(d > 0, (H * H - d * d) / (2.0 * bottom * safe_d), torch.ones_like(d))
    return torch.clamp(mu_s, -1.0, 1.0)


FULL_MU_S = (0.0, 1.0)
"""The mu_s axis over all of :func:`mu_s_unit`'s range, ``mu_s_min`` to 1 (2017's tables)."""


def mu_s_window(lo: float, hi: float, bottom: float, top: float, mu_s_min: float) -> tuple[float, float]:
    """The range of :func:`mu_s_unit`'s coordinate between the sun zenith cosines ``lo`` < ``hi`` (clipped to
    [mu_s_min, 1]): a table's mu_s axis over one sun's elevations instead of all (:func:`mu_s_index`)."""
    x = mu_s_unit(torch.tensor([max(lo, mu_s_min), min(hi, 1.0)], dtype=torch.float64), bottom, top, mu_s_min)
    a, b = float(x[0]), float(x[1])
    if not b > a:
        raise ValueError(f"an empty mu_s window: sun zenith cosines {lo} to {hi} with mu_s_min {mu_s_min}")
    return a, b


SUN_MARGIN_DEG = 5.0
"""Tables for one sun (:func:`sun_window`) span its zenith angle and this much beyond on either side. [deg]"""
SUN_SPACING_DEG = 2.0
"""The largest spacing in sun zenith angle between the mu_s texels of :func:`sun_window`'s tables: six texels for one
sun, within 0.2 % of a window of 1 deg spacing for a hazy sky's orders >= 2 at sun zeniths 23-80 deg where 2017's
axis of 16 texels was 2.3x off at the zenith (docs/multiple_scattering.md, "One sun's mu_s window"). [deg]"""


def sun_window(zenith_min_deg: float, zenith_max_deg: float, texels: int, margin_deg: float = SUN_MARGIN_DEG,
               spacing_deg: float = SUN_SPACING_DEG, mu_s_min: float = MU_S_MIN_DEFAULT) -> tuple[tuple[float, float] | None, int]:
    """``(mu_s_range, texels)`` of Bruneton tables for suns between these zenith angles: the cosines of the angles widened
    by ``margin_deg`` (clipped to [mu_s_min, 1]), in texels at most ``spacing_deg`` apart
    (:func:`skyfit.scattering.multiple.precompute`'s ``mu_s_range``); ``(None, texels)`` (2017's axis) where the
    window would be empty."""
    lo_deg = max(0.0, float(zenith_min_deg) - margin_deg)
    hi_deg = min(180.0, float(zenith_max_deg) + margin_deg)
    lo, hi = max(math.cos(math.radians(hi_deg)), mu_s_min), math.cos(math.radians(lo_deg))
    if not hi > lo:
        return None, texels
    return (lo, hi), max(int(math.ceil((hi_deg - lo_deg) / spacing_deg - 1e-9)) + 1, 2)


def mu_s_index(mu_s: Tensor, bottom: float, top: float, mu_s_min: float, n: int,
               window: tuple[float, float] = FULL_MU_S) -> Tensor:
    """Continuous texel index on a table's mu_s axis of ``n`` texels: :func:`mu_s_unit`'s coordinate, the first and
    last texels at the ends of ``window`` (a range of that coordinate; :data:`FULL_MU_S`: 2017's axis, bit for bit).

    A window is this project's, not 2017's: a scene with one sun needs its tables only at sun zenith angles near that
    sun's, and 2017's axis gives a high sun about one texel (the mapping spends its range near the horizon: 20-35 deg
    from the zenith is 0.975-0.999 of it). Lookups outside the window take its edge texel's value."""
    x = mu_s_unit(mu_s, bottom, top, mu_s_min)
    lo, hi = window
    if (float(lo), float(hi)) != FULL_MU_S:
        x = (x - lo) / (hi - lo)
    return x * (n - 1)


def scattering_index(
    r: Tensor, mu: Tensor, mu_s: Tensor, nu: Tensor, hits_ground: Tensor, bottom: float, top: float, mu_s_min: float, sizes: TableSizes,
    mu_s_window: tuple[float, float] = FULL_MU_S,
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Continuous texel indices (i_r, i_mu, i_mu_s, i_nu) (2017 GetScatteringTextureUvwzFromRMuMuSNu).

    Args:
        r: shape (...), in [bottom, top]. [m]
        mu, mu_s, nu: view zenith, sun zenith and view-sun cosines, shape (...). [1]
        hits_ground: whether the ray (r, mu) hits the ground, bool shape (...); decides the half
            of the mu axis (the horizon discontinuity of Bruneton & Neyret 2008 Sec. 4).
        mu_s_window: the range of :func:`mu_s_unit`'s coordinate the mu_s axis spans (:func:`mu_s_index`).
    """
    rho, H = _horizon_distances(r, bottom, top)
    x_r = rho / H
    half = sizes.scattering_mu // 2
    # Ground half: distance to the ground relative to its range [r - bottom, rho].
    d_g = distance_to_bottom(r, mu, bottom)
    dmin_g = r - bottom
    span_g = rho - dmin_g
    ok_g = span_g > 0
    x_g = torch.where(ok_g, (d_g - dmin_g) / torch.where(ok_g, span_g, torch.ones_like(span_g)), torch.zeros_like(d_g))
    i_mu_g = (half - 1) * (1.0 - x_g)
    # Sky half: distance to the top relative to its range [top - r, rho + H].
    d_t = distance_to_top(r, mu, top)
    x_t = (d_t - (top - r)) / (rho + H - (top - r))
    i_mu_t = half + (half - 1) * x_t
    i_mu = torch.where(hits_ground, i_mu_g, i_mu_t)
    x_nu = (nu + 1.0) / 2.0
    return (
        x_r * (sizes.scattering_r - 1),
        i_mu,
        mu_s_index(mu_s, bottom, top, mu_s_min, sizes.scattering_mu_s, mu_s_window),
        x_nu * (sizes.scattering_nu - 1),
    )


@dataclasses.dataclass
class ScatteringTexels:
    """Physical parameters at the scattering texel centres, each of shape (R, MU, MU_S, NU).

    From 2017 GetRMuMuSNuFromScatteringTextureFragCoord, including its clamp of nu to the
    range that (mu, mu_s) allow.
    """

    r: Tensor
    mu: Tensor
    mu_s: Tensor
    nu: Tensor
    hits_ground: Tensor


def scattering_texel_params(bottom: float, top: float, mu_s_min: float, sizes: TableSizes, dtype, device,
                            mu_s_window: tuple[float, float] = FULL_MU_S) -> ScatteringTexels:
    R, MU, MUS, NU = sizes.scattering_shape
    half = MU // 2
    H = math.sqrt(top * top - bottom * bottom)
    lin = lambda n: torch.linspace(0.0, 1.0, n, dtype=dtype, device=device)  # noqa: E731
    rho = H * lin(R)[:, None]  # (R, 1)
    r = torch.sqrt(rho * rho + bottom * bottom)
    i = torch.arange(MU, device=device)
    ground = i < half
    x = torch.where(ground, (half - 1 - i), (i - half)).to(dtype) / (half - 1)  # (MU,)
    # Ground half: d in [r - bottom, rho]; mu = -(rho^2 + d^2) / (2 r d).
    d_g = (r - bottom) + (rho - (r - bottom)) * x
    safe_g = torch.where(d_g > 0, d_g, torch.ones_like(d_g))
    mu_g = torch.where(d_g > 0, -(rho * rho + d_g * d_g) / (2.0 * r * safe_g), -torch.ones_like(d_g))
    # Sky half: d in [top - r, rho + H]; mu = (H^2 - rho^2 - d^2) / (2 r d).
    d_t = (top - r) + (rho + H - (top - r)) * x
    safe_t = torch.where(d_t > 0, d_t, torch.ones_like(d_t))
    mu_t = torch.where(d_t > 0, (H * H - rho * rho - d_t * d_t) / (2.0 * r * safe_t), torch.ones_like(d_t))
    mu = torch.clamp(torch.where(ground, mu_g, mu_t), -1.0, 1.0)  # (R, MU)
    x_mu_s = lin(MUS) if tuple(mu_s_window) == FULL_MU_S else mu_s_window[0] + (mu_s_window[1] - mu_s_window[0]) * lin(MUS)
    mu_s = mu_s_from_unit(x_mu_s, bottom, top, mu_s_min)  # (MUS,)
    nu = lin(NU) * 2.0 - 1.0  # (NU,)
    shape = (R, MU, MUS, NU)
    r4 = r[:, :, None, None].expand(shape)
    mu4 = mu[:, :, None, None].expand(shape)
    mus4 = mu_s[None, None, :, None].expand(shape)
    nu4 = nu[None, None, None, :].expand(shape)
    s = safe_sqrt((1.0 - mu4 * mu4) * (1.0 - mus4 * mus4))
    nu4 = torch.clamp(nu4, mu4 * mus4 - s, mu4 * mus4 + s)
    g4 = ground[None, :, None, None].expand(shape)
    return ScatteringTexels(r4.contiguous(), mu4.contiguous(), mus4.contiguous(), nu4.contiguous(), g4.contiguous())


def irradiance_index(r: Tensor, mu_s: Tensor, bottom: float, top: float, sizes: TableSizes) -> tuple[Tensor, Tensor]:
    """Continuous texel indices (i_r, i_mu_s) (2017 GetIrradianceTextureUvFromRMuS)."""
    x_r = (r - bottom) / (top - bottom)
    x_mu_s = mu_s * 0.5 + 0.5
    return x_r * (sizes.irradiance_r - 1), x_mu_s * (sizes.irradiance_mu_s - 1)


def irradiance_texel_params(bottom: float, top: float, sizes: TableSizes, dtype, device) -> tuple[Tensor, Tensor]:
    """(r, mu_s) at the irradiance texel centres, shapes (n_r, n_mu_s)."""
    x_r = torch.linspace(0.0, 1.0, sizes.irradiance_r, dtype=dtype, device=device)[:, None]
    x_mu_s = torch.linspace(0.0, 1.0, sizes.irradiance_mu_s, dtype=dtype, device=device)[None, :]
    r = bottom + x_r * (top - bottom)
    mu_s = torch.clamp(2.0 * x_mu_s - 1.0, -1.0, 1.0)
    r, mu_s = torch.broadcast_tensors(r, mu_s)
    return r.contiguous(), mu_s.contiguous()


# ----------------------------------------------------------------------------------------
# Interpolation


def _axis(f: Tensor, n: int) -> tuple[Tensor, Tensor]:
    """Lower corner (long) and fraction of continuous index f on an axis of n texels, edge-clamped."""
    f = torch.clamp(f, 0.0, float(n - 1))
    i0 = torch.clamp(torch.floor(f), 0.0, float(n - 2))
    return i0.long(), f - i0


def corner_plan(grid: Sequence[int], indices: tuple[Tensor, ...]) -> tuple[Tensor, Tensor, tuple[int, ...]]:
    """Flat texel indices and weights of the 2^D corners of multilinear interpolation.

    They depend on the query points and the grid only, so a precomputation that looks up
    the same points in several tables (every scattering order) computes them once
    (:func:`interpolate_planned`).

    Args:
        grid: the D texel counts of the tables.
        indices: D tensors of continuous texel indices, each of shape (...); clamped to
            [0, n - 1] per axis (GL CLAMP_TO_EDGE).

    Returns:
        (index (n, 2^D) long, weight (n, 2^D), batch shape) with n the number of points.
    """
    D = len(grid)
    if len(indices) != D:
        raise ValueError(f"interpolate: {len(indices)} index tensors for a {D}-D grid")
    batch = torch.broadcast_shapes(*(i.shape for i in indices))
    n = math.prod(batch)
    ix = None
    w = None
    for d, (f, size) in enumerate(zip(indices, grid)):
        lo, fr = _axis(f.expand(batch).reshape(-1), size)
        stride = math.prod(grid[d + 1 :])
        # corners of this axis appended as a new trailing dimension of size 2
        ix_d = torch.stack([lo * stride, (lo + 1) * stride], dim=-1)  # (n, 2)
        w_d = torch.stack([1.0 - fr, fr], dim=-1)
        if ix is None:
            ix, w = ix_d, w_d
        else:
            ix = (ix.unsqueeze(-1) + ix_d.view(n, 1, 2)).reshape(n, -1)
            w = (w.unsqueeze(-1) * w_d.view(n, 1, 2)).reshape(n, -1)
    return ix, w, tuple(batch)


def interpolate_planned(tables: list[Tensor] | tuple[Tensor, ...], index: Tensor, weight: Tensor, batch: tuple[int, ...]) -> list[Tensor]:
    """Multilinear interpolation with the corners of :func:`corner_plan` (any integer dtype of index).

    Returns one tensor of shape (*batch, C) per table of shape (*grid, C).
    """
    n, k = index.shape
    flat_ix = index.reshape(-1)
    outs = []
    for t in tables:
        v = t.reshape(-1, t.shape[-1]).index_select(0, flat_ix).view(n, k, t.shape[-1])
        outs.append(torch.bmm(weight.unsqueeze(1), v).reshape(*batch, t.shape[-1]))
    return outs


def interpolate(tables: list[Tensor] | tuple[Tensor, ...], indices: tuple[Tensor, ...]) -> list[Tensor]:
    """Multilinear interpolation of tables sharing a grid, at continuous texel indices.

    Args:
        tables: each of shape (*grid, C) (grid of D axes, any channel count C, same grid).
        indices: D tensors of continuous texel indices, each of shape (...); clamped to
            [0, n - 1] per axis (GL CLAMP_TO_EDGE).

    Returns:
        One tensor of shape (..., C) per table.
    """
    ix, w, batch = corner_plan(tables[0].shape[:-1], indices)
    return interpolate_planned(tables, ix, w, batch)


def grid_coordinate(index: Tensor, n: int) -> Tensor:
    """A continuous texel index on an axis of n texels as ``grid_sample``'s coordinate (align_corners=True).

    ``grid_sample(..., mode="bilinear", padding_mode="border", align_corners=True)`` at these
    coordinates is the edge-clamped multilinear interpolation of :func:`interpolate` (to rounding).
    """
    return index * (2.0 / (n - 1)) - 1.0
