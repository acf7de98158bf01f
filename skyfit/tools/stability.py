"""The extreme-grid stability check (issue #7 part 4): NaN/Inf and error counts per method.

Nothing here is used by the renderer: it evaluates every optical-depth
integrator, and the multiple-scattering paths, on a grid of extreme inputs
and counts what goes wrong, for ``tests/test_extremes.py`` (a coarse grid)
and ``scripts/stability_report.py`` (the full grid, docs/stability.md).

The grid (:class:`Grid`) crosses

* geometry, batched in one scene: observer altitude (ground, 1 m, 10 km,
  top - 1 m, top, 2 x top = space), sun zenith (0, 85, 90, 90.27 = the disc
  half below the horizon, 95, 108 degrees), view cosine (straight up and down,
  +-1e-3, +-1e-6 and 0 around the horizontal, the ground's horizon mu_h and
  mu_h +- 1e-6 for raised observers, and the view straight at the sun);
* the atmosphere, one scene each: both scale heights H in {10 m, 100 m,
  1.2 km, 8 km, 100 km}, every scattering and extinction coefficient
  beta in {0, 1e-9, 1e-5, 1e-2} /m (Mie single-scattering albedo 0.9),
  the Mie asymmetry g in {-0.9999, -0.9, 0, 0.9, 0.9999}; each axis swept from
  Earth's values (Bruneton 2017: H = 8 km / 1.2 km, g = 0.8) or, with
  ``cross=True``, all 100 combinations;
* float64 and float32.

What is counted (:func:`radiance_scene`, :func:`column_errors`):

* values: non-finite entries of the spectral radiance, per ray and wavelength,
  and negative ones;
* gradients: non-finite entries of d(sum of the group's radiance)/d(beta_R,
  beta_M^s, beta_M^e, H_R, H_M, g, albedo), one backward pass per group of rays
  (one observer altitude and sun zenith), so a NaN is located to its group;
* refusals: a method that raises ValueError for a group is counted as refusing
  it, with its message (the documented regimes: chapman, height_fog);
* errors: optical-depth columns along the view segments and the sun rays
  against the float64 scipy quadrature :func:`skyfit.tools.reference.column_quad`, as
  the relative error of :func:`skyfit.tools.reference.relative_column_error`.
"""
from __future__ import annotations

import dataclasses
import math
from collections import defaultdict
from typing import Callable, Iterable

import numpy as np
import torch
from torch import Tensor

from ..atmosphere import Atmosphere, load_atmosphere
from ..geometry import atmosphere_segment, distance_to_top, point_along_ray
from ..scattering import single_scattering
from ..scattering.bruneton_tables import TableSizes
from ..scattering.hillaire import hillaire_lut, hillaire_sky_radiance
from ..scattering.multiple import Quadrature, precompute, sky_radiance
from ..scattering.single import sun_ray_cosine
from ..transmittance import INTEGRATORS, make_integrator
from .reference import column_quad, relative_column_error

WAVELENGTHS_NM: tuple[float, float] = (440.0, 680.0)
"""Two wavelengths: enough for the spectral code paths (matmul over W). [nm]"""

ALTITUDES_M: tuple[tuple[str, float], ...] = (
    ("ground", 0.0),
    ("1 m", 1.0),
    ("10 km", 1e4),
    ("top-1m", None),  # filled from the atmosphere: top - bottom - 1
    ("top", None),
    ("space (2 x top)", None),
)
SUN_ZENITH_DEG: tuple[float, ...] = (0.0, 85.0, 90.0, 90.27, 95.0, 108.0)
MIE_G: tuple[float, ...] = (-0.9999, -0.9, 0.0, 0.9, 0.9999)
SCALE_HEIGHTS_M: tuple[float, ...] = (10.0, 100.0, 1200.0, 8000.0, 100_000.0)
BETAS: tuple[float, ...] = (0.0, 1e-9, 1e-5, 1e-2)
MIE_SSA: float = 0.9
"""Single-scattering albedo of the aerosol in the beta sweep (Bruneton 2017). [1]"""

GRADIENT_LEAVES: tuple[str, ...] = (
    "rayleigh_scattering", "mie_scattering", "mie_extinction", "rayleigh_scale_height", "mie_scale_height", "mie_g", "ground_albedo",
)
"""Fields of :class:`~skyfit.atmosphere.Atmosphere` made leaves requiring grad: the renderer's raw
coefficients (per-wavelength beta_R, beta_M^s, beta_M^e, albedo; H_R, H_M, g), not the fit's
parameters (:data:`skyfit.fit.parameters.PARAMETERS`: scales, beta_550, AOD, Angstrom alpha, ssa...,
which map onto these), so they are not derived from that table."""

# Per-method settings: the defaults, except where precomputation would dominate the run time.
REPORT_SETTINGS: dict[str, dict] = {name: {} for name in INTEGRATORS}
FAST_SETTINGS: dict[str, dict] = {
    "trapezoid": {"samples": 16},
    "midpoint": {"samples": 16},
    "simpson": {"samples": 17},
    "gauss": {"samples": 16},
    "bruneton_lut": {"mu_size": 32, "r_size": 8, "samples": 16},
    "spline": {"height_points": 16, "distance_points": 8},
}


@dataclasses.dataclass(frozen=True)
class Grid:
    """Axis values of the extreme grid (see the module docstring)."""

    altitudes: tuple = ALTITUDES_M
    sun_zenith_deg: tuple = SUN_ZENITH_DEG
    mie_g: tuple = MIE_G
    scale_heights: tuple = SCALE_HEIGHTS_M
    betas: tuple = BETAS
    horizon_views: bool = True
    cross: bool = False


COARSE = Grid(
    altitudes=(("ground", 0.0), ("top", None), ("space (2 x top)", None)),
    sun_zenith_deg=(0.0, 90.27, 108.0),
    mie_g=(-0.9999, 0.9999),
    scale_heights=(10.0, 100_000.0),
    betas=(0.0, 1e-2),
)
"""The test module's grid: the ends of every axis."""


def _altitude_values(grid: Grid, atm: Atmosphere) -> list[tuple[str, float]]:
    top = atm.top_radius - atm.bottom_radius
    fill = {"top-1m": top - 1.0, "top": top, "space (2 x top)": 2.0 * top}
    return [(lab, fill[lab] if v is None else v) for lab, v in grid.altitudes]


def view_cosines(altitude: float, bottom_radius: float, horizon: bool = True) -> list[tuple[str, float]]:
    """(label, mu) of the view rays from one altitude (the sun-direction view is added separately)."""
    out = [("up", 1.0), ("+1e-3", 1e-3), ("+1e-6", 1e-6), ("0", 0.0), ("-1e-6", -1e-6), ("-1e-3", -1e-3), ("down", -1.0)]
    r = bottom_radius + altitude
    if horizon and altitude > 0:
        mu_h = -math.sqrt(max(1.0 - (bottom_radius / r) ** 2, 0.0))
        out += [("ground horizon", mu_h), ("ground horizon+1e-6", mu_h + 1e-6), ("ground horizon-1e-6", mu_h - 1e-6)]
    return out


@dataclasses.dataclass
class RayGroup:
    """Rays from one observer altitude with one sun zenith angle, float64 (cast per dtype later)."""

    altitude_label: str
    sun_label: str
    r: Tensor
    mu: Tensor
    mu_s: Tensor
    nu: Tensor
    view_labels: list


def ray_groups(grid: Grid, atm: Atmosphere) -> list[RayGroup]:
    """Every (altitude, sun zenith) group with its view rays: each view cosine at relative
    azimuths 0 and 180 degrees (towards and away from the sun), and the view at the sun."""
    groups = []
    for alab, alt in _altitude_values(grid, atm):
        for sz in grid.sun_zenith_deg:
            mu_s = math.cos(math.radians(sz)) if sz != 90.0 else 0.0
            sin_s = math.sqrt(max(1.0 - mu_s * mu_s, 0.0))
            rows = []
            for vlab, mu in view_cosines(alt, atm.bottom_radius, grid.horizon_views):
                sin_v = math.sqrt(max(1.0 - mu * mu, 0.0))
                for sgn in (1.0, -1.0):
                    rows.append((vlab, mu, max(-1.0, min(1.0, mu * mu_s + sgn * sin_v * sin_s))))
            rows.append(("at the sun", mu_s, 1.0))
            n = len(rows)
            T = lambda v: torch.tensor(v, dtype=torch.float64)  # noqa: E731
            groups.append(
                RayGroup(alab, f"{sz:g}", T([atm.bottom_radius + alt] * n), T([x[1] for x in rows]), T([mu_s] * n), T([x[2] for x in rows]), [x[0] for x in rows])
            )
    return groups


# ---------------------------------------------------------------------------
# atmospheres


def base_atmosphere(dtype=torch.float64) -> Atmosphere:
    """Earth (Bruneton 2017's parameters) at :data:`WAVELENGTHS_NM`."""
    return load_atmosphere("earth", list(WAVELENGTHS_NM), dtype=dtype)


def atmosphere_cases(grid: Grid) -> list[tuple[dict, dict]]:
    """(axis labels, parameter overrides) of every atmosphere of the grid.

    Overrides: ``H`` (both scale heights) [m], ``beta`` (every coefficient) [1/m], ``g`` [1].
    """
    if grid.cross:
        return [
            ({"H": f"{h:g} m", "beta": f"{b:g} /m", "g": f"{g:g}"}, {"H": h, "beta": b, "g": g})
            for h in grid.scale_heights for b in grid.betas for g in grid.mie_g
        ]
    cases = [({"base": "Earth"}, {})]
    cases += [({"H": f"{h:g} m"}, {"H": h}) for h in grid.scale_heights]
    cases += [({"beta": f"{b:g} /m"}, {"beta": b}) for b in grid.betas]
    cases += [({"g": f"{g:g}"}, {"g": g}) for g in grid.mie_g]
    return cases


def make_atmosphere(overrides: dict, dtype, ozone: bool = True) -> tuple[Atmosphere, dict[str, Tensor]]:
    """An Atmosphere with the overrides and every leaf of :data:`GRADIENT_LEAVES` requiring grad
    (Earth's ozone layer kept unless ``ozone=False``)."""
    base = base_atmosphere(torch.float64)
    v = {n: getattr(base, n).detach().clone() for n in GRADIENT_LEAVES}
    if "H" in overrides:
        v["rayleigh_scale_height"] = torch.tensor(float(overrides["H"]), dtype=torch.float64)
        v["mie_scale_height"] = torch.tensor(float(overrides["H"]), dtype=torch.float64)
    if "beta" in overrides:
        b = float(overrides["beta"])
        v["rayleigh_scattering"] = torch.tensor([b, 0.5 * b], dtype=torch.float64)
        v["mie_extinction"] = torch.tensor([b, 0.8 * b], dtype=torch.float64)
        v["mie_scattering"] = MIE_SSA * v["mie_extinction"]
    if "g" in overrides:
        v["mie_g"] = torch.tensor(float(overrides["g"]), dtype=torch.float64)
    leaves = {n: t.to(dtype).requires_grad_(True) for n, t in v.items()}
    atm = base.to(dtype=dtype).replace(**leaves)
    if not ozone:
        atm = atm.replace(ozone_absorption=None)
    return atm, leaves


# ---------------------------------------------------------------------------
# counting


@dataclasses.dataclass
class Tally:
    """Counts for one (method, dtype, axis, value) cell of the report."""

    rays: int = 0
    values: int = 0
    bad_values: int = 0
    negative: int = 0
    grads: int = 0
    bad_grads: int = 0
    refused: int = 0
    messages: set = dataclasses.field(default_factory=set)
    errors: set = dataclasses.field(default_factory=set)  # unexpected exceptions (not ValueError)
    bad_where: list = dataclasses.field(default_factory=list)  # a few locations of non-finite results

    def add(self, other: "Tally") -> None:
        for f in ("rays", "values", "bad_values", "negative", "grads", "bad_grads", "refused"):
            setattr(self, f, getattr(self, f) + getattr(other, f))
        self.messages |= other.messages
        self.errors |= other.errors
        self.bad_where += other.bad_where[: max(0, 5 - len(self.bad_where))]


def _first_line(e: BaseException) -> str:
    return f"{type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''}"


def evaluate_group(render: Callable[[Tensor, Tensor, Tensor, Tensor], Tensor], group: RayGroup, leaves: dict[str, Tensor], dtype, where: str) -> tuple[Tally, dict[str, Tally]]:
    """Render one group, count non-finite values (per view label too) and gradients.

    Returns:
        (the group's tally, tallies per view label).
    """
    t = Tally(rays=group.r.numel())
    per_view: dict[str, Tally] = defaultdict(Tally)
    r, mu, mu_s, nu = (x.to(dtype) for x in (group.r, group.mu, group.mu_s, group.nu))
    try:
        out = render(r, mu, mu_s, nu)
    except ValueError as e:
        t.refused = t.rays
        t.messages.add(_first_line(e))
        for lab in group.view_labels:
            per_view[lab].rays += 1
            per_view[lab].refused += 1
            per_view[lab].messages.add(_first_line(e))
        return t, per_view
    except Exception as e:  # noqa: BLE001 - anything else is a bug the report must show
        t.errors.add(_first_line(e))
        for lab in group.view_labels:
            per_view[lab].rays += 1
            per_view[lab].errors.add(_first_line(e))
        return t, per_view
    with torch.no_grad():
        finite = torch.isfinite(out)
        neg = out < 0
    t.values, t.bad_values, t.negative = out.numel(), int((~finite).sum()), int(neg.sum())
    for i, lab in enumerate(group.view_labels):
        pv = per_view[lab]
        pv.rays += 1
        pv.values += out.shape[-1]
        pv.bad_values += int((~finite[i]).sum())
        pv.negative += int(neg[i].sum())
        if not bool(finite[i].all()):
            pv.bad_where.append(f"{where}, view {lab}, nu={float(group.nu[i]):.6g}")
    if t.bad_values:
        t.bad_where.append(f"{where}: values")
    names = list(leaves)
    # retain_graph: a table built once per atmosphere (multiple scattering) is shared by the groups.
    grads = torch.autograd.grad(
        torch.where(finite, out, torch.zeros_like(out)).sum(), [leaves[n] for n in names], allow_unused=True, retain_graph=True
    )
    for n, g in zip(names, grads):
        if g is None:
            continue  # the method does not depend on it (e.g. albedo with no ground ray)
        t.grads += g.numel()
        nb = int((~torch.isfinite(g)).sum())
        t.bad_grads += nb
        if nb:
            t.bad_where.append(f"{where}: d/d{n}")
    for pv in per_view.values():  # gradients are per group; a bad group marks all its views
        pv.grads += 1
        pv.bad_grads += int(t.bad_grads > 0)
    return t, per_view


# ---------------------------------------------------------------------------
# single scattering over the grid


def single_renderer(name: str, settings: dict, atm: Atmosphere, view_samples: int = 16) -> Callable:
    integ = make_integrator(name, **settings)
    column_fn = integ.prepare(atm.scale_heights, atm.bottom_radius, atm.top_radius)  # tables once per atmosphere

    def render(r, mu, mu_s, nu):
        return single_scattering(atm, r, mu, mu_s, nu, integ, view_samples=view_samples, rule="gauss", sun_disk=True, column_fn=column_fn)

    return render


MULTIPLE_TABLE_SIZES = dict(
    transmittance_mu=32, transmittance_r=8, irradiance_mu_s=8, irradiance_r=4,
    scattering_r=4, scattering_mu=8, scattering_mu_s=4, scattering_nu=4,
)
"""Small Bruneton tables (CPU time): the check is for NaN/Inf, not accuracy (docs/multiple_scattering.md)."""
MULTIPLE_QUADRATURE = dict(transmittance_samples=40, single_samples=8, multiple_samples=8, density_theta=4, density_phi=8, irradiance_theta=3, irradiance_phi=8)
HILLAIRE_LUT = dict(size=(8, 8), directions=16, samples=8)


def bruneton_renderer(atm: Atmosphere, orders: int = 3, below_mu_s_min: str = "raise") -> Callable:
    """Bruneton & Neyret 2008 tables (small sizes) for ``atm``, and their lookup."""
    tables = precompute(atm, orders=orders, sizes=TableSizes(**MULTIPLE_TABLE_SIZES), quadrature=Quadrature(**MULTIPLE_QUADRATURE))

    def render(r, mu, mu_s, nu):
        return sky_radiance(tables, atm, r, mu, mu_s, nu, sun_disk=True, below_mu_s_min=below_mu_s_min)

    return render


def hillaire_renderer(atm: Atmosphere, integrator: str = "gauss", settings: dict | None = None, view_samples: int = 16) -> Callable:
    """Hillaire 2020's multiple-scattering LUT (small) plus single scattering with ``integrator``."""
    sizes = TableSizes(transmittance_mu=MULTIPLE_TABLE_SIZES["transmittance_mu"], transmittance_r=MULTIPLE_TABLE_SIZES["transmittance_r"])
    lut = hillaire_lut(atm, transmittance_sizes=sizes, transmittance_samples=MULTIPLE_QUADRATURE["transmittance_samples"], **HILLAIRE_LUT)
    integ = make_integrator(integrator, **(FAST_SETTINGS.get(integrator, {}) if settings is None else settings))

    def render(r, mu, mu_s, nu):
        return hillaire_sky_radiance(atm, r, mu, mu_s, nu, integ, view_samples=view_samples, lut=lut, rule="gauss", sun_disk=True)

    return render


def radiance_scene(
    method: str,
    make_render: Callable[[Atmosphere], Callable],
    grid: Grid,
    dtypes: Iterable = (torch.float64, torch.float32),
    progress: Callable | None = None,
) -> dict:
    """Tallies of one method over the grid: ``{(dtype, axis, value): Tally}``.

    Axes: "H", "beta", "g", "base" (atmospheres), "altitude", "sun zenith", "view" (geometry).
    Geometry cells aggregate over every atmosphere; atmosphere cells over every ray.
    ``make_render(atm)`` returns ``render(r, mu, mu_s, nu) -> radiance``; a ValueError from it
    (e.g. a table's regime) refuses the whole atmosphere.
    """
    cells: dict = defaultdict(Tally)
    for dtype in dtypes:
        dn = str(dtype).replace("torch.", "")
        for labels, over in atmosphere_cases(grid):
            atm, leaves = make_atmosphere(over, dtype)
            where = f"{method} {dn} " + ", ".join(f"{k}={v}" for k, v in labels.items())
            try:
                render = make_render(atm)
                groups = ray_groups(grid, atm)
            except ValueError as e:
                render, groups = None, ray_groups(grid, atm)
                msg = _first_line(e)
            for grp in groups:
                if render is None:
                    t = Tally(rays=grp.r.numel(), refused=grp.r.numel(), messages={msg})
                    pv = {}
                    for lab in grp.view_labels:
                        pv.setdefault(lab, Tally()).add(Tally(rays=1, refused=1, messages={msg}))
                else:
                    t, pv = evaluate_group(render, grp, leaves, dtype, f"{where}, alt={grp.altitude_label}, sun={grp.sun_label}")
                for k, v in labels.items():
                    cells[(dn, k, v)].add(t)
                cells[(dn, "altitude", grp.altitude_label)].add(t)
                cells[(dn, "sun zenith", grp.sun_label)].add(t)
                for lab, tv in pv.items():
                    cells[(dn, "view", lab)].add(tv)
                if progress:
                    progress()
    return dict(cells)


# ---------------------------------------------------------------------------
# optical-depth columns against scipy


def column_segments(grid: Grid, atm: Atmosphere) -> list[tuple[str, str, float, float, float]]:
    """(axis, label, r, mu, length) of the view segments and sun rays of the grid (float64).

    View segments: the part of each view ray inside the atmosphere (from the
    observer, or from where a ray from space enters). Sun rays: from the
    observer (inside the atmosphere) to the top, along max(mu_s, horizon) as
    single scattering does.
    """
    Rb, Rt = atm.bottom_radius, atm.top_radius
    out = []
    T = lambda v: torch.tensor([v], dtype=torch.float64)  # noqa: E731
    for alab, alt in _altitude_values(grid, atm):
        r = Rb + alt
        for vlab, mu in view_cosines(alt, Rb, grid.horizon_views):
            start, end, _ = atmosphere_segment(T(r), T(mu), Rb, Rt)
            r0, mu0 = point_along_ray(T(r), T(mu), start)
            L = float(end - start)
            if L > 0:
                out.append(("view", f"{vlab} @ {alab}", float(r0), float(mu0), L))
        if r <= Rt:
            for sz in grid.sun_zenith_deg:
                mu_s = math.cos(math.radians(sz)) if sz != 90.0 else 0.0
                mu_c = float(sun_ray_cosine(T(r), T(mu_s), Rb))
                L = float(distance_to_top(T(r), T(mu_c), Rt))
                if L > 0:
                    out.append(("sun", f"sun {sz:g} @ {alab}", r, mu_c, L))
    return out


def column_errors(
    name: str,
    settings: dict,
    grid: Grid,
    dtypes: Iterable = (torch.float64, torch.float32),
    reference_cache: dict | None = None,
) -> dict:
    """Max relative column error vs scipy and non-finite counts, ``{(dtype, axis, value): dict}``.

    Axes: "H" (each scale height alone, K = 1), "segment" ("view"/"sun"), and "altitude".
    The reference is evaluated at the inputs the method saw (rounded to its dtype), so the
    error is the method's, not the rounding of r to float32 (0.5 m at Earth's radius).
    """
    atm = base_atmosphere()
    Rb, Rt = atm.bottom_radius, atm.top_radius
    segs = column_segments(grid, atm)
    cache = {} if reference_cache is None else reference_cache
    integ = make_integrator(name, **settings)
    cells: dict = defaultdict(lambda: {"n": 0, "max_rel_err": 0.0, "worst": "", "bad_values": 0, "bad_grads": 0, "refused": 0, "messages": set()})
    for dtype in dtypes:
        dn = str(dtype).replace("torch.", "")
        for H in grid.scale_heights:
            Ht = torch.tensor([H], dtype=dtype, requires_grad=True)
            for kind in ("view", "sun"):
                rows = [s for s in segs if s[0] == kind]
                if not rows:
                    continue
                r = torch.tensor([s[2] for s in rows], dtype=dtype)
                mu = torch.tensor([s[3] for s in rows], dtype=dtype)
                L = torch.tensor([s[4] for s in rows], dtype=dtype)
                keys = [(dn, "H", f"{H:g} m"), (dn, "segment", kind)]
                try:
                    fn = integ.prepare(Ht, Rb, Rt)
                    col = fn(r, mu, L)[..., 0]
                except ValueError as e:
                    # refused as a batch: try each segment, to count what the method accepts
                    col = None
                    msg = _first_line(e)
                if col is None:
                    vals = []
                    for i in range(len(rows)):
                        try:
                            vals.append(integ.prepare(Ht, Rb, Rt)(r[i : i + 1], mu[i : i + 1], L[i : i + 1])[..., 0])
                        except ValueError as e:
                            vals.append(None)
                            msg = _first_line(e)
                    ok = [i for i, v in enumerate(vals) if v is not None]
                    for i, s in enumerate(rows):
                        if vals[i] is None:
                            for key in keys + [(dn, "altitude", s[1].split(" @ ")[1])]:
                                cells[key]["refused"] += 1
                                cells[key]["messages"].add(msg)
                    if not ok:
                        continue
                    rows = [rows[i] for i in ok]
                    r, mu, L = r[ok], mu[ok], L[ok]
                    col = torch.cat([vals[i] for i in ok])
                (gH,) = torch.autograd.grad(torch.where(torch.isfinite(col), col, torch.zeros_like(col)).sum(), [Ht])
                bad_g = int((~torch.isfinite(gH)).sum())
                c = col.detach().double().cpu().numpy()
                ref = []
                for i in range(len(rows)):
                    args = (float(r[i]), float(mu[i]), float(L[i]), float(H), Rb)
                    if args not in cache:
                        cache[args] = column_quad(*args)
                    ref.append(cache[args])
                err = relative_column_error(c, np.array(ref))
                for i, s in enumerate(rows):
                    e = float(err[i]) if np.isfinite(err[i]) else math.inf
                    for key in keys + [(dn, "altitude", s[1].split(" @ ")[1])]:
                        cell = cells[key]
                        cell["n"] += 1
                        cell["bad_values"] += int(not np.isfinite(c[i]))
                        if e > cell["max_rel_err"] or (e == cell["max_rel_err"] == 0 and not cell["worst"]):
                            cell["max_rel_err"] = e
                            cell["worst"] = f"{s[1]}, H={H:g} m"
                for key in keys:
                    cells[key]["bad_grads"] += bad_g
    return dict(cells)


# ---------------------------------------------------------------------------
# single-scattering radiance against the scipy reference

REFERENCE_GRID = Grid(
    altitudes=(("ground", 0.0), ("10 km", 1e4), ("top", None), ("space (2 x top)", None)),
    sun_zenith_deg=(0.0, 85.0, 90.27, 108.0),
)
"""Geometry of the radiance comparison (each scipy reference ray costs ~0.05 s)."""
RADIANCE_FLOOR: float = 1e-6
"""Radiance errors are relative to max(|reference|, this x the atmosphere's largest reference radiance). [1]"""


def _vectors(mu: float, mu_s: float, nu: float) -> tuple[np.ndarray, np.ndarray]:
    """Unit view and sun vectors (z up) with the given cosines."""
    sin_s = math.sqrt(max(1.0 - mu_s * mu_s, 0.0))
    s = np.array([sin_s, 0.0, mu_s])
    sin_v2 = max(1.0 - mu * mu, 0.0)
    a = (nu - mu * mu_s) / sin_s if sin_s > 0 else math.sqrt(sin_v2)
    a = max(-math.sqrt(sin_v2), min(math.sqrt(sin_v2), a))
    v = np.array([a, math.sqrt(max(sin_v2 - a * a, 0.0)), mu])
    return v, s


def radiance_errors(
    name: str,
    settings: dict,
    reference_factory: Callable,
    grid: Grid = REFERENCE_GRID,
    dtypes: Iterable = (torch.float64, torch.float32),
    view_samples: int = 64,
    cache: dict | None = None,
    progress: Callable | None = None,
) -> dict:
    """Max relative error of single scattering (no sun disc, no ozone) against an independent float64 reference.

    Args:
        reference_factory: ``atm -> obj`` with ``obj.radiance(r, v, s) -> (W,)`` numpy array, e.g. the
            scipy reference of tests/test_single_scattering_reference.py.
        cache: reference radiances by (atmosphere overrides, r, mu, mu_s, nu), shared across methods.

    Returns:
        ``{(dtype, axis, value): {"n", "max_rel_err", "worst", "refused", "messages"}}``.
    """
    cache = {} if cache is None else cache
    integ = make_integrator(name, **settings)
    cells: dict = defaultdict(lambda: {"n": 0, "max_rel_err": 0.0, "worst": "", "refused": 0, "messages": set()})
    for labels, over in atmosphere_cases(grid):
        atm64, _ = make_atmosphere(over, torch.float64, ozone=False)
        key0 = tuple(sorted(over.items()))
        groups = ray_groups(grid, atm64)
        refs = []
        ref_obj = None
        for grp in groups:
            rows = []
            for i in range(grp.r.numel()):
                k = (key0, float(grp.r[i]), float(grp.mu[i]), float(grp.mu_s[i]), float(grp.nu[i]))
                if k not in cache:
                    ref_obj = ref_obj or reference_factory(atm64)
                    v, s = _vectors(*k[2:])
                    cache[k] = np.asarray(ref_obj.radiance(k[1], v, s), float)
                rows.append(cache[k])
            refs.append(np.stack(rows))
        floor = RADIANCE_FLOOR * max(float(np.abs(x).max()) for x in refs)
        for dtype in dtypes:
            dn = str(dtype).replace("torch.", "")
            atm, _ = make_atmosphere(over, dtype, ozone=False)
            try:
                column_fn = integ.prepare(atm.scale_heights, atm.bottom_radius, atm.top_radius)
            except ValueError as e:
                column_fn, msg = None, _first_line(e)
            for grp, ref in zip(groups, refs):
                keys = [(dn, k, v) for k, v in labels.items()] + [(dn, "altitude", grp.altitude_label), (dn, "sun zenith", grp.sun_label)]
                out = None
                if column_fn is not None:
                    try:
                        with torch.no_grad():
                            out = single_scattering(
                                atm, *(x.to(dtype) for x in (grp.r, grp.mu, grp.mu_s, grp.nu)), integ,
                                view_samples=view_samples, rule="gauss", column_fn=column_fn,
                            )
                    except ValueError as e:
                        msg = _first_line(e)
                if out is None:
                    for k in keys:
                        cells[k]["refused"] += grp.r.numel()
                        cells[k]["messages"].add(msg)
                    continue
                val = out.double().cpu().numpy()
                err = np.abs(val - ref) / np.maximum(np.abs(ref), floor)
                err = np.where(np.isfinite(err), err, np.inf).max(-1)
                at = f"{', '.join(f'{k}={v}' for k, v in labels.items())}, alt={grp.altitude_label}, sun={grp.sun_label}"
                for i, lab in enumerate(grp.view_labels):
                    where = f"{at}, view {lab} (nu={float(grp.nu[i]):.4g})"
                    for k in keys + [(dn, "view", lab)]:
                        c = cells[k]
                        c["n"] += 1
                        if float(err[i]) >= c["max_rel_err"]:
                            c["max_rel_err"], c["worst"] = float(err[i]), where
            if progress:
                progress()
    return dict(cells)
