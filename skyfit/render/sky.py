"""Render skies from directions: unit vectors or (zenith, azimuth) angles.

Fisheye images (a camera's pixels) are rendered one layer up, by
:func:`skyfit.camera.image.render_fisheye`.
"""
from __future__ import annotations

import torch
from torch import Tensor

from ..atmosphere import Atmosphere
from ..geometry import zenith_azimuth_to_enu
from ..scattering import single_scattering
from ..scattering.single import ray_parameters
from ..scattering.hillaire import hillaire_sky_radiance
from ..scattering.multiple import precompute, sky_radiance
from ..transmittance import OpticalDepthIntegrator


def render_vectors(
    atm: Atmosphere,
    view: Tensor,
    sun: Tensor,
    integrator: OpticalDepthIntegrator,
    altitude: float | Tensor = 0.0,
    orders: int = 1,
    tables=None,
    table_sizes=None,
    multiple: str = "bruneton",
    **kwargs,
) -> Tensor:
    """Spectral radiance seen from ``altitude`` along unit view vectors (local East, North, Up frame).

    ``orders=1`` is single scattering integrated along each view ray with
    ``integrator`` (:func:`skyfit.scattering.single_scattering`). ``orders >= 2``
    uses Bruneton's precomputed tables (:mod:`skyfit.scattering.multiple`): they
    are built here for ``atm`` (or passed in as ``tables`` to reuse them), and
    ``integrator`` is not used. ``multiple="hillaire"`` instead adds Hillaire
    2020's multiple-scattering LUT to the directly integrated single scattering
    (:mod:`skyfit.scattering.hillaire`; ``tables`` may then be a prebuilt LUT):
    cheaper, a few percent off for a high sun (docs/hillaire.md).

    Args:
        view: unit view directions, shape (..., 3). [1]
        sun: unit direction to the sun, shape (3,) or (..., 3). [1]
        integrator: optical-depth method (single scattering).
        altitude: observer height above the ground (may exceed the atmosphere). [m]
        orders: scattering orders; 1 = single scattering.
        tables: a :class:`~skyfit.scattering.multiple.PrecomputedAtmosphere` to reuse (orders >= 2).
        table_sizes: :class:`~skyfit.scattering.bruneton_tables.TableSizes` for a new precomputation.
        multiple: "bruneton" (full orders) or "hillaire" (approximation) for orders >= 2.
        **kwargs: passed to :func:`skyfit.scattering.single_scattering` (orders 1) or
            :func:`skyfit.scattering.multiple.sky_radiance` (``ground``, ``sun_disk``, ``below_mu_s_min``).

    Returns:
        shape (..., W). [W/(m^2 sr nm)]
    """
    if not (isinstance(orders, int) and orders >= 1):
        raise ValueError(f"orders must be an integer >= 1, got {orders!r}")
    r, mu, mu_s, nu = ray_parameters(atm, view, sun, altitude)
    if orders == 1:
        return single_scattering(atm, r, mu, mu_s, nu, integrator, **kwargs)
    if multiple == "hillaire":
        return hillaire_sky_radiance(atm, r, mu, mu_s, nu, integrator, lut=tables, **kwargs)
    if multiple != "bruneton":
        raise ValueError(f"unknown multiple-scattering method {multiple!r}; valid: bruneton, hillaire")
    if tables is None:
        tables = precompute(atm, orders=orders, sizes=table_sizes)
    elif tables.orders < orders:
        raise ValueError(f"tables hold {tables.orders} orders, {orders} requested")
    extra = {k: kwargs[k] for k in ("ground", "sun_disk", "below_mu_s_min") if k in kwargs}
    return sky_radiance(tables, atm, r, mu, mu_s, nu, orders=None if tables.orders == orders else orders, **extra)


def render_directions(
    atm: Atmosphere,
    zenith: Tensor,
    azimuth: Tensor,
    sun_zenith: float | Tensor,
    sun_azimuth: float | Tensor,
    integrator: OpticalDepthIntegrator,
    altitude: float | Tensor = 0.0,
    orders: int = 1,
    **kwargs,
) -> Tensor:
    """Spectral radiance in directions (zenith, azimuth), angles in rad (see :func:`render_vectors`).

    Args:
        zenith, azimuth: view directions (azimuth clockwise from North), shape (...). [rad]
        sun_zenith, sun_azimuth: sun direction, scalars or shape (...). [rad]

    Returns:
        shape (..., W). [W/(m^2 sr nm)]
    """
    T = lambda v: torch.as_tensor(v, dtype=atm.dtype, device=atm.device)  # noqa: E731
    view = zenith_azimuth_to_enu(T(zenith), T(azimuth))
    sun = zenith_azimuth_to_enu(T(sun_zenith), T(sun_azimuth))
    return render_vectors(atm, view, sun, integrator, altitude, orders, **kwargs)
