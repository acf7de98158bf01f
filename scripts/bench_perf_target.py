"""Time the renderer's performance target (benchmark, not a test).

Target: a 256 x 256 fisheye, 16 wavelengths, Taylor transmittance, 32 view
samples, float32, under 1 s on 2 CPU cores and under 5 ms on a GPU.

Prints, per device, the median and the minimum wall time of ``--repeats``
renders (``render_fisheye``, spectral radiance, XYZ and sRGB) after
``--warmup`` renders, with ``torch.cuda.synchronize`` around each CUDA render.
The renderer runs eagerly (no ``torch.compile``) unless ``--compile`` is given,
which adds a line with ``skyfit.scattering.single._render_chunk`` compiled.

``--baseline DIR`` repeats the CPU and CUDA timings, in a subprocess, with the
``skyfit`` package found in DIR (e.g. ``git worktree add /tmp/base <commit>``),
so that before and after are measured in one run on one machine.

    python scripts/bench_perf_target.py [--devices cpu,cuda] [--threads 2] [--json]
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import time
from pathlib import Path


def _cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def time_renders(device: str, size: int, n_wavelengths: int, view_samples: int, dtype_name: str, repeats: int,
                 warmup: int, compile_chunk: bool = False) -> dict:
    """Median and min seconds of one fisheye render on ``device``."""
    import numpy as np
    import torch

    import skyfit
    from skyfit.atmosphere import load_atmosphere
    from skyfit.camera import FisheyeCamera, render_fisheye
    from skyfit.transmittance import make_integrator

    if compile_chunk:
        import skyfit.scattering.single as single

        single._render_chunk = torch.compile(single._render_chunk, dynamic=False)
    dtype = {"float32": torch.float32, "float64": torch.float64}[dtype_name]
    atm = load_atmosphere("earth", np.linspace(400.0, 700.0, n_wavelengths), dtype=dtype, device=device)
    cam = FisheyeCamera(size)
    integrator = make_integrator("taylor")

    def sync():
        if device.startswith("cuda"):
            torch.cuda.synchronize()

    def once() -> float:
        sync()
        t0 = time.perf_counter()
        with torch.no_grad():
            img = render_fisheye(atm, cam, 40.0, 120.0, integrator, view_samples=view_samples)
        sync()
        dt = time.perf_counter() - t0
        assert bool(torch.isfinite(img.spectral).all())
        return dt

    t_first = once()
    for _ in range(max(0, warmup - 1)):
        once()
    times = [once() for _ in range(repeats)]
    return {
        "device": device,
        "device_name": torch.cuda.get_device_name() if device.startswith("cuda") else _cpu_model(),
        "torch_threads": torch.get_num_threads(),
        "torch": torch.__version__,
        "skyfit_path": str(Path(skyfit.__file__).resolve().parent),
        "compiled": compile_chunk,
        "first_s": t_first,
        "median_s": statistics.median(times),
        "min_s": min(times),
        "repeats": repeats,
        "load_average_1min": round(os.getloadavg()[0], 2),
    }


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--devices", default=None, help="comma list (default: cpu, and cuda when available)")
    p.add_argument("--threads", type=int, default=2, help="torch CPU threads (default 2)")
    p.add_argument("--size", type=int, default=256)
    p.add_argument("--wavelengths", type=int, default=16)
    p.add_argument("--view-samples", type=int, default=32)
    p.add_argument("--dtype", choices=("float32", "float64"), default="float32")
    p.add_argument("--repeats", type=int, default=9)
    p.add_argument("--warmup", type=int, default=3)
    p.add_argument("--compile", action="store_true", help="also time a torch.compile'd chunk renderer")
    p.add_argument("--baseline", help="folder holding an older skyfit package to time in the same run")
    p.add_argument("--json", action="store_true")
    p.add_argument("--_child", action="store_true", help=argparse.SUPPRESS)
    a = p.parse_args(argv)

    import torch

    torch.set_num_threads(a.threads)
    devices = a.devices.split(",") if a.devices else ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])
    common = dict(size=a.size, n_wavelengths=a.wavelengths, view_samples=a.view_samples, dtype_name=a.dtype,
                  repeats=a.repeats, warmup=a.warmup)
    results = []
    if a.baseline:
        cmd = [sys.executable, __file__, "--_child", "--json", "--devices", ",".join(devices), "--threads", str(a.threads),
               "--size", str(a.size), "--wavelengths", str(a.wavelengths), "--view-samples", str(a.view_samples),
               "--dtype", a.dtype, "--repeats", str(a.repeats), "--warmup", str(a.warmup)]
        env = {**os.environ, "PYTHONPATH": os.pathsep.join([a.baseline, os.environ.get("PYTHONPATH", "")])}
        out = subprocess.run(cmd, env=env, capture_output=True, text=True, check=True).stdout
        results += [{**r, "label": "baseline"} for r in json.loads(out)]
    for dev in devices:
        results.append({**time_renders(dev, **common), "label": "current"})
        if a.compile:
            results.append({**time_renders(dev, compile_chunk=True, **common), "label": "current, compiled"})
    if a.json:
        print(json.dumps(results))
        return 0
    print(f"{a.size}x{a.size} fisheye, {a.wavelengths} wavelengths, taylor, {a.view_samples} view samples, {a.dtype}; "
          f"median (min) of {a.repeats} after {a.warmup} warm-up renders")
    for r in results:
        unit, k = ("ms", 1e3) if r["median_s"] < 0.1 else ("s", 1.0)
        print(f"  {r['label']:18s} {r['device']:5s} {r['device_name'][:40]:40s} {r['torch_threads']} thr  "
              f"{r['median_s'] * k:8.3f} {unit} ({r['min_s'] * k:.3f})   first {r['first_s']:.2f} s   "
              f"load {r['load_average_1min']}   torch {r['torch']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
