"""How far the trade study's multiple-scattering reference is from a better one (docs/benchmarks.md, section 5).

`skyfit bench --study trade` takes orders >= 2 from Bruneton tables 16 x 64 x 16 x 8 with 6 orders, precomputed by
2017's rules (equal steps along each view ray, 16 texels over 2017's whole mu_s axis), and checks them only against
smaller tables of the same rules. Here the same scenes (FULL_TRADE_PLAN: 40 x 40 fisheye, 8 wavelengths, `earth`
without ozone) get that reference and one with Gauss-Legendre view rays, the zenith density bands split
(ACCURATE_QUADRATURE) and 64 mu_s texels on the same axis; both on the trade study's converged single scattering.
Per scene: relative RMS error and mean CIE 1976 Delta E of the study's reference against the better one
(skyfit.tools.trade.image_errors), and the same for the orders >= 2 alone.

    OMP_NUM_THREADS=2 .venv/bin/python scripts/trade_reference_check.py --out docs/bench_trade/reference_check.json
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

from skyfit.atmosphere import load_atmosphere
from skyfit.camera import FisheyeCamera, render_fisheye
from skyfit.render import spectral_to_xyz_matrix
from skyfit.scattering.bruneton_tables import TableSizes
from skyfit.scattering.multiple import ACCURATE_QUADRATURE, Quadrature, precompute
from skyfit.tools.trade import FULL_TRADE_PLAN, bruneton_directions, image_errors
from skyfit.transmittance import make_integrator


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--mu-s", type=int, default=64, help="mu_s texels of the better reference")
    ap.add_argument("--rule", choices=("accurate", "2017"), default="accurate",
                    help="the better reference's precomputation rules (2017: only its mu_s texels differ)")
    ap.add_argument("--out", default="docs/bench_trade/reference_check.json")
    args = ap.parse_args(argv)
    plan = FULL_TRADE_PLAN
    lam = np.asarray(plan.wavelengths_nm, float)
    atm = load_atmosphere("earth", lam, dtype=torch.float64).replace(ozone_absorption=None)
    xyz_m = spectral_to_xyz_matrix(torch.as_tensor(lam, dtype=torch.float64)).numpy()
    cam = FisheyeCamera(plan.size)
    r, mu, mus, nu = plan.reference_tables
    rules = {"study": (Quadrature(), TableSizes(scattering_r=r, scattering_mu=mu, scattering_mu_s=mus, scattering_nu=nu)),
             "better": (ACCURATE_QUADRATURE if args.rule == "accurate" else Quadrature(), TableSizes(scattering_r=r, scattering_mu=mu, scattering_mu_s=args.mu_s, scattering_nu=nu))}
    tables, secs = {}, {}
    for name, (q, sizes) in rules.items():
        c0 = time.process_time()
        with torch.no_grad():
            tables[name] = precompute(atm, orders=plan.reference_orders, sizes=sizes, quadrature=q, progress=False)
        secs[name] = time.process_time() - c0
        print(f"{name}: {dataclasses.astuple(sizes)[4:]} tables, {plan.reference_orders} orders, {secs[name]:.0f} s CPU", flush=True)
    rows = []
    for sc in plan.scenes:
        with torch.no_grad():
            img = render_fisheye(atm, cam, sc.sun_zenith_deg, sc.sun_azimuth_deg, make_integrator("gauss", samples=plan.reference_light),
                                 altitude=sc.altitude_m, view_samples=plan.reference_view, rule="gauss")
        single = img.spectral[img.valid].detach().cpu().double().numpy()
        ms = {k: bruneton_directions(atm, t, cam, sc, t.orders) - bruneton_directions(atm, t, cam, sc, 1) for k, t in tables.items()}
        total = image_errors(single + ms["better"], single + ms["study"], xyz_m)
        only = float(np.linalg.norm(ms["study"] - ms["better"]) / np.linalg.norm(ms["better"]))
        rows.append({"scene": sc.name, "rel": total["rel_rmse"], "delta_e": total["mean_delta_e"], "ms_rel": only})
        print(f"{sc.name}: study reference vs better: rel {total['rel_rmse']:.4f}, mean dE {total['mean_delta_e']:.3f}; orders >= 2 alone rel {only:.4f}", flush=True)
    out = {"command": "scripts/trade_reference_check.py " + " ".join(sys.argv[1:] if argv is None else argv),
           "reference_tables": list(plan.reference_tables), "better_mu_s": args.mu_s, "better_rule": args.rule,
           "orders": plan.reference_orders,
           "precompute_cpu_s": secs, "scenes": rows}
    Path(args.out).write_text(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
