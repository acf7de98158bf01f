"""Every optical-depth integrator against scipy quad (float64) on the docs/accuracy.md grid.

The bounds are the documented maxima of docs/accuracy.md (measured by
scripts/accuracy_table.py) with a margin; a regression that makes any method
less accurate than documented fails here.
"""
import numpy as np
import pytest
import torch

from skyfit.tools.reference import accuracy_cases, column_quad, relative_column_error
from skyfit.transmittance import make_integrator

BOTTOM, TOP = 6_360_000.0, 6_420_000.0
SCALE_HEIGHTS = (8000.0, 1200.0)

# (method, settings, max relative error for H = 8 km, for H = 1.2 km)
BOUNDS = [
    ("trapezoid", {"samples": 64}, 2e-3, 8e-2),
    ("trapezoid", {"samples": 1024}, 1e-5, 4e-4),
    ("midpoint", {"samples": 256}, 6e-5, 3e-3),
    ("simpson", {"samples": 257}, 1e-8, 2e-5),
    ("gauss", {"samples": 32}, 1e-12, 3e-8),
    ("gauss", {"samples": 128}, 1e-12, 1e-11),
    # Gałaj 2021 eq. 17 with a = b = 0.45: exact for vertical rays, a few percent for
    # Rayleigh near the horizon, and out of its regime for the Mie layer at grazing
    # incidence, where the exact upper bound L exp(-h_low / H) caps it (docs/accuracy.md).
    ("taylor", {}, 0.5, 11.0),
    ("spline", {}, 7e-5, 5e-4),
    ("spline", {"kind": "akima"}, 5e-6, 3e-4),
    ("spline", {"height_points": 200, "distance_points": 80}, 1e-6, 1e-5),
    ("chapman", {}, 2e-3, 3e-4),
    # Column = difference of two lookups: 1 m segments near the ground carry the table's
    # interpolation error of the ~8 km columns they subtract (docs/lut_chapman_fog.md).
    ("bruneton_lut", {}, 4.5, 4.5),
    ("bruneton_lut", {"mu_size": 1024, "r_size": 256}, 0.45, 0.45),
]


@pytest.fixture(scope="module")
def grid():
    cases = accuracy_cases(BOTTOM, TOP)
    refs = np.array([[column_quad(r, mu, L, H, BOTTOM) for H in SCALE_HEIGHTS] for r, mu, L, _ in cases])
    t = lambda i: torch.tensor([c[i] for c in cases], dtype=torch.float64)  # noqa: E731
    return t(0), t(1), t(2), refs, cases


def _columns(name, settings, grid, dtype=torch.float64):
    r, mu, L, _, _ = grid
    integ = make_integrator(name, **settings)
    H = torch.tensor(SCALE_HEIGHTS, dtype=dtype)
    return integ.prepare(H, BOTTOM, TOP)(r.to(dtype), mu.to(dtype), L.to(dtype)).double().numpy()


def test_grid_covers_the_required_cases(grid):
    labels = " ".join(c[3] for c in grid[4])
    for needle in ("r=ground,", "r=ground+1m,", "r=ground+1km,", "r=top-1m,", "r=top,", "mu=up", "mu=down", "mu=0,", "mu=+1e-6", "mu=-1e-6", "horizon"):
        assert needle in labels, needle


@pytest.mark.parametrize("name,settings,bound_r,bound_m", BOUNDS, ids=lambda v: str(v))
def test_column_against_scipy_quad(name, settings, bound_r, bound_m, grid):
    rel = relative_column_error(_columns(name, settings, grid), grid[3])
    assert np.isfinite(rel).all()
    assert rel[:, 0].max() <= bound_r, f"{name} {settings}: max rel err {rel[:, 0].max():.3e} (H=8 km)"
    assert rel[:, 1].max() <= bound_m, f"{name} {settings}: max rel err {rel[:, 1].max():.3e} (H=1.2 km)"


def test_taylor_is_exact_for_vertical_rays(grid):
    """d = 0 makes h(t) linear, so eq. 17 is exact whatever a and b (Gałaj 2021 Sec. IV.F)."""
    r, mu, L, refs, cases = grid
    rel = relative_column_error(_columns("taylor", {}, grid), refs)
    vertical = np.array([abs(c[1]) == 1.0 for c in cases])
    assert vertical.sum() >= 6
    assert rel[vertical].max() < 1e-9


def test_bruneton_lut_median_error_is_small(grid):
    """Away from the short-segment cancellation the LUT is accurate: median over the grid."""
    rel = relative_column_error(_columns("bruneton_lut", {}, grid), grid[3])
    assert np.median(rel) < 5e-4


def test_quadrature_converges_with_samples(grid):
    errs = [relative_column_error(_columns("trapezoid", {"samples": n}, grid), grid[3]).max() for n in (16, 64, 256)]
    assert errs[0] > errs[1] > errs[2]
    # composite trapezoid is second order: 4x the samples, ~16x smaller error
    assert errs[1] / errs[2] > 10


@pytest.mark.parametrize("name", ["trapezoid", "gauss", "taylor", "spline", "bruneton_lut", "chapman", "height_fog"])
def test_settings_round_trip(name):
    """RESULT.json stores integrator.settings(); make_integrator must rebuild the same integrator from it."""
    integ = make_integrator(name)
    settings = {k: v for k, v in integ.settings().items() if k != "name"}
    assert make_integrator(name, **settings).settings() == integ.settings()
