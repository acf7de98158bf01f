"""Hillaire 2020 LUT vs Bruneton's precomputed orders 2-4: error and time side by side.

Clear Earth without ozone (as first measured; both methods include it consistently), ground observer,
view zenith 0-89 deg x azimuth 0/45/90/135/180, both methods with the same direct single
scattering. Error = |M_hillaire - M_bruneton| / (single + M_bruneton), M = orders >= 2.

    .venv/bin/python scripts/hillaire_compare.py [--wavelengths 440 550 680] [--threads 1]
"""
from __future__ import annotations

import argparse
import math
import time

import torch

from skyfit.atmosphere import load_atmosphere
from skyfit.scattering import single_scattering
from skyfit.scattering.bruneton_tables import TableSizes
from skyfit.scattering.hillaire import hillaire_lut, hillaire_multiple
from skyfit.scattering.multiple import precompute, sky_radiance
from skyfit.transmittance import make_integrator


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--wavelengths", type=float, nargs="+", default=[440.0, 550.0, 680.0])
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--lut", type=int, nargs=2, default=[32, 32])
    a = p.parse_args()
    torch.set_num_threads(a.threads)
    atm = load_atmosphere("earth", a.wavelengths).replace(ozone_absorption=None)
    sizes = TableSizes(scattering_r=8, scattering_mu=32, scattering_mu_s=8, scattering_nu=4, transmittance_mu=64,
                       transmittance_r=16, irradiance_mu_s=16, irradiance_r=8)
    t = time.process_time()
    tab = precompute(atm, orders=4, sizes=sizes)
    t_b = time.process_time() - t
    t = time.process_time()
    lut = hillaire_lut(atm, size=tuple(a.lut), directions=64, samples=20)
    t_h = time.process_time() - t
    integ = make_integrator("gauss", samples=16)
    vz = torch.tensor([0.0, 15, 30, 45, 60, 70, 80, 85, 89], dtype=torch.float64)
    az = torch.tensor([0.0, 45, 90, 135, 180], dtype=torch.float64)
    V, A = torch.meshgrid(torch.deg2rad(vz), torch.deg2rad(az), indexing="ij")
    print(f"Bruneton orders 4, tables {sizes.scattering_shape}: {t_b:.2f} s CPU;  "
          f"Hillaire LUT {tuple(a.lut)}, 64 dirs, 20 samples: {t_h:.2f} s CPU;  W = {len(a.wavelengths)}")
    print("| sun zenith | max err | mean signed err | ms share of total | render Bruneton [ms] | render Hillaire [ms] |")
    print("|---|---|---|---|---|---|")
    for sz in (0, 30, 60, 85, 90):
        s = math.radians(sz)
        mu = torch.cos(V)
        nu = mu * math.cos(s) + torch.sin(V) * math.sin(s) * torch.cos(A)
        mus = torch.full_like(mu, math.cos(s))
        r = torch.full_like(mu, atm.bottom_radius + 1.0)
        t = time.process_time()
        full = sky_radiance(tab, None, r, mu, mus, nu, ground=False)
        t_rb = time.process_time() - t
        m_b = full - sky_radiance(tab, None, r, mu, mus, nu, orders=1, ground=False)
        single = single_scattering(atm, r, mu, mus, nu, integ, 32, ground=False)
        t = time.process_time()
        m_h = hillaire_multiple(atm, r, mu, mus, nu, integ, 32, lut=lut)
        t_rh = time.process_time() - t
        e = (m_h - m_b) / (single + m_b)
        share = float((m_b / (single + m_b)).mean())
        print(f"| {sz} | {float(e.abs().max()):.3f} | {float(e.mean()):+.3f} | {share:.3f} | {1e3 * t_rb:.1f} | {1e3 * t_rh:.1f} |")


if __name__ == "__main__":
    main()
