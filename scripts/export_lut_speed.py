"""`skyfit export-lut` end to end at the default table sizes, now and at a git revision, side by side.

    .venv/bin/python scripts/export_lut_speed.py --baseline c3bb8a0

Makes one RESULT.json with the baseline's code (a small Earth sky rendered and fitted with cheap settings; its model's
wavelengths, 3 by default here), then runs `skyfit export-lut RESULT.json --out DIR` (default layout,
2017's table sizes, 4 orders) as a child process with this checkout's code and with the code of
``--baseline`` (a detached worktree under /tmp), alternating, ``--repeats`` times each. Prints wall
seconds, the child's CPU seconds (user + system) and the load average, and the largest relative
difference between the two exports' tables.
"""
from __future__ import annotations

import argparse
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _worktree(rev: str) -> Path:
    path = Path("/tmp/bruneton_speed_rev") / rev
    if not (path / "skyfit").is_dir():
        subprocess.run(["git", "-C", str(ROOT), "worktree", "add", "--detach", str(path), rev], check=True, capture_output=True)
    return path


def _skyfit(code: Path, *argv: str, threads: int) -> tuple[float, float]:
    """Run ``skyfit argv`` with the package at ``code``; (wall s, CPU s of the child)."""
    env = dict(os.environ, PYTHONPATH=str(code), OMP_NUM_THREADS=str(threads))
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    subprocess.run([sys.executable, "-m", "skyfit.cli", *argv], check=True, env=env, cwd=code, stdout=subprocess.DEVNULL)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    return wall, (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--baseline", required=True, help="git revision to compare with")
    ap.add_argument("--repeats", type=int, default=1)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--wavelengths", default="440,550,680")
    args = ap.parse_args()
    import numpy as np

    tmp = Path(tempfile.mkdtemp(prefix="export_lut_speed_"))
    sky, result = tmp / "sky.exr", tmp / "RESULT.json"
    old = _worktree(args.baseline)  # the older code writes the RESULT.json, which both versions read
    _skyfit(old, "render", "earth", "--out", str(sky), "--size", "12", "--sun-zenith", "40", "--wavelengths", args.wavelengths,
            "--spectral", "--dtype", "float64", threads=args.threads)
    _skyfit(old, "fit", str(sky), "--config", "earth", "--out", str(result), "--free", "mie_g,exposure", "--no-plots",
            "--integrator", "chapman", "--view-samples", "8", threads=args.threads)
    codes = {"now": ROOT, args.baseline: old}
    rows: dict[str, list[tuple[float, float, float]]] = {k: [] for k in codes}
    for _ in range(args.repeats):
        for name, code in codes.items():
            load = os.getloadavg()[0]
            wall, cpu = _skyfit(code, "export-lut", str(result), "--out", str(tmp / f"lut_{name}"), "--format", "npz",
                                "--force", threads=args.threads)
            rows[name].append((wall, cpu, load))
            print(f"{name}: {wall:.1f} s wall, {cpu:.1f} s CPU, load {load:.1f}", flush=True)
    diff = 0.0
    for f in sorted((tmp / "lut_now").glob("*.npz")):
        a, b = np.load(f), np.load(tmp / f"lut_{args.baseline}" / f.name)
        for k in a.files:
            if a[k].dtype.kind == "f":
                x, y = a[k].astype(np.float64), b[k].astype(np.float64)  # the files are float32
                diff = max(diff, float(np.max(np.abs(x - y) / np.maximum(np.abs(y), 1e-300))))
    best = {k: min(v) for k, v in rows.items()}
    print(f"| export-lut (default sizes, 4 orders, W = {len(args.wavelengths.split(','))}, {args.threads} threads) | wall s | CPU s | load |")
    print("|---|---|---|---|")
    for k, (wall, cpu, load) in best.items():
        print(f"| {k} | {wall:.1f} | {cpu:.1f} | {load:.1f} |")
    print(f"ratio {args.baseline}/now: {best[args.baseline][0] / best['now'][0]:.2f} wall, {best[args.baseline][1] / best['now'][1]:.2f} CPU;"
          f" max relative difference of the tables {diff:.1e}")


if __name__ == "__main__":
    main()
