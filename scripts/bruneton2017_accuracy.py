"""How well ``export-lut --layout bruneton2017`` files reproduce ``skyfit render`` (docs/luts.md).

Precomputes Earth's tables (2017's sizes and quadrature by default), exports them in float32 and
float16, renders them with the NumPy transcription of the exported GLSL
(skyfit.export.shader_reference: OpenGL texel fetches and filtering, not skyfit's sampler) and
compares with skyfit's own lookup of the same tables (spectral, then linear sRGB), over view
zenith 0.25 deg x azimuth 15 deg steps (sky and ground) for suns at 0, 30, 60, 80, 90, 95 deg.

    .venv/bin/python scripts/bruneton2017_accuracy.py [--table-sizes 32,128,32,8] [--orders 4]
        [--wavelengths 400:700:50] [--out docs/luts/bruneton2017_accuracy.json]

On the shared 2-core machine the precomputation at 2017's sizes takes several minutes.
"""
from __future__ import annotations

import argparse
import json
import math
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from skyfit.atmosphere import load_atmosphere, parse_wavelengths
from skyfit.export import bruneton2017 as b17
from skyfit.export.shader_reference import BANDS_DEG, Bruneton2017Shader, band_table, relative_errors, view_grid
from skyfit.scattering.bruneton_tables import TableSizes
from skyfit.scattering.multiple import precompute

SUNS = (0.0, 30.0, 60.0, 80.0, 90.0, 95.0)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--table-sizes", default="32,128,32,8")
    ap.add_argument("--orders", type=int, default=4)
    ap.add_argument("--wavelengths", default="400:700:50")
    ap.add_argument("--zenith-step", type=float, default=0.25)
    ap.add_argument("--azimuth-step", type=float, default=15.0)
    ap.add_argument("--out", default="docs/luts/bruneton2017_accuracy.json")
    args = ap.parse_args()
    torch.set_num_threads(2)
    lam = parse_wavelengths(args.wavelengths)
    atm = load_atmosphere("earth", lam)
    atm_rgb = load_atmosphere("earth", np.array(b17.LAMBDAS_RGB_NM))
    sizes = TableSizes.parse(args.table_sizes)
    t0 = time.perf_counter()
    with torch.no_grad():
        tables = precompute(atm, orders=args.orders, sizes=sizes,
                            mu_s_min=b17.skyfit_mu_s_min(b17.UPSTREAM_MU_S_MIN, atm.bottom_radius, atm.top_radius))
    t_pre = time.perf_counter() - t0
    print(f"precomputed {args.table_sizes}, {args.orders} orders, {len(lam)} wavelengths in {t_pre:.0f} s", flush=True)
    view = view_grid(args.zenith_step, args.azimuth_step)
    views = np.concatenate([view] * len(SUNS))
    result = {"table_sizes": args.table_sizes, "orders": args.orders, "wavelengths_nm": lam.tolist(), "suns_deg": list(SUNS),
              "view_grid": {"zenith_step_deg": args.zenith_step, "azimuth_step_deg": args.azimuth_step},
              "precompute_seconds": round(t_pre, 1), "bands_deg": [list(b) for b in BANDS_DEG], "tables": {}}
    with tempfile.TemporaryDirectory() as tmp:
        lum = {}
        for prec in ("f32", "f16"):
            d = b17.export_bruneton2017(tables, Path(tmp) / prec, precision=prec, atm_rgb=atm_rgb)
            for combined in (False, True):
                sh = Bruneton2017Shader.from_dir(d, combined=combined)
                errs = [relative_errors(sh, tables, view, sz)[0] for sz in SUNS]
                key = f"{prec}_{'combined' if combined else 'separate'}"
                result["tables"][key] = {"all_suns": band_table(np.concatenate(errs), views),
                                         "per_sun": {f"{sz:g}": band_table(e, view) for sz, e in zip(SUNS, errs)}}
                print(key, flush=True)
            sh = Bruneton2017Shader.from_dir(d, combined=False)
            cam = np.tile([0.0, 0.0, atm.bottom_radius / 1000.0], (view.shape[0], 1))
            lum[prec] = [sh.sky_luminance(cam, view, np.array([0.0, math.sin(math.radians(s)), math.cos(math.radians(s))]))[0]
                         for s in SUNS]
        # Half precision's own error: |f16 - f32| / f32 of the same shader, sky only, by band.
        sky = view[:, 2] > 0
        rel = np.concatenate([np.abs(h - f)[sky] / np.maximum(f[sky], 1e-300) for h, f in zip(lum["f16"], lum["f32"])])
        result["f16_vs_f32_sky"] = band_table(rel, np.concatenate([view[sky]] * len(SUNS)), BANDS_DEG[:-1])
        # What float16 would do to the transmittance texture (2017 keeps it float32): relative error at the texels.
        tex, _ = b17.bruneton2017_textures(tables, atm_rgb)
        t = tex["transmittance"]
        th = t.astype(np.float16).astype(np.float64)
        mu_cols = {"zenith": slice(0, 1), "last 10 % of x_mu (horizon)": slice(int(0.9 * t.shape[1]), None)}
        result["transmittance_if_f16"] = {k: {"max_rel": float((np.abs(th - t) / t)[:, s].max()),
                                              "min_value": float(t[:, s].min())} for k, s in mu_cols.items()}
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=1) + "\n")
    print(f"wrote {out}")
    print("\n| view zenith | " + " | ".join(result["tables"]) + " |")
    print("|---|" + "---|" * len(result["tables"]))
    for i, (lo, hi) in enumerate(BANDS_DEG):
        cells = [f"{v['all_suns'][i]['median']:.2%} / {v['all_suns'][i]['max']:.2%}" for v in result["tables"].values()]
        name = "ground (90-180)" if lo >= 90 else f"{lo:g}-{hi:g}"
        print(f"| {name} | " + " | ".join(cells) + " |")
    print("\nf16 vs f32 (sky):", [(r["band_deg"], f"{r['max']:.2e}") for r in result["f16_vs_f32_sky"]])
    print("transmittance if f16:", result["transmittance_if_f16"])


if __name__ == "__main__":
    main()
