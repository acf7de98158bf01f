"""Hillaire's multiple scattering against converged orders as the aerosol thickens (docs/hillaire.md, "Hazy skies").

For an `earth` atmosphere whose aerosol is a 1.2 km exponential Henyey-Greenstein layer (g 0.76) at AOD 0.03-0.5,
the total radiance at 550 nm over 5-90 deg elevation x 0-180 deg from the sun's azimuth, of

* the fits' Hillaire model: `configs/kider.yaml`'s LUT (32 directions x 12 steps) on Chapman single scattering with
  16 Gauss view nodes, and
* the error budget's converged reference (skyfit.fit.budget.ReferenceModel: Gauss-32 optical depth, 128 Gauss view
  nodes, Bruneton tables 16 x 64 x window x 8 with 6 orders spanning the sun, Gauss-Legendre view rays),

as the RMS, lowest and highest of Hillaire / reference - 1, and at the zenith.

    OMP_NUM_THREADS=2 .venv/bin/python scripts/hillaire_haze.py --sun-zenith 30
"""
from __future__ import annotations

import argparse
import copy
import dataclasses
import math
from pathlib import Path

import torch

import skyfit
from skyfit.atmosphere import atmosphere_from_config, load_yaml
from skyfit.fit.budget import ReferenceModel
from skyfit.fit.model import SkyModel
from skyfit.render.sky import render_vectors
from skyfit.scattering.hillaire import hillaire_lut
from skyfit.transmittance import make_integrator


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sun-zenith", type=float, default=30.0)
    ap.add_argument("--aods", default="0.03,0.1,0.2,0.3,0.5")
    ap.add_argument("--scale-height", type=float, default=1200.0)
    ap.add_argument("--g", type=float, default=0.76)
    args = ap.parse_args()
    base = load_yaml(Path(skyfit.__file__).parent / "configs" / "earth.yaml")
    sz = math.radians(args.sun_zenith)
    sun = torch.tensor([math.sin(sz), 0.0, math.cos(sz)], dtype=torch.float64)
    dirs = [[math.cos(math.radians(e)) * math.cos(math.radians(a)), math.cos(math.radians(e)) * math.sin(math.radians(a)),
             math.sin(math.radians(e))] for e in range(5, 91, 5) for a in range(0, 181, 30)]
    d = torch.tensor(dirs, dtype=torch.float64)
    zenith = int(torch.argmax(d[:, 2]))
    for aod in (float(v) for v in args.aods.split(",")):
        cfg = copy.deepcopy(base)
        cfg["mie"].pop("angstrom_beta", None)
        cfg["mie"].update(extinction_550=aod / args.scale_height, scale_height_m=args.scale_height,
                          phase="henyey_greenstein", g=args.g)
        atm = atmosphere_from_config(cfg, torch.tensor([550.0], dtype=torch.float64))
        ref = dataclasses.replace(ReferenceModel.of(SkyModel(make_integrator("chapman"), orders=2)),
                                  sun_zenith_deg=(args.sun_zenith, args.sun_zenith))
        converged = ref.renderer(atm)(d, sun)
        lut = hillaire_lut(atm, size=(32, 32), directions=32, samples=12)
        hillaire = render_vectors(atm, d, sun, make_integrator("chapman"), 0.0, 2, view_samples=16, rule="gauss",
                                  multiple="hillaire", tables=lut, ground=True)
        rel = (hillaire / converged - 1.0)[:, 0]
        print(f"AOD {aod:.2f}: Hillaire 32x12 / converged - 1: rms {float(rel.pow(2).mean().sqrt()):.3f}, "
              f"min {float(rel.min()):+.3f}, max {float(rel.max()):+.3f}, zenith {float(rel[zenith]):+.3f}", flush=True)


if __name__ == "__main__":
    main()
