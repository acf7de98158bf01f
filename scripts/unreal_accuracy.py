"""The sky of the exported Unreal SkyAtmosphere parameters against skyfit's own (docs/luts.md, "Unreal").

Earth (or --config) on 680, 550, 440 nm: Bruneton's tables of the atmosphere (4 orders) are skyfit's
sky; "unreal" is Hillaire 2020's model (skyfit's implementation, LUT 32 x 32, 64 directions, 20 steps)
on the atmosphere rebuilt from the exported parameters; "mapping" is Bruneton's tables on that
rebuilt atmosphere (only what the parameters cannot hold differs: Henyey-Greenstein for
Cornette-Shanks, 8-bit albedo). Sky directions at view zenith 0.5-89.5 deg (1 deg) x 15 deg azimuths,
ground observer, relative error per channel.

    .venv/bin/python scripts/unreal_accuracy.py [--config earth] [--table-sizes 16,64,16,8]
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch

from skyfit.atmosphere import load_atmosphere
from skyfit.export.shader_reference import view_grid
from skyfit.export.unreal import unreal_render_errors
from skyfit.scattering.bruneton_tables import TableSizes
from skyfit.scattering.multiple import ACCURATE_QUADRATURE, precompute

SUNS = (0.0, 30.0, 60.0, 80.0, 90.0)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", default="earth")
    ap.add_argument("--table-sizes", default="16,64,16,8")
    ap.add_argument("--out", default="docs/luts/unreal_accuracy.json")
    args = ap.parse_args()
    torch.set_num_threads(2)
    atm = load_atmosphere(args.config, np.array([680.0, 550.0, 440.0]))
    with torch.no_grad():
        tables = precompute(atm, orders=4, sizes=TableSizes.parse(args.table_sizes), quadrature=ACCURATE_QUADRATURE)
    view = torch.as_tensor(view_grid(1.0, 15.0))
    view = view[view[:, 2] > 0]
    rows = []
    cache: dict = {}  # the rebuilt atmosphere's tables and LUT, shared by the suns
    for sz in SUNS:
        e = unreal_render_errors(atm, view, sz, tables=tables, cache=cache)
        row = {"sun_zenith_deg": sz}
        for k, v in e.items():
            row[k] = {"median": float(np.median(v)), "p99": float(np.percentile(v, 99)), "max": float(v.max()),
                      "median_per_channel_680_550_440": np.median(v, axis=0).tolist()}
        rows.append(row)
        print(sz, {k: (round(row[k]["median"], 4), round(row[k]["max"], 4)) for k in e}, flush=True)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"config": args.config, "table_sizes": args.table_sizes, "rows": rows}, indent=1) + "\n")
    print("\n| sun zenith | unreal median | unreal p99 | unreal max | mapping median | mapping max |\n|---|---|---|---|---|---|")
    for r in rows:
        u, m = r["unreal"], r["mapping"]
        print(f"| {r['sun_zenith_deg']:g} | {u['median']:.2%} | {u['p99']:.2%} | {u['max']:.2%} | {m['median']:.2%} | {m['max']:.2%} |")


if __name__ == "__main__":
    main()
