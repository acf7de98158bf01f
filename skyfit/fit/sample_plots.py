"""Plots of ``skyfit sample``: trace, corner and posterior-predictive spread (atomic PNG writes)."""
from __future__ import annotations

from pathlib import Path
from typing import Mapping

import numpy as np
import torch

from .model import FitProblem
from .parameters import PARAMETERS
from .report import sanitize, save_fig


QUANTILES = (0.16, 0.5, 0.84)
"""Quantiles marked on the corner plot's histograms and printed in its titles (median +- 1 sigma)."""


def corner_figure(samples: np.ndarray, names: list[str], units: Mapping[str, str] | None = None,
                  truths: Mapping[str, float] | None = None):
    """The corner plot of posterior samples, drawn by corner.py (Foreman-Mackey 2016, JOSS 1, 24).

    Args:
        samples: physical values, shape (N, P). [the parameters' units]
        names: the P parameter names (docs/fitting.md), shown with their units.
        units: name -> unit string; a name's ``[k]`` suffix is looked up without it.
        truths: name -> true value, drawn as lines where known (e.g. ``skyfit demo``). [the parameters' units]

    Returns:
        the matplotlib Figure (P x P axes; the caller saves and closes it).
    """
    import corner

    samples = np.asarray(samples, dtype=float)
    units = dict(units or {})
    truths = dict(truths or {})

    def label(n: str) -> str:
        u = units.get(n, units.get(n.split("[")[0], ""))
        return n if u in ("", "1") else f"{n} [{u}]"

    # corner refuses a column without spread (a parameter stuck at a bound): give it a small range
    ranges = []
    for k in range(samples.shape[1]):
        lo, hi = float(np.min(samples[:, k])), float(np.max(samples[:, k]))
        t = truths.get(names[k])
        if t is not None and np.isfinite(t):
            lo, hi = min(lo, float(t)), max(hi, float(t))
        pad = 0.05 * (hi - lo) if hi > lo else max(abs(lo) * 1e-3, 1e-12)
        ranges.append((lo - pad, hi + pad))
    truth_list = [truths.get(n) for n in names]
    fig = corner.corner(samples, bins=30, range=ranges, labels=[label(n) for n in names], quantiles=list(QUANTILES),
                        show_titles=True, title_quantiles=list(QUANTILES), title_fmt=".4g", title_kwargs={"fontsize": 8},
                        label_kwargs={"fontsize": 8}, truths=truth_list if any(t is not None for t in truth_list) else None,
                        truth_color="tab:red", plot_datapoints=False, fill_contours=False, smooth=1.0,
                        levels=(1 - np.exp(-0.5), 1 - np.exp(-2.0)))  # 1 and 2 sigma of a 2-D Gaussian
    return fig


def write_plots(out_dir: Path, chain: np.ndarray, diag: dict, phys: dict, names: list[str], problem: FitProblem,
                pstd: list[np.ndarray], truths: Mapping[str, float] | None = None) -> list[str]:
    """corner.png, trace.png and predictive_std_<obs>.png (atomic writes); returns the paths.

    ``truths`` (name -> true value) draws truth lines on the corner plot where known."""
    # matplotlib only when plots are written (0.4 s to import; use("Agg") sets the process-wide backend), as in report.py
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = []
    P = len(names)
    units = {n: spec.unit for n, spec in PARAMETERS.items()}
    # trace (unconstrained x, every walker), burn-in marked
    fig, axes = plt.subplots(P, 1, figsize=(8, 1.6 * P + 0.6), sharex=True, squeeze=False)
    for k, ax in enumerate(axes[:, 0]):
        ax.plot(chain[:, :, k], color="k", alpha=0.15, lw=0.5)
        ax.axvline(diag["burn_in"], color="r", lw=1)
        ax.set_ylabel(f"x: {names[k]}", fontsize=7)
    axes[-1, 0].set_xlabel(f"step (red: burn-in {diag['burn_in']}; tau max {diag['tau_max']:.1f})")
    fig.tight_layout()
    out.append(str(save_fig(fig, out_dir / "trace.png")))
    # corner (physical units; corner.py: contours, 16/50/84 % quantiles, truth lines)
    S = np.stack([phys[n] for n in names], 1)
    fig = corner_figure(S, names, units=units, truths=truths)
    out.append(str(save_fig(fig, out_dir / "corner.png")))
    # posterior-predictive spread
    for o, s in zip(problem.observations, pstd):
        meas = o.values[o.mask].detach().cpu().double()
        rel = s / np.maximum(meas.numpy(), 1e-300)
        fig, ax = plt.subplots(figsize=(5.5, 4.8))
        if "image_shape" in o.metadata and "pixel_index" in o.metadata:
            h, w = o.metadata["image_shape"]
            idx = torch.as_tensor(o.metadata["pixel_index"]).cpu()[o.mask.cpu()].numpy()
            a = np.full(h * w, np.nan)
            a[idx] = rel.mean(-1)
            im = ax.imshow(a.reshape(h, w), cmap="viridis")
            fig.colorbar(im, ax=ax, fraction=0.046, label="std / measured (mean over channels)")
            ax.set_title(f"{o.name}: posterior-predictive std\n(fisheye: North up, East left)", fontsize=9)
        else:
            ax.plot(rel.mean(-1), ".")
            ax.set_xlabel("sample")
            ax.set_ylabel("std / measured (mean over channels)")
            ax.set_title(f"{o.name}: posterior-predictive std", fontsize=9)
        fig.tight_layout()
        out.append(str(save_fig(fig, out_dir / f"predictive_std_{sanitize(o.name)}.png")))
    return out

