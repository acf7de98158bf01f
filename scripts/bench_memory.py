"""Peak memory of a large render (benchmark, not a test): a 1024 x 1024 fisheye must not need more than ~2 GB.

Each case runs in a fresh subprocess that reports the peak resident set size
(``VmHWM`` of /proc/self/status: tracemalloc and ``resource`` do not see
torch's allocations reliably), the resident size just before the render
(imports, atmosphere) and the render time; on CUDA also
``torch.cuda.max_memory_allocated``.

    python scripts/bench_memory.py [--size 1024] [--device cpu] [--only taylor] [--json]
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time

CASES = (
    ("float32", "taylor", {}),
    ("float64", "taylor", {}),
    ("float32", "trapezoid", {"samples": 128}),
)


def _vm(key: str) -> float:
    """A /proc/self/status entry in MiB."""
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith(key + ":"):
                return int(line.split()[1]) / 1024.0
    return float("nan")


def child(size: int, dtype_name: str, integrator: str, settings: dict, device: str, threads: int) -> dict:
    import numpy as np
    import torch

    from skyfit.atmosphere import load_atmosphere
    from skyfit.camera import FisheyeCamera, render_fisheye
    from skyfit.transmittance import make_integrator

    torch.set_num_threads(threads)
    dtype = {"float32": torch.float32, "float64": torch.float64}[dtype_name]
    atm = load_atmosphere("earth", np.linspace(400.0, 700.0, 16), dtype=dtype, device=device)
    integ = make_integrator(integrator, **settings)
    before = _vm("VmRSS")
    t0 = time.perf_counter()
    with torch.no_grad():
        img = render_fisheye(atm, FisheyeCamera(size), 40.0, 120.0, integ, view_samples=32)
    if device.startswith("cuda"):
        torch.cuda.synchronize()
    out = {
        "size": size, "dtype": dtype_name, "integrator": integrator, "settings": settings, "device": device,
        "seconds": time.perf_counter() - t0, "rss_before_render_mib": before, "peak_rss_mib": _vm("VmHWM"),
        "image_mib": img.spectral.numel() * img.spectral.element_size() / 2**20,
        "finite": bool(torch.isfinite(img.spectral).all()),
    }
    if device.startswith("cuda"):
        out["cuda_max_allocated_mib"] = torch.cuda.max_memory_allocated() / 2**20
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--size", type=int, default=1024)
    p.add_argument("--device", default="cpu")
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--only", help="run only the cases of this integrator (e.g. taylor)")
    p.add_argument("--json", action="store_true")
    p.add_argument("--_child", help=argparse.SUPPRESS)
    a = p.parse_args(argv)
    if a._child:
        dt, name, settings = json.loads(a._child)
        print(json.dumps(child(a.size, dt, name, settings, a.device, a.threads)))
        return 0
    results = []
    for dt, name, settings in CASES:
        if a.only and name != a.only:
            continue
        cmd = [sys.executable, __file__, "--size", str(a.size), "--device", a.device, "--threads", str(a.threads),
               "--_child", json.dumps([dt, name, settings])]
        r = subprocess.run(cmd, capture_output=True, text=True, env=os.environ.copy())
        if r.returncode != 0:
            raise SystemExit(f"{dt} {name}: child failed:\n{r.stderr}")
        results.append(json.loads(r.stdout.strip().splitlines()[-1]))
    if a.json:
        print(json.dumps(results))
        return 0
    for r in results:
        extra = f", CUDA max allocated {r['cuda_max_allocated_mib']:.0f} MiB" if "cuda_max_allocated_mib" in r else ""
        label = r["integrator"] + "".join(f":{k}={v}" for k, v in r["settings"].items())
        print(f"{r['size']}x{r['size']} {r['dtype']} {label:24s} on {r['device']}: peak RSS {r['peak_rss_mib']:.0f} MiB "
              f"(before render {r['rss_before_render_mib']:.0f} MiB, image {r['image_mib']:.0f} MiB){extra}, "
              f"{r['seconds']:.1f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
