"""Kider per-capture fit, before and after (issue 15, "Fits in seconds"): CPU time, iterations, convergence, RMSE.

Both fits run in this process, one after the other, on the same captures with configs/kider.yaml:

* before: Adam (10 steps) + L-BFGS (``optimiser: lbfgs``) with Hillaire's LUT rebuilt row by row,
  its geometry recomputed per call (``SkyModel.lut_method = "rows"``): the code path of earlier versions;
* after: the config's own settings (``optimiser: auto`` = Levenberg-Marquardt with NL2SOL's secant
  term, forward-difference Jacobian) and the cached, batched LUT.

Time is CPU time (``time.process_time``), single-threaded, so that other processes on a shared
machine do not count; wall time is printed beside it. Each fit's time is split into setup (data,
atmosphere, problem), LUT (Hillaire's table, forward), forward (the rest of the model), backward
(autograd through everything, LUT included) and optimiser (the rest: linear algebra, line search,
bookkeeping). The process's first setup also imports the solar spectrum's dependency (colour-science);
a warm-up setup runs before the timings so that no fit pays for it.

    OMP_NUM_THREADS=1 .venv/bin/python scripts/kider_fit_speed.py                  # 3 captures
    OMP_NUM_THREADS=1 .venv/bin/python scripts/kider_fit_speed.py --captures all --json docs/kider/speed.json
"""
from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import os
import platform
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
DAY = ROOT.parent / "shared" / "data" / "kider2014" / "2013-05-27"
CONFIG = ROOT / "configs" / "kider.yaml"
DEFAULT_CAPTURES = "09.30,12.00,13.30"
VARIANTS = {"before": {"optimiser": "lbfgs", "lut_method": "rows"}, "after": {"optimiser": None, "lut_method": "cached"}}
"""Optimiser (None: the config's) and LUT evaluation of each side."""


class Clock:
    """CPU seconds spent inside wrapped functions, by label (the outermost call of each label counts)."""

    def __init__(self):
        self.seconds: dict[str, float] = {}
        self._depth: dict[str, int] = {}

    def wrap(self, fn, label: str):
        def timed(*a, **k):
            depth = self._depth.get(label, 0)
            self._depth[label] = depth + 1
            t0 = time.process_time()
            try:
                return fn(*a, **k)
            finally:
                self._depth[label] = depth
                if depth == 0:
                    self.seconds[label] = self.seconds.get(label, 0.0) + time.process_time() - t0
        return timed


@contextlib.contextmanager
def instrumented(clock: Clock):
    """Time the LUT, the model (spectra and tables, LUT included) and autograd's backward passes while inside."""
    import skyfit.scattering.hillaire as hillaire
    from skyfit.fit.model import FitProblem, SkyModel

    saved = [(hillaire, "hillaire_lut"), (FitProblem, "spectra"), (SkyModel, "tables"), (torch.autograd, "backward"),
             (torch.autograd, "grad")]
    originals = [getattr(o, n) for o, n in saved]
    labels = ["lut", "model", "model", "backward", "backward"]
    try:
        for (o, n), fn, label in zip(saved, originals, labels):
            setattr(o, n, clock.wrap(fn, label))
        yield clock
    finally:
        for (o, n), fn in zip(saved, originals):
            setattr(o, n, fn)


def fit_one(cap: Path, cfg: dict, variant: str) -> dict:
    from skyfit.fit.optimise import fit
    from skyfit.fit.problem import fit_settings, prepare

    v = VARIANTS[variant]
    overrides = {"optimiser": v["optimiser"]} if v["optimiser"] else None
    clock = Clock()
    with instrumented(clock):
        c0, w0 = time.process_time(), time.perf_counter()
        prep = prepare([cap], cfg, fit_settings(cfg.get("fit"), overrides))
        prep = dataclasses.replace(prep, model=dataclasses.replace(prep.model, lut_method=v["lut_method"]))
        problem = prep.fit_problem()
        c1 = time.process_time()
        res = fit(problem, prep.settings.options())
        c2, w2 = time.process_time(), time.perf_counter()
    m = problem.metrics(res.x)
    s = clock.seconds
    lut, spectra, backward = s.get("lut", 0.0), s.get("model", 0.0), s.get("backward", 0.0)
    conv = res.convergence
    return {
        "capture": cap.name.split("___")[-1][:5], "variant": variant, "method": conv.get("method", "lbfgs"),
        "cpu_s": c2 - c0, "wall_s": w2 - w0, "rmse": m["rmse"], "loss": res.loss,
        "converged": conv["converged"], "reason": conv["reason"], "iterations": conv["iterations"],
        "evaluations": conv["evaluations"], "grad_norm": conv["grad_norm"],
        "split_cpu_s": {"setup": c1 - c0, "lut": lut, "forward": spectra - lut, "backward": backward,
                        "optimiser": (c2 - c1) - spectra - backward},
        "free": res.free, "parameters": {n: res.parameters[n] for n in res.free},
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--captures", default=DEFAULT_CAPTURES, help="comma list of HH.MM, or 'all' (default %(default)s)")
    ap.add_argument("--day", default=str(DAY))
    ap.add_argument("--config", default=str(CONFIG))
    ap.add_argument("--variants", default="before,after", help="comma list of before, after")
    ap.add_argument("--json", help="write every row here")
    a = ap.parse_args()
    torch.set_num_threads(1)
    from skyfit.atmosphere import load_yaml
    from skyfit.fit.problem import fit_settings, prepare

    cfg = load_yaml(a.config)
    day = Path(a.day)
    caps = sorted(p for p in day.iterdir() if p.is_dir() and "___" in p.name)
    if a.captures != "all":
        want = a.captures.split(",")
        caps = [p for p in caps if p.name.split("___")[-1][:5] in want]
        if len(caps) != len(want):
            raise SystemExit(f"captures {want}: found only {[p.name for p in caps]} in {day}")
    prepare([caps[0]], cfg, fit_settings(cfg.get("fit")))  # warm-up: one-time imports out of the timings
    variants = a.variants.split(",")
    rows = []
    print(f"machine {platform.processor() or platform.machine()}, {os.cpu_count()} CPUs, torch threads "
          f"{torch.get_num_threads()}, load average {os.getloadavg()[0]:.1f} at start", flush=True)
    head = (f"{'capture':7} {'variant':7} {'method':6} {'CPU s':>6} {'wall s':>6} {'iter':>4} {'evals':>5} "
            f"{'converged':9} {'reason':22} {'RMSE':>7}   split CPU s: setup / LUT / forward / backward / optimiser")
    print(head, flush=True)
    for cap in caps:
        for variant in variants:
            r = fit_one(cap, cfg, variant)
            rows.append(r)
            sp = r["split_cpu_s"]
            print(f"{r['capture']:7} {variant:7} {r['method']:6} {r['cpu_s']:6.1f} {r['wall_s']:6.1f} {r['iterations']:4d} "
                  f"{r['evaluations']:5d} {str(r['converged']):9} {r['reason'][:22]:22} {r['rmse']:7.3f}   "
                  + " / ".join(f"{sp[k]:.2f}" for k in ("setup", "lut", "forward", "backward", "optimiser")), flush=True)
    for variant in variants:
        rs = [r for r in rows if r["variant"] == variant]
        n = len(rs)
        print(f"{variant}: mean CPU {sum(r['cpu_s'] for r in rs) / n:.1f} s, max {max(r['cpu_s'] for r in rs):.1f} s, "
              f"mean RMSE {sum(r['rmse'] for r in rs) / n:.3f}, converged {sum(r['converged'] for r in rs)}/{n}", flush=True)
    if len(variants) == 2:
        d = [abs(a_["rmse"] - b["rmse"]) for a_, b in zip(rows[::2], rows[1::2])]
        print(f"largest |RMSE after - RMSE before| {max(d):.2e}; load average {os.getloadavg()[0]:.1f} at the end")
    if a.json:
        Path(a.json).write_text(json.dumps({"rows": rows, "load_average_end": os.getloadavg()}, indent=1))


if __name__ == "__main__":
    main()
