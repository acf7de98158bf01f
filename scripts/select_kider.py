"""The model ladder (``skyfit fit --select``) on every Kider et al. 2014 capture: the chosen model per capture.

For each capture folder, :func:`skyfit.fit.run.run_fit` with ``select=True`` and the
fit settings of configs/kider.yaml (its ``orders`` is replaced by the ladder's choice);
one RESULT.json per capture in ``--out`` (default docs/selection/kider), then a Markdown
table of the chosen rung per capture and the summary lines docs/selection.md quotes
(:func:`summary`: ranges over the captures, and the comparison with docs/kider/fit_*.json)
in ``--out``/table.md, pasted into docs/selection.md.
CPU time per capture is process time (the machine is shared: wall time is not a measure).

    .venv/bin/python scripts/select_kider.py                       # all captures
    .venv/bin/python scripts/select_kider.py --captures 09.30,12.00 --max-iter 40
    .venv/bin/python scripts/select_kider.py --table-only          # rebuild table.md from the JSON files
    .venv/bin/python scripts/select_kider.py --nuisance exposure,sun_azimuth_offset --out docs/selection/kider_instrument
    .venv/bin/python scripts/select_kider.py --extra-model --captures 10.00,12.00,09.30   # (below)

``--extra-model``: instead of the ladder, fit the model the greedy ladder cannot reach once it
has rejected ``multiple``: multiple scattering *and* free scale heights. A second ladder, with
the same settings, instrument parameters and held-out split (same seed), whose rungs are
``rayleigh``, ``mie``, ``ozone`` and one rung ``multiple + scale_heights`` (orders 2, both scale
heights freed) on top of the best of those, then the backward step as usual. One
extra_HH.MM.json per capture in ``--out``; table.md then adds a table comparing its best
multiple-scattering row with the chosen model of select_HH.MM.json (the BICs share n and the
Gaussian constant, so they compare directly; the ``rayleigh`` rungs of both ladders must agree,
which checks the split).
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
DAY = ROOT.parent / "shared" / "data" / "kider2014" / "2013-05-27"


def table(results: list[dict]) -> str:
    """Markdown: one row per capture (chosen components, BIC margins, held-out choice, fit quality, CPU time)."""
    lines = [
        "| capture | sun zenith [deg] | chosen rung | components | ΔBIC to parent | held-out choice (Δloss ± SE) "
        "| `multiple` rung: ΔBIC, held-out loss (chosen's) | RMSE [mW/(m² sr nm)] | ΔE | CPU [s] |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in results:
        sel = r["selection"]
        rows = {x["name"]: x for x in sel["rungs"]}
        c = rows[sel["chosen"]]
        dpar = "" if c.get("delta_bic_parent") is None else f"{c['delta_bic_parent']:+.1f}"
        held = sel["heldout_choice"]
        m = sel.get("heldout_margin")
        held_s = "same" if sel["heldout_agrees"] else f"{held} ({m['loss_difference']:+.0f} ± {m['standard_error']:.0f})" if m else str(held)
        sz = r["data"][0].get("sun_zenith_deg")
        sz = sz.get("mean") if isinstance(sz, dict) else sz
        sz_s = "" if sz is None else f"{float(sz):.1f}"
        cpu = sum(x.get("cpu_seconds", 0.0) for x in sel["rungs"])
        ms = rows.get("multiple", {})
        ms_s = (f"{ms['delta_bic']:+.0f}, {ms['heldout_loss']:.3g} ({c['heldout_loss']:.3g})" if "bic" in ms
                else ms.get("skipped", ms.get("failed", "")))
        comps = sel["components"] + [x for x, n in (("ground albedo", "ground_albedo"), ("free scale heights", "rayleigh_scale_height"))
                                     if n in r["free"]]  # freed by a rung, not a component of the renderer
        lines.append(f"| {r['capture']} | {sz_s} | {sel['chosen']} | {' + '.join(comps)} | {dpar} | {held_s} | {ms_s} "
                     f"| {r['metrics']['rmse']:.3g} | {r['metrics']['delta_e']:.3g} | {cpu:.0f} |")
    return "\n".join(lines) + "\n"


def _rng(v, fmt: str = ".3g") -> str:
    return "–" if not v else f"{min(v):{fmt}}–{max(v):{fmt}}" if min(v) != max(v) else f"{v[0]:{fmt}}"


def _scalar(v):
    return v[0] if isinstance(v, list) and len(v) == 1 else v


def summary(results: list[dict], config: dict) -> str:
    """Markdown bullets: the facts docs/selection.md states about the table, computed from the JSON files."""
    n = len(results)
    if not n:
        return ""
    h_r0 = float(config.get("rayleigh", {}).get("scale_height_m", 8000.0))
    chosen, no_mie, ms_d, ms_held_better, ms_held, free_h, hr, hm, rs, tau, oz, oz_caps, exp_ = (
        {}, [], [], [], [], [], [], [], [], [], [], [], [])
    ms_in, alb, n_free, kider_free = [], [], [], []
    agree, smaller, within, loss, rmse, at_max, held_loss, held_n = 0, 0, 0, [], [], 0, [], []
    kider = []
    for r in results:
        sel, p = r["selection"], r["parameters"]
        rows = {x["name"]: x for x in sel["rungs"]}
        c = rows[sel["chosen"]]
        chosen[sel["chosen"]] = chosen.get(sel["chosen"], 0) + 1
        no_mie += [min(x["delta_bic"] for x in sel["rungs"] if "bic" in x and "mie" not in x["components"])]
        ms = rows.get("multiple", {})
        if "multiple" in sel["components"]:
            ms_in.append(f"{r['capture']} (`multiple` rung ΔBIC {ms.get('delta_bic_parent', float('nan')):+.0f} to its parent)")
        elif "bic" in ms:
            ms_d.append(ms["delta_bic"])
            ms_held.append((r["capture"], ms["heldout_loss"], c["heldout_loss"]))
            if ms["heldout_loss"] < c["heldout_loss"]:
                ms_held_better.append(r["capture"])
        if "rayleigh_scale_height" in r["free"]:
            free_h.append(r["capture"])
            hr.append(p["rayleigh_scale_height"] / 1e3)
            rs.append(p["rayleigh_scale"])
            tau.append(p["rayleigh_scale"] * p["rayleigh_scale_height"] / h_r0)
            if "mie_scale_height" in r["free"]:
                hm.append(p["mie_scale_height"])
        if "ground_albedo" in r["free"]:
            alb.append((r["capture"], _scalar(p["ground_albedo"])))
        if "ozone" in sel["components"]:
            oz.append(p["ozone_column"])
            oz_caps.append(r["capture"])
        exp_.append((_scalar(p["exposure"]), "multiple" in sel["components"]))
        n_free.append(len(r["free"]))
        if sel["heldout_agrees"]:
            agree += 1
        else:
            h = rows[sel["heldout_choice"]]
            smaller += h["k"] < c["k"]
            m = sel.get("heldout_margin")
            within += bool(m) and abs(m["loss_difference"]) < 2 * m["standard_error"]
        loss.append(c["loss"])
        held_loss.append(c["heldout_loss"])
        held_n.append(sel["n_heldout"] / len(r["data"][0]["channels"]))
        rmse.append(r["metrics"]["rmse"])
        at_max += not (c.get("convergence") or {}).get("converged", True)
        kp = ROOT / "docs" / "kider" / f"fit_{r['capture']}.json"
        if kp.exists():
            kj = json.loads(kp.read_text())
            kider.append((r["capture"], kj["metrics"]["rmse"], r["metrics"]["rmse"]))
            kider_free.append(len(kj["free"]))
    out = [f"- held out: {_rng(held_n, '.0f')} of {r['data'][0]['n_samples']} samples per capture",
           f"- captures: {n}; chosen rung: " + ", ".join(f"`{k}` {v}" for k, v in sorted(chosen.items())),
           f"- best model without aerosol: ΔBIC {_rng(no_mie, '+.0f')} against the chosen",
           f"- multiple scattering in the chosen model: {len(ms_in)} ({', '.join(ms_in) or 'none'}); elsewhere the "
           f"`multiple` rung has ΔBIC {_rng(ms_d, '+.0f')} against the chosen, and a lower held-out loss than the "
           f"chosen model's in {len(ms_held_better)} ({', '.join(ms_held_better) or 'none'})",
           f"- ground albedo freed in the chosen model: {len(alb)} ("
           + (", ".join(f"{c} {a:.3g}" for c, a in alb) or "none") + ")",
           f"- free scale heights in the chosen model: {len(free_h)} of {n}; H_R {_rng(hr)} km, rayleigh_scale "
           f"{_rng(rs)}, rayleigh_scale × H_R / {h_r0 / 1e3:g} km {_rng(tau)}; H_M {_rng(hm)} m",
           f"- ozone kept in {len(oz)} ({', '.join(oz_caps) or 'none'}): {_rng(oz, '.0f')} DU",
           f"- exposure of the chosen model: {_rng([e for e, m in exp_ if not m])} with single scattering, "
           f"{_rng([e for e, m in exp_ if m])} with multiple scattering",
           f"- held-out choice agrees in {agree} of {n}; of the {n - agree} others it prefers a smaller model in "
           f"{smaller}, and the held-out difference is within 2 standard errors in {within}",
           f"- chosen model: training loss {_rng(loss)} per element, held-out loss {_rng(held_loss)}, "
           f"RMSE (refitted on all samples) {_rng(rmse)}; "
           f"chosen rung stopped at max_iter in {at_max}"]
    if kider:
        better = [c for c, k, s in kider if s < k]
        out.append(f"- against docs/kider/fit_*.json (orders 2, the config's free list: {_rng(kider_free, 'd')} free "
                   f"parameters; the chosen models free {_rng(n_free, 'd')}): the chosen model's RMSE is "
                   f"lower in {len(better)} of {len(kider)}; " + ", ".join(f"{c} {s:.2f} vs {k:.2f}" for c, k, s in kider))
    return "\n".join(out) + "\n"


EXTRA = "multiple + scale_heights"


def fit_extra(folder: Path, cfg: dict, overrides: dict) -> dict:
    """The ``--extra-model`` ladder on one capture (module docstring): its report, JSON-ready."""
    from skyfit.fit.optimise import FitOptions
    from skyfit.fit.problem import fit_settings, initial_values, prepare
    from skyfit.fit.select import RUNGS, SELECT_NUISANCE, Ladder, Rung, strip_private

    s = fit_settings(cfg.get("fit"), overrides)
    prep = prepare([folder], cfg, s, orders=1)  # as run_select: single scattering until a rung says otherwise
    rings = any("ring" in o.metadata for o in prep.observations)
    nuisance = [n for n in (s.free or []) if n in SELECT_NUISANCE] if s.free is not None else \
        ["exposure"] + (["sun_azimuth_offset"] if rings else [])
    by = {r.name: r for r in RUNGS}
    rungs = (by["rayleigh"], by["mie"], by["ozone"],
             Rung(EXTRA, "+ multiple scattering and free Rayleigh and aerosol scale heights in one step",
                  by["scale_heights"].free, {"orders": 2}))
    options = FitOptions(starts=s.starts, seed=s.seed, adam_steps=s.adam_steps, max_iter=s.max_iter,
                         grad_tol=s.grad_tol, rel_tol=s.rel_tol)
    ladder = Ladder(prep.base, prep.model, prep.observations, prep.loss, nuisance_free=nuisance,
                    per_observation=s.per_observation,
                    initial=initial_values(s, prep.observations, nuisance, s.per_observation), options=options,
                    sigma=s.select_sigma, heldout=s.select_heldout, seed=s.seed, base_sun_distance_au=prep.base_dist,
                    rungs=rungs)
    return strip_private(ladder.run())


def extra_table(out: Path) -> str:
    """Markdown: per capture, the extra ladder's best multiple-scattering row against the ladder's chosen model."""
    lines = ["| capture | ladder's choice | best row with multiple + free scale heights | components "
             "| ΔBIC to the ladder's choice | held-out loss (choice's) | rayleigh_scale | H_R [km] | H_M [m] | stopped by "
             "| CPU [s] |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    checks = []
    for p in sorted(out.glob("extra_*.json")):
        capture = p.stem.split("_", 1)[1]
        sp = out / f"select_{capture}.json"
        if not sp.exists():
            continue
        ex = json.loads(p.read_text())
        sel = json.loads(sp.read_text())["selection"]
        main = {r["name"]: r for r in sel["rungs"]}
        c = main[sel["chosen"]]
        xr = {r["name"]: r for r in ex["rungs"]}
        if "bic" in xr.get("rayleigh", {}) and "bic" in main.get("rayleigh", {}):
            checks.append(abs(xr["rayleigh"]["bic"] - main["rayleigh"]["bic"]))
        ms = [r for r in ex["rungs"] if "bic" in r and r["name"].startswith(EXTRA)]
        cpu = sum(r.get("cpu_seconds", 0.0) for r in ex["rungs"])
        if not ms:
            why = "; ".join(f"{r['name']}: {r.get('skipped', r.get('failed'))}" for r in ex["rungs"] if r["name"].startswith(EXTRA))
            lines.append(f"| {capture} | {sel['chosen']} | not fitted ({why}) | | | | | | | | {cpu:.0f} |")
            continue
        b = min(ms, key=lambda r: r["bic"])
        par = b["parameters"]
        hm = par.get("mie_scale_height")
        lines.append(f"| {capture} | {sel['chosen']} | {b['name']} | {' + '.join(b['components'])} "
                     f"| {b['bic'] - c['bic']:+.1f} | {b['heldout_loss']:.3g} ({c['heldout_loss']:.3g}) "
                     f"| {par['rayleigh_scale']:.3g} | {par['rayleigh_scale_height'] / 1e3:.3g} "
                     f"| {'' if hm is None else f'{hm:.3g}'} | {(b.get('convergence') or {}).get('reason', '')} | {cpu:.0f} |")
    if len(lines) == 2:
        return ""
    note = (f"Split check: the `rayleigh` rungs of the two ladders differ in BIC by at most {max(checks):.2g} "
            f"({len(checks)} captures).") if checks else "Split check: no `rayleigh` rung to compare."
    return "\n".join(lines) + "\n\n" + note + "\n"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--day", default=str(DAY))
    ap.add_argument("--captures", default="all", help="comma list of HH.MM, or 'all'")
    ap.add_argument("--config", default=str(ROOT / "configs" / "kider.yaml"))
    ap.add_argument("--out", default=str(ROOT / "docs" / "selection" / "kider"))
    ap.add_argument("--max-iter", type=int, help="L-BFGS iterations per rung (default: the config's)")
    ap.add_argument("--sigma", choices=("scaled", "known"), default="scaled")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--optimiser", choices=("auto", "lm", "lbfgs"), help="the rungs' optimiser (default: the config's)")
    ap.add_argument("--nuisance", help="comma list: the instrument's free parameters in every rung (default: those of "
                                       "the config's free list), e.g. exposure,sun_azimuth_offset (issue 14)")
    ap.add_argument("--table-only", action="store_true", help="only rebuild table.md from the JSON files in --out")
    ap.add_argument("--extra-model", action="store_true",
                    help="instead of the ladder: fit multiple scattering + free scale heights (extra_HH.MM.json)")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    from skyfit.atmosphere import load_yaml
    from skyfit.fit.report import dumps
    from skyfit.fit.run import run_fit

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    day = Path(args.day)
    folders = sorted(day.glob("2013-05-27___*")) if args.captures == "all" else [
        day / f"2013-05-27___{c}.00" for c in args.captures.split(",")]
    cfg = load_yaml(args.config)
    if args.nuisance:  # the ladder keeps only the instrument's parameters of the free list
        cfg["fit"]["free"] = [n.strip() for n in args.nuisance.split(",") if n.strip()]
    overrides = {"max_iter": args.max_iter, "select_sigma": args.sigma, "optimiser": args.optimiser}
    if args.extra_model and not args.table_only:
        for folder in folders:
            capture = folder.name.split("___")[-1][:5]
            c0 = time.process_time()
            rep = fit_extra(folder, cfg, overrides)
            (out / f"extra_{capture}.json").write_text(dumps(rep))  # strict JSON, as RESULT.json
            print(json.dumps({"capture": capture, "chosen": rep["chosen"], "heldout_choice": rep["heldout_choice"],
                              "cpu_s": round(time.process_time() - c0, 1)}), flush=True)
    elif not args.table_only:
        for folder in folders:
            capture = folder.name.split("___")[-1][:5]
            c0 = time.process_time()
            res = run_fit([folder], cfg, out / f"select_{capture}.json", config_source=args.config, plots=False,
                          progress=sys.stderr.isatty(), select=True,
                          overrides=overrides)
            sel = res["selection"]
            print(json.dumps({"capture": capture, "chosen": sel["chosen"], "components": sel["components"],
                              "heldout_choice": sel["heldout_choice"], "rmse": round(res["metrics"]["rmse"], 3),
                              "cpu_s": round(time.process_time() - c0, 1)}), flush=True)
    results = []
    for p in sorted(out.glob("select_*.json")):
        r = json.loads(p.read_text())
        r["capture"] = p.stem.split("_", 1)[1]
        results.append(r)
    extra = extra_table(out)
    md = table(results) + "\nSummary (`summary()`):\n\n" + summary(results, cfg) + (
        f"\n`--extra-model`: multiple scattering + free scale heights\n\n{extra}" if extra else "")
    (out / "table.md").write_text(md)
    print(md)
    return 0


if __name__ == "__main__":
    sys.exit(main())
