"""Kider 2013-05-27 per-capture fits with exposure and heading as the only nuisances: the plain aerosol
against the two-term Henyey-Greenstein phase and the boundary-layer profile (docs/aerosol.md).

    .venv/bin/python scripts/kider_aerosol.py --variants hg,tthg_bl,tthg,bl --out /tmp/kider_aerosol

One JSON line per fit (variant, capture, RMSE, CPU s, fitted values); then per variant the mean and worst RMSE.
Config: configs/kider.yaml with its fit.free reduced to the atmosphere's five values + exposure + sun_azimuth_offset.
"""
from __future__ import annotations

import argparse
import copy
import json
import statistics
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
DAY = ROOT.parent / "shared" / "data" / "kider2014" / "2013-05-27"
CONFIG = ROOT / "configs" / "kider.yaml"
ATMOSPHERE = ["rayleigh_scale", "mie_beta_550", "mie_angstrom_alpha", "mie_scale_height", "mie_g"]
NUISANCE = ["exposure", "sun_azimuth_offset"]
VARIANTS = {
    "hg": [],
    "tthg": ["mie_g2", "mie_hg_weight"],
    "bl": ["mie_mixing_height"],
    "tthg_bl": ["mie_g2", "mie_hg_weight", "mie_mixing_height"],
}


def main() -> None:
    from skyfit.atmosphere import load_yaml
    from skyfit.fit.run import run_fit

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--variants", default="hg,tthg_bl")
    ap.add_argument("--captures", default="all")
    ap.add_argument("--out", default="/tmp/kider_aerosol")
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    caps = sorted(p for p in DAY.iterdir() if p.is_dir() and "___" in p.name)
    if args.captures != "all":
        caps = [c for c in caps if c.name.split("___")[-1][:5] in args.captures.split(",")]
    base = load_yaml(str(CONFIG))
    for v in args.variants.split(","):
        cfg = copy.deepcopy(base)
        cfg["fit"]["free"] = ATMOSPHERE + VARIANTS[v] + NUISANCE
        rmse = {}
        for cap in caps:
            name = cap.name.split("___")[-1][:5]
            t0 = time.process_time()
            res = run_fit([cap], cfg, out / f"{v}_{name}.json", config_source=str(CONFIG), plots=False)
            rmse[name] = res["metrics"]["rmse"]
            print(json.dumps({"variant": v, "capture": name, "rmse": round(rmse[name], 3),
                              "cpu_s": round(time.process_time() - t0, 1),
                              "free": {k: res["parameters"][k] for k in res["free"]}}), flush=True)
        worst = max(rmse, key=rmse.get)
        print(json.dumps({"variant": v, "mean_rmse": round(statistics.mean(rmse.values()), 3),
                          "worst": [worst, round(rmse[worst], 3)], "n": len(rmse)}), flush=True)


if __name__ == "__main__":
    main()
