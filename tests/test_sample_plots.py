"""The corner plot of ``skyfit sample`` (corner.py): axes, quantile lines, truth lines, units, PNG."""
from __future__ import annotations

import matplotlib

matplotlib.use("Agg")

import numpy as np  # noqa: E402
import pytest  # noqa: E402
import skimage.io  # noqa: E402
from matplotlib.colors import to_rgba  # noqa: E402

from skyfit.fit.report import save_fig  # noqa: E402
from skyfit.fit.sample_plots import QUANTILES, corner_figure  # noqa: E402

NAMES = ["mie_beta_550", "mie_g", "ground_albedo"]
UNITS = {"mie_beta_550": "1/m", "mie_g": "1", "ground_albedo": "1"}
TRUTHS = {"mie_beta_550": 2.5e-5, "mie_g": 0.76}  # ground_albedo's truth unknown: no line


def _samples(n=4000, seed=3):
    rng = np.random.default_rng(seed)
    cov = np.array([[1.0, 0.6, 0.0], [0.6, 1.0, 0.0], [0.0, 0.0, 1.0]])
    z = rng.multivariate_normal(np.zeros(3), cov, size=n)
    return np.stack([2.4e-5 + 2e-6 * z[:, 0], 0.75 + 0.02 * z[:, 1], 0.25 + 0.01 * z[:, 2]], 1)


def _vlines(ax, color):
    """x of the vertical full-height lines of ``color`` on ``ax`` (axvline: two equal x in data units)."""
    out = []
    for line in ax.get_lines():
        x = np.asarray(line.get_xdata(), float)
        if len(x) == 2 and x[0] == x[1] and to_rgba(line.get_color()) == to_rgba(color):
            out.append(float(x[0]))
    return out


def _hlines(ax, color):
    out = []
    for line in ax.get_lines():
        y = np.asarray(line.get_ydata(), float)
        x = np.asarray(line.get_xdata(), float)
        if len(y) == 2 and y[0] == y[1] and x[0] != x[1] and to_rgba(line.get_color()) == to_rgba(color):
            out.append(float(y[0]))
    return out


def test_corner_axes_quantiles_truths_units(tmp_path):
    S = _samples()
    fig = corner_figure(S, NAMES, units=UNITS, truths=TRUTHS)
    P = len(NAMES)
    axes = np.array(fig.axes).reshape(P, P)
    assert len(fig.axes) == P * P
    for k, n in enumerate(NAMES):
        diag = axes[k, k]
        # truth lines exactly at the truth, only where one is known
        truth = _vlines(diag, "tab:red")
        if n in TRUTHS:
            assert truth == pytest.approx([TRUTHS[n]], rel=1e-12)
        else:
            assert truth == []
        # the 16/50/84 % quantile lines (dashed) at numpy's quantiles of the same samples
        dashed = sorted(float(ln.get_xdata()[0]) for ln in diag.get_lines() if ln.get_linestyle() == "--")
        assert dashed == pytest.approx(list(np.quantile(S[:, k], QUANTILES)), rel=1e-9)
        # upper triangle empty: no frame, nothing drawn
        for j in range(k + 1, P):
            assert not axes[k, j].get_frame_on() and not axes[k, j].get_lines()
    # 2-D panels: the column's truth as a vertical line, the row's as a horizontal one
    assert _vlines(axes[1, 0], "tab:red") == pytest.approx([TRUTHS["mie_beta_550"]])
    assert _hlines(axes[1, 0], "tab:red") == pytest.approx([TRUTHS["mie_g"]])
    assert _hlines(axes[2, 0], "tab:red") == []  # no truth for ground_albedo
    # labels with units (dimensionless ones bare), on the bottom row
    assert axes[P - 1, 0].get_xlabel() == "mie_beta_550 [1/m]"
    assert axes[P - 1, 1].get_xlabel() == "mie_g"
    # the PNG is written and is an image of the figure's size
    path = save_fig(fig, tmp_path / "corner.png")
    img = skimage.io.imread(path)
    assert img.ndim == 3 and img.shape[0] > 300 and img.shape[1] > 300
    assert img[..., :3].std() > 10  # not blank


def test_corner_without_truths_and_a_stuck_parameter():
    S = _samples()
    S[:, 2] = 0.25  # no spread (a parameter at a bound): corner would refuse it without a range
    fig = corner_figure(S, NAMES, units=UNITS)
    assert len(fig.axes) == 9
    assert all(_vlines(ax, "tab:red") == [] for ax in fig.axes)


def test_demo_passes_the_truth_to_the_sampler(monkeypatch, tmp_path):
    from skyfit.tools import demo

    seen = {}

    def fake(*a, **kw):
        seen.update(kw)
        return {"sampler": {"steps": 1, "walkers": 2}, "diagnostics": {"tau_max": 1.0}, "laplace_vs_emcee": {}}

    monkeypatch.setattr(demo, "run_sample", fake)
    demo._sample(tmp_path / "observed.exr", tmp_path, False, lambda *_: None)
    assert seen["truths"] == demo.TRUTH
