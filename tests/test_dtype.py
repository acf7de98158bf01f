"""float32 against float64 (and CUDA against CPU) for the rendered radiance of every integrator.

The float64 render of the same integrator is the expectation; the tolerance
table holds, per integrator, (rtol, atol relative to the largest radiance of
the scene), as kornia's _DTYPE_PRECISIONS. Measured worst float32 relative
errors (CPU, 32 Gauss view samples, 3 wavelengths; the worst ray is a horizon
ray with the sun at 89°, where float32 radii, ulp 0.5 m at 6.4e6 m, limit the
altitude to ~4e-4 of the Mie scale height):

    ============== ======== ======== ========
    integrator     ground   5 km     space
    ============== ======== ======== ========
    quadrature     3.3e-4   6.1e-5   3.2e-5
    taylor         8.2e-4   6.1e-5   3.6e-5
    spline         2.9e-4   3.9e-5   3.2e-5
    bruneton_lut   3.9e-4   1.2e-4   3.2e-5
    chapman        2.9e-4   3.9e-5   3.2e-5
    ============== ======== ======== ========
"""
from __future__ import annotations

import functools
import math

import pytest
import torch

from skyfit.atmosphere import load_atmosphere
from skyfit.scattering import single_scattering
from skyfit.transmittance import INTEGRATORS, integrator_class, make_integrator

torch.set_num_threads(2)

R_BOTTOM, R_TOP = 6_360_000.0, 6_420_000.0
WAVELENGTHS = [440.0, 550.0, 680.0]

# float32 vs float64: (rtol, atol as a fraction of the scene's largest radiance).
_DTYPE_PRECISIONS = {
    "trapezoid": (1e-3, 1e-4),
    "midpoint": (1e-3, 1e-4),
    "simpson": (1e-3, 1e-4),
    "gauss": (1e-3, 1e-4),
    "taylor": (2.5e-3, 2e-4),
    "spline": (1e-3, 1e-4),
    "bruneton_lut": (1.5e-3, 2e-4),
    "chapman": (1e-3, 1e-4),
}
# The same device in float64 on CUDA: only libm differences.
_CUDA_F64 = (1e-9, 1e-12)

SETTINGS = {"spline": {"height_points": 16, "distance_points": 8}}
RENDERED = [n for n in INTEGRATORS if n != "height_fog"]  # the flat fog refuses full skies (tested below)


def _integrator(name: str):
    try:
        integrator_class(name)
    except (ModuleNotFoundError, AttributeError):
        pytest.skip(f"integrator module for {name!r} not implemented yet")
    return make_integrator(name, **SETTINGS.get(name, {}))


def _hor_space() -> float:
    return 180.0 - math.degrees(math.asin(R_TOP / (R_TOP + 1e5)))


# altitude [m], view zenith angles [deg], sun zenith angles [deg]
SCENES = {
    "ground": (10.0, [0, 20, 45, 60, 75, 85, 88, 89.5, 90, 30, 70, 89], (0.0, 45.0, 85.0, 89.0)),
    "5km": (5000.0, [0, 45, 89, 91, 92, 93, 120, 180], (30.0, 85.0, 93.0)),
    "space": (R_TOP - R_BOTTOM + 1e5, [180, 170, 160, 150, _hor_space() + 0.5, _hor_space() + 0.1], (30.0, 85.0)),
}


def _rays(scene: str, dtype, device="cpu"):
    alt, zen_deg, suns = SCENES[scene]
    zen = torch.tensor(zen_deg, dtype=torch.float64).deg2rad()
    az = torch.linspace(0, 2 * math.pi, len(zen_deg), dtype=torch.float64)
    parts = []
    for sz in suns:
        szr = math.radians(sz)
        mu = torch.cos(zen)
        mu_s = torch.full_like(mu, math.cos(szr))
        nu = torch.clamp(mu * mu_s + torch.sin(zen) * math.sin(szr) * torch.cos(az), -1.0, 1.0)
        parts.append((mu, mu_s, nu))
    mu, mu_s, nu = (torch.cat(t) for t in zip(*parts))
    r = torch.full_like(mu, R_BOTTOM + alt)
    return [t.to(dtype=dtype, device=device) for t in (r, mu, mu_s, nu)]


@functools.lru_cache(maxsize=None)
def _atm(dtype, device="cpu"):
    return load_atmosphere("earth", WAVELENGTHS, dtype=dtype, device=device)


def _render(name, scene, dtype, device="cpu"):
    return single_scattering(_atm(dtype, device), *_rays(scene, dtype, device), _integrator(name), view_samples=32, rule="gauss")


@functools.lru_cache(maxsize=None)
def _cpu64(name, scene):
    return _render(name, scene, torch.float64)


def _assert_close_to(out, expected, rtol, atol_frac):
    torch.testing.assert_close(out.double().cpu(), expected, rtol=rtol, atol=atol_frac * float(expected.max()))


@pytest.mark.parametrize("scene", list(SCENES))
@pytest.mark.parametrize("name", RENDERED)
def test_float32_matches_float64(name, scene):
    expected = _cpu64(name, scene)
    assert float(expected.max()) > 0
    out = _render(name, scene, torch.float32)
    assert out.dtype == torch.float32  # follows the input's dtype
    _assert_close_to(out, expected, *_DTYPE_PRECISIONS[name])


def test_height_fog_float32_matches_float64():
    """The flat fog's column on short near-ground segments (its regime), float32 vs float64."""
    integ = _integrator("height_fog")
    mu = torch.cos(torch.tensor([0.0, 30.0, 60.0, 89.0, 90.0, 100.0, 180.0], dtype=torch.float64).deg2rad())
    r = R_BOTTOM + torch.tensor([2.0, 10.0, 100.0, 2.0, 50.0, 30.0, 40.0], dtype=torch.float64)
    L = torch.tensor([300.0, 200.0, 100.0, 100.0, 150.0, 100.0, 40.0], dtype=torch.float64)
    H = torch.tensor([8000.0, 1200.0, 50.0], dtype=torch.float64)
    expected = integ.column(r, mu, L, H, R_BOTTOM, R_TOP)
    out = integ.column(*(t.float() for t in (r, mu, L, H)), R_BOTTOM, R_TOP)
    assert out.dtype == torch.float32
    # float32 r - R loses ~2e-4 m at 6.4e6 m: 4e-6 of the 50 m layer.
    torch.testing.assert_close(out.double(), expected, rtol=2e-5, atol=0.0)


needs_cuda = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")


@needs_cuda
@pytest.mark.cuda
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64], ids=["f32", "f64"])
@pytest.mark.parametrize("scene", list(SCENES))
@pytest.mark.parametrize("name", RENDERED)
def test_cuda_matches_cpu(name, scene, dtype):
    expected = _cpu64(name, scene)
    out = _render(name, scene, dtype, device="cuda")
    assert out.device.type == "cuda" and out.dtype == dtype
    rtol, atol = _CUDA_F64 if dtype == torch.float64 else _DTYPE_PRECISIONS[name]
    _assert_close_to(out, expected, rtol, atol)


@needs_cuda
@pytest.mark.cuda
@pytest.mark.parametrize("name", [n for n in RENDERED if n in ("gauss", "taylor", "chapman")])
def test_cuda_gradients_match_cpu(name):
    """d(sum radiance)/d(beta_R, H_M, g) on CUDA float64 equal those on the CPU."""

    def grads(device):
        atm0 = _atm(torch.float64, device)
        leaves = [atm0.rayleigh_scattering.clone().requires_grad_(True), atm0.mie_scale_height.clone().requires_grad_(True), atm0.mie_g.clone().requires_grad_(True)]
        atm = atm0.replace(rayleigh_scattering=leaves[0], mie_scale_height=leaves[1], mie_g=leaves[2])
        out = single_scattering(atm, *_rays("ground", torch.float64, device), _integrator(name), view_samples=16, rule="gauss")
        return [g.cpu() for g in torch.autograd.grad(out.sum(), leaves)]

    for gc, gg in zip(grads("cpu"), grads("cuda")):
        torch.testing.assert_close(gg, gc, rtol=1e-9, atol=0.0)
