"""Precomputation time and memory of the Bruneton tables (docs/multiple_scattering.md).

    python scripts/multiple_bench.py --threads 2 --wavelengths 3 16            # CPU, default sizes
    python scripts/multiple_bench.py --device cuda --dtype float32 float64 --grad
    python scripts/multiple_bench.py --size small --wavelengths 3                # quick

Prints one markdown row per configuration (and JSON with --json): total and per-stage
seconds of :func:`skyfit.scattering.multiple.precompute` (4 orders by default), the size of
the tables, the peak memory, and with ``--grad`` the time of a backward pass from a scalar
of sky radiances to every Atmosphere tensor (chunks checkpointed).
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from skyfit.atmosphere import load_atmosphere  # noqa: E402
from skyfit.scattering.bruneton_tables import TableSizes  # noqa: E402
from skyfit.scattering.multiple import precompute, sky_radiance  # noqa: E402

SIZES = {
    "default": TableSizes(),
    "small": TableSizes(transmittance_mu=64, transmittance_r=16, irradiance_mu_s=64, irradiance_r=8,
                        scattering_r=8, scattering_mu=32, scattering_mu_s=16, scattering_nu=8),
    "half": TableSizes(transmittance_mu=128, transmittance_r=32, irradiance_mu_s=64, irradiance_r=16,
                       scattering_r=16, scattering_mu=64, scattering_mu_s=16, scattering_nu=8),
}
GRAD_PARAMS = ("rayleigh_scattering", "mie_scattering", "mie_extinction", "rayleigh_scale_height",
               "mie_scale_height", "mie_g", "ground_albedo", "ozone_absorption")


def wavelengths(n: int) -> list[float]:
    return [440.0, 550.0, 680.0] if n == 3 else np.linspace(400.0, 700.0, n).tolist()


def peak_memory_mb(device: str) -> float:
    if device == "cuda":
        return torch.cuda.max_memory_allocated() / 2**20
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # Linux: KiB


def run(size: str, n_w: int, orders: int, device: str, dtype: torch.dtype, grad: bool, chunk_bytes: float) -> dict:
    atm = load_atmosphere("earth", wavelengths(n_w), dtype=dtype, device=device)
    if device == "cuda":
        torch.cuda.reset_peak_memory_stats()
        torch.cuda.synchronize()
    leaves = {}
    if grad:
        leaves = {n: getattr(atm, n).clone().requires_grad_(True) for n in GRAD_PARAMS}
        atm = atm.replace(**leaves)
    t0 = time.perf_counter()
    tab = precompute(atm, orders=orders, sizes=SIZES[size], chunk_bytes=chunk_bytes)
    out = {"size": size, "wavelengths": n_w, "orders": orders, "device": device, "dtype": str(dtype).split(".")[-1],
           "threads": torch.get_num_threads(), "seconds": tab.timings["total"], "stages": tab.timings,
           "tables_mb": tab.nbytes() / 2**20}
    if grad:
        mu = torch.linspace(-0.3, 1.0, 64, dtype=dtype, device=device)
        r = torch.full_like(mu, atm.bottom_radius + 100.0)
        loss = sky_radiance(tab, None, r, mu, torch.full_like(mu, 0.5), torch.full_like(mu, 0.2) * mu).sum()
        t1 = time.perf_counter()
        loss.backward()
        if device == "cuda":
            torch.cuda.synchronize()
        out["backward_seconds"] = time.perf_counter() - t1
        out["forward_backward_seconds"] = time.perf_counter() - t0
        out["grad_finite"] = all(bool(torch.isfinite(v.grad).all()) for v in leaves.values())
    out["peak_memory_mb"] = peak_memory_mb(device)
    return out


def row(res: dict) -> str:
    st = res["stages"]
    order_s = sum(v for k, v in st.items() if k.startswith("order_"))
    cols = [res["device"], res["dtype"], str(res["threads"]) if res["device"] == "cpu" else "-", res["size"], str(res["wavelengths"]),
            str(res["orders"]), f"{res['seconds']:.1f}", f"{st['single_scattering']:.1f}", f"{order_s:.1f}",
            f"{res['tables_mb']:.0f}", f"{res['peak_memory_mb']:.0f}",
            f"{res['backward_seconds']:.1f}" if "backward_seconds" in res else "-"]
    return "| " + " | ".join(cols) + " |"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--size", choices=sorted(SIZES), default="default")
    ap.add_argument("--wavelengths", type=int, nargs="+", default=[3, 16])
    ap.add_argument("--orders", type=int, default=4)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--dtype", nargs="+", default=["float64"], choices=["float32", "float64"])
    ap.add_argument("--threads", type=int, default=2, help="torch intra-op threads on CPU")
    ap.add_argument("--grad", action="store_true", help="also time a backward pass")
    ap.add_argument("--chunk-mb", type=float, default=128.0, help="precompute(chunk_bytes=...) in MiB")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    print(f"# torch {torch.__version__}, {os.cpu_count()} CPUs, load average {os.getloadavg()}", flush=True)
    if args.device == "cuda":
        print(f"# {torch.cuda.get_device_name()}", flush=True)
    print("| device | dtype | threads | size | W | orders | total s | single s | orders>=2 s | tables MB | peak MB | backward s |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|", flush=True)
    results = []
    for dt in args.dtype:
        for n_w in args.wavelengths:
            res = run(args.size, n_w, args.orders, args.device, getattr(torch, dt), args.grad, args.chunk_mb * 2**20)
            results.append(res)
            print(row(res), flush=True)
    if args.json:
        args.json.write_text(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()
