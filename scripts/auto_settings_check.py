"""Check skyfit.render.auto's choices on the fixed scenes against converged references, and time them.

For every scene of the shipped trade study (skyfit/data/auto_settings.json), every tolerance and
both families (single scattering; multiple scattering: orders >= 2 by Hillaire's LUT or Bruneton's
tables), render a SIZE x SIZE sky (another pixel set than the bench's) with the chosen setting and
with the most expensive measured setting of the family, and compare both with a converged reference
computed here (single: Gauss-Legendre 32 x 128 nodes, float64; multiple: plus Bruneton orders 2-6 from
16 x 64 x 16 x 8 tables, float64, as the bench). Prints a Markdown table; exit status 1 if a choice
misses its tolerance.

    .venv/bin/python scripts/auto_settings_check.py [--size 26] [--families single,multiple]

Times are process CPU seconds with 1 torch thread (render + per-atmosphere precomputation), best of 2.
"Most expensive": the setting of the family with the largest median render cost over the scenes plus the
median precomputation cost of its method (float32).
"""
from __future__ import annotations

import argparse
import sys
import time

import numpy as np
import torch

from skyfit.atmosphere import load_atmosphere
from skyfit.tools.trade import Scene, _sizes, bruneton_directions, image_errors
from skyfit.camera import FisheyeCamera, render_fisheye
from skyfit.transmittance import parse_integrator
from skyfit.render import spectral_to_xyz_matrix
from skyfit.render.auto import choose, describe, load_frontier, parse_accuracy
from skyfit.scattering.hillaire import hillaire_lut
from skyfit.scattering.multiple import precompute
from skyfit.transmittance import make_integrator

TOLERANCES = {"single": ("de=1", "de=0.3", "rel=0.01", "rel=0.003"), "multiple": ("de=3", "de=2", "rel=0.05", "rel=0.03")}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=26)
    ap.add_argument("--families", default="single,multiple")
    a = ap.parse_args()
    torch.set_num_threads(1)
    fr = load_frontier()
    lam = np.asarray(fr["wavelengths_nm"])
    atms = {d: load_atmosphere("earth", lam, dtype=getattr(torch, d)).replace(ozone_absorption=None) for d in ("float32", "float64")}
    xyz = spectral_to_xyz_matrix(torch.as_tensor(lam, dtype=torch.float64)).numpy()
    cam = FisheyeCamera(a.size)
    fams = a.families.split(",")
    ref_tab = precompute(atms["float64"], orders=6, sizes=_sizes((16, 64, 16, 8))) if "multiple" in fams else None
    cache: dict = {}

    def render(setting: dict, sc: Scene) -> tuple[np.ndarray, float]:
        """Best of two renders (each with its precomputation): (radiance, process CPU s)."""
        (img, c1), (_, c2) = render_once(setting, sc), render_once(setting, sc)
        return img, min(c1, c2)

    def render_once(setting: dict, sc: Scene) -> tuple[np.ndarray, float]:
        atm = atms[setting["dtype"]]
        c0 = time.process_time()
        if setting["multiple"] == "bruneton":
            tab = precompute(atm, orders=int(setting["orders"]), sizes=_sizes(tuple(int(v) for v in setting["table_sizes"].split(","))))
            img = bruneton_directions(atm, tab, cam, sc, int(setting["orders"]))
            return img, time.process_time() - c0
        kw = {"view_samples": int(setting["view_samples"]), "rule": setting["rule"]}
        if setting["multiple"] == "hillaire":
            nh, nm, nd, ns = (int(v) for v in setting["hillaire_lut"].split(","))
            kw.update(orders=2, multiple="hillaire", tables=hillaire_lut(atm, size=(nh, nm), directions=nd, samples=ns))
        with torch.no_grad():
            im = render_fisheye(atm, cam, sc.sun_zenith_deg, sc.sun_azimuth_deg, parse_integrator(setting["integrator"]),
                                altitude=sc.altitude_m, **kw)
        return im.spectral[im.valid].double().numpy(), time.process_time() - c0

    print("| Scene | Family | Tolerance | Chosen | Error here | Cost here [ms] | Most expensive | its cost [ms] | Speed-up | OK |")
    print("|---|---|---|---|---:|---:|---|---:|---:|---|")
    failures = 0
    for s in fr["scenes"]:
        sc = Scene(s["name"], s["sun_zenith_deg"], s["altitude_m"], s["sun_azimuth_deg"])
        a64 = atms["float64"]
        with torch.no_grad():
            im = render_fisheye(a64, cam, sc.sun_zenith_deg, sc.sun_azimuth_deg, make_integrator("gauss", samples=32),
                                altitude=sc.altitude_m, view_samples=128, rule="gauss")
        refs = {"single": im.spectral[im.valid].double().numpy()}
        if ref_tab is not None:
            refs["multiple"] = refs["single"] + (bruneton_directions(a64, ref_tab, cam, sc, 6) - bruneton_directions(a64, ref_tab, cam, sc, 1))
        for fam in fams:
            orders = 1 if fam == "single" else 2
            ids = {st["id"]: st for st in fr["settings"] if st["family"] == fam and st["dtype"] == "float32"}
            # The most expensive setting: largest median render cost over the scenes plus the median precomputation
            # cost of its method (each precomputation was timed once; one was a 10x load spike).
            def prep_key(st):
                return (st["integrator"].split(":")[0] if st["multiple"] is None else st["multiple"], st["hillaire_lut"],
                        st["table_sizes"], st["orders"])

            prep = {}
            for i, st in ids.items():
                prep.setdefault(prep_key(st), []).append(next(iter(fr["results"][i].values())).get("prepare_cpu_s", 0.0))

            def typical_cost(i):
                return float(np.median([v["cpu_s"] for v in fr["results"][i].values()]) + np.median(prep[prep_key(ids[i])]))

            dear_id = max(ids, key=typical_cost)
            for tol_text in TOLERANCES[fam]:
                tol = parse_accuracy(tol_text)
                try:
                    c = choose(tol, sc.sun_zenith_deg, sc.altitude_m, orders=orders, dtype="float32", frontier=fr)
                except ValueError as e:
                    print(f"| {sc.name} | {fam} | {tol_text} | none: {str(e)[:80]} | | | | | | |")
                    continue
                key = (c.setting["id"], sc.name)
                if key not in cache:
                    cache[key] = render(c.setting, sc)
                img, cost = cache[key]
                if (dear_id, sc.name) not in cache:
                    cache[(dear_id, sc.name)] = render(ids[dear_id], sc)
                _, dear_cost = cache[(dear_id, sc.name)]
                e = image_errors(refs[fam], img, xyz)
                got = e["mean_delta_e"] if tol.metric == "de" else e["rel_rmse"]
                ok = got <= tol.value
                failures += not ok
                print(f"| {sc.name} | {fam} | {tol_text} | {describe(c.setting)} | {got:.3g} | {1e3 * cost:.3g} | "
                      f"{describe(ids[dear_id])} | {1e3 * dear_cost:.4g} | {dear_cost / cost:.0f}× | {'yes' if ok else 'NO'} |",
                      flush=True)
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
