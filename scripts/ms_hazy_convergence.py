"""Orders >= 2 of Bruneton's tables on a hazy sky against a converged reference: which table size or rule decides.

    OMP_NUM_THREADS=2 .venv/bin/python scripts/ms_hazy_convergence.py [--threads 2] [--by-order] [--sun 23] [--out docs/multiple/hazy_convergence.json]

Hazy Earth (configs/earth.yaml with AOD 0.3 at 550 nm in its 1.2 km Mie layer, Angstrom alpha 1.3, single-scattering
albedo 0.9, g 0.82, Cornette-Shanks), sun at 23 deg zenith (``--sun``), a ground observer, 6 wavelengths 420-680 nm, 4 orders,
float64. Views (elevation, azimuth from the sun): (10, 0), (30, 0), (45, 0), (60, 0), (90, -), (30, 90), (30, 180),
(10, 180). Printed: each setting's orders >= 2 (sky_radiance with all orders minus order 1, at 570 nm) over the
reference's. The reference: scattering mu 128, 200 Gauss-Legendre view-ray nodes, 32 x 64 density directions, the
photo fit's other sizes (minutes of CPU). The photo fit's tables: (64, 32, 16, 8, 16, 128, 16, 8) since session 14
(mu 64 before). Every row and the reference keep 2017's mu_s axis of 16 texels, which is not converged for a high sun
(2.3x at the zenith with the sun at 23 and 50 deg): scripts/ms_sun_window.py measures that axis, and the photo fit
builds its tables for the photo's sun since session 16 (docs/multiple_scattering.md, "One sun's mu_s window").
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

from skyfit.atmosphere import load_atmosphere  # noqa: E402
from skyfit.scattering.bruneton_tables import TableSizes  # noqa: E402
from skyfit.scattering.multiple import Quadrature, precompute, sky_radiance  # noqa: E402

WAVELENGTHS = [420.0, 470.0, 520.0, 570.0, 620.0, 680.0]
VIEWS = [(10.0, 0.0), (30.0, 0.0), (45.0, 0.0), (60.0, 0.0), (90.0, 0.0), (30.0, 90.0), (30.0, 180.0), (10.0, 180.0)]
PHOTO = dict(transmittance_mu=64, transmittance_r=32, irradiance_mu_s=16, irradiance_r=8, scattering_r=16, scattering_mu=64,
             scattering_mu_s=16, scattering_nu=8)
SETTINGS = [  # (label, table sizes changed from the photo fit's, quadrature)
    ("photo fit (2017 trapezoid)", {}, {}),
    ("photo fit, Gauss rays", {}, {"ray_rule": "gauss"}),
    ("Gauss rays, density 32 x 64", {}, {"ray_rule": "gauss", "density_theta": 32, "density_phi": 64}),
    ("Gauss rays, mu 128", {"scattering_mu": 128}, {"ray_rule": "gauss"}),
    ("Gauss rays, mu 96", {"scattering_mu": 96}, {"ray_rule": "gauss"}),
    ("Gauss rays, nu 16", {"scattering_nu": 16}, {"ray_rule": "gauss"}),
    ("Gauss rays, mu 128, density 32 x 64 (the generator's since session 14)", {"scattering_mu": 128},
     {"ray_rule": "gauss", "density_theta": 32, "density_phi": 64}),
    ("trapezoid, 200 intervals", {}, {"multiple_samples": 200, "single_samples": 200}),
    # session 15: which of the density directions' two axes decides at mu 128
    ("Gauss rays, mu 128, density 32 x 32", {"scattering_mu": 128}, {"ray_rule": "gauss", "density_theta": 32, "density_phi": 32}),
    ("Gauss rays, mu 128, density 24 x 32", {"scattering_mu": 128}, {"ray_rule": "gauss", "density_theta": 24, "density_phi": 32}),
    ("Gauss rays, mu 128, density 32 x 16", {"scattering_mu": 128}, {"ray_rule": "gauss", "density_theta": 32, "density_phi": 16}),
    ("Gauss rays, mu 128, density 16 x 64", {"scattering_mu": 128}, {"ray_rule": "gauss", "density_theta": 16, "density_phi": 64}),
    ("Gauss rays, mu 128, density 16 x 32, 2 zenith bands split (the photo fit's since session 15)",
     {"scattering_mu": 128}, {"ray_rule": "gauss", "density_zenith": 2}),
]
SUN_ZENITH_DEG = 23.0
"""The sun's zenith angle of every setting and the reference unless ``--sun`` says otherwise. [deg]"""
BY_ORDER = [(16, 32), (32, 32), (8, 16)]
"""``--by-order``: density directions (theta, phi) whose orders 2, 3 and 4 are each compared with the same order of
the generator's tables (mu 128, Gauss rays, 32 x 64)."""
REFERENCE = ({"scattering_mu": 128}, {"ray_rule": "gauss", "multiple_samples": 200, "single_samples": 200,
                                      "density_theta": 32, "density_phi": 64})


def hazy_atmosphere():
    a = load_atmosphere("earth", WAVELENGTHS)
    ext = 0.3 / 1200.0 * (torch.tensor(WAVELENGTHS, dtype=torch.float64) / 550.0) ** -1.3
    return a.replace(mie_extinction=ext, mie_scattering=0.9 * ext, mie_g=torch.tensor(0.82, dtype=torch.float64))


def view_geometry(atm, sun_deg: float) -> tuple[torch.Tensor, ...]:
    """(r, mu, mu_s, nu) of a ground observer's :data:`VIEWS` with the sun at zenith angle ``sun_deg``."""
    sz = math.radians(sun_deg)
    el = torch.tensor([v[0] for v in VIEWS], dtype=torch.float64)
    az = torch.deg2rad(torch.tensor([v[1] for v in VIEWS], dtype=torch.float64))
    vz = torch.deg2rad(90.0 - el)
    mu, mu_s = torch.sin(torch.deg2rad(el)), torch.full_like(el, math.cos(sz))
    nu = torch.cos(vz) * math.cos(sz) + torch.sin(vz) * math.sin(sz) * torch.cos(az)
    return torch.full_like(mu, float(atm.bottom_radius) + 1.0), mu, mu_s, nu


def orders_2_up(atm, sizes: dict, quad: dict, sun_deg: float) -> tuple[torch.Tensor, float]:
    r, mu, mu_s, nu = view_geometry(atm, sun_deg)
    t0 = time.process_time()
    with torch.no_grad():
        tab = precompute(atm, orders=4, sizes=TableSizes(**{**PHOTO, **sizes}), quadrature=Quadrature(**quad), progress=False)
        every = sky_radiance(tab, None, r, mu, mu_s, nu, ground=True)
        first = sky_radiance(tab, None, r, mu, mu_s, nu, orders=1, ground=False)
    return (every - first)[:, WAVELENGTHS.index(570.0)], time.process_time() - t0


def each_order(atm, theta: int, phi: int, sun_deg: float) -> list[torch.Tensor]:
    """Orders 2, 3, 4 apart (sky_radiance with 2, 3, 4 orders minus the one below; ground included) at 570 nm, tables
    of mu 128 with Gauss rays and ``theta`` x ``phi`` density directions."""
    r, mu, mu_s, nu = view_geometry(atm, sun_deg)
    with torch.no_grad():
        tab = precompute(atm, orders=4, sizes=TableSizes(**{**PHOTO, "scattering_mu": 128}), keep_orders=True,
                         quadrature=Quadrature(ray_rule="gauss", density_theta=theta, density_phi=phi), progress=False)
        up_to = [sky_radiance(tab, None, r, mu, mu_s, nu, orders=k, ground=True)[:, WAVELENGTHS.index(570.0)]
                 for k in (1, 2, 3, 4)]
    return [up_to[k] - up_to[k - 1] for k in (1, 2, 3)]


def by_order(atm, sun_deg: float) -> dict:
    """Each order's ratio to the generator's density directions (32 x 64) for :data:`BY_ORDER`, and the share of
    orders 3 and 4 in orders >= 2 there."""
    base = each_order(atm, 32, 64, sun_deg)
    out = {"share_orders_3_4": [float(x) for x in (base[1] + base[2]) / sum(base)], "rows": []}
    print("orders 3 + 4 of orders >= 2: " + " ".join(f"{x:.3f}" for x in out["share_orders_3_4"]), flush=True)
    for theta, phi in BY_ORDER:
        d = each_order(atm, theta, phi, sun_deg)
        row = {"density": [theta, phi], "order_over_32x64": [[float(x) for x in d[k] / base[k]] for k in range(3)]}
        out["rows"].append(row)
        print(f"density {theta} x {phi}: " + " | ".join(" ".join(f"{x:.3f}" for x in o) for o in row["order_over_32x64"]),
              flush=True)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--out", default="docs/multiple/hazy_convergence.json")
    ap.add_argument("--by-order", action="store_true", help="also each order 2, 3, 4 apart for the density directions "
                    "of BY_ORDER against 32 x 64 (mu 128, Gauss rays): the JSON's by_order")
    ap.add_argument("--sun", type=float, default=SUN_ZENITH_DEG, help="the sun's zenith angle [deg] (default %(default)s)")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    atm = hazy_atmosphere()
    ref, ref_cpu = orders_2_up(atm, *REFERENCE, args.sun)
    print(f"reference ({ref_cpu:.0f} s CPU); views (elevation, azimuth from the sun): {VIEWS}", flush=True)
    rows = []
    for label, sizes, quad in SETTINGS:
        v, cpu = orders_2_up(atm, sizes, quad, args.sun)
        ratio = [float(x) for x in v / ref]
        rows.append({"setting": label, "sizes": {**PHOTO, **sizes}, "quadrature": quad, "cpu_s": cpu, "over_reference": ratio})
        print(f"{label:30s} {cpu:6.1f} s CPU  " + " ".join(f"{x:.3f}" for x in ratio), flush=True)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"views": VIEWS, "sun_zenith_deg": args.sun, "reference": {"sizes": {**PHOTO, **REFERENCE[0]}, "quadrature": REFERENCE[1],
                                                             "orders_2_up_570nm": [float(x) for x in ref], "cpu_s": ref_cpu},
                               "rows": rows, **({"by_order": by_order(atm, args.sun)} if args.by_order else {})}, indent=1))


if __name__ == "__main__":
    main()
