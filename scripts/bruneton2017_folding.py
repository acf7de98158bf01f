"""2017's folded storage vs skyfit's separate one, against a finer nu grid (docs/luts.md, "Where the difference comes from").

Bruneton 2017 stores multiple scattering divided by the Rayleigh phase at the texel's nu, inside the
Rayleigh texture; skyfit stores it apart. Both interpolate the same 8 nu texels; a table with 32 nu
texels (otherwise equal: 8 r x 32 mu x 16 mu_s, orders 2, Earth at 440/550/680 nm) is the reference.
Sky directions 1 deg x 15 deg, ground observer; error of the multiple term relative to the total radiance.

    .venv/bin/python scripts/bruneton2017_folding.py
"""
from __future__ import annotations

import numpy as np
import torch

from skyfit.atmosphere import load_atmosphere
from skyfit.scattering.multiple import precompute, Quadrature
from skyfit.scattering.bruneton_tables import TableSizes, scattering_texel_params, scattering_index, interpolate
from skyfit.scattering.phase import rayleigh_phase, mie_phase
from skyfit.geometry import ray_hits_ground
from skyfit.export.shader_reference import view_grid

torch.set_num_threads(2)
atm = load_atmosphere("earth", np.array([440., 550., 680.]))
Q = Quadrature(density_theta=8, density_phi=16, irradiance_theta=8, irradiance_phi=16, multiple_samples=20)
def tabs(nu):
    s = TableSizes(scattering_r=8, scattering_mu=32, scattering_mu_s=16, scattering_nu=nu, transmittance_mu=64, transmittance_r=16, irradiance_mu_s=16, irradiance_r=8)
    return precompute(atm, orders=2, sizes=s, quadrature=Q)
t8, t32 = tabs(8), tabs(32)
v = torch.tensor(view_grid(1.0, 15.0)); v = v[v[:,2] > 0]
for sz in (30., 60., 90.):
    z = np.radians(sz); sun = torch.tensor([0, np.sin(z), np.cos(z)])
    r = torch.full_like(v[:,2], atm.bottom_radius); mu = v[:,2]; mus = sun[2].expand_as(mu); nu = v @ sun
    hits = ray_hits_ground(r, mu, atm.bottom_radius)
    res = {}
    for name, t in (("8", t8), ("32", t32)):
        idx = scattering_index(r, mu, mus, nu, hits, atm.bottom_radius, atm.top_radius, t.mu_s_min, t.sizes)
        p = scattering_texel_params(atm.bottom_radius, atm.top_radius, t.mu_s_min, t.sizes, torch.float64, "cpu")
        folded = t.multiple / rayleigh_phase(p.nu).unsqueeze(-1)
        a, b, sr, sm = interpolate([t.multiple, folded, t.single_rayleigh, t.single_mie], idx)
        single = sr*rayleigh_phase(nu).unsqueeze(-1) + sm*mie_phase(nu, atm.mie_g, atm.mie_phase).unsqueeze(-1)
        res[name] = (a, b * rayleigh_phase(nu).unsqueeze(-1), single)
    ref = res["32"][0]; tot = ref + res["32"][2]
    for k, lab in ((0, "separate (skyfit)"), (1, "folded (2017)")):
        e = ((res["8"][k] - ref).abs() / tot)
        print(sz, lab, "vs NU=32: median %.4f max %.4f" % (e.median(), e.max()))
