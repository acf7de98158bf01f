"""``skyfit demo``: the main job end to end on an embedded default (CONTRACT.md).

1. A known atmosphere (Earth, moderate aerosol, grass-like albedo) is rendered as a
   128 x 128 equidistant fisheye, 16 wavelengths, single + multiple scattering, with a
   finer model than the fit uses (Gauss-64 optical depth, 48 view samples, Hillaire's
   LUT at the paper's 32 x 32 x 64 directions), so the fit meets model error as it would
   on real data.
2. Realistic noise: sigma = hypot(1 % of the radiance, 0.5 % of the median radiance)
   (gain and read noise), written as a spectral EXR with its noise model in the header.
3. ``skyfit fit`` on that file (Chapman + Gauss-16, Hillaire 16 x 16, L-BFGS) with the
   Laplace covariance and the error budget (:mod:`skyfit.fit.budget`): the sigma printed is
   noise + numerical model error (the fit's renderer against the converged reference) +
   the discrepancy floor; unless ``--quick``, ``skyfit sample`` (emcee, 12 walkers on a pixel
   subsample, see :data:`SAMPLE_PIXELS`, run until the chain is 50 autocorrelation times
   long, :func:`_sample`; corner plot).
4. LUT export of the fitted atmosphere (Bruneton tables at reduced sizes).
5. Truth vs recovered +- sigma for every free parameter, printed and in ``report.md``.

``--quick`` (48 x 48, 6 wavelengths, no emcee, tiny LUTs) ends within a minute on 2 CPU cores.
"""
from __future__ import annotations

import copy
import json
import math
import time
from pathlib import Path

import numpy as np
import skimage.io
import torch

from .. import __version__
from ..atmosphere import atmosphere_from_config, load_yaml
from ..camera import FisheyeCamera, render_fisheye
from ..export import export_luts
from ..fit.data import noise_sigma
from ..fit.diagnostics import MIN_STEPS_PER_TAU
from ..fit.results import atmosphere_from_result
from ..fit.run import run_fit
from ..fit.sample import run_sample
from ..io import write_exr
from ..io.atomic import atomic_path, write_text_atomic
from ..render import spectral_to_xyz, tonemap_srgb8, xyz_to_linear_srgb
from ..scattering.bruneton_tables import TableSizes
from ..scattering.hillaire import hillaire_lut
from ..scattering.multiple import ACCURATE_QUADRATURE, precompute
from ..transmittance import make_integrator

CONFIGS = Path(__file__).resolve().parents[1] / "configs"
"""The package's shipped atmosphere configs (skyfit/configs)."""

TRUTH = {
    "rayleigh_scale": 1.0,
    "mie_beta_550": 2.5e-5,
    "mie_scale_height": 1400.0,
    "mie_g": 0.76,
    "ground_albedo": 0.25,
}
"""The demo's true values (SI units; docs/fitting.md names)."""
SUN = (50.0, 135.0)
"""Sun zenith and azimuth of the demo sky [deg]."""
NOISE = (0.01, 0.005)
"""Noise: relative sigma, and absolute sigma as a fraction of the median radiance [1]."""


def truth_config() -> dict:
    """The earth config with the demo's true aerosol and albedo (a plain config dict)."""
    cfg = copy.deepcopy(load_yaml(CONFIGS / "earth.yaml"))
    cfg["name"] = "demo_truth"
    cfg["rayleigh"]["scale"] = TRUTH["rayleigh_scale"]
    cfg["mie"].pop("angstrom_beta", None)
    cfg["mie"]["extinction_550"] = TRUTH["mie_beta_550"]
    cfg["mie"]["angstrom_alpha"] = 0.0
    cfg["mie"]["scale_height_m"] = TRUTH["mie_scale_height"]
    cfg["mie"]["g"] = TRUTH["mie_g"]
    cfg["ground"] = {"albedo": TRUTH["ground_albedo"]}
    return cfg


def fit_config(quick: bool) -> dict:
    """What the user would pass as --config: the plain earth config (the fit starts from its values) + fit:."""
    cfg = copy.deepcopy(load_yaml(CONFIGS / "earth.yaml"))
    cfg["fit"] = {
        "free": list(TRUTH), "orders": 2, "multiple": "hillaire", "integrator": "chapman", "view_samples": 16,
        "rule": "gauss", "starts": 1, "sun_mask_deg": 3.0, "min_elevation_deg": 2.0,
    }
    if quick:  # a smaller reference for the numerical term (3 s instead of 20 s of tables on one core), no refits
        cfg["fit"].update(sigma_reference=list(QUICK_SIGMA_REFERENCE), sigma_refits=0)
    return cfg


QUICK_SIGMA_REFERENCE = (8, 32, 8, 4, 4)
"""``--quick``: Bruneton table sizes and orders of the error budget's reference (fit.sigma_reference)."""


def _render_truth(size: int, lam: np.ndarray, quick: bool):
    atm = atmosphere_from_config(truth_config(), lam)
    with torch.no_grad():  # the paper's LUT (the fit uses 16 x 16 texels)
        lut = hillaire_lut(atm, size=(32, 32), directions=64, samples=20)
        img = render_fisheye(atm, FisheyeCamera(size), SUN[0], SUN[1], make_integrator("gauss", samples=32 if quick else 64),
                             orders=2, multiple="hillaire", tables=lut, view_samples=24 if quick else 48, rule="gauss")
    return atm, img


def _write_observation(out: Path, atm, img, seed: int) -> tuple[Path, Path]:
    """truth.exr (noise-free) and observed.exr (noisy, with its noise model in the header)."""
    spec = img.spectral.detach().cpu().double()
    valid = img.valid.cpu()
    median = float(spec[valid].median())
    rel, absolute = NOISE[0], NOISE[1] * median
    gen = torch.Generator().manual_seed(seed)
    sigma = noise_sigma(spec, rel, absolute)  # the model observation_from_exr reads back from the header
    noisy = torch.where(valid.unsqueeze(-1), spec + sigma * torch.randn(spec.shape, generator=gen, dtype=spec.dtype), 0.0)
    lam = atm.wavelengths.cpu().double()
    paths = []
    for name, s, noise in (("truth", spec, None), ("observed", noisy, {"sigma_relative": rel, "sigma_absolute": absolute})):
        xyz = spectral_to_xyz(s, lam)
        rgb = xyz_to_linear_srgb(xyz).numpy()
        chans = {"R": rgb[..., 0], "G": rgb[..., 1], "B": rgb[..., 2], "Y": xyz[..., 1].numpy()}
        for k, w in enumerate(lam.tolist()):
            chans[f"L{w:g}"] = s[..., k].numpy()
        meta = {
            "skyfit_version": __version__, "camera": img.camera.metadata(),
            "sun": {"zenith_deg": SUN[0], "azimuth_deg": SUN[1]}, "observer_altitude_m": 0.0,
            "units": {"L<nm>": "W/(m^2 sr nm)", "R,G,B": "linear sRGB of XYZ with 683 lm/W (Y in cd/m^2)", "Y": "cd/m^2"},
            "wavelengths_nm": lam.tolist(), "demo_truth": TRUTH,
        }
        if noise:
            meta["noise"] = noise
        paths.append(write_exr(out / f"{name}.exr", chans, meta))
    return paths[0], paths[1]


def _png(path: Path, rgb: np.ndarray, valid: np.ndarray) -> None:
    exposure = 1.0 / max(float(np.percentile(rgb.mean(-1)[valid], 90)), 1e-12)
    with atomic_path(path, ".tmp.png") as tmp:
        skimage.io.imsave(tmp, tonemap_srgb8(rgb, exposure), check_contrast=False)


def _uncertainty_rows(result: dict, posterior: dict | None) -> list[dict]:
    """Truth vs recovered with the total sigma of the full data (noise + numerical + discrepancy, and
    its parts; emcee's of the subsample); the aerosol optical depth (derived: beta550 x H_M) last."""
    lap = result.get("laplace") or {}
    budget = lap.get("budget") or {}
    post_all = (posterior or {}).get("parameters") or {}
    post_total = ((posterior or {}).get("error_budget") or {}).get("sigma_total") or {}
    truth = {**TRUTH, "mie_aod_550": TRUTH["mie_beta_550"] * TRUTH["mie_scale_height"]}
    rows = []
    for name, true in truth.items():
        if name in TRUTH:
            got, sig_l = float(result["parameters"][name]), (lap.get("sigma") or {}).get(name)
            parts = {k: (budget.get(k) or {}).get(name) for k in ("sigma_noise", "sigma_numerical", "sigma_discrepancy",
                                                                  "numerical_shift")}
        else:
            got = float(result["derived"][name])
            sig_l = ((lap.get("derived") or {}).get(name) or {}).get("sigma")
            parts = {k: ((budget.get("derived") or {}).get(name) or {}).get(k)
                     for k in ("sigma_noise", "sigma_numerical", "sigma_discrepancy", "numerical_shift")}
        if not budget:  # fit.sigma: noise
            parts["sigma_noise"] = sig_l
        post = post_all.get(name) or {}
        noise = parts["sigma_noise"]
        rows.append({"parameter": name, "truth": true, "recovered": got, "sigma_laplace": sig_l, **parts,
                     "sigma_emcee_subsample": post_total.get(name, post.get("std")),
                     "sigma_emcee_subsample_noise": post.get("std"), "posterior_median_subsample": post.get("median"),
                     "error": got - true, "error_in_sigma": None if not sig_l else (got - true) / sig_l,
                     "error_in_noise_sigma": None if not noise else (got - true) / noise,
                     "relative_error": (got - true) / true if name != "mie_g" else None})
    return rows


def _table(rows: list[dict], units: dict) -> str:
    lines = ["| parameter | unit | truth | recovered | ± σ (total) | σ noise | σ numerical | σ discrepancy | "
             "σ emcee, subsample | error | error / σ | error / σ noise |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    f = lambda v: "–" if v is None else f"{v:.4g}"  # noqa: E731
    for r in rows:
        err = f"{r['relative_error'] * 100:+.2f} %" if r["relative_error"] is not None else f"{r['error']:+.4f}"
        lines.append(f"| {r['parameter']} | {units.get(r['parameter'], '')} | {r['truth']:.4g} | {r['recovered']:.4g} | "
                     f"{f(r['sigma_laplace'])} | {f(r.get('sigma_noise'))} | {f(r.get('sigma_numerical'))} | "
                     f"{f(r.get('sigma_discrepancy'))} | {f(r['sigma_emcee_subsample'])} | {err} | "
                     f"{f(r['error_in_sigma'])} | {f(r.get('error_in_noise_sigma'))} |")
    return "\n".join(lines)


def run_demo(out: str | Path, quick: bool = False, progress: bool = False, log=print, seed: int = 0,
             device="cpu") -> dict:
    """Run the whole demo into ``out``; return the summary dict (also ``out/demo.json``).

    ``device`` is where the fit, the sampler and the LUT precomputation run (the truth is rendered
    on the CPU in float64, so that the observation is the same on every machine)."""
    t_start = time.perf_counter()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    timings = {}
    size, lam = (48, np.linspace(420.0, 680.0, 6)) if quick else (128, np.linspace(400.0, 700.0, 16))

    t0 = time.perf_counter()
    atm, img = _render_truth(size, lam, quick)
    truth_exr, observed_exr = _write_observation(out, atm, img, seed)
    valid = img.valid.cpu().numpy()
    _png(out / "truth.png", img.rgb.detach().cpu().numpy(), valid)
    timings["render_s"] = time.perf_counter() - t0
    log(f"rendered the true sky ({size}x{size}, {len(lam)} wavelengths, sun zenith {SUN[0]} deg) -> {truth_exr}, {observed_exr}")

    t0 = time.perf_counter()
    result = run_fit([observed_exr], fit_config(quick), out / "RESULT.json", config_source="skyfit demo (earth + fit:)",
                     plots=True, progress=progress, laplace=True, device=device)
    timings["fit_s"] = time.perf_counter() - t0
    m = result["metrics"]
    log(f"fit: loss {m['loss']:.4g} (0.5 = the noise), rmse {m['rmse']:.3g} {m['rmse_units']}, "
        f"{result['convergence']['reason']} -> {out / 'RESULT.json'}")

    posterior = None
    if not quick:
        t0 = time.perf_counter()
        posterior = _sample(observed_exr, out, progress, log, device)
        timings["sample_s"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    lut_dir = _export(result, out / "luts", quick, device)
    timings["export_s"] = time.perf_counter() - t0
    log(f"exported LUTs -> {lut_dir}")

    rows = _uncertainty_rows(result, posterior)
    table = _table(rows, result.get("units", {}))
    log(table)
    timings["total_s"] = time.perf_counter() - t_start
    emcee = {} if posterior is None else {
        "emcee": {k: posterior.get(k) for k in ("laplace_vs_emcee", "sampler", "diagnostics")}, "emcee_pixels": SAMPLE_PIXELS}
    summary = {**emcee, "quick": quick, "size": size, "wavelengths_nm": lam.tolist(), "sun_deg": list(SUN), "noise": list(NOISE),
               "truth": TRUTH, "rows": rows, "metrics": {k: m[k] for k in ("loss", "rmse", "rmse_units", "delta_e")},
               "timings_s": timings, "files": sorted(p.name for p in out.iterdir())}
    b = (result.get("laplace") or {}).get("budget") or {}
    note = ("σ is the total error bar: the noise (σ noise, the Hessian of the likelihood), the numerical model error "
            "(σ numerical: the parameter shift of refitting with the converged reference renderer, "
            f"{(b.get('reference') or {}).get('table_sizes')} Bruneton tables with {(b.get('reference') or {}).get('table_orders')} "
            f"orders, by {b.get('method')}) and "
            f"the model discrepancy (σ discrepancy: a relative error floor f = {b.get('floor_relative') or 0:.3g} that brings "
            f"χ²/dof from {b.get('chi2_per_dof_corrected') or float('nan'):.3g} to 1), added in quadrature. The truth was rendered "
            "with a finer model than the fit's (Hillaire LUT 32 x 32 vs 16 x 16 texels, Gauss-Legendre optical depth "
            "vs Chapman, more view samples): 'error / σ noise' shows how far the noise-only σ misses it "
            "(docs/uncertainty.md, 'Honest sigma under model error').")
    log(note)
    report = [f"# skyfit demo{' (--quick)' if quick else ''}", "",
              f"True sky: {size}x{size} equidistant fisheye, {len(lam)} wavelengths {lam[0]:g}-{lam[-1]:g} nm, sun zenith "
              f"{SUN[0]}° azimuth {SUN[1]}°, single + multiple scattering (finer model than the fit's); noise "
              f"sigma = hypot({NOISE[0]:g} L, {NOISE[1]:g} median L).", "",
              table, "", note, "", f"Fit: loss {m['loss']:.4g} per element (0.5 = at the noise), RMSE {m['rmse']:.3g} {m['rmse_units']}, "
              f"mean ΔE {m['delta_e']:.3g}.", "", "Times [s]: " + ", ".join(f"{k} {v:.1f}" for k, v in timings.items()), "",
              "Files: " + ", ".join(summary["files"]), ""]
    write_text_atomic(out / "report.md", "\n".join(report))
    write_text_atomic(out / "demo.json", json.dumps(summary, indent=2))
    return summary


SAMPLE_PIXELS = 800
"""emcee in the demo sees every k-th sky pixel so that at most this many remain: with multiple
scattering the walkers are evaluated one at a time, each rebuilding the Hillaire LUT
(skyfit.fit.batched covers single scattering), and 12 walkers x 150 steps on all 12 892
pixels would take most of an hour on 2 CPU cores. Its widths are those of the subsample
(about sqrt(16) = 4x the full data's); the ratio to the Laplace widths of the same
subsample is what it checks."""
PILOT_STEPS = 150
"""The pilot chain's length; the chain then grows to :data:`MIN_STEPS_PER_TAU` x its tau (:func:`chain_steps`)."""
MAX_SAMPLE_STEPS = 6000
"""The demo's chain stops growing here (then it says that it is short of the tau rule)."""
TAU_MARGIN = 1.2
"""Steps asked for = margin x 50 x the running tau: tau estimates from short chains run low."""


def chain_steps(tau_max: float, steps_done: int, margin: float = TAU_MARGIN, cap: int = MAX_SAMPLE_STEPS) -> int:
    """Total steps for emcee's rule (chain >= :data:`MIN_STEPS_PER_TAU` tau) from the running tau estimate,
    at least ``steps_done`` + 1 and at most ``cap``. [steps]"""
    if not math.isfinite(tau_max) or tau_max <= 0:
        return cap
    return int(min(cap, max(steps_done + 1, math.ceil(margin * MIN_STEPS_PER_TAU * tau_max))))


def _sample(observed_exr: Path, out: Path, progress: bool, log, device="cpu") -> dict | None:
    """``skyfit sample`` around the fit on a pixel subsample: posterior, corner and trace plots in ``out/posterior``.

    A pilot of :data:`PILOT_STEPS` steps estimates tau; the chain is then continued (``--resume``)
    to 1.2 x 50 tau, re-estimated and continued again until emcee's rule holds (or
    :data:`MAX_SAMPLE_STEPS`)."""
    cfg = fit_config(False)
    cfg["sample"] = {"walkers": 12, "steps": PILOT_STEPS, "predictive_draws": 16, "max_samples": SAMPLE_PIXELS}
    summ = run_sample([observed_exr], cfg, out / "RESULT.json", out / "posterior", progress=progress,
                      device=device, truths=TRUTH)  # truth lines on the corner plot
    for _ in range(4):
        d, done = summ["diagnostics"], summ["sampler"]["steps"]
        if d.get("long_enough") or done >= MAX_SAMPLE_STEPS:
            break
        steps = chain_steps(float(d.get("tau_max", float("nan"))), done)
        log(f"emcee: {done} steps are {done / d.get('tau_max', float('nan')):.1f} tau (tau_max "
            f"{d.get('tau_max', float('nan')):.3g}); continuing to {steps} steps for the {MIN_STEPS_PER_TAU} tau rule")
        cfg["sample"]["steps"] = steps
        summ = run_sample([observed_exr], cfg, out / "RESULT.json", out / "posterior", progress=progress, resume=True,
                          device=device, truths=TRUTH)
    ratios = ", ".join(f"{n} {'-' if r['ratio'] is None else format(r['ratio'], '.2f')}"
                       for n, r in (summ.get("laplace_vs_emcee") or {}).items())
    log(f"emcee on {SAMPLE_PIXELS} pixels: {summ['sampler']['steps']} steps x {summ['sampler']['walkers']} walkers, "
        f"max tau {summ['diagnostics'].get('tau_max', float('nan')):.3g}; Laplace sigma / emcee sigma on the subsample: "
        f"{ratios} -> {out / 'posterior'}")
    return summ


def _export(result: dict, lut_dir: Path, quick: bool, device="cpu") -> Path:
    """Bruneton LUTs of the fitted atmosphere (what ``skyfit export-lut`` writes), small tables with ``quick``."""
    atm = atmosphere_from_result(result, result["model"]["wavelengths_nm"], device=device)
    sizes = TableSizes(64, 16, 32, 8, 8, 16, 8, 4) if quick else TableSizes(128, 32, 32, 8, 16, 64, 16, 8)
    with torch.no_grad():
        tables = precompute(atm, orders=4, sizes=sizes, quadrature=ACCURATE_QUADRATURE)
    return export_luts(tables, atm, lut_dir, format="exr")
