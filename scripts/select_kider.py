"""The model ladder (``skyfit fit --select``) on every Kider et al. 2014 capture: the chosen model per capture.

For each capture folder, :func:`skyfit.fit.run.run_fit` with ``select=True`` and the
fit settings of configs/kider.yaml (its ``orders`` is replaced by the ladder's choice);
one RESULT.json per capture in ``--out`` (default docs/selection/kider), then a Markdown
table of the chosen rung per capture (``--out``/table.md, pasted into docs/selection.md).
CPU time per capture is process time (the machine is shared: wall time is not a measure).

    .venv/bin/python scripts/select_kider.py                       # all captures
    .venv/bin/python scripts/select_kider.py --captures 09.30,12.00 --max-iter 40
    .venv/bin/python scripts/select_kider.py --table-only          # rebuild table.md from the JSON files
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
        lines.append(f"| {r['capture']} | {sz_s} | {sel['chosen']} | {' + '.join(sel['components'])} | {dpar} | {held_s} | {ms_s} "
                     f"| {r['metrics']['rmse']:.3g} | {r['metrics']['delta_e']:.3g} | {cpu:.0f} |")
    return "\n".join(lines) + "\n"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--day", default=str(DAY))
    ap.add_argument("--captures", default="all", help="comma list of HH.MM, or 'all'")
    ap.add_argument("--config", default=str(ROOT / "configs" / "kider.yaml"))
    ap.add_argument("--out", default=str(ROOT / "docs" / "selection" / "kider"))
    ap.add_argument("--max-iter", type=int, help="L-BFGS iterations per rung (default: the config's)")
    ap.add_argument("--sigma", choices=("scaled", "known"), default="scaled")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--table-only", action="store_true", help="only rebuild table.md from the JSON files in --out")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    from skyfit.atmosphere import load_yaml
    from skyfit.fit.run import run_fit

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    day = Path(args.day)
    folders = sorted(day.glob("2013-05-27___*")) if args.captures == "all" else [
        day / f"2013-05-27___{c}.00" for c in args.captures.split(",")]
    cfg = load_yaml(args.config)
    if not args.table_only:
        for folder in folders:
            capture = folder.name.split("___")[-1][:5]
            c0 = time.process_time()
            res = run_fit([folder], cfg, out / f"select_{capture}.json", config_source=args.config, plots=False,
                          progress=sys.stderr.isatty(), select=True,
                          overrides={"max_iter": args.max_iter, "select_sigma": args.sigma})
            sel = res["selection"]
            print(json.dumps({"capture": capture, "chosen": sel["chosen"], "components": sel["components"],
                              "heldout_choice": sel["heldout_choice"], "rmse": round(res["metrics"]["rmse"], 3),
                              "cpu_s": round(time.process_time() - c0, 1)}), flush=True)
    results = []
    for p in sorted(out.glob("select_*.json")):
        r = json.loads(p.read_text())
        r["capture"] = p.stem.split("_", 1)[1]
        results.append(r)
    (out / "table.md").write_text(table(results))
    print(table(results))
    return 0


if __name__ == "__main__":
    sys.exit(main())
