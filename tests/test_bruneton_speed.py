"""The geometry-cached precomputation (skyfit.scattering.multiple.precompute) against the
implementation it replaced (skyfit.scattering.bruneton_reference.precompute_reference).

The rewrite only reorders arithmetic (corners computed once, separable and grid_sample
lookups, Rayleigh phase by its moments), so in float64 every table must agree to rounding.
Measured: differences < 1e-14 of each table's peak; per texel (texels above 1e-6 of the
peak) up to 1.1e-9 (Delta S_2 at SMALL); bounds 1e-12 of the peak and 1e-8 per texel
(the issue requires 1e-6). Texels below 1e-6 of the peak: see _max_rel. Independent physics checks of the tables are in
tests/test_multiple.py; this file pins the equivalence, the gradients and the progress bar.
"""
import pytest
import torch

from skyfit.atmosphere import load_atmosphere
from skyfit.scattering.bruneton_reference import precompute_reference
from skyfit.scattering.bruneton_tables import TableSizes
from skyfit.scattering.multiple import Quadrature, precompute

F64 = torch.float64
TINY = TableSizes(transmittance_mu=32, transmittance_r=8, irradiance_mu_s=8, irradiance_r=4,
                  scattering_r=4, scattering_mu=8, scattering_mu_s=4, scattering_nu=4)
QUAD = Quadrature(transmittance_samples=40, single_samples=8, multiple_samples=8,
                  density_theta=4, density_phi=8, irradiance_theta=3, irradiance_phi=8)
SMALL = TableSizes(transmittance_mu=64, transmittance_r=16, irradiance_mu_s=16, irradiance_r=4,
                   scattering_r=6, scattering_mu=16, scattering_mu_s=8, scattering_nu=6)
TABLES = ("transmittance_columns", "direct_irradiance", "irradiance", "single_rayleigh", "single_mie", "multiple")


def _max_rel(a: torch.Tensor, b: torch.Tensor) -> float:
    """Max relative difference per texel, over texels above 1e-6 of the peak (below it: the peak test).

    In twilight a table falls by decades from one texel to the next; a texture coordinate
    rounded differently by 1e-16 (grid_sample's normalised coordinates) then moves a value
    at 1e-11 of the peak by up to 4e-5 of itself (1e-16 of the peak)."""
    peak = float(b.abs().max())
    assert float((a - b).abs().max()) <= 1e-12 * peak
    return float(((a - b).abs() / b.abs().clamp_min(max(1e-6 * peak, 1e-300))).max())


@pytest.mark.parametrize("phase,sizes,quad", [("cornette_shanks", TINY, QUAD), ("henyey_greenstein", TINY, QUAD),
                                              ("cornette_shanks", SMALL, None)])
def test_fast_precompute_equals_reference(phase, sizes, quad):
    atm = load_atmosphere("earth", [440.0, 550.0, 680.0]).replace(mie_phase=phase)
    kw = dict(orders=4, sizes=sizes, quadrature=quad, keep_orders=True)
    with torch.no_grad():
        new = precompute(atm, progress=False, **kw)
        old = precompute_reference(atm, **kw)
    for name in TABLES:
        assert _max_rel(getattr(new, name), getattr(old, name)) < 1e-8, name
    for k, (a, b) in enumerate(zip(new.order_scattering + new.order_irradiance, old.order_scattering + old.order_irradiance)):
        assert _max_rel(a, b) < 1e-8, k


def test_negative_g_and_ground_bounce_equal_reference():
    atm = load_atmosphere("earth", [550.0]).replace(mie_g=torch.tensor(-0.6, dtype=F64),
                                                    ground_albedo=torch.tensor([0.8], dtype=F64))
    with torch.no_grad():
        new = precompute(atm, orders=3, sizes=TINY, quadrature=QUAD, progress=False)
        old = precompute_reference(atm, orders=3, sizes=TINY, quadrature=QUAD)
    for name in TABLES:
        assert _max_rel(getattr(new, name), getattr(old, name)) < 1e-8, name


def test_gradients_flow_and_equal_reference():
    """Autograd through the checkpointed fast path equals that of the reference (float64)."""
    base = load_atmosphere("earth", [440.0, 680.0])
    grads = []
    for fn in (precompute, precompute_reference):
        g = torch.tensor(0.76, dtype=F64, requires_grad=True)
        beta = base.rayleigh_scattering.clone().requires_grad_(True)
        atm = base.replace(mie_g=g, rayleigh_scattering=beta)
        kw = dict(progress=False) if fn is precompute else {}
        t = fn(atm, orders=3, sizes=TINY, quadrature=QUAD, chunk_bytes=2e5, **kw)
        (t.multiple.sum() + t.irradiance.sum() * 1e-3).backward()
        grads.append(torch.cat([g.grad.reshape(1), beta.grad]))
    assert torch.isfinite(grads[0]).all() and (grads[0] != 0).all()
    torch.testing.assert_close(grads[0], grads[1], rtol=1e-10, atol=0.0)


def test_progress_bar_on_request_and_off_by_default(capsys):
    atm = load_atmosphere("earth", [550.0])
    with torch.no_grad():
        precompute(atm, orders=2, sizes=TINY, quadrature=QUAD, progress=True)
        assert "Bruneton tables" in capsys.readouterr().err
        precompute(atm, orders=2, sizes=TINY, quadrature=QUAD)  # stderr is not a terminal under pytest
        assert capsys.readouterr().err == ""
