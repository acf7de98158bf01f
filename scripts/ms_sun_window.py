"""Orders >= 2 of Bruneton's tables on a hazy sky: 2017's mu_s axis against tables for one sun (a mu_s window).

    OMP_NUM_THREADS=1 .venv/bin/python scripts/ms_sun_window.py [--threads 1] [--suns 23,50,70,80] [--out docs/multiple/sun_window.json]
    OMP_NUM_THREADS=1 .venv/bin/python scripts/ms_sun_window.py --clear --suns 23,50 --out docs/multiple/sun_window_clear.json

The hazy sky, views and orders of scripts/ms_hazy_convergence.py (AOD 0.3 in a 1.2 km layer, g 0.82, a ground observer,
6 wavelengths, 4 orders, float64; printed at 570 nm), at the photo fit's other sizes (scattering mu 128, Gauss rays,
16 x 32 density directions with 2 zenith bands split). Each setting's orders >= 2 over the reference's: a window of the
sun's zenith angle +- 10 deg in 21 texels (1 deg apart). Rows: 2017's axis (mu_s_min to 1) of 16, 32 and 64 texels;
windows of margin 5, 10 and 20 deg at 2 deg spacing (the margin alone), and margin 5 deg at 4, 6 and 8 texels (the
spacing alone). ``--clear``: the ``earth`` config as it is (a clear sky) instead of the hazy one. The photo fit's tables: margin 5 deg, 6 texels since session 16 (2017's 16 before).
"""
from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "scripts"))

from ms_hazy_convergence import PHOTO, VIEWS, WAVELENGTHS, hazy_atmosphere, view_geometry  # noqa: E402

from skyfit.atmosphere import load_atmosphere  # noqa: E402
from skyfit.scattering.bruneton_tables import MU_S_MIN_DEFAULT, TableSizes  # noqa: E402
from skyfit.scattering.multiple import Quadrature, precompute, sky_radiance  # noqa: E402

QUADRATURE = Quadrature(ray_rule="gauss", density_zenith=2)
REFERENCE = ("window +-10 deg, 21 texels (the reference)", 10.0, 21)
ROWS = [("2017 axis, 16 texels (the photo fit's before)", None, 16), ("2017 axis, 32 texels", None, 32),
        ("2017 axis, 64 texels", None, 64),
        ("window +-5 deg, 6 texels (the photo fit's)", 5.0, 6), ("window +-10 deg, 11 texels", 10.0, 11),
        ("window +-20 deg, 21 texels", 20.0, 21),
        ("window +-5 deg, 4 texels", 5.0, 4), ("window +-5 deg, 8 texels", 5.0, 8),
        ("window +-10 deg, 16 texels (the generator's)", 10.0, 16)]


def sun_range(sun_deg: float, margin_deg: float) -> tuple[float, float]:
    return (max(math.cos(math.radians(min(sun_deg + margin_deg, 180.0))), MU_S_MIN_DEFAULT),
            math.cos(math.radians(max(sun_deg - margin_deg, 0.0))))


def orders_2_up(atm, sun_deg: float, margin_deg: float | None, texels: int) -> tuple[torch.Tensor, float]:
    r, mu, mu_s, nu = view_geometry(atm, sun_deg)
    t0 = time.process_time()
    with torch.no_grad():
        tab = precompute(atm, orders=4, sizes=TableSizes(**{**PHOTO, "scattering_mu": 128, "scattering_mu_s": texels}),
                         quadrature=QUADRATURE, progress=False,
                         mu_s_range=None if margin_deg is None else sun_range(sun_deg, margin_deg))
        every = sky_radiance(tab, None, r, mu, mu_s, nu, ground=True)
        first = sky_radiance(tab, None, r, mu, mu_s, nu, orders=1, ground=False)
    return (every - first)[:, WAVELENGTHS.index(570.0)], time.process_time() - t0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--suns", default="23,50,70,80", help="sun zenith angles [deg], comma-separated")
    ap.add_argument("--out", default="docs/multiple/sun_window.json")
    ap.add_argument("--clear", action="store_true", help="the earth config as it is instead of the hazy sky")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    atm = load_atmosphere("earth", WAVELENGTHS) if args.clear else hazy_atmosphere()
    out = {"command": "scripts/ms_sun_window.py " + " ".join(sys.argv[1:]), "atmosphere": "earth (clear)" if args.clear else "hazy (AOD 0.3, g 0.82)", "views": VIEWS, "wavelength_nm": 570.0,
           "sizes": {**PHOTO, "scattering_mu": 128}, "quadrature": {"ray_rule": "gauss", "density_zenith": 2},
           "reference": {"setting": REFERENCE[0], "margin_deg": REFERENCE[1], "texels": REFERENCE[2]}, "suns": []}
    for sun in (float(v) for v in args.suns.split(",")):
        ref, ref_cpu = orders_2_up(atm, sun, REFERENCE[1], REFERENCE[2])
        print(f"sun {sun:g} deg: reference {ref_cpu:.1f} s CPU; views (elevation, azimuth from the sun): {VIEWS}", flush=True)
        rows = []
        for label, margin, texels in ROWS:
            v, cpu = orders_2_up(atm, sun, margin, texels)
            ratio = [float(x) for x in v / ref]
            rows.append({"setting": label, "margin_deg": margin, "texels": texels, "cpu_s": cpu, "over_reference": ratio})
            print(f"  {label:48s} {cpu:5.1f} s  " + " ".join(f"{x:.3f}" for x in ratio), flush=True)
        out["suns"].append({"sun_zenith_deg": sun, "reference_orders_2_up": [float(x) for x in ref], "reference_cpu_s": ref_cpu,
                            "rows": rows})
    path = Path(args.out)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
