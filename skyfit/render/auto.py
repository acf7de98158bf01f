"""Automatic renderer settings: the cheapest measured setting that meets an accuracy target.

``skyfit bench --study trade`` measures, on fixed scenes (sun zenith x observer altitude),
the cost and the error against a converged reference of every setting of the trade study
(optical-depth method, light and view samples, outer rule, dtype, single scattering or
multiple scattering by Hillaire's LUT or Bruneton's tables). Its ``frontier.json`` is
shipped as ``skyfit/data/auto_settings.json``; this module reads it and answers "which
setting is cheapest while meeting a tolerance, for this scene".

The rule, stated so that it can be checked (tests/test_auto_settings.py does, against a
converged reference computed in the test):

1. Scene bracket: the measured sun zeniths Z_1 < ... < Z_k and altitudes A_1 < ... < A_m
   bound the query's bins. A query sun zenith z in [Z_i, Z_i+1] uses both Z_i and Z_i+1
   (outside [Z_1, Z_k], the nearest one); likewise the altitude. A fit with several
   observations uses the union of their brackets.
2. Error of a setting: the largest measured error over the bracket's scenes; cost: the
   largest measured process CPU time (render of one image plus precomputation such as a
   LUT) over those scenes.
3. Choice: the cheapest setting whose error is at most ``MARGIN`` x the tolerance (the
   margin covers other pixel sets and wavelength grids than the bench's); ties go to the
   smaller error. No setting meets it: :class:`ValueError` naming the best measured error.

Tolerances: ``de=X`` (mean CIE 1976 ΔE of the sky, white = 99th percentile luminance,
as ``skyfit bench``), ``rel=X`` (relative RMS radiance error ||L - L_ref|| / ||L_ref|| over
pixels and wavelengths), ``auto`` (render: ``de=1``; fit and sample: the data's noise, see
:func:`noise_tolerance`).
"""
from __future__ import annotations

import dataclasses
import functools
import json
import math
from collections.abc import Iterable, Sequence
from pathlib import Path

import numpy as np

FRONTIER_PATH: Path = Path(__file__).resolve().parents[1] / "data" / "auto_settings.json"
"""The measured trade study shipped with the package (written by ``skyfit bench --study trade``)."""

MARGIN: float = 0.7
"""A setting is chosen only if its measured error is <= MARGIN x the tolerance [1]. Measured
on the fixed scenes, the error of a setting on another pixel set or wavelength grid of the
same scene changed by up to ~20 % (docs/benchmarks.md, "Automatic settings")."""

RENDER_DEFAULTS: dict = {"integrator": "gauss:samples=16", "view_samples": 24, "rule": "gauss", "spacing": "geometric"}
"""``skyfit render``'s settings without ``--accuracy`` (single scattering): Gauss-Legendre optical depth
(16 nodes) and a 24-node Gauss-Legendre view integral on geometrically spaced nodes
(:func:`skyfit.scattering.single.geometric_nodes`). Every pixel above 5° elevation within 1 % of the
converged float64 radiance, for every shipped config, sun zenith 0-93° and observers at 0 and 10 km
(measured: docs/accuracy.md, "Render defaults"; scripts/render_defaults_check.py;
tests/test_render_defaults.py). ``--accuracy`` trades it for speed."""

DEFAULT_DELTA_E: float = 1.0
"""``--accuracy auto`` for a render: mean ΔE 1 (CIE 1976), about the just-noticeable difference."""

NOISE_FRACTION: float = 1.0 / 3.0
"""Fit/sample ``accuracy: auto`` (or ``noise``): relative model error <= this fraction of the
data's median relative sigma, so that the model error adds < 6 % in quadrature to the noise
(sqrt(1 + 1/9) = 1.054) [1]."""

METRICS = {"de": "mean_delta_e", "rel": "rel_rmse"}


@dataclasses.dataclass(frozen=True)
class Tolerance:
    """An accuracy target: ``metric`` ("de" or "rel") and its largest allowed ``value``."""

    metric: str
    value: float

    def __str__(self) -> str:
        return f"{self.metric}={self.value:g}"


def parse_accuracy(text: str, noise_rel: float | None = None) -> Tolerance:
    """``auto``, ``noise``, ``de=X`` or ``rel=X`` -> :class:`Tolerance`.

    Args:
        text: the flag or config value.
        noise_rel: the data's median relative sigma (fit/sample); ``auto`` and ``noise`` then
            mean ``rel = NOISE_FRACTION * noise_rel``; without it ``auto`` is ``de=1``.

    Raises:
        ValueError: an unknown form, a non-positive or non-finite value, or ``noise`` without data.
    """
    t = str(text).strip().lower()
    if t in ("auto", "noise"):
        if noise_rel is not None:
            return Tolerance("rel", NOISE_FRACTION * float(noise_rel))
        if t == "noise":
            raise ValueError("accuracy 'noise' needs data with a noise model (fit or sample); use de=X or rel=X")
        return Tolerance("de", DEFAULT_DELTA_E)
    key, eq, val = t.partition("=")
    if not eq or key.strip() not in METRICS:
        raise ValueError(f"accuracy must be 'auto', 'de=X' (mean ΔE) or 'rel=X' (relative radiance error), got {text!r}")
    try:
        v = float(val)
    except ValueError:
        raise ValueError(f"accuracy {text!r}: {val!r} is not a number") from None
    if not (math.isfinite(v) and v > 0):
        raise ValueError(f"accuracy {text!r}: the tolerance must be a finite number > 0")
    return Tolerance(key.strip(), v)


def noise_tolerance(values: Sequence, sigmas: Sequence) -> float:
    """The data's median relative sigma, median(sigma / |value|) over samples with value != 0. [1]

    Args:
        values, sigmas: per observation, arrays of the same shape (any). [data unit]
    """
    rel = []
    for v, s in zip(values, sigmas):
        v, s = np.abs(np.asarray(v, float)).ravel(), np.asarray(s, float).ravel()
        ok = v > 0
        rel.append(s[ok] / v[ok])
    rel = np.concatenate(rel) if rel else np.array([])
    if rel.size == 0:
        raise ValueError("no positive data values to derive a noise level from")
    return float(np.median(rel))


@dataclasses.dataclass(frozen=True)
class Choice:
    """A chosen setting, what the measurement predicts for it, and the most expensive alternative.

    Attributes:
        setting: the frontier's setting dict (``integrator``, ``view_samples``, ``rule``, ``dtype``,
            ``orders``, ``multiple``, ``table_sizes``, ``hillaire_lut``).
        tolerance: the target.
        predicted_error: largest measured error over the bracket's scenes (the target's metric).
        predicted_cpu_s: largest measured cost over the bracket's scenes. [s]
        scenes: names of the measured scenes the choice is based on.
        max_cpu_s: cost of the most expensive measured setting of the family over the same scenes. [s]
    """

    setting: dict
    tolerance: Tolerance
    predicted_error: float
    predicted_cpu_s: float
    scenes: tuple[str, ...]
    max_cpu_s: float

    def integrator_text(self) -> str:
        return self.setting["integrator"]

    def summary(self) -> dict:
        return {"tolerance": str(self.tolerance), "setting": self.setting, "predicted_error": self.predicted_error,
                "predicted_cpu_s": self.predicted_cpu_s, "scenes": list(self.scenes), "max_cpu_s": self.max_cpu_s}


@functools.lru_cache(maxsize=4)
def _load(path: str) -> dict:
    with open(path) as f:
        return json.load(f)


def load_frontier(path: str | Path | None = None) -> dict:
    """The trade study's measurements (default: the shipped :data:`FRONTIER_PATH`)."""
    p = Path(path) if path is not None else FRONTIER_PATH
    if not p.is_file():
        raise ValueError(f"no trade-study measurements at {p}; run `skyfit bench --study trade --frontier-out {p}`")
    return _load(str(p))


def _bracket(grid: Sequence[float], x: float) -> list[float]:
    g = sorted(set(float(v) for v in grid))
    if x <= g[0]:
        return [g[0]]
    if x >= g[-1]:
        return [g[-1]]
    i = int(np.searchsorted(g, x, side="right")) - 1
    return [g[i]] if g[i] == x else [g[i], g[i + 1]]


EXTRAPOLATE_ZENITH_DEG: float = 2.0
"""A sun zenith up to this much beyond the largest measured one uses that scene; further: refused. [deg]
(Below the smallest measured zenith, 20°, the high-sun scene is used: the sky changes slowly there.)"""


def bracket_scenes(frontier: dict, sun_zeniths_deg: Iterable[float], altitudes_m: Iterable[float]) -> list[str]:
    """Names of the measured scenes bracketing each (sun zenith, altitude) pair (rule 1 above).

    Raises:
        ValueError: a sun zenith beyond the measured ones (+ EXTRAPOLATE_ZENITH_DEG), or an altitude
            outside the measured range.
    """
    scenes = frontier["scenes"]
    zs = [s["sun_zenith_deg"] for s in scenes]
    hs = [s["altitude_m"] for s in scenes]
    by = {(float(s["sun_zenith_deg"]), float(s["altitude_m"])): s["name"] for s in scenes}
    names: list[str] = []
    for z, h in zip(sun_zeniths_deg, altitudes_m):
        if z > max(zs) + EXTRAPOLATE_ZENITH_DEG:
            raise ValueError(f"sun zenith {z:.4g} deg is beyond the measured scenes (up to {max(zs):g} deg); "
                             "give the renderer settings explicitly")
        if not (min(hs) - 1.0 <= h <= max(hs) + 1.0):
            raise ValueError(f"observer altitude {h:.6g} m is outside the measured scenes ({min(hs):g}-{max(hs):g} m); "
                             "give the renderer settings explicitly")
        for zb in _bracket(zs, float(z)):
            for hb in _bracket(hs, float(h)):
                name = by.get((zb, hb))
                if name is None:
                    raise ValueError(f"the trade study has no scene at sun zenith {zb:g} deg, altitude {hb:g} m")
                if name not in names:
                    names.append(name)
    return names


def _family(orders: int) -> str:
    return "single" if orders == 1 else "multiple"


def choose(tolerance: Tolerance, sun_zenith_deg: float | Sequence[float], altitude_m: float | Sequence[float] = 0.0,
           orders: int = 1, dtype: str = "float32", frontier: dict | None = None, margin: float = MARGIN) -> Choice:
    """The cheapest measured setting meeting ``tolerance`` on the scene(s) (rules 1-3 of the module).

    Args:
        tolerance: the target.
        sun_zenith_deg: sun zenith of the scene, or one per observation. [deg]
        altitude_m: observer altitude, scalar or one per observation. [m]
        orders: 1 chooses among single-scattering settings; >= 2 among the multiple-scattering
            ones (Hillaire's LUT and Bruneton's tables with 2-4 orders, measured against a
            reference with more orders).
        dtype: "float32" or "float64": settings measured in that dtype (all if none were).
        frontier: measurements (default :func:`load_frontier`).
        margin: see :data:`MARGIN`.

    Raises:
        ValueError: no measured setting meets the tolerance (the message names the best one).
    """
    fr = load_frontier() if frontier is None else frontier
    z = np.atleast_1d(np.asarray(sun_zenith_deg, float))
    h = np.broadcast_to(np.atleast_1d(np.asarray(altitude_m, float)), z.shape)
    names = bracket_scenes(fr, z.tolist(), h.tolist())
    metric = METRICS[tolerance.metric]
    family = _family(int(orders))
    settings = [s for s in fr["settings"] if s["family"] == family]
    if any(s["dtype"] == dtype for s in settings):
        settings = [s for s in settings if s["dtype"] == dtype]
    if not settings:
        raise ValueError(f"the trade study has no {family}-scattering settings")
    results = fr["results"]  # setting id -> scene name -> {cpu_s, mean_delta_e, rel_rmse, ...}
    best, fallback, most = None, None, 0.0
    for s in settings:
        per = [results[s["id"]].get(n) for n in names]
        if any(p is None or p.get(metric) is None or not math.isfinite(p[metric]) for p in per):
            continue
        err = max(p[metric] for p in per)
        cost = max(p["cpu_s"] + p.get("prepare_cpu_s", 0.0) for p in per)
        most = max(most, cost)
        if fallback is None or err < fallback[0]:
            fallback = (err, s)
        if err <= margin * tolerance.value and (best is None or (cost, err) < (best[0], best[1])):
            best = (cost, err, s)
    if best is None:
        if fallback is None:
            raise ValueError(f"the trade study has no finite {metric} for scenes {names}")
        raise ValueError(f"no measured setting reaches {tolerance} (x margin {margin:g}) on scenes {', '.join(names)}; "
                         f"the most accurate one measured, {describe(fallback[1])}, has {tolerance.metric} {fallback[0]:.3g}")
    cost, err, s = best
    return Choice(dict(s), tolerance, err, cost, tuple(names), most)


def describe(setting: dict) -> str:
    """One line: what the setting renders with."""
    if setting.get("multiple") == "bruneton":
        return f"bruneton tables {setting['table_sizes']}, {setting['orders']} orders ({setting['dtype']})"
    text = f"{setting['integrator']}, {setting['view_samples']} view samples ({setting['rule']}), {setting['dtype']}"
    if setting.get("multiple") == "hillaire":
        text = f"hillaire LUT {setting['hillaire_lut']} + " + text
    return text


def fit_overrides(accuracy: str, observations: Sequence, orders: int = 1, dtype: str = "float64",
                  frontier: dict | None = None) -> tuple[dict, Choice]:
    """FitSettings fields for ``accuracy`` on a fit's observations -> (overrides, choice).

    ``auto``/``noise``: the tolerance is ``rel = NOISE_FRACTION x`` the observations' median
    relative sigma (over their masked samples); ``de=X``/``rel=X`` as given. The scene bracket
    covers every observation's sun zeniths and altitude.

    Args:
        accuracy: the ``fit.accuracy`` value.
        observations: :class:`skyfit.fit.data.Observation` (``values``, ``sigma``, ``mask``,
            ``sun_zenith`` [rad], ``altitude_m`` [m]).
        orders, dtype: the fit's.
    """
    noise = noise_tolerance([o.values[o.mask].detach().cpu().numpy() for o in observations],
                            [o.sigma[o.mask].detach().cpu().numpy() for o in observations])
    tol = parse_accuracy(accuracy, noise_rel=noise)
    zen, alt = [], []
    for o in observations:
        z = np.degrees(np.atleast_1d(o.sun_zenith.detach().cpu().numpy().astype(float)))
        z = np.unique(np.round(z, 1))
        zen += z.tolist()
        alt += [float(o.altitude_m)] * len(z)
    c = choose(tol, zen, alt, orders=orders, dtype=dtype, frontier=frontier)
    return setting_fields(c.setting), c


def setting_fields(st: dict) -> dict:
    """A measured setting (a frontier row) as renderer fields of :class:`skyfit.fit.problem.FitSettings`
    (integrator spec, view_samples, rule; orders, multiple, LUT or table sizes for multiple scattering)."""
    if st["multiple"] == "bruneton":
        # TableSizes fields in order: transmittance mu, r, irradiance mu_s, r (Bruneton 2017's, as measured), scattering.
        out = {"orders": int(st["orders"]), "multiple": "bruneton",
               "table_sizes": [256, 64, 64, 16] + [int(v) for v in st["table_sizes"].split(",")]}
    else:
        out = {"integrator": st["integrator"], "view_samples": int(st["view_samples"]), "rule": st["rule"]}
        if st["multiple"] == "hillaire":
            nh, nm, nd, ns = (int(v) for v in st["hillaire_lut"].split(","))
            out.update(multiple="hillaire", lut_size=[nh, nm], lut_directions=nd, lut_samples=ns)
    return out
