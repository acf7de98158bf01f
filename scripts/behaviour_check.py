"""Same numbers before and after a refactor: the Kider 12:00 fit, `evaluate` on 11:45, `demo --quick`.

Runs the commands through the CLI (so that any checkout can be measured: ``--tree`` puts another
checkout's package first on PYTHONPATH) and writes what they report to a JSON file; ``--compare``
prints the largest differences of two such files.

    .venv/bin/python scripts/behaviour_check.py --tree /tmp/base --out /tmp/before.json
    .venv/bin/python scripts/behaviour_check.py --out /tmp/after.json
    .venv/bin/python scripts/behaviour_check.py --compare /tmp/before.json /tmp/after.json
"""
from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DAY = ROOT.parent / "shared" / "data" / "kider2014" / "2013-05-27"


def _cli(tree: Path, *args: str) -> dict:
    env = {**os.environ, "PYTHONPATH": str(tree)}
    out = subprocess.run([sys.executable, "-m", "skyfit.cli", *args, "--json", "--threads", "1"], cwd=tree, env=env,
                         capture_output=True, text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def measure(tree: Path) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        r = str(Path(tmp) / "r.json")
        fit = _cli(tree, "fit", str(DAY / "2013-05-27___12.00.00"), "--config", "configs/kider.yaml", "--out", r,
                   "--no-plots")
        ev = _cli(tree, "evaluate", r, str(DAY / "2013-05-27___11.45.00"))
        ref = _cli(tree, "evaluate", r, str(DAY / "2013-05-27___11.45.00"), "--refit-nuisance")
        demo = _cli(tree, "demo", "--quick", "--out", str(Path(tmp) / "demo"))
    return {"fit_rmse": fit["rmse"], "fit_loss": fit["loss"], "fit_free": fit["free"], "evaluate_rmse": ev["rmse"],
            "evaluate_refit_rmse": ref["rmse"],
            "demo": {row["parameter"]: {k: row[k] for k in ("recovered", "sigma_laplace")} for row in demo["rows"]}}


def _flatten(d, prefix=""):
    if isinstance(d, dict):
        for k, v in d.items():
            yield from _flatten(v, f"{prefix}{k}.")
    elif isinstance(d, (int, float)) and d is not None:
        yield prefix[:-1], float(d)


def compare(a: dict, b: dict) -> None:
    fa, fb = dict(_flatten(a)), dict(_flatten(b))
    worst = 0.0
    for k in sorted(set(fa) | set(fb)):
        va, vb = fa.get(k, math.nan), fb.get(k, math.nan)
        diff = abs(va - vb) / max(abs(va), 1e-300)
        worst = max(worst, diff) if math.isfinite(diff) else math.inf
        print(f"{k:40s} {va:.12g} {vb:.12g} rel diff {diff:.3g}")
    print(f"largest relative difference: {worst:.3g}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--tree", type=Path, default=ROOT, help="checkout whose skyfit package is measured")
    ap.add_argument("--out", type=Path)
    ap.add_argument("--compare", nargs=2, type=Path)
    args = ap.parse_args()
    if args.compare:
        compare(*(json.loads(p.read_text()) for p in args.compare))
        return
    res = measure(args.tree.resolve())
    text = json.dumps(res, indent=1)
    if args.out:
        args.out.write_text(text + "\n")
    print(text)


if __name__ == "__main__":
    main()
