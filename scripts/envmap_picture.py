"""The environment-map pictures of docs/envmap.md: Earth at the Kider site, 2013-05-27 16:00 EDT.

    .venv/bin/python scripts/envmap_picture.py [--size 256] [--table-sizes 16,64,16,8]

Writes docs/envmap/latlong.png (tone-mapped lat-long, sun disc on), docs/envmap/cubemap.png (the
six faces as a strip) and prints the hemisphere integrals against a fisheye render of the same sky.
"""
from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import numpy as np
import torch

import skyfit
from skyfit.camera import FisheyeCamera
from skyfit.export.envmap import write_preview
from skyfit.geometry import zenith_angle_deg
from skyfit.render.colour import spectral_to_xyz, xyz_to_linear_srgb, xyz_to_srgb_matrix

WHEN, WHERE = "2013-05-27T16:00:00-04:00", (42.443449, -76.481962, 250.0)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--table-sizes", default="16,64,16,8")
    ap.add_argument("--out", default="docs/envmap")
    args = ap.parse_args()
    torch.set_num_threads(2)
    atm = skyfit.load_atmosphere("earth")
    sun = skyfit.sun_vector(time=WHEN, location=WHERE)
    model = skyfit.api.render_model(orders=4)
    import dataclasses

    from skyfit.scattering.bruneton_tables import TableSizes

    model = dataclasses.replace(model, table_sizes=dataclasses.astuple(TableSizes.parse(args.table_sizes)))
    out = Path(args.out)
    # once for every map, for their one sun (the default renderer's tables: SkyModel.sun_window)
    tables = model.sun_tables(atm, zenith_angle_deg(sun))
    env = skyfit.envmap(atm, sun, size=args.size, sun_disk=True, model=model, tables=tables)
    sky = skyfit.envmap(atm, sun, size=args.size, sun_disk=False, model=model, tables=tables)
    # one exposure for both pictures: the sky's 90th percentile
    k = 1.0 / float(np.percentile(sky.rgb[: args.size // 2].mean(-1), 90))
    write_preview(out / "latlong.png", env.rgb, k)
    cube = skyfit.envmap(atm, sun, size=args.size // 2, layout="cubemap", sun_disk=True, model=model, tables=tables)
    write_preview(out / "cubemap.png", cube.image(), k)
    fn = model.renderer(atm, tables=tables)
    cam = FisheyeCamera(512)
    vec, valid = cam.pixel_vectors(torch.float64)
    v = vec[valid]
    rgb = xyz_to_linear_srgb(spectral_to_xyz(fn(v, sun), atm.wavelengths))
    th = torch.acos(v[:, 2].clamp(-1, 1))
    f = float(cam.r90) / (math.pi / 2)
    om = torch.where(th > 0, torch.sin(th) / (f * f * th), torch.full_like(th, 1 / (f * f)))
    fish = (rgb * (v[:, 2].clamp_min(0) * om)[:, None]).sum(0).numpy()
    y = np.linalg.inv(xyz_to_srgb_matrix())[1]
    summary = {"time": WHEN, "location": WHERE, "sun": env.sun, "size": args.size, "table_sizes": args.table_sizes,
               "sky_horizontal_illuminance_lux": {"latlong": float(sky.irradiance() @ y), "fisheye_512": float(fish @ y)},
               "with_sun_disc_lux": float(env.irradiance() @ y)}
    (out / "summary.json").write_text(json.dumps(summary, indent=1) + "\n")
    print(json.dumps(summary, indent=1))


if __name__ == "__main__":
    main()
