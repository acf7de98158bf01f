"""Fit reports: atomic JSON, residual maps of fisheye images, spectra and per-ring errors of scans.

Every file is written to a temporary name beside its target and renamed into
place when complete (CONTRACT.md: no partial output files).
"""
from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Sequence

import numpy as np
import torch
from torch import Tensor

from .data import Observation
from ..render.colour import xyz_to_srgb_matrix, spectral_to_xyz_matrix
from ..io.atomic import atomic_path, write_text_atomic  # noqa: F401  (write_text_atomic: re-exported)


def _json_default(o):
    if isinstance(o, Tensor):
        return o.detach().cpu().tolist()
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON-serialisable: {type(o).__name__}")


def _clean(o):
    """NaN/Inf -> None, recursively (JSON has no NaN)."""
    if isinstance(o, float):
        return o if math.isfinite(o) else None
    if isinstance(o, dict):
        return {k: _clean(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [_clean(v) for v in o]
    return o


def dumps(obj, indent: int | None = 2) -> str:
    """JSON text of ``obj`` with tensors and arrays as lists and NaN as null."""
    return json.dumps(_clean(json.loads(json.dumps(obj, default=_json_default))), indent=indent)


def save_fig(fig, path: Path) -> Path:
    """Write ``fig`` as a PNG to ``path`` atomically (100 dpi) and close it; returns ``path``."""
    import matplotlib.pyplot as plt

    try:
        with atomic_path(path, ".tmp.png") as tmp:
            fig.savefig(tmp, dpi=100)
    finally:
        plt.close(fig)
    return path


def luminance(values: Tensor, obs: Observation) -> np.ndarray:
    """Luminance Y [cd/m^2] of (N, C) values of ``obs`` (CIE 1931 from spectra; sRGB inverse for RGB)."""
    v = values.detach().cpu().double()
    if obs.kind == "spectral":
        return (v @ spectral_to_xyz_matrix(obs.wavelengths.detach().cpu().double())[:, 1]).numpy()
    inv = np.linalg.inv(xyz_to_srgb_matrix())
    return v.numpy() @ inv[1]


def sanitize(name: str) -> str:
    """``name`` fit for a file name: every character but letters, digits and ``-_.`` becomes ``_``."""
    return "".join(c if c.isalnum() or c in "-_." else "_" for c in name)


def plot_observation(obs: Observation, pred: Tensor, out_dir: Path, stem: str) -> list[str]:
    """Plots of one observation vs the model; returns the written paths.

    Fisheye images: measured and model luminance (log scale), relative luminance error and
    the normalised residual (mean over channels of (model - data) / sigma) in image layout.
    Kider scans: measured vs model spectrum per sample, and RMSE per ring / error vs sun angle.
    """
    # matplotlib only when plots are written (0.4 s to import; use("Agg") sets the process-wide backend)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    mask = obs.mask.detach().cpu()  # the observation may live on CUDA; its metadata (pixel_index, ring) on the CPU
    meas = obs.values.detach().cpu().double()[mask]
    mod = pred.detach().cpu().double()
    base = f"{stem}_{sanitize(obs.name)}"
    written = []
    if "image_shape" in obs.metadata and "pixel_index" in obs.metadata:
        h, w = obs.metadata["image_shape"]
        idx = torch.as_tensor(obs.metadata["pixel_index"]).cpu()[mask].numpy()

        def img(vals):
            a = np.full(h * w, np.nan)
            a[idx] = vals
            return a.reshape(h, w)

        y_m, y_p = luminance(meas, obs), luminance(mod, obs)
        rel = (y_p - y_m) / np.where(y_m > 0, y_m, np.nan)
        resid = ((mod - meas) / obs.sigma.detach().cpu().double()[mask]).mean(-1).numpy()
        fig, axes = plt.subplots(2, 2, figsize=(9, 8))
        lo = np.nanpercentile(np.log10(np.maximum(y_m, 1e-12)), 1)
        hi = np.nanpercentile(np.log10(np.maximum(y_m, 1e-12)), 99.5)
        for ax, data, title in ((axes[0, 0], y_m, "measured"), (axes[0, 1], y_p, "model")):
            im = ax.imshow(img(np.log10(np.maximum(data, 1e-12))), cmap="inferno", vmin=lo, vmax=hi)
            ax.set_title(f"{title}: log10 luminance [cd/m^2]")
            fig.colorbar(im, ax=ax, fraction=0.046)
        lim = max(float(np.nanpercentile(np.abs(rel), 99)), 1e-3)
        im = axes[1, 0].imshow(img(rel * 100), cmap="RdBu_r", vmin=-lim * 100, vmax=lim * 100)
        axes[1, 0].set_title("relative error (model - data) / data [%]")
        fig.colorbar(im, ax=axes[1, 0], fraction=0.046)
        lim = max(float(np.nanpercentile(np.abs(resid), 99)), 1e-3)
        im = axes[1, 1].imshow(img(resid), cmap="RdBu_r", vmin=-lim, vmax=lim)
        axes[1, 1].set_title("residual (model - data) / sigma, channel mean")
        fig.colorbar(im, ax=axes[1, 1], fraction=0.046)
        for ax in axes.flat:
            ax.set_xticks([])
            ax.set_yticks([])
        fig.suptitle(f"{obs.name}  (North up, East left)")
        fig.tight_layout()
        written.append(str(save_fig(fig, out_dir / f"{base}_maps.png")))
    if obs.kind == "spectral" and "ring" in obs.metadata:
        lam = obs.wavelengths.detach().cpu().numpy()
        rings = torch.as_tensor(obs.metadata["ring"]).cpu()[mask].numpy()
        n = meas.shape[0]
        cols = int(math.ceil(math.sqrt(n)))
        rows = int(math.ceil(n / cols))
        # small multiples without tick labels (each panel's own y range; the title gives the peak):
        # tight_layout on 81 axes costs seconds, fixed margins do not
        fig, axes = plt.subplots(rows, cols, figsize=(cols * 1.3, rows * 1.0), squeeze=False)
        fig.subplots_adjust(left=0.01, right=0.99, bottom=0.01, top=0.94, wspace=0.08, hspace=0.35)
        for k, ax in enumerate(axes.flat):
            ax.set_xticks([])
            ax.set_yticks([])
            if k >= n:
                ax.axis("off")
                continue
            ax.plot(lam, meas[k].numpy() * 1e3, "k-", lw=0.7)
            ax.plot(lam, mod[k].numpy() * 1e3, "r-", lw=0.7)
            ax.set_title(f"#{k} r{rings[k]} {float(meas[k].max()) * 1e3:.0f}", fontsize=5, pad=1)
        fig.suptitle(f"{obs.name}: measured (black) vs model (red) over {lam[0]:g}-{lam[-1]:g} nm; "
                     "title: sample, ring, measured peak [mW/(m^2 sr nm)]", fontsize=8)
        written.append(str(save_fig(fig, out_dir / f"{base}_spectra.png")))

        err = (mod - meas).numpy() * 1e3
        rel = ((mod - meas) / meas).numpy()
        fig, (a1, a2) = plt.subplots(1, 2, figsize=(10, 4))
        ids = sorted(set(rings.tolist()))
        a1.bar([str(r) for r in ids], [float(np.sqrt(np.mean(err[rings == r] ** 2))) for r in ids], color="C0")
        a1.set_xlabel("ring (0 = elevation 12°, 4 = zenith)")
        a1.set_ylabel("RMSE [mW/(m^2 sr nm)]")
        a1.set_title("RMSE per ring")
        sun = obs.sun.detach().cpu().double()
        sun = sun[mask] if sun.ndim == 2 else sun
        ang = torch.rad2deg(torch.arccos(torch.clamp((obs.directions.detach().cpu().double()[mask] * sun).sum(-1), -1, 1)))
        a2.scatter(ang.numpy(), rel.mean(-1) * 100, c=rings, cmap="viridis", s=12)
        a2.axhline(0, color="k", lw=0.5)
        a2.set_xlabel("angle to the sun [deg]")
        a2.set_ylabel("mean relative error [%]")
        a2.set_title("error vs sun angle (colour = ring)")
        fig.tight_layout()
        written.append(str(save_fig(fig, out_dir / f"{base}_rings.png")))
    return written


def plot_all(observations: Sequence[Observation], preds: Sequence[Tensor], out_dir: Path, stem: str) -> list[str]:
    paths = []
    for o, p in zip(observations, preds):
        paths += plot_observation(o, p, out_dir, stem)
    return paths
