"""How an exported LUT's precomputation rule moves its sky (docs/luts.md, "The view-ray rule of an exported LUT").

All-sun Bruneton tables as ``skyfit export-lut`` builds them (2017's default sizes 32 x 128 x 32 x 8 unless
--table-sizes, 4 orders, 440/550/680 nm), with three precomputation rules: 2017's (equal steps along each view ray,
16 x 32 density directions), the export's since session 20 (:data:`skyfit.scattering.multiple.ACCURATE_QUADRATURE`:
Gauss-Legendre view rays, the two density bands nearest the zenith split; the error budget's reference rule) and
Gauss-Legendre view rays with 32 x 64 density directions (the converged one of the three). The sky from the tables
alone (single scattering included: what an engine reads), at a ground observer, 10 x 36 directions from 2 to 88 deg
of elevation, suns at 30, 60, 80 deg; quantiles of each rule's radiance over the last's.

    OMP_NUM_THREADS=2 .venv/bin/python scripts/export_ray_rule.py --out docs/luts/export_ray_rule.json
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
import time
from pathlib import Path

import numpy as np
import torch

from skyfit.atmosphere import load_atmosphere
from skyfit.geometry import zenith_azimuth_to_enu
from skyfit.scattering.bruneton_tables import TableSizes
from skyfit.scattering.multiple import ACCURATE_QUADRATURE, Quadrature, precompute, sky_radiance

RULES = {"2017": Quadrature(), "export": ACCURATE_QUADRATURE,
         "gauss 32x64": dataclasses.replace(ACCURATE_QUADRATURE, density_theta=32, density_phi=64, density_zenith=0)}
SUNS = (30.0, 60.0, 80.0)


def directions(dtype) -> torch.Tensor:
    el = torch.linspace(2.0, 88.0, 10, dtype=dtype)
    az = torch.arange(0.0, 360.0, 10.0, dtype=dtype)
    z, a = torch.meshgrid(90.0 - el, az, indexing="ij")
    return zenith_azimuth_to_enu(torch.deg2rad(z.flatten()), torch.deg2rad(a.flatten()))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--configs", default="earth,earth_hazy")
    ap.add_argument("--table-sizes", default="32,128,32,8")
    ap.add_argument("--orders", type=int, default=4)
    ap.add_argument("--out", default="docs/luts/export_ray_rule.json")
    args = ap.parse_args(argv)
    sizes = TableSizes.parse(args.table_sizes)
    view = directions(torch.float64)
    out = {"command": "scripts/export_ray_rule.py " + " ".join(sys.argv[1:] if argv is None else argv), "table_sizes": args.table_sizes,
           "orders": args.orders, "wavelengths_nm": [440.0, 550.0, 680.0], "rules": {k: dataclasses.asdict(v) for k, v in RULES.items()},
           "results": {}}
    for cfg in args.configs.split(","):
        atm = load_atmosphere(cfg, np.array(out["wavelengths_nm"]), dtype=torch.float64)
        sky, secs = {}, {}
        for name, q in RULES.items():
            c0 = time.process_time()
            with torch.no_grad():
                tab = precompute(atm, orders=args.orders, sizes=sizes, quadrature=q, progress=False)
            secs[name] = time.process_time() - c0
            rows = []
            for sz in SUNS:
                sun = zenith_azimuth_to_enu(torch.tensor(math.radians(sz), dtype=torch.float64), torch.tensor(math.radians(180.0), dtype=torch.float64))
                r = torch.full_like(view[:, 2], atm.bottom_radius)
                with torch.no_grad():
                    rows.append(sky_radiance(tab, atm, r, view[:, 2], sun[2].expand_as(r), view @ sun))
            sky[name] = torch.stack(rows)  # (suns, directions, wavelengths)
        last = sky["gauss 32x64"]
        res = {"precompute_cpu_s": secs}
        for name in ("2017", "export"):
            ratio = sky[name] / last
            res[name] = {}
            for i, sz in enumerate(SUNS):
                v = ratio[i].flatten()
                res[name][f"sun {sz:g}"] = {"median": float(v.median()), "p10": float(torch.quantile(v, 0.1)),
                                           "p90": float(torch.quantile(v, 0.9)), "min": float(v.min()), "max": float(v.max())}
        out["results"][cfg] = res
        for name in ("2017", "export"):
            print(cfg, name, "; ".join(f"{k}: median {d['median']:.4f} p10 {d['p10']:.4f} p90 {d['p90']:.4f} max {d['max']:.4f}"
                                       for k, d in res[name].items()), flush=True)
        print(cfg, "precompute CPU s", {k: round(v, 1) for k, v in secs.items()}, flush=True)
    Path(args.out).write_text(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
