"""Plots of ``skyfit sample``: trace, corner and posterior-predictive spread (atomic PNG writes)."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from .model import FitProblem
from .report import sanitize, save_fig


def write_plots(out_dir: Path, chain: np.ndarray, diag: dict, phys: dict, names: list[str], problem: FitProblem,
                pstd: list[np.ndarray]) -> list[str]:
    """corner.png, trace.png and predictive_std_<obs>.png (atomic writes); returns the paths."""
    # matplotlib only when plots are written (0.4 s to import; use("Agg") sets the process-wide backend), as in report.py
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = []
    P = len(names)
    # trace (unconstrained x, every walker), burn-in marked
    fig, axes = plt.subplots(P, 1, figsize=(8, 1.6 * P + 0.6), sharex=True, squeeze=False)
    for k, ax in enumerate(axes[:, 0]):
        ax.plot(chain[:, :, k], color="k", alpha=0.15, lw=0.5)
        ax.axvline(diag["burn_in"], color="r", lw=1)
        ax.set_ylabel(f"x: {names[k]}", fontsize=7)
    axes[-1, 0].set_xlabel(f"step (red: burn-in {diag['burn_in']}; tau max {diag['tau_max']:.1f})")
    fig.tight_layout()
    out.append(str(save_fig(fig, out_dir / "trace.png")))
    # corner (physical units)
    S = np.stack([phys[n] for n in names], 1)
    fig, axes = plt.subplots(P, P, figsize=(2.0 * P + 1, 2.0 * P + 1), squeeze=False)
    for i in range(P):
        for j in range(P):
            ax = axes[i, j]
            if j > i:
                ax.axis("off")
                continue
            if i == j:
                ax.hist(S[:, i], bins=40, color="k", histtype="step")
                q = np.percentile(S[:, i], [16, 50, 84])
                for v in q:
                    ax.axvline(v, color="b", lw=0.8, ls="--")
                ax.set_title(f"{names[i]}\n{q[1]:.4g} +{q[2] - q[1]:.2g} -{q[1] - q[0]:.2g}", fontsize=7)
            else:
                ax.hist2d(S[:, j], S[:, i], bins=40, cmap="Greys")
            if i == P - 1:
                ax.set_xlabel(names[j], fontsize=7)
            if j == 0 and i > 0:
                ax.set_ylabel(names[i], fontsize=7)
            ax.tick_params(labelsize=6)
    fig.tight_layout()
    out.append(str(save_fig(fig, out_dir / "corner.png")))
    # posterior-predictive spread
    for o, s in zip(problem.observations, pstd):
        meas = o.values[o.mask].detach().cpu().double()
        rel = s / np.maximum(meas.numpy(), 1e-300)
        fig, ax = plt.subplots(figsize=(5.5, 4.8))
        if "image_shape" in o.metadata and "pixel_index" in o.metadata:
            h, w = o.metadata["image_shape"]
            idx = torch.as_tensor(o.metadata["pixel_index"])[o.mask].numpy()
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

