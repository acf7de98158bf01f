"""Stability at the ends of every axis of the extreme grid (issue #7 part 4; docs/stability.md).

The coarse grid :data:`skyfit.tools.stability.COARSE` takes the ends of each axis
(H = 10 m and 100 km, beta = 0 and 1e-2 /m, g = +-0.9999; observer on the
ground, at the top and in space; sun at the zenith, half below the horizon
and 18 deg below it; views straight up/down, +-1e-3, +-1e-6 and 0 around the
horizontal, the ground's horizon +-1e-6, and at the sun) in float64 and
float32. Every method must return finite, non-negative radiance with finite
gradients w.r.t. beta, H, g and the albedo, or refuse with the ValueError of
its documented regime. The optical-depth columns are compared with the
float64 scipy reference (skyfit.tools.reference.column_quad) where the methods
document an accuracy. The full grid is scripts/stability_report.py
(test_full_grid_report, marked slow).
"""
from __future__ import annotations

import math
import re

import pytest
import torch

from skyfit.tools import stability as S
from skyfit.transmittance import INTEGRATORS, make_integrator

# Documented regimes (module docstrings), matched on their messages.
REFUSALS = {
    "height_fog": r"^ValueError: height_fog: flat-Earth curvature fraction",
    "chapman": r"^ValueError: chapman: (X = r/H|a segment dips)",
    "bruneton": r"^SunBelowTables: sun zenith cosine .* below the tables' mu_s_min",  # a ValueError
    "taylor": r"^ValueError: taylor: scale height H = .* is below its regime",
}


def _expected_rays(grid: S.Grid) -> int:
    atm = S.base_atmosphere()
    return len(S.atmosphere_cases(grid)) * sum(g.r.numel() for g in S.ray_groups(grid, atm))


def _assert_stable(name: str, cells: dict, grid: S.Grid):
    for dn in ("float64", "float32"):
        tot = S.Tally()
        for (d, axis, _), t in cells.items():
            if d == dn and axis == "altitude":
                tot.add(t)
        assert tot.rays == _expected_rays(grid), (name, dn, tot.rays)
        assert not tot.errors, (name, dn, tot.errors)
        assert tot.bad_values == 0 and tot.bad_grads == 0, (name, dn, tot.bad_where)
        assert tot.negative == 0, (name, dn)
        if tot.refused:
            assert name in REFUSALS, (name, dn, tot.messages)
            assert all(re.search(REFUSALS[name], m) for m in tot.messages), tot.messages
        accepted = tot.rays - tot.refused
        assert tot.values == 2 * accepted  # two wavelengths per accepted ray, all counted
        if accepted:
            assert tot.grads > 0


@pytest.mark.parametrize("name", INTEGRATORS)
def test_single_scattering_finite_or_refused_on_the_coarse_grid(name):
    cells = S.radiance_scene(name, lambda atm: S.single_renderer(name, S.FAST_SETTINGS.get(name, {}), atm, view_samples=8), S.COARSE)
    _assert_stable(name, cells, S.COARSE)
    if name == "taylor":  # refuses exactly the atmospheres with a scale height below 1 km
        from skyfit.transmittance.taylor import TAYLOR_MIN_SCALE_HEIGHT

        h_cells = [(label, t) for (_, axis, label), t in cells.items() if axis == "H"]
        assert h_cells
        for label, t in h_cells:  # labels "10 m", "100000 m"
            small = float(label.split()[0]) < TAYLOR_MIN_SCALE_HEIGHT
            assert t.refused == (t.rays if small else 0), (label, t.refused, t.rays)
    elif name != "height_fog":  # the flat fog refuses Earth-scale view rays; every other method accepts all
        assert all(t.refused == 0 for t in cells.values())


@pytest.mark.parametrize("method", ["hillaire", "bruneton"])
def test_multiple_scattering_finite_or_refused_on_the_coarse_grid(method):
    mk = S.hillaire_renderer if method == "hillaire" else S.bruneton_renderer
    cells = S.radiance_scene(method, mk, S.COARSE)
    _assert_stable(method, cells, S.COARSE)
    # Bruneton's tables refuse exactly the sun 18 deg below the horizon (mu_s < mu_s_min = -0.2).
    for (dn, axis, v), t in cells.items():
        if axis == "sun zenith":
            assert (t.refused == t.rays) == (method == "bruneton" and v == "108"), (dn, v, t.refused)


def test_the_counter_finds_nan_values_and_gradients():
    """The instrument itself: a renderer with a NaN value in one ray, one with a NaN gradient only."""
    atm, leaves = S.make_atmosphere({}, torch.float64)
    grp = S.ray_groups(S.COARSE, atm)[0]
    at_sun = torch.tensor([lab == "at the sun" for lab in grp.view_labels])

    def nan_value(r, mu, mu_s, nu):
        x = (atm.rayleigh_scattering * atm.mie_g).expand(r.shape[0], -1)
        return torch.where(at_sun.unsqueeze(-1), torch.full_like(x, math.nan), x.abs())

    def nan_gradient(r, mu, mu_s, nu):
        # sqrt'(0) = inf times 0: a finite value, a NaN gradient w.r.t. g.
        return (torch.sqrt(atm.mie_g * 0.0) * 0.0 + atm.rayleigh_scattering).expand(r.shape[0], -1)

    t, per_view = S.evaluate_group(nan_value, grp, leaves, torch.float64, "test")
    assert t.bad_values == 2 and per_view["at the sun"].bad_values == 2 and per_view["up"].bad_values == 0
    t, _ = S.evaluate_group(nan_gradient, grp, leaves, torch.float64, "test")
    assert t.bad_values == 0 and t.bad_grads == 1 and "d/dmie_g" in t.bad_where[0]


def test_coarse_grid_holds_the_ends_of_every_axis():
    g, atm = S.COARSE, S.base_atmosphere()
    assert min(g.scale_heights) == 10.0 and max(g.scale_heights) == 100_000.0
    assert set(g.betas) == {0.0, 1e-2} and set(g.mie_g) == {-0.9999, 0.9999}
    assert 90.27 in g.sun_zenith_deg and max(g.sun_zenith_deg) == 108.0
    alts = dict(S._altitude_values(g, atm))
    assert alts["ground"] == 0.0 and alts["space (2 x top)"] > atm.top_radius - atm.bottom_radius
    mus = {lab: mu for lab, mu in S.view_cosines(alts["top"], atm.bottom_radius)}
    assert mus["+1e-6"] == 1e-6 and mus["-1e-6"] == -1e-6 and mus["0"] == 0.0
    mu_h = -math.sqrt(1.0 - (atm.bottom_radius / atm.top_radius) ** 2)
    assert mus["ground horizon"] == pytest.approx(mu_h, abs=1e-15)
    assert S.Grid().cross is False and len(S.atmosphere_cases(S.Grid(cross=True))) == 100


@pytest.fixture(scope="module")
def reference_cache():
    return {}


# Bounds on the max relative column error over the coarse grid's segments (docs/stability.md, measured
# with a margin): (method, settings, dtype, H [m], bound).
COLUMN_BOUNDS = [
    # Fitzmaurice 1964 is exact to first order in 1/X = H/R: 1/X = 1.6% at H = 100 km.
    ("chapman", {}, torch.float64, 100_000.0, 2.0e-2),
    ("chapman", {}, torch.float64, 10.0, 1e-5),
    # float32 cancels in the difference of Chapman columns along chords (docs/stability.md).
    ("chapman", {}, torch.float32, 100_000.0, 8e-2),
    ("chapman", {}, torch.float32, 10.0, 5e-3),
    # Gauss-Legendre on smooth columns (H >> node spacing): float64 rounding, float32 rounding.
    ("gauss", {"samples": 64}, torch.float64, 100_000.0, 1e-12),
    ("gauss", {"samples": 64}, torch.float32, 100_000.0, 1e-4),
    ("spline", {}, torch.float64, 100_000.0, 1e-4),
]


@pytest.mark.parametrize("name, settings, dtype, H, bound", COLUMN_BOUNDS)
def test_column_error_against_scipy_at_the_extreme_scale_heights(name, settings, dtype, H, bound, reference_cache):
    grid = S.Grid(**{**S.COARSE.__dict__, "scale_heights": (H,)})
    cells = S.column_errors(name, settings, grid, dtypes=(dtype,), reference_cache=reference_cache)
    c = cells[(str(dtype).replace("torch.", ""), "H", f"{H:g} m")]
    assert c["n"] >= 15 and c["refused"] == 0
    assert c["bad_values"] == 0 and c["bad_grads"] == 0
    assert c["max_rel_err"] <= bound, (c["max_rel_err"], c["worst"])


def test_height_fog_accepts_only_segments_within_its_documented_error(reference_cache):
    """Flat-Earth fog: every segment it accepts is within max_curvature_fraction (1%) of scipy; the rest are refused."""
    cells = S.column_errors("height_fog", {}, S.COARSE, reference_cache=reference_cache)
    for dn in ("float64", "float32"):
        seg = [cells[(dn, "segment", k)] for k in ("view", "sun")]
        assert sum(c["n"] for c in seg) > 0 and sum(c["refused"] for c in seg) > 0
        for c in seg:
            assert c["bad_values"] == 0 and c["bad_grads"] == 0
            assert c["max_rel_err"] <= 0.01 + (1e-4 if dn == "float32" else 1e-12), (dn, c["worst"])
            assert all(re.search(REFUSALS["height_fog"], m) for m in c["messages"])


def test_taylor_is_exact_for_vertical_rays_at_every_scale_height(reference_cache):
    """Gałaj 2021 eq. 17 is exact where h is linear in t (vertical rays), from 10 m to 100 km; below 1 km
    (where grazing rays are off by > 10x) the integrator refuses, so the formula is checked directly."""
    from skyfit.transmittance.taylor import TAYLOR_MIN_SCALE_HEIGHT
    grid = S.Grid(altitudes=(("ground", 0.0), ("10 km", 1e4)), sun_zenith_deg=(0.0,), horizon_views=False)
    atm = S.base_atmosphere()
    integ = make_integrator("taylor")
    from skyfit.tools.reference import column_quad
    from skyfit.transmittance.taylor import taylor_column

    for H in S.SCALE_HEIGHTS_M:
        for axis, label, r, mu, L in S.column_segments(grid, atm):
            if abs(mu) != 1.0:
                continue
            args = (torch.tensor([r], dtype=torch.float64), torch.tensor([mu], dtype=torch.float64),
                    torch.tensor([L], dtype=torch.float64), torch.tensor([H], dtype=torch.float64), atm.bottom_radius,
                    atm.top_radius)
            if H < TAYLOR_MIN_SCALE_HEIGHT:
                with pytest.raises(ValueError, match=REFUSALS["taylor"][len("^ValueError: "):]):
                    integ.column(*args)
                col = float(taylor_column(*args, torch.tensor(0.45, dtype=torch.float64),
                                          torch.tensor(0.45, dtype=torch.float64))[0, 0])
            else:
                col = float(integ.column(*args)[0, 0])
            ref = column_quad(r, mu, L, H, atm.bottom_radius)
            assert col == pytest.approx(ref, rel=1e-9, abs=1e-3), (label, H)


def test_single_scattering_matches_scipy_at_the_extreme_phase_and_extinction():
    """g = +-0.9999 (forward/backward peak, the view at the sun included) and beta = 1e-2 /m, against the
    independent scipy reference of tests/test_single_scattering_reference.py, float64, converged outer rule
    (measured max 2.9e-5: Earth from space at the ground horizon, sun 90.27 deg)."""
    from test_single_scattering_reference import Reference

    grid = S.Grid(
        altitudes=(("ground", 0.0), ("space (2 x top)", None)), sun_zenith_deg=(0.0, 90.27),
        scale_heights=(), betas=(1e-2,), mie_g=(-0.9999, 0.9999),
    )
    cells = S.radiance_errors("gauss", {"samples": 64}, Reference, grid, dtypes=(torch.float64,), view_samples=512)
    for key in [("float64", "base", "Earth"), ("float64", "beta", "0.01 /m"), ("float64", "g", "-0.9999"), ("float64", "g", "0.9999")]:
        c = cells[key]
        assert c["n"] == 72 and c["refused"] == 0
        assert c["max_rel_err"] <= 2e-4, (key, c["max_rel_err"], c["worst"])
    assert cells[("float64", "view", "at the sun")]["n"] == 16


def test_chapman_refuses_scale_heights_beyond_its_regime():
    atm = S.base_atmosphere()
    integ = make_integrator("chapman")
    H = torch.tensor([atm.bottom_radius / 40.0], dtype=torch.float64)  # X = 40 < min_x = 50
    with pytest.raises(ValueError, match=r"chapman: X = r/H = 40 .* below min_x = 50"):
        integ.prepare(H, atm.bottom_radius, atm.top_radius)


@pytest.mark.slow
def test_full_grid_report(tmp_path):
    """scripts/stability_report.py on the full grid: zero non-finite values and gradients in every row."""
    import importlib.util
    from pathlib import Path

    path = Path(__file__).resolve().parents[1] / "scripts" / "stability_report.py"
    spec = importlib.util.spec_from_file_location("stability_report", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    out = tmp_path / "stability.md"
    assert mod.main(["--out", str(out)]) == 0
    text = out.read_text()
    rows = [ln.split("|") for ln in text.splitlines() if re.match(r"\| \S.* \| float(32|64) \| \d+ \| \d+ \|", ln)]
    assert rows
    for row in rows:
        # | method | dtype | rays | values checked | non-finite | negative | gradients checked | non-finite | refused | errors |
        assert int(row[4]) > 0 or int(row[9]) == int(row[3]), row
        assert row[5].strip() == "0" and row[6].strip() == "0" and row[8].strip() == "0" and row[10].strip() == "0", row
