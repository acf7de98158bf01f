"""Old vs new Bruneton precomputation, side by side in one run: seconds, ratio, memory, max difference.

    .venv/bin/python scripts/bruneton_speed.py                   # small + 2017 default sizes, writes docs/benchmarks.md
    .venv/bin/python scripts/bruneton_speed.py --sizes 8,32,16,8 --no-write

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
    t0 = time.perf_counter()
    with torch.no_grad():
        tab = precompute(atm, orders=orders, sizes=ts, progress=False) if which == "new" else precompute_reference(atm, orders=orders, sizes=ts)
    sec = time.perf_counter() - t0
    rss1 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    names = ("transmittance_columns", "direct_irradiance", "irradiance", "single_rayleigh", "single_mie", "multiple")
    torch.save({n: getattr(tab, n) for n in names}, out + ".pt")
    Path(out).write_text(json.dumps({"seconds": sec, "timings": tab.timings, "peak_rss_growth_mb": (rss1 - rss0) / 1024,
                                     "tables_mb": tab.nbytes() / 2**20, "load_start": load0, "load_end": os.getloadavg()[0]}))


def measure(which: str, sizes: str, threads: int, orders: int, tmp: Path) -> dict:
    out = str(tmp / f"{which}_{sizes.replace(',', 'x')}.json")
    p = mp.get_context("spawn").Process(target=_run, args=(which, sizes, threads, orders, out))
    p.start()
    p.join()
    if p.exitcode:
        raise SystemExit(f"{which} at {sizes} failed (exit {p.exitcode})")
    res = json.loads(Path(out).read_text())
    print(f"{which} {sizes}: {res['seconds']:.1f} s, peak RSS +{res['peak_rss_growth_mb']:.0f} MB, "
          f"load {res['load_start']:.1f} -> {res['load_end']:.1f}", flush=True)
    return res


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", default="8,32,16,8;32,128,32,8", help="';'-separated R,MU,MUS,NU (default: small and 2017's)")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--orders", type=int, default=4)
    ap.add_argument("--tmp", default="/tmp/bruneton_speed")
    ap.add_argument("--no-write", action="store_true", help="do not write docs/benchmarks.md")
    args = ap.parse_args()
    import torch

    tmp = Path(args.tmp)
    tmp.mkdir(parents=True, exist_ok=True)
    rows = []
    for sizes in args.sizes.split(";"):
        new = measure("new", sizes, args.threads, args.orders, tmp)
        old = measure("old", sizes, args.threads, args.orders, tmp)
        a = torch.load(tmp / f"new_{sizes.replace(',', 'x')}.json.pt")
        b = torch.load(tmp / f"old_{sizes.replace(',', 'x')}.json.pt")
        diff = max(float(((a[k] - b[k]).abs() / b[k].abs().clamp_min(1e-300)).max()) for k in a)
        rows.append((sizes, old, new, diff))
        print(f"  ratio {old['seconds'] / new['seconds']:.1f}x, max relative difference {diff:.1e}", flush=True)
    cmd = "python scripts/bruneton_speed.py " + " ".join(sys.argv[1:])
    lines = [
        "| sizes R,MU,MUS,NU | old s | new s | ratio | old peak RSS MB | new peak RSS MB | tables MB | max rel. diff | load avg (old; new) |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for sizes, old, new, diff in rows:
        lines.append(f"| {sizes} | {old['seconds']:.1f} | {new['seconds']:.1f} | {old['seconds'] / new['seconds']:.1f} | "
                     f"{old['peak_rss_growth_mb']:.0f} | {new['peak_rss_growth_mb']:.0f} | {new['tables_mb']:.0f} | {diff:.1e} | "
                     f"{old['load_start']:.1f}-{old['load_end']:.1f}; {new['load_start']:.1f}-{new['load_end']:.1f} |")
    stages = ", ".join(f"{k} {v:.2f}" for k, v in rows[-1][2]["timings"].items())
    ostages = ", ".join(f"{k} {v:.2f}" for k, v in rows[-1][1]["timings"].items())
    table = "\n".join(lines)
    print(table)
    print("new stages (s):", stages)
    print("old stages (s):", ostages)
    if args.no_write:
        return
    machine = f"{platform.machine()}, {os.cpu_count()} CPU cores, torch {torch.__version__}, {args.threads} threads, float64, W = 3, {args.orders} orders"
    section = (f"## Bruneton precomputation\n\n`{cmd.strip()}` ({time.strftime('%Y-%m-%d')}; {machine}).\n\n{table}\n\n"
               f"Stages at {rows[-1][0]}, new (s): {stages}.\n\nOld (s): {ostages}.\n")
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
