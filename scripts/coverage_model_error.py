"""Coverage of skyfit's sigma under model error: synthetic skies from a richer model than the fit's.

Each sky: a random atmosphere (AOD via beta550, Angstrom alpha, H_M, g, albedo, Rayleigh scale;
sun zenith 25-65 deg), rendered by a richer model than the fit uses:

* single scattering with Gauss-Legendre optical depth (``--truth-light`` nodes) and a
  ``--truth-view``-node Gauss view integral, plus orders 2..``--truth-orders`` of Bruneton &
  Neyret 2008 tables at ``--truth-tables`` (skyfit.fit.budget.ReferenceModel with the truth's
  sizes: finer than the budget's default reference, so the reference does not reproduce the truth);
* every other sky a two-term Henyey-Greenstein aerosol phase (g1 = g, g2 in (-0.4, -0.1),
  forward weight f in (0.85, 0.97)) that the fit's one-term HG cannot represent; its "true g" is
  the asymmetry parameter f g1 + (1 - f) g2 (HG's g is its own asymmetry).

Observed as a ``--size`` x ``--size`` equidistant fisheye with ``--wavelengths`` wavelengths and the
demo's noise, sigma = hypot(1 % L, 0.5 % median L), known to the fit. The fit: the demo's model
(Chapman optical depth, 16-node Gauss view integral, Hillaire's LUT 16 x 16, HG phase), free
rayleigh_scale, mie_beta_550, mie_angstrom_alpha, mie_scale_height, mie_g, ground_albedo; then the
Laplace sigma of the noise and the total sigma of skyfit.fit.budget. Coverage = the fraction of
skies whose 68 % / 95 % interval (Gaussian in the unconstrained parameter, mapped to physical
units) holds the truth, with its binomial error sqrt(p (1 - p) / n) at the nominal p.

``--compare`` adds other discrepancy models of skyfit.fit.budget beside the default total, from the
same fit and numerical term (e.g. ``sandwich:12`` = the jackknife sandwich over 12 sky regions,
``sandwich:24:cr1``, ``larger:12``): columns ``in68_<name>``, ``in95_<name>``, ``z_<name>``. Besides the
parameters, ``mie_g_forward_lobe`` scores the same fitted g against the forward lobe g1 of the truth
(= g on HG skies): on a two-term sky the asymmetry parameter is not what a one-term fit estimates.

    OMP_NUM_THREADS=1 nohup .venv/bin/python scripts/coverage_model_error.py --skies 20 \\
        --compare sandwich:12,sandwich:24,sandwich:24:cr1,larger:12 --out run.json > coverage.log 2>&1 &
    .venv/bin/python scripts/coverage_model_error.py --merge run.json --out docs/uncertainty/coverage_model_error.json

The JSON is rewritten after every sky (per-sky rows and the running table), so a killed run
keeps what it finished; ``--resume`` skips the skies already in it.
"""
from __future__ import annotations

import argparse
import copy
import json
import math
import sys
import time
from pathlib import Path

import numpy as np
import torch

from skyfit.atmosphere import atmosphere_from_config, load_yaml
from skyfit.camera import FisheyeCamera
from skyfit.fit import FitOptions, FitProblem, Observation, Parameterisation, fit, make_loss
from skyfit.fit.budget import DISCREPANCY_MODELS, SANDWICH_FORMS, ReferenceModel, error_budget, numerical_term, phase_expansion
from skyfit.fit.data import noise_sigma
from skyfit.fit.laplace import laplace_summary
from skyfit.fit.problem import fit_settings, prepare
from skyfit.transmittance import make_integrator

CONFIGS = Path(__file__).resolve().parents[1] / "skyfit" / "configs"
FREE = ["rayleigh_scale", "mie_beta_550", "mie_angstrom_alpha", "mie_scale_height", "mie_g", "ground_albedo"]
REPORTED = FREE + ["mie_aod_550"]
SIDE = {"mie_g_forward_lobe": "mie_g"}
"""Scored but not pooled into "all": name -> the fitted parameter it scores (its truth: the truth's g1)."""
NOISE = (0.01, 0.005)
FIT = {"orders": 2, "multiple": "hillaire", "integrator": "chapman", "view_samples": 16, "rule": "gauss", "starts": 1,
       "sun_mask_deg": 3.0, "min_elevation_deg": 2.0, "max_iter": 200}


TRUTH_DEFAULTS = {"size": 10, "wavelengths": 3, "truth_light": 64, "truth_view": 64, "truth_tables": "16,64,16,8",
                  "truth_orders": 8, "reference_axis": "window", "truth_axis": None, "beta_range": "1e-5,8e-5"}
"""How the truths are observed and rendered (the command line's defaults): what :func:`observe` reads of its args."""


def truth_args(**kw) -> argparse.Namespace:
    """:data:`TRUTH_DEFAULTS` with ``kw`` over them, as :func:`observe` takes them (for the scripts that draw these
    truths without this one's command line)."""
    return argparse.Namespace(**{**TRUTH_DEFAULTS, **kw})


def draw_truth(rng: np.random.Generator, two_term: bool, beta: tuple[float, float] = (1e-5, 8e-5)) -> dict:
    t = {
        "rayleigh_scale": float(rng.uniform(0.9, 1.1)),
        "mie_beta_550": float(math.exp(rng.uniform(math.log(beta[0]), math.log(beta[1])))),
        "mie_angstrom_alpha": float(rng.uniform(0.2, 1.8)),
        "mie_scale_height": float(rng.uniform(800.0, 2500.0)),
        "g1": float(rng.uniform(0.6, 0.85)),
        "ground_albedo": float(rng.uniform(0.1, 0.35)),
        "sun_zenith_deg": float(rng.uniform(25.0, 65.0)),
        "sun_azimuth_deg": float(rng.uniform(0.0, 360.0)),
    }
    if two_term:
        t["g2"] = float(rng.uniform(-0.4, -0.1))
        t["hg_weight"] = float(rng.uniform(0.85, 0.97))
        t["mie_g"] = t["hg_weight"] * t["g1"] + (1 - t["hg_weight"]) * t["g2"]  # the asymmetry parameter
    else:
        t["mie_g"] = t["g1"]
    t["mie_aod_550"] = t["mie_beta_550"] * t["mie_scale_height"]
    return t


def truth_config(t: dict) -> dict:
    cfg = copy.deepcopy(load_yaml(CONFIGS / "earth.yaml"))
    cfg["name"] = "coverage_truth"
    cfg["rayleigh"]["scale"] = t["rayleigh_scale"]
    cfg["mie"].pop("angstrom_beta", None)
    cfg["mie"]["extinction_550"] = t["mie_beta_550"]
    cfg["mie"]["angstrom_alpha"] = t["mie_angstrom_alpha"]
    cfg["mie"]["scale_height_m"] = t["mie_scale_height"]
    cfg["mie"]["g"] = t["g1"]
    if "g2" in t:
        cfg["mie"].update(phase="two_term_hg", g2=t["g2"], hg_weight=t["hg_weight"])
    else:
        cfg["mie"]["phase"] = "henyey_greenstein"
    cfg["ground"] = {"albedo": t["ground_albedo"]}
    return cfg


def fit_config() -> dict:
    cfg = copy.deepcopy(load_yaml(CONFIGS / "earth.yaml"))
    cfg["mie"]["phase"] = "henyey_greenstein"
    cfg["fit"] = {**FIT, "free": list(FREE)}
    return cfg


def observe(t: dict, args, rng: np.random.Generator) -> tuple[Observation, dict]:
    """The truth rendered with the richer model at the fisheye's sky pixels, plus known noise."""
    lam = np.linspace(420.0, 680.0, args.wavelengths)
    view, valid = FisheyeCamera(args.size).pixel_vectors(torch.float64)
    view = view[valid]
    n = view.shape[0]
    rad = lambda d: torch.tensor(math.radians(d), dtype=torch.float64)  # noqa: E731
    chans = tuple(f"L{x:g}" for x in lam)
    ones = torch.ones(n, len(lam), dtype=torch.float64)
    dummy = Observation("truth", "truth", "spectral", view, rad(t["sun_zenith_deg"]), rad(t["sun_azimuth_deg"]), ones, ones,
                        torch.ones(n, dtype=torch.bool), chans, torch.tensor(lam))
    base = atmosphere_from_config(truth_config(t), lam)
    tables = tuple(int(v) for v in args.truth_tables.split(","))
    # the truth's tables span its sun, or (--reference-axis whole, the studies before session 18) 2017's whole axis
    window = (getattr(args, "truth_axis", None) or getattr(args, "reference_axis", "window")) == "window"
    model = ReferenceModel(make_integrator("gauss", samples=args.truth_light), orders=2, view_samples=args.truth_view,
                           rule="gauss", reference_tables=tables, reference_orders=args.truth_orders, sun_window=window,
                           sun_zenith_deg=(t["sun_zenith_deg"],) * 2 if window else None)
    prob = FitProblem(Parameterisation(base, []), model, [dummy], make_loss("squared"))
    t0 = time.process_time()
    with torch.no_grad():
        clean = prob.predict(prob.param.initial_vector())[0]
    secs = time.process_time() - t0
    sigma = noise_sigma(clean, NOISE[0], NOISE[1] * float(clean.median()))
    gen = torch.Generator().manual_seed(int(rng.integers(2**31)))
    noisy = clean + sigma * torch.randn(clean.shape, generator=gen, dtype=clean.dtype)
    obs = Observation("sky", "coverage sky", "spectral", view, rad(t["sun_zenith_deg"]), rad(t["sun_azimuth_deg"]), noisy,
                      sigma, torch.ones(n, dtype=torch.bool), chans, torch.tensor(lam))
    return obs, {"truth_render_cpu_s": secs, "n_samples": n}


def inside(interval, v) -> bool:
    return interval is not None and interval[0] <= v <= interval[1]


def derived_interval(d: dict, z: float):
    if not d or d.get("sigma") is None:
        return None
    return [d["value"] - z * d["sigma"], d["value"] + z * d["sigma"]]


def variants(spec: str) -> dict[str, dict]:
    """``--compare`` "MODEL[:G[:FORM]],..." -> name -> error_budget keywords."""
    out = {}
    for item in filter(None, (v.strip() for v in spec.split(","))):
        parts = item.split(":")
        if parts[0] not in DISCREPANCY_MODELS or len(parts) > 3 or (len(parts) == 3 and parts[2] not in SANDWICH_FORMS):
            raise SystemExit(f"--compare: {item!r} is not MODEL[:G[:FORM]] with MODEL in {DISCREPANCY_MODELS}, FORM in {SANDWICH_FORMS}")
        kw = {"discrepancy": parts[0]}
        if len(parts) > 1:
            kw["clusters"] = int(parts[1])
        if len(parts) > 2:
            kw["sandwich_form"] = parts[2]
        out[item.replace(":", "_")] = kw
    return out


def one_sky(k: int, args) -> dict:
    rng = np.random.default_rng([args.seed, k])
    two_term = k % 2 == 1
    t = draw_truth(rng, two_term, tuple(float(v) for v in getattr(args, "beta_range", "1e-5,8e-5").split(",")))
    t["mie_g_forward_lobe"] = t["g1"]
    obs, info = observe(t, args, rng)
    cfg = fit_config()
    prep = prepare([obs], cfg, fit_settings(cfg["fit"]))
    problem = prep.fit_problem()
    c0 = time.process_time()
    res = fit(problem, prep.settings.options(False))
    c_fit = time.process_time() - c0
    c0 = time.process_time()
    lap = laplace_summary(problem, res.x)
    reference = ReferenceModel.of(problem.model, sun_window=getattr(args, "reference_axis", "window") == "window")
    term = numerical_term(problem, res.x, lap, reference=reference, refits=args.refits, polish=getattr(args, "polish", 0),
                          options=FitOptions(starts=1, adam_steps=0, max_iter=FIT["max_iter"]))
    sigmas = {"total": error_budget(problem, res.x, lap, term=term)}
    for name, kw in variants(args.compare).items():
        sigmas[name] = error_budget(problem, res.x, lap, term=term, **kw)
    expansion = None
    if args.expand:  # the default total plus the phase term (skyfit.fit.budget.phase_expansion)
        expansion = phase_expansion(problem, res.x, term, reference=reference,
                                    options=FitOptions(starts=1, adam_steps=0, max_iter=FIT["max_iter"]))
        sigmas["expand"] = error_budget(problem, res.x, lap, term=term, expansion=expansion)
    tot = sigmas["total"]
    # the numerically corrected estimate (value at x + dx, the shift not an error): error_budget's "corrected"
    for name in [n for n in sigmas if n in ("total", "expand")]:
        sigmas[f"{name}_corrected"] = sigmas[name]["corrected"]
    c_unc = time.process_time() - c0
    row = {"sky": k, "two_term_hg": two_term, "truth": t, "fitted": {}, "z_noise": {}, "in68_noise": {}, "in95_noise": {},
           "budget": {kk: tot["budget"].get(kk) for kk in ("chi2_per_dof", "chi2_per_dof_corrected", "floor_relative",
                                                        "floor_relative_68", "model_difference", "sigma_noise", "method", "nonlinearity",
                                                        "refit_steps_in_sigma", "numerical_tail", "numerical_shift_newton",
                                                        "polish",
                                                        "sigma_numerical", "sigma_discrepancy", "numerical_shift")},
           "discrepancy": {name: {kk: b["budget"].get(kk) for kk in ("discrepancy", "sigma_discrepancy")}
                           for name, b in sigmas.items() if "budget" in b},
           "convergence": res.convergence["reason"], "loss": res.loss,
           "expand_budget": None if expansion is None else {kk: sigmas["expand"]["budget"].get(kk) for kk in (
               "sigma_phase", "sigma_phase_spread", "derived")},
           "budget_derived": tot["budget"].get("derived"),
           "phase_expansion": None if expansion is None else {k: expansion[k] for k in ("values", "loss", "converged", "seconds", "spread")},
           "cpu_s": {"truth_render": info["truth_render_cpu_s"], "fit": c_fit, "uncertainty": c_unc},
           "n_samples": info["n_samples"]}
    for name in sigmas:
        row[f"z_{name}"], row[f"in68_{name}"], row[f"in95_{name}"] = {}, {}, {}
    row["estimates"] = {name: {} for name in ["noise", *sigmas]}  # name -> parameter -> [value, sigma, 68 %, 95 %]
    z68, z95 = 0.9944578832097535, 1.959963984540054
    for n in REPORTED + list(SIDE):
        p = SIDE.get(n, n)
        tv = t[n]
        for name, b in [("noise", lap), *sigmas.items()]:
            if p in FREE:
                v, s_, i68, i95 = b["values"][p], b["sigma"][p], b["interval68"][p], b["interval95"][p]
            else:
                v, s_ = b["derived"][p]["value"], b["derived"][p]["sigma"]
                i68, i95 = derived_interval(b["derived"][p], z68), derived_interval(b["derived"][p], z95)
            if name == "noise":  # the fit's own value (a corrected estimate has its own)
                row["fitted"][n] = v
            row[f"z_{name}"][n] = None if not s_ else (v - tv) / s_
            row[f"in68_{name}"][n], row[f"in95_{name}"][n] = inside(i68, tv), inside(i95, tv)
            row["estimates"][name][n] = [v, s_, i68, i95]
    add_extended(row)
    return row


def add_extended(row: dict) -> None:
    """Score ``<name>_extended`` beside each corrected reading of ``row``: its intervals extended to the fitted
    value (the fit's own estimate kept inside, the corrected one's width kept on its far side). z: the truth's
    distance from the segment between the two values in the corrected sigma (0 between them)."""
    est = row.get("estimates", {})
    for name in [n for n in list(est) if n.endswith("_corrected")]:
        ext = f"{name[:-len('_corrected')]}_extended"
        row[f"z_{ext}"], row[f"in68_{ext}"], row[f"in95_{ext}"], est[ext] = {}, {}, {}, {}
        for n, (c, s_, i68, i95) in est[name].items():
            v, tv = row["fitted"][n], row["truth"][n]
            grow = lambda i: None if i is None else [min(i[0], v), max(i[1], v)]
            e68, e95 = grow(i68), grow(i95)
            lo, hi = min(v, c), max(v, c)
            row[f"z_{ext}"][n] = None if not s_ else (0.0 if lo <= tv <= hi else (tv - hi if tv > hi else tv - lo) / s_)
            row[f"in68_{ext}"][n], row[f"in95_{ext}"][n] = inside(e68, tv), inside(e95, tv)
            est[ext][n] = [v, s_, e68, e95]


def sigma_names(rows: list[dict]) -> list[str]:
    """The sigmas scored in ``rows``: noise, total and the ``--compare`` variants, in their order."""
    return [k[len("in68_"):] for k in rows[0] if k.startswith("in68_")] if rows else ["noise", "total"]


def table(rows: list[dict]) -> dict:
    n = len(rows)
    out = {"n_skies": n, "binomial_error_68": math.sqrt(0.68 * 0.32 / max(n, 1)),
           "binomial_error_95": math.sqrt(0.95 * 0.05 / max(n, 1)), "parameters": {}}
    for p in REPORTED + ["all"] + list(SIDE):
        names = REPORTED if p == "all" else [p]
        d = {}
        for sig in sigma_names(rows):
            for level in ("68", "95"):
                hits = [r[f"in{level}_{sig}"][q] for r in rows for q in names if q in r[f"in{level}_{sig}"]]
                d[f"coverage{level}_{sig}"] = sum(hits) / max(len(hits), 1)
            zs = [r[f"z_{sig}"][q] for r in rows for q in names if r[f"z_{sig}"].get(q) is not None]
            d[f"rms_z_{sig}"] = math.sqrt(sum(z * z for z in zs) / max(len(zs), 1))
            d["n"] = len(zs)
        out["parameters"][p] = d
    return out


def markdown(doc: dict) -> str:
    """The coverage tables of a merged run as markdown (docs/uncertainty.md): 68 / 95 % coverage and RMS z per sigma."""
    lines = []
    for key, title in (("table", "all skies"), ("table_hg", "HG truth"), ("table_two_term", "two-term HG truth")):
        t = doc[key]
        sigs = [k[len("coverage68_"):] for k in next(iter(t["parameters"].values())) if k.startswith("coverage68_")]
        lines += [f"{title}: n = {t['n_skies']} skies (binomial error {t['binomial_error_68']:.3f} at 68 %, "
                  f"{t['binomial_error_95']:.3f} at 95 %); 68 / 95 % coverage (RMS z)", "",
                  "| parameter | " + " | ".join(f"{s} σ" for s in sigs) + " |", "|---" * (len(sigs) + 1) + "|"]
        for p, d in t["parameters"].items():
            lines.append(f"| {p} | " + " | ".join(f"{d['coverage68_' + s]:.2f} / {d['coverage95_' + s]:.2f} ({d['rms_z_' + s]:.2f})"
                                                 for s in sigs) + " |")
        lines.append("")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--skies", type=int, default=20)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--size", type=int, default=TRUTH_DEFAULTS["size"], help="fisheye pixels across (a 12 x 12 image has ~100 sky pixels)")
    ap.add_argument("--wavelengths", type=int, default=TRUTH_DEFAULTS["wavelengths"])
    ap.add_argument("--truth-light", type=int, default=TRUTH_DEFAULTS["truth_light"])
    ap.add_argument("--truth-view", type=int, default=TRUTH_DEFAULTS["truth_view"])
    ap.add_argument("--truth-tables", default=TRUTH_DEFAULTS["truth_tables"], help="R,MU,MU_S,NU of the truth's Bruneton tables")
    ap.add_argument("--truth-orders", type=int, default=TRUTH_DEFAULTS["truth_orders"])
    ap.add_argument("--refits", type=int, default=1, help="the budget's lagged refits (fit.sigma_refits)")
    ap.add_argument("--reference-axis", choices=("window", "whole"), default=TRUTH_DEFAULTS["reference_axis"],
                    help="the truth's and the budget reference's Bruneton tables: spanning the sky's sun (default, "
                         "fit.sigma_reference_axis) or 2017's whole mu_s axis (every study before session 18)")
    ap.add_argument("--truth-axis", choices=("window", "whole"), help="the truth's tables alone (default: --reference-axis)")
    ap.add_argument("--beta-range", default=TRUTH_DEFAULTS["beta_range"], help="LO,HI of the truths' log-uniform Mie beta_550 [1/m]")
    ap.add_argument("--polish", type=int, default=0, help="the budget's reference polish after the refits "
                    "(fit.sigma_polish: Levenberg-Marquardt steps on the reference, skyfit.fit.budget.reference_polish)")
    ap.add_argument("--compare", default="", help="other discrepancy models beside the default total, MODEL[:G[:FORM]],... "
                    "(e.g. sandwich:12,sandwich:24:cr1,larger:12)")
    ap.add_argument("--expand", action="store_true", help="also score the total sigma with the phase term (a two-term HG "
                    "refit's shift, skyfit.fit.budget.phase_expansion): columns in68_expand, in95_expand, z_expand")
    ap.add_argument("--part", default="0/1", help="K/N: run only the skies k with k %% N == K (N processes side by side)")
    ap.add_argument("--descending", action="store_true", help="run the part's skies from the last (a second process per part)")
    ap.add_argument("--merge", nargs="+", help="merge the JSON files of the parts into --out (no fitting)")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--resume", action="store_true")
    ap.add_argument("--out", default="docs/uncertainty/coverage_model_error.json")
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    if args.merge:
        docs = [json.loads(Path(m).read_text()) for m in args.merge]
        rows = list({r["sky"]: r for d in docs for r in reversed(d["skies"])}.values())  # one row per sky
        rows.sort(key=lambda r: r["sky"])
        good = [r for r in rows if "failed" not in r]
        doc = {**docs[0], "command": docs[0]["command"].split(" --part")[0] + " (parts merged: " + ", ".join(args.merge) + ")",
               "table": table(good), "table_hg": table([r for r in good if not r["two_term_hg"]]),
               "table_two_term": table([r for r in good if r["two_term_hg"]]), "skies": rows,
               "wall_s": max(d["wall_s"] for d in docs), "cpu_s": sum(sum(r["cpu_s"].values()) for r in good)}
        out.write_text(json.dumps(doc, indent=1))
        print(markdown(doc))
        return 0
    part, parts = (int(v) for v in args.part.split("/"))
    rows = json.loads(out.read_text())["skies"] if args.resume and out.exists() else []
    done = {r["sky"] for r in rows}
    t_start = time.perf_counter()
    for k in (reversed(range(args.skies)) if args.descending else range(args.skies)):
        if k in done or k % parts != part:
            continue
        t0 = time.perf_counter()
        try:
            row = one_sky(k, args)
        except Exception as e:  # a failed sky is recorded, not hidden
            print(f"sky {k}: FAILED {type(e).__name__}: {e}", flush=True)
            rows.append({"sky": k, "failed": f"{type(e).__name__}: {e}"})
            continue
        row["wall_s"] = time.perf_counter() - t0
        rows.append(row)
        good = [r for r in rows if "failed" not in r]
        summ = table(good)
        all_ = summ["parameters"]["all"]
        print(f"sky {k + 1}/{args.skies} ({'two-term' if row['two_term_hg'] else 'HG'}, sun {row['truth']['sun_zenith_deg']:.0f} deg): "
              f"chi2/dof {row['budget']['chi2_per_dof']:.3g} -> {row['budget']['chi2_per_dof_corrected']:.3g}, floor "
              f"{row['budget']['floor_relative']:.3g}; max |z| " + ", ".join(
                  f"{sig} {max(abs(z) for z in row['z_' + sig].values() if z is not None):.2f}" for sig in sigma_names([row]))
              + "; running coverage 68/95 " + ", ".join(
                  f"{sig} {all_['coverage68_' + sig]:.2f}/{all_['coverage95_' + sig]:.2f}" for sig in sigma_names([row]))
              + f"; {row['wall_s']:.0f} s", flush=True)
        doc = {"command": "scripts/coverage_model_error.py " + " ".join(sys.argv[1:] if argv is None else argv),
               "settings": vars(args), "fit": FIT, "free": FREE, "noise": NOISE, "table": summ, "skies": rows,
               "wall_s": time.perf_counter() - t_start}
        tmp = out.with_suffix(".tmp")
        tmp.write_text(json.dumps(doc, indent=1))
        tmp.replace(out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
