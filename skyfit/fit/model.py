"""The forward model of a fit: parameters -> atmosphere -> radiance -> each observation's channels.

:class:`SkyModel` holds the renderer's settings; :meth:`SkyModel.renderer` is the
single place where radiance is computed for fitting and evaluation (orders > 1 plug
in there: precompute once per atmosphere, then look up per observation).
:class:`FitProblem` ties a :class:`~skyfit.fit.parameters.Parameterisation`, a
SkyModel, observations and a :class:`~skyfit.fit.losses.Loss` into a scalar
objective of the unconstrained vector x.
"""
from __future__ import annotations

import dataclasses
import math
from typing import Callable, Sequence

import numpy as np
import torch
from torch import Tensor

from ..atmosphere import Atmosphere
from ..camera.fisheye import zenith_azimuth_to_enu
from ..camera.sensor import spectral_response_matrix
from ..render.colour import srgb_luminance_weights, xyz_to_srgb_matrix, spectral_to_xyz_matrix
from ..transmittance import OpticalDepthIntegrator, prepare_columns
from .data import DataError, Observation
from .losses import Loss
from .parameters import FitError, Parameterisation

Renderer = Callable[[Tensor, Tensor], Tensor]


MULTIPLE_METHODS = ("hillaire", "bruneton", "bruneton_lagged")


@dataclasses.dataclass
class SkyModel:
    """Renderer settings shared by every observation of a fit.

    Attributes:
        integrator: optical-depth method (single scattering, and T(x, y) of Hillaire's term).
        orders: scattering orders (1 = single scattering; >= 2 adds multiple scattering).
        view_samples: samples of the view-ray integral.
        rule: outer quadrature rule.
        ground: add the sunlit Lambertian ground for rays that hit it.
        chunk_bytes: working memory per chunk (None: the renderer's default). [bytes]
        multiple: "hillaire" (Hillaire 2020's LUT, rebuilt per atmosphere; all orders >= 2
            by its geometric series, so ``orders`` only switches it on) or "bruneton"
            (Bruneton & Neyret 2008 tables with ``orders`` orders at ``table_sizes``, rebuilt per
            atmosphere) or "bruneton_lagged" (the renderer gives single scattering; the caller holds
            the tables' orders >= 2 as a factor on it, frozen per fit and refreshed at its result:
            ``FitProblem.frozen_factor``, :func:`skyfit.fit.photo.lagged_fit`; docs/fitting.md).
        lut_size, lut_directions, lut_samples: Hillaire LUT (n_h, n_mu_s), sphere directions
            and steps per direction (docs/hillaire.md; the paper: 32 x 32, 64, 20). The
            defaults 16 x 16 texels, 64 directions, 20 steps with a 64 x 16 sun-transmittance
            table differ from the paper's LUT by 0.34 % (median |error| of Psi over
            mu_s > -0.25; 0.17 s per build for 16 wavelengths on one core). 32 directions and
            12 steps build in 0.07 s but differ by 2.2 %, which biased a 128 x 128, 1 %-noise
            fit by 7-9 % in the albedo and the aerosol (docs/fitting.md, "Multiple scattering").
        table_sizes: Bruneton :class:`~skyfit.scattering.bruneton_tables.TableSizes` fields as
            a tuple (transmittance mu, r, irradiance mu_s, r, scattering r, mu, mu_s, nu);
            None = a reduced set that precomputes in seconds on a CPU.
        ray_rule: the Bruneton tables' view-ray rule (:attr:`skyfit.scattering.multiple.Quadrature.ray_rule`):
            2017's ``trapezoid`` or ``gauss``, which resolves a thin aerosol layer with the same nodes.
        density_directions: (theta, phi) or (theta, phi, zenith) incident directions of the Bruneton tables'
            scattering density (:attr:`skyfit.scattering.multiple.Quadrature.density_theta`, ``density_phi``,
            ``density_zenith``: the first ``zenith`` theta bands split in two): 2017's 16 x 32, or more where a
            hazy sky's multiple scattering at the zenith must converge (docs/photos.md, "A generator with
            converged multiple scattering"; docs/multiple_scattering.md, "The density directions' pole").
    """

    integrator: OpticalDepthIntegrator
    orders: int = 1
    view_samples: int = 32
    rule: str = "trapezoid"
    ground: bool = True
    chunk_bytes: float | None = None
    multiple: str = "hillaire"
    lut_size: tuple[int, int] = (16, 16)
    lut_directions: int = 64
    lut_samples: int = 20
    table_sizes: tuple[int, ...] | None = None
    ray_rule: str = "trapezoid"
    density_directions: tuple[int, ...] = (16, 32)
    spacing: str = "uniform"
    """Single scattering: view-ray nodes ``uniform`` in distance or ``geometric``
    (:func:`skyfit.scattering.single.geometric_nodes`; :func:`skyfit.render`'s default)."""
    sun_window: bool = False
    """Bruneton tables for one sun (:meth:`sun_tables`: the scattering table's mu_s axis over the sun's zenith angle
    +- 5 deg in texels 2 deg apart instead of 2017's axis, whose texels give a high sun about one and put a hazy sky's
    orders >= 2 at the zenith 2x high; docs/multiple_scattering.md, "One sun's mu_s window"); used by
    :func:`skyfit.render` and :func:`skyfit.envmap` (their default Bruneton renderer), which render one sun. ``table_sizes``' mu_s count is then unused."""
    lut_method: str = "cached"
    """How Hillaire's LUT is evaluated (:data:`skyfit.scattering.hillaire.LUT_METHODS`; equal to 1e-12):
    ``rows`` is the slower original, kept for before/after timings (scripts/kider_fit_speed.py)."""

    REDUCED_TABLES = (64, 16, 32, 8, 8, 32, 8, 4)
    """Bruneton table sizes for fits on a CPU (docs/fitting.md, "Multiple scattering")."""

    def __post_init__(self) -> None:
        if self.multiple not in MULTIPLE_METHODS:
            raise FitError(f"unknown multiple-scattering method {self.multiple!r}; valid: {', '.join(MULTIPLE_METHODS)}")
        if not (isinstance(self.orders, int) and self.orders >= 1):
            raise FitError(f"orders must be an integer >= 1, got {self.orders!r}")
        self.lut_size = tuple(int(v) for v in self.lut_size)  # type: ignore[assignment]
        if self.table_sizes is not None:
            self.table_sizes = tuple(int(v) for v in self.table_sizes)
        check_ray_rule(self.ray_rule, "ray_rule")
        self.density_directions = check_density_directions(self.density_directions, "density_directions")

    def quadrature(self):
        """The Bruneton precomputation's sample counts: 2017's, with this model's :attr:`ray_rule` and
        :attr:`density_directions`."""
        from ..scattering.multiple import Quadrature

        theta, phi, *zenith = self.density_directions
        return Quadrature(ray_rule=self.ray_rule, density_theta=theta, density_phi=phi, density_zenith=zenith[0] if zenith else 0)

    @property
    def lagged(self) -> bool:
        """Multiple scattering held outside the renderer: ``bruneton_lagged``'s factor, frozen by the caller."""
        return self.orders > 1 and self.multiple == "bruneton_lagged"

    def factor_model(self) -> "SkyModel":
        """The Bruneton tables behind ``bruneton_lagged``'s factor (:func:`skyfit.fit.photo.freeze_tables`)."""
        return dataclasses.replace(self, multiple="bruneton")

    def tables(self, atm: Atmosphere):
        """Multiple-scattering tables for ``atm`` (None for single scattering, and for ``bruneton_lagged``,
        whose factor on the single scattering the fit freezes and refreshes: :func:`skyfit.fit.photo.lagged_fit`)."""
        from ..scattering.bruneton_tables import TableSizes

        if self.orders == 1 or self.lagged:
            return None
        if self.multiple == "hillaire":
            from ..scattering.hillaire import hillaire_lut

            return hillaire_lut(atm, size=self.lut_size, directions=self.lut_directions, samples=self.lut_samples,
                                transmittance_sizes=TableSizes(transmittance_mu=64, transmittance_r=16), method=self.lut_method)
        from ..scattering.multiple import precompute

        sizes = TableSizes(*(self.table_sizes or self.REDUCED_TABLES))
        return precompute(atm, orders=self.orders, sizes=sizes, quadrature=self.quadrature(),
                          progress=False)  # once per loss evaluation: no bar

    def sun_tables(self, atm: Atmosphere, sun_zenith_deg: float, altitude_m: float = 0.0, *,
                   margin_deg: float | None = None, texels: int | None = None):
        """:meth:`tables`, built for one sun where :attr:`sun_window` asks it of Bruneton tables and the observer is
        inside the atmosphere (one in space sees the sun from where its rays enter, elsewhere on the sphere).

        ``margin_deg``, ``texels``: the window's margin and its texel count instead of
        :func:`~skyfit.scattering.bruneton_tables.sun_window`'s (its margin, texels at most its spacing apart)."""
        inside = altitude_m < float(atm.top_radius - atm.bottom_radius)
        if not (self.sun_window and self.orders > 1 and self.multiple == "bruneton" and inside):
            return self.tables(atm)
        from ..scattering.bruneton_tables import TableSizes, sun_window
        from ..scattering.multiple import precompute

        sizes = TableSizes(*(self.table_sizes or self.REDUCED_TABLES))
        kw = {} if margin_deg is None else {"margin_deg": margin_deg}
        mu_s_range, n = sun_window(sun_zenith_deg, sun_zenith_deg, sizes.scattering_mu_s, **kw)
        return precompute(atm, orders=self.orders, sizes=dataclasses.replace(sizes, scattering_mu_s=texels or n),
                          mu_s_range=mu_s_range, quadrature=self.quadrature(), progress=False)

    def renderer(self, atm: Atmosphere, altitude_m: float = 0.0, tables=None) -> Renderer:
        """A function ``(directions (N, 3), sun (3,) or (N, 3)) -> radiance (N, W)`` for ``atm``.

        Called once per atmosphere (one loss evaluation), then once per observation:
        precomputation that depends only on the atmosphere happens here (the optical-depth
        integrator's preparation; for orders > 1 the multiple-scattering tables, unless
        ``tables`` from :meth:`tables` are passed in to share them between altitudes).
        """
        from ..render.sky import render_vectors

        if self.orders > 1 and not self.lagged:
            tables = self.tables(atm) if tables is None else tables

            def render_ms(directions: Tensor, sun: Tensor) -> Tensor:
                # Bruneton's lookup ignores view_samples and rule (render_vectors passes it only ground).
                return render_vectors(atm, directions, sun, self.integrator, altitude_m, self.orders, tables=tables,
                                      multiple=self.multiple, view_samples=self.view_samples, rule=self.rule,
                                      ground=self.ground)

            return render_ms
        column_fn = prepare_columns(self.integrator, atm)

        def render(directions: Tensor, sun: Tensor) -> Tensor:  # single scattering (bruneton_lagged: its live part)
            return render_vectors(
                atm, directions, sun, self.integrator, altitude_m, 1, view_samples=self.view_samples,
                rule=self.rule, ground=self.ground, chunk_bytes=self.chunk_bytes, column_fn=column_fn,
                spacing=self.spacing,
            )

        return render

    def settings(self) -> dict:
        out = {"orders": self.orders, "view_samples": self.view_samples, "rule": self.rule, "ground": self.ground}
        if self.orders == 1 and self.spacing != "uniform":
            out["spacing"] = self.spacing
        if self.orders > 1:
            out["multiple"] = self.multiple
            if self.multiple == "hillaire":
                out.update(lut_size=list(self.lut_size), lut_directions=self.lut_directions, lut_samples=self.lut_samples)
            else:
                out["table_sizes"] = list(self.table_sizes or self.REDUCED_TABLES)
                if self.ray_rule != "trapezoid":
                    out["ray_rule"] = self.ray_rule
                if self.density_directions != (16, 32):
                    out["density_directions"] = list(self.density_directions)
                if self.sun_window:
                    out["sun_window"] = True
        return out


def check_ray_rule(value, where: str) -> str:
    """``value`` if it is a Bruneton view-ray rule (:data:`skyfit.scattering.multiple.RAY_RULES`); else FitError
    naming ``where``."""
    from ..scattering.multiple import RAY_RULES

    if value not in RAY_RULES:
        raise FitError(f"{where} must be one of {', '.join(RAY_RULES)}, got {value!r}")
    return value


def check_density_directions(value, where: str) -> tuple[int, ...]:
    """``value`` as (theta, phi) or (theta, phi, zenith) incident directions of the scattering density: integers,
    theta and phi >= 2, zenith in [0, theta] (the theta bands split in two from the zenith). Raises FitError naming
    ``where`` otherwise."""
    ok = (isinstance(value, (list, tuple)) and len(value) in (2, 3)
          and all(isinstance(v, int) and not isinstance(v, bool) for v in value)
          and all(v >= 2 for v in value[:2]) and (len(value) == 2 or 0 <= value[2] <= value[0]))
    if not ok:
        raise FitError(f"{where} must be [theta, phi] or [theta, phi, zenith]: integers, theta and phi >= 2, zenith in "
                       f"[0, theta], got {value!r}")
    out = tuple(int(v) for v in value)
    return out[:2] if len(out) == 3 and out[2] == 0 else out  # no split bands: 2017's rule, written as such


def channel_matrix(model_wavelengths: Tensor, obs: Observation) -> Tensor:
    """Matrix M (W, C) with obs channels = model spectral radiance (N, W) @ M.

    Spectral data select their wavelengths from the model grid (each must be on it,
    to 1e-6 nm); RGB data take CIE 1931 XYZ (683 lm/W) then linear sRGB
    (:mod:`skyfit.render.colour`).
    """
    lam = model_wavelengths
    if obs.kind == "rgb" and obs.metadata.get("response") is not None:
        # a camera's own spectral sensitivities (wavelengths [nm] (K,), sensitivities (K, 3)) instead of CIE -> sRGB
        wl, sens = obs.metadata["response"]
        return spectral_response_matrix(lam, torch.as_tensor(np.asarray(sens), dtype=lam.dtype, device=lam.device),
                                        torch.as_tensor(np.asarray(wl), dtype=lam.dtype, device=lam.device))
    if obs.kind == "rgb":
        xyz = spectral_to_xyz_matrix(lam)
        return xyz @ torch.as_tensor(xyz_to_srgb_matrix(), dtype=lam.dtype, device=lam.device).T
    wl = obs.wavelengths.to(lam.dtype)
    diff = (wl[None, :] - lam[:, None]).abs()
    hit = diff < 1e-6
    missing = ~hit.any(0)
    if bool(missing.any()):
        raise DataError(f"{obs.source}: wavelength(s) {wl[missing].tolist()} nm are not on the model grid")
    return hit.to(lam.dtype)


def sun_zenith_span(problem: "FitProblem", x: Tensor | None = None) -> tuple[float, float] | None:
    """The smallest and largest sun zenith angle over ``problem``'s observations at ``x`` (default its starting
    values) [deg]: the suns a fit's Bruneton tables must span. None where a ``sun_zenith_offset`` is fitted (the sun
    moves with it), an observer is at or above the top of the atmosphere (the tables are looked up where its rays
    enter, under other sun angles: :meth:`SkyModel.sun_tables`'s rule), or there are no observations."""
    base = problem.param.base
    top = float(base.top_radius - base.bottom_radius)
    if ("sun_zenith_offset" in problem.param.free or not problem.observations
            or any(float(o.altitude_m) >= top for o in problem.observations)):
        return None
    with torch.no_grad():
        x = problem.param.initial_vector(base.dtype, base.device) if x is None else x
        ph = problem.param.to_physical(x)
        cos = torch.cat([problem.sun_vectors(ph, i).reshape(-1, 3)[:, 2] for i in range(len(problem.observations))])
    zen = torch.rad2deg(torch.arccos(cos.clamp(-1.0, 1.0)))
    return float(zen.min()), float(zen.max())


def aerosol_log_depth(atm: Atmosphere) -> Tensor:
    """ln of the aerosol's vertical optical depth at each of the atmosphere's wavelengths, shape (W,). [1]"""
    return torch.log(atm.mie_extinction * atm.mie_column_height)


def lens_directions(d: Tensor, k: Tensor) -> Tensor:
    """Directions (..., 3) about the +z (optical) axis with their angle theta_p from it moved to
    theta = theta_p + k theta_p ((pi/2)^2 - theta_p^2), azimuth kept: a lens that departs from its nominal
    projection (``lens_radial`` k), the axis and the 90-degree circle (the image circle's calibration) fixed.

    To first order in k this is a Kannala-Brandt lens r = f (theta + k1 theta^3) seen as equidistant with k1 = k
    (Kannala & Brandt 2006, IEEE TPAMI 28, 1335, eq. 6: their odd polynomial in theta); on any classical projection
    it is the smallest radial departure that keeps centre and horizon: a cubic, zero at both. Monotonic for k in
    (-0.4, 0.2). Written here: no library moves fisheye rays by a radial law on the sphere. [1]
    """
    x, y, z = d.unbind(-1)
    h = torch.sqrt((x * x + y * y).clamp_min(1e-30))
    theta = torch.atan2(h, z)
    q = (math.pi / 2) ** 2 - theta * theta
    new = theta + k * theta * q
    # sin(new) / sin(theta), -> 1 + k (pi/2)^2 on the axis (where h -> 0)
    near = theta < 1e-6
    ratio = torch.where(near, 1.0 + k * q, torch.sin(new) / torch.where(near, torch.ones_like(h), torch.sin(theta)))
    return torch.stack([x * ratio, y * ratio, torch.cos(new)], -1)


def applied_lens(problem: "FitProblem", phys: dict, i: int) -> Tensor | None:
    """Observation i's ``lens_radial`` k where the problem applies it (free, or held at a value other than 0), else
    None; shared by :meth:`FitProblem.view_directions` and a photo's sun datum."""
    k = phys.get("lens_radial")
    if k is None:
        return None
    k = k[i] if k.ndim else k
    return k if "lens_radial" in problem.param.free or float(k) != 0.0 else None


def tilt_directions(d: Tensor, tilt_north: Tensor, tilt_east: Tensor) -> Tensor:
    """Instrument directions (..., 3) in the world frame of an instrument whose zenith axis is tilted by
    ``tilt_north`` toward North and ``tilt_east`` toward East: R_y(tilt_east) R_x(-tilt_north) d (ENU axes). [rad]"""
    cn, sn, ce, se = torch.cos(tilt_north), torch.sin(tilt_north), torch.cos(tilt_east), torch.sin(tilt_east)
    x, y, z = d.unbind(-1)
    y1, z1 = y * cn + z * sn, -y * sn + z * cn  # R_x(-tilt_north): the zenith goes to (0, sn, cn)
    return torch.stack([x * ce + z1 * se, y1, -x * se + z1 * ce], -1)  # R_y(tilt_east)


class FitProblem:
    """Observations sharing one atmosphere, each with its own sun and nuisance values.

    Args:
        parameterisation: maps x to physical values and the atmosphere.
        model: renderer settings.
        observations: the data (converted to the base atmosphere's dtype and device).
        loss: the loss of each observation's channels.
        base_sun_distance_au: Earth-Sun distance the base atmosphere's solar spectrum is for;
            an observation with a known distance d is scaled by (base / d)^2. [AU]
    """

    def __init__(self, parameterisation: Parameterisation, model: SkyModel, observations: Sequence[Observation],
                 loss: Loss, base_sun_distance_au: float = 1.0):
        atm = parameterisation.base
        if len(observations) != parameterisation.n_observations:
            raise FitError(f"{len(observations)} observations but the parameterisation expects {parameterisation.n_observations}")
        self.param = parameterisation
        self.model = model
        self.loss = loss
        self.observations = [o.to(atm.dtype, atm.device) for o in observations]
        self.matrices = [channel_matrix(atm.wavelengths, o) for o in self.observations]
        self.solar_scale = [
            1.0 if o.sun_distance_au is None else (base_sun_distance_au / o.sun_distance_au) ** 2 for o in self.observations
        ]
        self.n_elements = sum(int(o.mask.sum()) * len(o.channels) for o in self.observations)
        self.n_evaluations = 0
        self.frozen_tables = None
        """Multiple-scattering tables to use instead of rebuilding them per evaluation (a lagged fit:
        :func:`skyfit.fit.photo.lagged_fit` freezes Hillaire's LUT at each fit's start and refreshes it)."""
        self.frozen_factor: list[Tensor] | None = None
        """Per observation, a factor (N_i, W) on the rendered radiance: all orders over the first, computed
        elsewhere and held fixed (:func:`skyfit.fit.photo.lagged_fit` with Bruneton's tables). [1]"""
        self.frozen_slope: tuple[list[Tensor], Tensor] | None = None
        """(D per observation (N_i, W), ln tau_0 (W,)): the frozen factor's first-order dependence on the aerosol
        optical depth (:meth:`frozen_factor_at`), or None (held fixed)."""
        self.frozen_slope_g: tuple[list[Tensor], float] | None = None
        """(D_g per observation (N_i, W), g_0): the frozen factor's first-order dependence on the aerosol asymmetry g
        (:meth:`frozen_factor_at`), or None (held fixed in g)."""
        self.frozen_follow: tuple[list[Tensor], object] | None = None
        """(the frozen factor it belongs to, f(phys, i) -> (N_i, W)): the factor re-evaluated at the current view
        and sun geometry (:func:`skyfit.fit.photo.multiple_from_tables`), used while :attr:`frozen_factor` is that
        factor and the geometry is fitted (heading, tilt, lens); None: the factor stays on each sample."""
        self.held_ratio: list[Tensor] | None = None
        """Per observation, a ratio (N_i, W) on the model after :attr:`frozen_factor`, held fixed: the error budget's
        lagged refits of a fit whose reference keeps the fit's own multiple-scattering factor, so that the factor
        goes on following the aerosol and the camera (:func:`skyfit.fit.budget.held_reference`). [1]"""

    # -- forward ----------------------------------------------------------------
    def sun_vectors(self, phys: dict, i: int) -> Tensor:
        """Observation i's sun with its fitted offsets, shape (3,) or (N, 3)."""
        o, nu = self.observations[i], self.param.nuisance(phys, i)
        return zenith_azimuth_to_enu(o.sun_zenith + nu["sun_zenith_offset"], o.sun_azimuth + nu["sun_azimuth_offset"])

    def view_directions(self, phys: dict, i: int) -> Tensor:
        """Observation i's used view directions in the world frame, shape (N_i, 3).

        Image data with ``lens_radial`` free or held at a value other than 0 (:func:`applied_lens`) first move each
        direction radially about the optical axis (:func:`lens_directions`; the observation's directions are those
        of its camera's nominal projection).

        The instrument's zenith axis is tilted by ``camera_tilt_north`` toward North and
        ``camera_tilt_east`` toward East: world = R_y(tilt_east) R_x(-tilt_north) instrument
        (ENU axes; R_x, R_y the right-handed rotations about East and North). A rigid rotation,
        unlike a sun zenith offset: every view moves with it, horizon and sun alike.
        """
        o = self.observations[i]
        tn, te = phys["camera_tilt_north"], phys["camera_tilt_east"]
        if tn.ndim:
            tn, te = tn[i], te[i]
        d = o.directions[o.mask]
        k = applied_lens(self, phys, i) if o.image_radius is not None else None
        if k is not None:
            d = lens_directions(d, k)  # image data: the lens's own projection
        return tilt_directions(d, tn, te)

    def frozen_factor_at(self, atm: Atmosphere, i: int, phys: dict | None = None) -> Tensor:
        """Observation i's frozen multiple-scattering factor F (N_i, W), followed to first order in the aerosol
        optical depth when :attr:`frozen_slope` = (D, ln tau_0(lambda)) is set: F = 1 + (F_0 - 1) (tau(lambda) /
        tau_0(lambda))^D, D the logarithmic derivative of the multiple-over-single ratio per sample and wavelength
        (:func:`skyfit.fit.photo.aod_slope`) and tau(lambda) the aerosol's optical depth at each wavelength
        (extinction x column height). Radiative transfer is monochromatic, so F at a wavelength follows that
        wavelength's optical depth: one slope covers the AOD and the Angstrom exponent alike. The fit then sees how
        the multiple scattering's share grows with the aerosol, which a factor held fixed hides. With
        :attr:`frozen_slope_g` = (D_g, g_0) the exponent also has D_g (g - g_0), g the aerosol's asymmetry
        (:func:`skyfit.fit.photo.g_slope`): the share of multiple scattering in a sample's radiance moves with g as
        the single scattering's phase does, and a factor held in g let a low-sun photo's g creep 0.78 -> 0.87 with
        its AOD 38 % high (docs/photos.md).

        With ``phys`` and :attr:`frozen_follow` set for this factor, F_0 is that of the current view and sun geometry
        rather than of each sample's geometry when it was frozen: a factor held per sample while the fit turns the
        camera (heading, tilt) keeps the multiple-scattering pattern where the camera was, and the lagged refreshes
        then chased it (a hazy photo under a high sun drifted 20 deg in heading, its loss rising 0.77 -> 4.1 over the
        refreshes; docs/photos.md). [1]"""
        follow = self.frozen_follow
        if phys is not None and follow is not None and follow[0] is self.frozen_factor:
            f = follow[1](phys, i)
        else:
            f = self.frozen_factor[i]
        exponent = None
        if self.frozen_slope is not None:
            slope, log_tau0 = self.frozen_slope
            exponent = slope[i] * (aerosol_log_depth(atm) - log_tau0)
        if self.frozen_slope_g is not None:
            slope_g, g0 = self.frozen_slope_g
            term = slope_g[i] * (atm.mie_g - g0)
            exponent = term if exponent is None else exponent + term
        return f if exponent is None else 1.0 + (f - 1.0) * torch.exp(exponent)

    def spectra(self, phys: dict, atm: Atmosphere | None = None) -> list[Tensor]:
        """Model spectral radiance for every used sample of each observation (N_i, W), no exposure."""
        atm = self.param.atmosphere(phys) if atm is None else atm
        out, renderers = [], {}
        # once per atmosphere, shared by every altitude (None: single scattering); or frozen by the caller
        tables = self.model.tables(atm) if self.frozen_tables is None else self.frozen_tables
        for i, o in enumerate(self.observations):
            if o.altitude_m not in renderers:
                renderers[o.altitude_m] = self.model.renderer(atm, o.altitude_m, tables)
            sun = self.sun_vectors(phys, i)
            if sun.ndim == 2:
                sun = sun[o.mask]
            rad = renderers[o.altitude_m](self.view_directions(phys, i), sun)
            if self.frozen_factor is not None:
                rad = rad * self.frozen_factor_at(atm, i, phys)
            if self.held_ratio is not None:
                rad = rad * self.held_ratio[i]
            out.append(rad * self.solar_scale[i])
        return out

    @property
    def _saturates(self) -> bool:
        """Whether the camera's saturations act: free, or set away from 1 (decided from the parameterisation, so that
        an evaluation reads no parameter value back from the device)."""
        p = self.param
        return any(n in p.free or bool(np.any(np.asarray(p.values[n], dtype=float) != 1.0))
                   for n in ("saturation_red", "saturation_blue"))

    def predict_unscaled(self, phys: dict) -> list[Tensor]:
        """Each observation's channels for its used samples, (N_i, C_i), exposure 1.

        RGB image data go through the camera's response: its colour rendering (red becomes Y + ``saturation_red``
        (R - Y) and blue Y + ``saturation_blue`` (B - Y) about the sample's luminance Y, sRGB's weights; green as
        rendered), channel gains (1 for green, ``gain_red``, ``gain_blue``: a white balance) and the relative illumination
        ``1 + vignetting r^2`` at each sample's normalised image radius r
        (:attr:`Observation.image_radius`); other data are left as rendered.

        The saturations stand for what a camera does to colour that a white balance cannot: its sensitivities
        are not the CIE observer's, and the 3x3 matrix to sRGB, fitted on reflectances, renders the smooth
        spectra of a sky less or more saturated than colorimetry, and not equally along red and blue (a Foveon
        sensor through its rawtoaces matrix renders a Rayleigh sky's red/green 1.7x the CIE value relative to
        white: red 0.35, blue 0.82; docs/photos.md), as picture styles do by choice. Without them an aerosol's
        whitening is the only way the model can desaturate.
        """
        if self.model.lagged and self.frozen_factor is None:  # spectra() alone is the live single scattering
            raise FitError("multiple: bruneton_lagged needs its multiple-scattering factor frozen first "
                           "(skyfit fit and evaluate do it; skyfit.fit.photo.freeze_tables)")
        out = []
        for i, (s, m, o) in enumerate(zip(self.spectra(phys), self.matrices, self.observations)):
            p = s @ m
            if o.kind == "rgb":
                nu = self.param.nuisance(phys, i)
                if self._saturates:
                    s_r = nu["saturation_red"]
                    y = (p @ torch.as_tensor(srgb_luminance_weights(), dtype=p.dtype, device=p.device))[:, None]
                    p = y + torch.stack([s_r, torch.ones_like(s_r), nu["saturation_blue"]]) * (p - y)
                one = torch.ones_like(nu["gain_red"])
                p = p * torch.stack([nu["gain_red"], one, nu["gain_blue"]])
                if o.image_radius is not None:
                    p = p * (1.0 + nu["vignetting"] * o.image_radius[o.mask] ** 2)[:, None]
            out.append(p)
        return out

    def censor(self, pred: Tensor, i: int) -> Tensor:
        """Observation i's prediction with each censored value that the model already satisfies set to
        the data (a saturated value is a lower bound: any model at or above it fits; a black one an upper
        bound), so that it adds nothing to the loss and pulls no gradient; the limit of the censored
        (Tobit) likelihood of :func:`skyfit.camera.censored_gaussian_nll` for noise small against the bound."""
        o = self.observations[i]
        if o.censored is None:
            return pred
        c, v = o.censored[o.mask], o.values[o.mask]
        done = ((c > 0) & (pred >= v)) | ((c < 0) & (pred <= v))
        return torch.where(done, v, pred)

    def predict(self, x: Tensor) -> list[Tensor]:
        """Each observation's predicted channels for its used samples, (N_i, C_i)."""
        phys = self.param.to_physical(x)
        return [p * self.param.nuisance(phys, i)["exposure"] for i, p in enumerate(self.predict_unscaled(phys))]

    def loss_from_predictions(self, preds: Sequence[Tensor], phys: dict) -> Tensor:
        total = preds[0].new_zeros(())
        for i, (p, o) in enumerate(zip(preds, self.observations)):
            nu = self.param.nuisance(phys, i)
            total = total + self.loss(self.censor(p, i), o.values[o.mask], o.sigma[o.mask], noise_scale=nu["noise_scale"],
                                      reduction="sum")
        return total / max(self.n_elements, 1)

    def penalty(self, phys: dict) -> Tensor:
        """The objective's part that is not the data's, on the scale of the loss per element, shape () (none here;
        :class:`skyfit.fit.photo.PhotoProblem`'s priors and sun datum)."""
        return torch.zeros((), dtype=torch.float64)

    def objective(self, x: Tensor) -> Tensor:
        """Mean loss per used element (sample x channel), shape ()."""
        self.n_evaluations += 1
        return self.loss_from_predictions(self.predict(x), self.param.to_physical(x))

    # -- exposure in closed form ----------------------------------------------------
    def profile_exposure(self, x: Tensor) -> Tensor:
        """x with every free exposure set to its weighted least-squares value for the rest of x.

        k = sum(m o / s^2) / sum(m^2 / s^2) per observation (or pooled when shared): the
        maximum-likelihood scale for Gaussian noise (:func:`skyfit.camera.fit_exposure_scale`).
        A starting point for the optimiser, not a replacement for fitting it.
        """
        if "exposure" not in self.param.free:
            return x
        with torch.no_grad():
            preds = self.predict_unscaled(self.param.to_physical(x))
            # censored values are bounds, not measurements: they take no part in the closed form
            w = [(1.0 / o.sigma[o.mask] ** 2) * (1.0 if o.censored is None else (o.censored[o.mask] == 0).to(p.dtype))
                 for p, o in zip(preds, self.observations)]
            num = [float((p * o.values[o.mask] * wi).sum()) for p, o, wi in zip(preds, self.observations, w)]
            den = [float((p * p * wi).sum()) for p, wi in zip(preds, w)]
        per = self.param.is_per_observation("exposure")
        ks = [n / d if d > 0 else 1.0 for n, d in zip(num, den)] if per else [sum(num) / sum(den) if sum(den) > 0 else 1.0]
        ks = [k if k > 0 and math.isfinite(k) else 1.0 for k in ks]
        vals = self.param.physical_dict(x)
        vals["exposure"] = ks if per else ks[0]
        return self.param.to_unconstrained({n: vals[n] for n in self.param.free}, x.dtype, x.device)

    # -- metrics -------------------------------------------------------------------
    def metrics(self, x: Tensor) -> dict:
        """RMSE, mean CIE 1976 Delta E and loss, pooled and per observation (see :func:`observation_metrics`)."""
        with torch.no_grad():
            preds = self.predict(x)
            loss = float(self.loss_from_predictions(preds, self.param.to_physical(x)))
            preds = [self.censor(p, i) for i, p in enumerate(preds)]  # a satisfied bound is no error
        per = [observation_metrics(p, o) for p, o in zip(preds, self.observations)]
        return {**pool_metrics(per), "loss": loss, "per_observation": per}


def observation_metrics(pred: Tensor, obs: Observation) -> dict:
    """RMSE over used samples and channels, and mean CIE 1976 Delta E of one observation.

    Spectral data: RMSE in mW/(m^2 sr nm) (Bruneton 2017 / Gałaj 2021's score when
    the channels are 360-720 nm); XYZ by CIE 1931 from the spectra. RGB data: RMSE
    in linear sRGB units; XYZ by the inverse sRGB matrix. Delta E: both sides scaled
    by the measured 99th-percentile luminance (:func:`skyfit.render.delta_e_1976`).
    """
    from ..render.colour import delta_e_1976

    meas = obs.values[obs.mask].detach().cpu().double()
    mod = pred.detach().cpu().double()
    if obs.kind == "spectral":
        scale, units = 1e3, "mW/(m^2 sr nm)"
        m_xyz = spectral_to_xyz_matrix(obs.wavelengths.detach().cpu().double())
        xyz_meas, xyz_mod = meas @ m_xyz, mod @ m_xyz
    else:
        scale, units = 1.0, "linear sRGB (Y in cd/m^2)"
        inv = torch.as_tensor(np.linalg.inv(xyz_to_srgb_matrix()), dtype=torch.float64)
        xyz_meas, xyz_mod = meas @ inv.T, mod @ inv.T
    err = (mod - meas) * scale
    rmse = float(torch.sqrt((err**2).mean()))
    white = float(np.percentile(xyz_meas[:, 1].numpy(), 99))
    de = delta_e_1976(xyz_mod.numpy(), xyz_meas.numpy(), white) if white > 0 else np.full(meas.shape[0], np.nan)
    rel = (mod - meas) / torch.where(meas > 0, meas, torch.ones_like(meas))
    return {
        "name": obs.name, "rmse": rmse, "rmse_units": units, "delta_e": float(np.mean(de)),
        "relative_rms": float(torch.sqrt((rel**2).mean())), "bias": float(err.mean()),
        "n_samples": int(obs.mask.sum()), "n_elements": int(err.numel()), "_sse": float((err**2).sum()),
        "_de_sum": float(np.sum(de)),
    }


def pool_metrics(per: Sequence[dict]) -> dict:
    """Pooled RMSE and Delta E over observations (each element / sample counts once)."""
    units = {p["rmse_units"] for p in per}
    n_el = sum(p["n_elements"] for p in per)
    n = sum(p["n_samples"] for p in per)
    out = {
        "rmse": math.sqrt(sum(p["_sse"] for p in per) / n_el) if len(units) == 1 else None,
        "rmse_units": units.pop() if len(units) == 1 else "mixed (see per_observation)",
        "delta_e": sum(p["_de_sum"] for p in per) / n,
        "n_samples": n,
    }
    for p in per:
        p.pop("_sse", None)
        p.pop("_de_sum", None)
    return out
