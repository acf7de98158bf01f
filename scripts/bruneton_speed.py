"""Old vs new Bruneton precomputation, side by side in one run: seconds, ratio, memory, max difference.

    .venv/bin/python scripts/bruneton_speed.py                   # small + 2017 default sizes, writes docs/benchmarks.md
    .venv/bin/python scripts/bruneton_speed.py --sizes 8,32,16,8 --no-write
    .venv/bin/python scripts/bruneton_speed.py --sizes 32,128,32,8 --baseline c3bb8a0   # + the new path at a revision

"old" is skyfit.scattering.bruneton_reference.precompute_reference (the implementation before
the rewrite), "new" skyfit.scattering.multiple.precompute; Earth of configs/earth.yaml at
440, 550, 680 nm, 4 orders, float64, CPU, torch.set_num_threads(--threads). Memory: peak RSS
growth of a child process per run (resource.getrusage ru_maxrss), so runs do not share a peak.
The load average is printed with each run: on a shared machine it matters more than anything else.
"""
from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
import platform
import resource
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def _run(which: str, sizes: str, threads: int, orders: int, out: str) -> None:
    if which.startswith("rev:"):  # the new path as it was at a git revision (a worktree made by _worktree)
        sys.path.insert(0, str(_worktree(which[4:])))
        which = "new"
    import torch

    torch.set_num_threads(threads)
    from skyfit.atmosphere import load_atmosphere
    from skyfit.scattering.bruneton_reference import precompute_reference
    from skyfit.scattering.bruneton_tables import TableSizes
    from skyfit.scattering.multiple import precompute

    atm = load_atmosphere("earth", [440.0, 550.0, 680.0])
    ts = TableSizes.parse(sizes)
    rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    load0 = os.getloadavg()[0]
    t0, c0 = time.perf_counter(), time.process_time()
    with torch.no_grad():
        tab = precompute(atm, orders=orders, sizes=ts, progress=False) if which == "new" else precompute_reference(atm, orders=orders, sizes=ts)
    sec, cpu = time.perf_counter() - t0, time.process_time() - c0
    rss1 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    names = ("transmittance_columns", "direct_irradiance", "irradiance", "single_rayleigh", "single_mie", "multiple")
    torch.save({n: getattr(tab, n) for n in names}, out + ".pt")
    Path(out).write_text(json.dumps({"seconds": sec, "cpu_seconds": cpu, "timings": tab.timings, "peak_rss_growth_mb": (rss1 - rss0) / 1024,
                                     "tables_mb": tab.nbytes() / 2**20, "load_start": load0, "load_end": os.getloadavg()[0]}))


def _worktree(rev: str) -> Path:
    """A detached git worktree of ``rev`` under /tmp (made once), for a before/after run in one session."""
    path = Path("/tmp/bruneton_speed_rev") / rev
    if not (path / "skyfit").is_dir():
        import subprocess

        subprocess.run(["git", "-C", str(ROOT), "worktree", "add", "--detach", str(path), rev], check=True,
                       capture_output=True)
    return path


def measure(which: str, sizes: str, threads: int, orders: int, tmp: Path) -> dict:
    out = str(tmp / f"{which.replace(':', '_')}_{sizes.replace(',', 'x')}.json")
    p = mp.get_context("spawn").Process(target=_run, args=(which, sizes, threads, orders, out))
    p.start()
    p.join()
    if p.exitcode:
        raise SystemExit(f"{which} at {sizes} failed (exit {p.exitcode})")
    res = json.loads(Path(out).read_text())
    print(f"{which} {sizes}: {res['seconds']:.1f} s ({res['cpu_seconds']:.1f} s CPU), peak RSS +{res['peak_rss_growth_mb']:.0f} MB, "
          f"load {res['load_start']:.1f} -> {res['load_end']:.1f}", flush=True)
    return res


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", default="8,32,16,8;32,128,32,8", help="';'-separated R,MU,MUS,NU (default: small and 2017's)")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--orders", type=int, default=4)
    ap.add_argument("--baseline", help="also time the new path as it was at this git revision (a worktree under /tmp)")
    ap.add_argument("--no-old", action="store_true", help="skip the reference implementation (minutes at 2017's sizes)")
    ap.add_argument("--tmp", default="/tmp/bruneton_speed")
    ap.add_argument("--no-write", action="store_true", help="do not write docs/benchmarks.md")
    args = ap.parse_args()
    import torch

    tmp = Path(args.tmp)
    tmp.mkdir(parents=True, exist_ok=True)
    others = ([] if args.no_old else ["old"]) + ([f"rev:{args.baseline}"] if args.baseline else [])
    rows = []
    for sizes in args.sizes.split(";"):
        key = sizes.replace(",", "x")
        res = {w: measure(w, sizes, args.threads, args.orders, tmp) for w in ["new", *others]}
        tabs = {w: torch.load(tmp / f"{w.replace(':', '_')}_{key}.json.pt") for w in res}
        diffs = {w: max(float(((tabs["new"][k] - tabs[w][k]).abs() / tabs[w][k].abs().clamp_min(1e-300)).max()) for k in tabs[w])
                 for w in others}
        rows.append((sizes, res, diffs))
        for w in others:
            print(f"  {w}/new {res[w]['seconds'] / res['new']['seconds']:.1f}x, max relative difference {diffs[w]:.1e}", flush=True)
    cmd = "python scripts/bruneton_speed.py " + " ".join(sys.argv[1:])
    cols = ["new", *others]
    lines = [
        "| sizes R,MU,MUS,NU | " + " | ".join(f"{w} s (CPU s)" for w in cols) + " | " + " | ".join(f"{w}/new" for w in others)
        + " | " + " | ".join(f"{w} peak RSS +MB" for w in cols) + " | " + " | ".join(f"max rel. diff vs {w}" for w in others)
        + " | load (" + "; ".join(cols) + ") |",
        "|" + "---|" * (2 + 3 * len(cols) + 2 * len(others) - 1),
    ]
    for sizes, res, diffs in rows:
        lines.append(f"| {sizes} | " + " | ".join(f"{res[w]['seconds']:.1f} ({res[w]['cpu_seconds']:.1f})" for w in cols) + " | "
                     + " | ".join(f"{res[w]['seconds'] / res['new']['seconds']:.1f}" for w in others) + " | "
                     + " | ".join(f"{res[w]['peak_rss_growth_mb']:.0f}" for w in cols) + " | "
                     + " | ".join(f"{diffs[w]:.1e}" for w in others) + " | "
                     + "; ".join(f"{res[w]['load_start']:.1f}-{res[w]['load_end']:.1f}" for w in cols) + " |")
    table = "\n".join(lines)
    print(table)
    stages = {w: ", ".join(f"{k} {v:.2f}" for k, v in rows[-1][1][w]["timings"].items()) for w in cols}
    for w in cols:
        print(f"{w} stages (s):", stages[w])
    if args.no_write:
        return
    machine = f"{platform.machine()}, {os.cpu_count()} CPU cores, torch {torch.__version__}, {args.threads} threads, float64, W = 3, {args.orders} orders"
    section = (f"## Bruneton precomputation\n\n`{cmd.strip()}` ({time.strftime('%Y-%m-%d')}; {machine}).\n\n{table}\n\n"
               + "".join(f"Stages at {rows[-1][0]}, {w} (s): {stages[w]}.\n\n" for w in cols))
    path = ROOT / "docs" / "benchmarks.md"
    text = path.read_text() if path.exists() else "# Benchmarks\n\n"
    if "## Bruneton precomputation" in text:
        head, _, rest = text.partition("## Bruneton precomputation")
        tail = rest[rest.find("\n## "):] if "\n## " in rest else ""
        text = head + section + tail
    else:
        text = text.rstrip("\n") + "\n\n" + section
    path.write_text(text)
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
