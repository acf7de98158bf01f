"""Profile one photo fit of the synthetic suite: wall and CPU time, the split, Bruneton builds, AOD vs truth.

    OMP_NUM_THREADS=1 .venv/bin/python scripts/photo_profile.py /tmp/photo_cases/case_006 [--threads 1] [--cprofile out.prof]
"""
from __future__ import annotations

import argparse
import cProfile
import json
import os
import pstats
import sys
import time
from pathlib import Path

import torch


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("case", nargs="+", help="case folder(s) of scripts/photo_study.py's suite")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--cprofile", help="write a cProfile dump here (first case) and print the top 25 by cumulative time")
    ap.add_argument("--no-laplace", action="store_true", help="skip the Laplace sigma (and its budget)")
    ap.add_argument("--set", action="append", default=[], help="NAME=VALUE of skyfit.fit.photo to change (a number or None)")
    ap.add_argument("--json", help="append one JSON line per case to this file")
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    import skyfit
    from skyfit.scattering import multiple

    builds = []
    orig = multiple.precompute

    def counted(*a, **k):
        t0, c0 = time.perf_counter(), time.process_time()
        out = orig(*a, **k)
        builds.append((time.perf_counter() - t0, time.process_time() - c0))
        return out

    multiple.precompute = counted
    from skyfit.fit import photo as fp

    for kv in args.set:
        k, v = kv.split("=", 1)
        setattr(fp, k, None if v == "None" else json.loads(v))
        if k in ("MS_WAVELENGTH_NODES", "FACTOR_TOL"):  # defaults bound at definition
            fn = fp.freeze_tables if k == "MS_WAVELENGTH_NODES" else fp.lagged_fit
            d = list(fn.__defaults__ or ())
            kd = dict(fn.__kwdefaults__ or {})
            if k == "MS_WAVELENGTH_NODES":
                d[-1] = getattr(fp, k)
                fn.__defaults__ = tuple(d)
            else:
                kd["factor_tol"] = getattr(fp, k)
                fn.__kwdefaults__ = kd
    for i, case in enumerate(args.case):
        f = Path(case)
        truth = json.loads((f / "truth.json").read_text())
        builds.clear()
        prof = cProfile.Profile() if (args.cprofile and i == 0) else None
        t0, c0, l0 = time.perf_counter(), time.process_time(), os.getloadavg()[0]
        if prof:
            prof.enable()
        r = skyfit.fit_photo(f / truth["photo"].rstrip("/"), time=truth["time"], location=truth["location"],
                            laplace=not args.no_laplace)
        if prof:
            prof.disable()
            prof.dump_stats(args.cprofile)
        wall, cpu = time.perf_counter() - t0, time.process_time() - c0
        tp = truth["atmosphere"]["parameters"]
        a = r.result["aerosol"]
        row = {"case": f.name, "bracket": truth["bracket"] is not None, "wall_s": round(wall, 1), "cpu_s": round(cpu, 1),
               "load": round(l0, 2), "split": r.result["seconds_split"], "builds": len(builds),
               "build_wall_s": round(sum(b[0] for b in builds), 1),
               "aod_true": round(tp["mie_aod_550"], 3), "aod_fit": round(a["aod_550"], 3),
               "aod_err": round(a["aod_550"] / tp["mie_aod_550"] - 1, 3),
               "alpha": [round(tp["mie_angstrom_alpha"], 2), round(a["angstrom_alpha"], 2)],
               "g": [round(tp["mie_g"], 2), round(a["g"], 2)], "rmse_rel": r.result["metrics"]["rmse_rel"], "loss": r.result["metrics"]["loss"],
               "projection": [truth["camera"]["projection"], r.result["camera"]["projection"]],
               "vig": [truth["vignetting"]["rim_value"], r.result["camera"].get("vignetting")],
               "gains": [r.result["camera"].get("gain_red"), r.result["camera"].get("gain_blue")],
               "convergence": {k: r.result.get("convergence", {}).get(k) for k in ("ms_refreshes", "ms_table_builds", "ms_factor_change",
                                                                                   "iterations", "evaluations")},
               "sun_sep_deg": r.result["sun"]["separation_deg"], "settings": args.set}
        print(json.dumps(row), flush=True)
        if args.json:
            with open(args.json, "a") as fh:
                fh.write(json.dumps(row) + "\n")
    if args.cprofile:
        pstats.Stats(args.cprofile).sort_stats("cumulative").print_stats(25)
    return 0


if __name__ == "__main__":
    sys.exit(main())
