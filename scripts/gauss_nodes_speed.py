#!/usr/bin/env python
"""Side by side (docs/benchmarks.md, "Third pass: the Gauss nodes cached"): Bruneton build (PHOTO_TABLES, 6 wavelengths, float32, 2 threads) with the Gauss-Legendre rule
recomputed per call (before) and cached (after), alternating, 5 pairs."""
import time, torch, numpy as np
torch.set_num_threads(2)
import skyfit.scattering.multiple as M
from skyfit.atmosphere.config import atmosphere_from_config, load_yaml
from skyfit.scattering.bruneton_tables import TableSizes
from skyfit.fit.photo import PHOTO_TABLES
cached = M.ray_nodes
def uncached(n, rule, dtype, device):
    if rule == "trapezoid":
        return M._trapezoid(n, dtype, device)
    t, w = np.polynomial.legendre.leggauss(n + 1)
    return torch.as_tensor(0.5 * (t + 1.0), dtype=dtype, device=device), torch.as_tensor(0.5 * w, dtype=dtype, device=device)
atm = atmosphere_from_config(load_yaml('skyfit/configs/earth_hazy.yaml'), np.linspace(440, 660, 6), dtype=torch.float32)
sizes = TableSizes(*PHOTO_TABLES)
out = {"before": [], "after": []}
for rep in range(6):
    for name, fn in (("before", uncached), ("after", cached)):
        M.ray_nodes = fn
        t = time.perf_counter()
        with torch.no_grad():
            M.precompute(atm, orders=4, sizes=sizes, quadrature=M.Quadrature(ray_rule="gauss"), progress=False)
        if rep:
            out[name].append(time.perf_counter() - t)
for k, v in out.items():
    print(k, "median %.2f s" % np.median(v), [round(x, 2) for x in v])
print("ratio after/before of medians %.3f" % (np.median(out["after"]) / np.median(out["before"])))
