"""Log-likelihood of a whole ensemble of parameter vectors in one batched forward pass.

emcee's stretch move (Goodman & Weare 2010; Foreman-Mackey et al. 2013, Sec. 3) with
``vectorize=True`` asks for log p of an array X (B, P): half the ensemble per call.
:class:`BatchedLikelihood` evaluates it as one torch computation over a leading walker
axis B, reusing everything that does not depend on the parameters.

What the parameters do not touch (precomputed once per observation, see
:class:`_ObsGeometry`): the view-ray sample positions r_j and their sun cosines
(:func:`skyfit.scattering.single.view_ray_samples`), the quadrature weights times the
segment lengths, the sun's visible fraction, the ray/sun/ground segments' Chapman
arguments (start and end altitude, radius and |mu| of each column term), the Rayleigh
phase, and the column of every layer whose scale height is not free.

What they do (evaluated with the walker axis B in front):
the columns of free-scale-height layers, T = exp(-column @ extinction) over wavelengths,
the density weights exp(-(r_j - R) / H), the ray integral, the Mie phase of each g,
the ground term, the channel projection, exposure and the loss. This is Bruneton &
Neyret 2008 eqs. 1-7 / Gałaj 2019 eq. 9 exactly as :func:`skyfit.scattering.single_scattering`
computes them (same operations in the same order), so the batched log-likelihood
equals the per-walker one to rounding (tests/test_sample.py checks 1e-10).

Supported: single scattering (orders 1) with the ``chapman`` or a quadrature
(``gauss``, ``trapezoid``, ``midpoint``, ``simpson``) optical-depth integrator, and
fixed sun offsets (they move the geometry). Anything else: :meth:`BatchedLikelihood.supported`
says why, and :class:`~skyfit.fit.sample.LogPosterior` loops over the walkers instead.

``torch.func.vmap`` over :meth:`FitProblem.objective` is not an option: the objective
reads Python numbers from tensors (``Atmosphere.validate``'s ``bool(...)`` checks,
Chapman's ``float(scale_heights.max())`` regime check, the chunk-size arithmetic),
which vmap refuses ("data-dependent control flow").
"""
from __future__ import annotations

import dataclasses
import math
from typing import Sequence

import torch
from torch import Tensor

from ..geometry import distance_to_top, point_along_ray, safe_sqrt, sun_cosine_along_ray
from ..quadrature import nodes_weights
from ..scattering.phase import mie_phase, rayleigh_phase
from ..scattering.single import sun_ray_cosine, sun_visible_fraction, view_ray_samples
from ..transmittance.chapman import ChapmanOpticalDepth, segment_geometry
from ..transmittance.quadrature import QuadratureOpticalDepth
from .model import FitProblem
from .parameters import ORIENTATION, PARAMETERS


# -- columns of segments with the scale height as a batched argument ----------------------------
def _column_up(h: Tensor, r: Tensor, mu: Tensor, H: Tensor) -> Tensor:
    """Fitzmaurice 1964 column to infinity (as :func:`skyfit.transmittance.chapman.chapman_column_up`).

    Args:
        h, r, mu: altitude [m], radius [m], zenith cosine >= 0 [1], shape S (broadcastable with H).
        H: scale heights, shape broadcastable against S (e.g. (B, 1, ..., 1)). [m]
    """
    X = r / H
    return H * torch.exp(-h / H) * math.sqrt(math.pi / 2.0) * torch.sqrt(X) * torch.special.erfcx(torch.sqrt(X / 2.0) * mu)


@dataclasses.dataclass
class _ChapmanPlan:
    """Arguments of :func:`skyfit.transmittance.chapman.chapman_segment_column` for fixed segments.

    The three column terms A (start), B (end) and the tangent term are evaluated only
    where the branch that uses them occurs; ``a_h``... may have a smaller (broadcastable)
    shape than the segments (e.g. one start per view ray).
    """

    a: tuple[Tensor, Tensor, Tensor]
    b: tuple[Tensor, Tensor, Tensor]
    t: tuple[Tensor, Tensor] | None
    up: Tensor
    before: Tensor
    all_up: bool

    @classmethod
    def build(cls, r: Tensor, mu: Tensor, length: Tensor, bottom_radius: float, start_shape=None) -> "_ChapmanPlan":
        rb, mub, lb = torch.broadcast_tensors(r, mu, length)
        g = segment_geometry(rb, mub, lb, bottom_radius)
        a_mu = torch.where(g.up, mub, -mub)
        if start_shape is not None:  # every segment of a row starts at the same point: keep one per row
            a = tuple(t[..., :1] for t in (g.h, rb, a_mu))
        else:
            a = (g.h, rb, a_mu)
        b = (g.h_d, g.r_d, torch.where(g.before, -g.mu_d, g.mu_d))
        t = (g.h_t, g.r_t) if bool(g.through.any()) else None
        up, before = g.up, g.before
        return cls(a, b, t, up, before, bool(up.all()))

    def column(self, H: Tensor) -> Tensor:
        """Column for scale height(s) H, shape H's batch shape + segment shape. [m]

        Args:
            H: shape (B, 1, ..., 1) with as many trailing ones as the segments have dims, or ().
        """
        a = _column_up(*self.a, H)
        b = _column_up(*self.b, H)
        if self.all_up:
            return a - b
        t = _column_up(self.t[0], self.t[1], torch.zeros_like(self.t[1]), H) if self.t is not None else torch.zeros_like(b)
        return torch.where(self.up, a - b, torch.where(self.before, b - a, 2.0 * t - a - b))


@dataclasses.dataclass
class _QuadraturePlan:
    """Quadrature column sum_m w_m exp(-alt_m / H) L (as :class:`QuadratureOpticalDepth`) with fixed alt."""

    alt: Tensor  # (..., M)
    w: Tensor  # (M,)
    length: Tensor  # (...)

    @classmethod
    def build(cls, integ: QuadratureOpticalDepth, r: Tensor, mu: Tensor, length: Tensor, bottom_radius: float,
              start_shape=None) -> "_QuadraturePlan":
        x, w = nodes_weights(integ.name, integ.samples, r.dtype, r.device)
        r_, mu_, L_ = (t.unsqueeze(-1) for t in torch.broadcast_tensors(r, mu, length))
        s = L_ * x
        alt = safe_sqrt(r_ * r_ + 2.0 * r_ * mu_ * s + s * s) - bottom_radius
        return cls(alt, w, L_.squeeze(-1))

    def column(self, H: Tensor) -> Tensor:
        dens = torch.exp(-self.alt / H.unsqueeze(-1))  # (B, ..., M)
        return (dens * self.w).sum(-1) * self.length


def _plan(integ, r, mu, length, bottom_radius, start_shape=None):
    if isinstance(integ, ChapmanOpticalDepth):
        return _ChapmanPlan.build(r, mu, length, bottom_radius, start_shape)
    return _QuadraturePlan.build(integ, r, mu, length, bottom_radius, start_shape)


class _LayerColumns:
    """Columns (B, *S, K) of K layers along fixed segments; layers with a fixed scale height are cached."""

    def __init__(self, plan, fixed_heights: dict[int, float], K: int, ndim: int):
        self.plan, self.K, self.ndim = plan, K, ndim
        self.cache: dict[int, Tensor] = {}
        self.fixed = fixed_heights

    def __call__(self, H: Tensor) -> Tensor:
        """H: (B, K) scale heights -> columns (B, *S, K)."""
        B = H.shape[0]
        out = []
        for k in range(self.K):
            if k in self.fixed:
                if k not in self.cache:
                    self.cache[k] = self.plan.column(H.new_tensor(self.fixed[k]))
                c = self.cache[k]
                out.append(c.expand(B, *c.shape))
            else:
                out.append(self.plan.column(H[:, k].reshape(B, *([1] * self.ndim))))
        return torch.stack(out, -1)


class _ObsGeometry:
    """Everything about one observation's used samples that the parameters do not change."""

    def __init__(self, problem: FitProblem, i: int, integrator, view_samples: int, rule: str, fixed_heights,
                 rays: slice = slice(None)):
        atm = problem.param.base
        o = problem.observations[i]
        phys0 = problem.param.to_physical(problem.param.initial_vector(atm.dtype, atm.device))
        sun = problem.sun_vectors(phys0, i)
        if sun.ndim == 2:
            sun = sun[o.mask][rays]
        view = problem.view_directions(phys0, i)[rays].to(atm.dtype)
        sun = torch.as_tensor(sun, dtype=atm.dtype, device=atm.device)
        mu = torch.clamp(view[..., 2], -1.0, 1.0)
        mu_s = torch.clamp(sun[..., 2], -1.0, 1.0)
        nu = torch.clamp((view * sun).sum(-1), -1.0, 1.0)
        r = atm.bottom_radius + torch.as_tensor(o.altitude_m, dtype=atm.dtype, device=atm.device)
        r, mu, mu_s, nu = (t.reshape(-1) for t in torch.broadcast_tensors(r, mu, mu_s, nu))
        Rb, Rt = atm.bottom_radius, atm.top_radius
        x, w = nodes_weights(rule, view_samples, atm.dtype, atm.device)
        hits, seg, r0, mu0, mus0, s, r_j, mus_j = view_ray_samples(atm, r, mu, mu_s, nu, x)
        r0e, mu0e = r0.unsqueeze(-1), mu0.unsqueeze(-1)
        mus_c = sun_ray_cosine(r_j, mus_j, Rb)
        K = 2
        self.view_cols = _LayerColumns(_plan(integrator, r0e, mu0e, s, Rb, start_shape=True), fixed_heights, K, 2)
        self.sun_cols = _LayerColumns(_plan(integrator, r_j, mus_c, distance_to_top(r_j, mus_c, Rt), Rb), fixed_heights, K, 2)
        # Ozone (when the atmosphere has it): its exact tent-layer column is geometry only (the ozone
        # spectrum is not fitted), appended as the last column as skyfit.scattering.single.path_columns does.
        from ..scattering import single as _single

        # (only where the renderer itself includes ozone: skyfit.scattering.single.path_columns)
        self.ozone = getattr(atm, "ozone_absorption", None) is not None and hasattr(_single, "path_columns")
        if self.ozone:
            from ..transmittance import ozone_column

            oz = lambda r_, mu_, l_: ozone_column(r_, mu_, l_, Rb, atm.ozone_layer_m)  # noqa: E731
            ov = oz(r0e, mu0e, s)
            self.oz_j = (ov.expand(r_j.shape) if ov.shape != r_j.shape else ov) + oz(r_j, mus_c, distance_to_top(r_j, mus_c, Rt))
            self.ozone_row = atm.ozone_absorption
        vis = sun_visible_fraction(r_j, mus_j, Rb, atm.sun_angular_radius)
        self.alt_j = r_j - Rb  # (n, N)
        self.wvis = vis * (w * seg.unsqueeze(-1))  # (n, N)
        self.nu = nu
        self.p_r = rayleigh_phase(nu).unsqueeze(-1)  # (n, 1)
        self.mie_phase = atm.mie_phase
        self.hits = hits
        self.ground = bool(hits.any())
        if self.ground:
            self.hitsf = hits.unsqueeze(-1)
            self.g_cols = _LayerColumns(_plan(integrator, r0, mu0, seg, Rb), fixed_heights, K, 1)
            r_g = torch.full_like(r, Rb)
            mus_g = sun_cosine_along_ray(r0, mus0, nu, seg, torch.clamp_min(point_along_ray(r0, mu0, seg)[0], Rb))
            mu_c = sun_ray_cosine(r_g, mus_g, Rb)
            self.gs_cols = _LayerColumns(_plan(integrator, r_g, mu_c, distance_to_top(r_g, mu_c, Rt), Rb), fixed_heights, K, 1)
            vis_g = sun_visible_fraction(r_g, mus_g, Rb, atm.sun_angular_radius)
            self.e_g_factor = vis_g.unsqueeze(-1) * torch.clamp_min(mus_g, 0.0).unsqueeze(-1)  # (n, 1)
            if self.ozone:
                self.oz_g = oz(r0, mu0, seg)
                self.oz_gs = oz(r_g, mu_c, distance_to_top(r_g, mu_c, Rt))
        self.n, self.N = r_j.shape
        self.obs = i
        o_val, o_sig = o.values[o.mask][rays], o.sigma[o.mask][rays]
        self.values, self.sigma = o_val.to(atm.dtype), o_sig.to(atm.dtype)
        self.matrix = problem.matrices[i]
        self.solar_scale = problem.solar_scale[i]


@dataclasses.dataclass
class BatchCoefficients:
    """Per-walker atmosphere coefficients (B walkers, W wavelengths, K = 2 layers)."""

    rayleigh_scattering: Tensor  # (B, W) [1/m]
    mie_extinction: Tensor  # (B, W) [1/m]
    mie_scattering: Tensor  # (B, W) [1/m]
    mie_g: Tensor  # (B,) [1]
    ground_albedo: Tensor  # (B, W) [1]
    scale_heights: Tensor  # (B, K) [m]

    @property
    def extinction_matrix(self) -> Tensor:
        """(B, K, W) rows (Rayleigh, Mie), as :attr:`Atmosphere.extinction_matrix`. [1/m]"""
        return torch.stack([self.rayleigh_scattering, self.mie_extinction], 1)


class BatchedLikelihood:
    """log L(x) for B parameter vectors at once: ``-sum over used elements of [rho(r/s) + log s]``.

    Equal to ``-problem.n_elements * problem.objective(x)`` for each row (module docstring).

    Args:
        problem: the fit problem (observations, loss, renderer settings, parameterisation).
        batch_hint: the number of walkers per call expected (half the ensemble); with ``chunk_bytes``
            it sets how many rays one chunk holds.
        chunk_bytes: size of the largest temporaries, B x rays x view_samples x W floats, per chunk
            (default 16 MB on the CPU, where cache-sized chunks measured faster, 1 GB elsewhere). [bytes]
    """

    def __init__(self, problem: FitProblem, batch_hint: int = 16, chunk_bytes: float | None = None):
        self.problem = problem
        why = self.unsupported_reason(problem)
        if why:
            raise ValueError(f"batched likelihood unsupported: {why}")
        p = problem.param
        self.param = p
        base = p.base
        self.touched = set(p.free) | set(p._overridden)
        self.dtype, self.device = base.dtype, base.device
        phys0 = p.to_physical(p.initial_vector(base.dtype, base.device))
        self.fixed_phys = phys0
        # Which layers have a fixed scale height (columns cached).
        atm0 = p.atmosphere(phys0)
        fixed = {}
        if "rayleigh_scale_height" not in p.free:
            fixed[0] = float(atm0.rayleigh_scale_height)
        if "mie_scale_height" not in p.free:
            fixed[1] = float(atm0.mie_scale_height)
        m = problem.model
        self.integrator = m.integrator
        if chunk_bytes is None:
            chunk_bytes = 16e6 if torch.device(base.device).type == "cpu" else 1e9
        W = base.wavelengths.shape[0]
        per_ray = max(1, batch_hint) * m.view_samples * (W + 4) * torch.finfo(base.dtype).bits // 8
        self.chunk_rays = max(8, int(chunk_bytes // per_ray))
        self.geoms = []
        for i, o in enumerate(problem.observations):
            n = int(o.mask.sum())
            for a in range(0, n, self.chunk_rays):
                self.geoms.append(_ObsGeometry(problem, i, m.integrator, m.view_samples, m.rule, fixed,
                                               slice(a, min(n, a + self.chunk_rays))))
        self.solar = base.solar_irradiance
        self.lam = base.wavelengths

    @staticmethod
    def unsupported_reason(problem: FitProblem) -> str:
        """Why the batched path cannot evaluate ``problem`` ('' when it can)."""
        m = problem.model
        if m.orders != 1:
            return f"orders={m.orders} (only single scattering is batched)"
        if not isinstance(m.integrator, (ChapmanOpticalDepth, QuadratureOpticalDepth)):
            return f"integrator {m.integrator.name!r} (batched: chapman, gauss, trapezoid, midpoint, simpson)"
        free = set(problem.param.free)
        if free & set(ORIENTATION):
            return f"free {sorted(free & set(ORIENTATION))} move the view geometry"
        return ""

    # -- parameters ------------------------------------------------------------------------
    def physical(self, X: Tensor) -> dict[str, Tensor]:
        """Physical values of every parameter for each row of X (B, P): shared (B,), per-observation (B, n_obs)."""
        p = self.param
        B = X.shape[0]
        out: dict[str, Tensor] = {}
        for n, spec in PARAMETERS.items():
            if n in p._slots:
                v = spec.forward(X[:, p._slots[n]], p._hi(n))  # (B, k)
                out[n] = v if p.is_per_observation(n) else v[:, 0]
            else:
                v = self.fixed_phys[n]
                out[n] = v.expand(B, *v.shape) if v.ndim else v.expand(B)
        return out

    def coefficients(self, phys: dict[str, Tensor]) -> BatchCoefficients:
        """Mirror of :meth:`Parameterisation.atmosphere` with a walker axis."""
        p, b, touched = self.param, self.param.base, self.touched
        B = phys["rayleigh_scale"].shape[0]

        def per_w(t: Tensor) -> Tensor:
            return t.expand(B, *t.shape)

        rs = b.rayleigh_scattering * phys["rayleigh_scale"][:, None] if "rayleigh_scale" in touched else per_w(b.rayleigh_scattering)
        h_r = phys["rayleigh_scale_height"] if "rayleigh_scale_height" in touched else per_w(b.rayleigh_scale_height.reshape(()))
        h_m = phys["mie_scale_height"] if "mie_scale_height" in touched else per_w(b.mie_scale_height.reshape(()))
        g = phys["mie_g"] if "mie_g" in touched else per_w(b.mie_g.reshape(()))
        ext, scat = per_w(b.mie_extinction), per_w(b.mie_scattering)
        if touched & {"mie_beta_550", "mie_aod_550", "mie_angstrom_alpha", "mie_ssa"}:
            if touched & {"mie_beta_550", "mie_aod_550", "mie_angstrom_alpha"}:
                if "mie_aod_550" in touched:
                    beta = phys["mie_aod_550"] / phys["mie_scale_height"]
                else:
                    beta = phys["mie_beta_550"]
                ext = beta[:, None] * (p._lam / 550.0) ** (-phys["mie_angstrom_alpha"][:, None]) * p._mie_shape
            scat = ext * (phys["mie_ssa"][:, None] if "mie_ssa" in touched else p._ssa_ratio)
        if "ground_albedo" in touched:
            alb = phys["ground_albedo"][:, None] * torch.ones_like(b.ground_albedo)
        elif "ground_albedo_scale" in touched:
            alb = b.ground_albedo * phys["ground_albedo_scale"][:, None]
        else:
            alb = per_w(b.ground_albedo)
        return BatchCoefficients(rs, ext, scat, g, alb, torch.stack([h_r, h_m], -1))

    # -- forward ---------------------------------------------------------------------------
    def _radiance(self, geo: _ObsGeometry, c: BatchCoefficients) -> Tensor:
        """Single-scattering radiance (B, n, W) of the observation's used samples. [W/(m^2 sr nm)]"""
        B = c.mie_g.shape[0]
        ext = c.extinction_matrix  # (B, K, W)
        H = c.scale_heights
        col = geo.view_cols(H) + geo.sun_cols(H)  # (B, n, N, K)
        n, N = geo.n, geo.N
        if geo.ozone:  # (B, n, N, K + 1) and (B, K + 1, W): ozone last (skyfit.scattering.single.path_extinction)
            col = torch.cat([col, geo.oz_j.expand(B, n, N).unsqueeze(-1)], -1)
            ext = torch.cat([ext, geo.ozone_row.expand(B, 1, -1)], 1)
        W = ext.shape[-1]
        trans = torch.matmul(col.reshape(B, n * N, -1), -ext).exp_().reshape(B * n, N, W)
        dens = torch.exp(geo.alt_j.unsqueeze(-1) * -(1.0 / H)[:, None, None, :])  # (B, n, N, K)
        wd = dens * geo.wvis.unsqueeze(-1)
        ray_int = torch.bmm(wd.reshape(B * n, N, -1).transpose(1, 2), trans).reshape(B, n, -1, W)  # (B, n, K, W)
        p_m = mie_phase(geo.nu, c.mie_g[:, None], geo.mie_phase).unsqueeze(-1)  # (B, n, 1)
        rad = ray_int[:, :, 0] * c.rayleigh_scattering[:, None] * geo.p_r + ray_int[:, :, 1] * c.mie_scattering[:, None] * p_m
        rad = rad * self.solar
        if geo.ground:
            cg, cgs = geo.g_cols(H), geo.gs_cols(H)
            if geo.ozone:
                cg = torch.cat([cg, geo.oz_g.expand(B, n).unsqueeze(-1)], -1)
                cgs = torch.cat([cgs, geo.oz_gs.expand(B, n).unsqueeze(-1)], -1)
            t_g = torch.exp(-torch.matmul(cg, ext))  # (B, n, W)
            e_g = torch.exp(-torch.matmul(cgs, ext)) * geo.e_g_factor
            rad = rad + geo.hitsf * t_g * c.ground_albedo[:, None] / math.pi * e_g * self.solar
        return rad

    def layers_ok(self, c: BatchCoefficients) -> Tensor:
        """(B,) bool: the integrator's regime (Chapman: X = R / max H >= min_x) holds for each walker."""
        if isinstance(self.integrator, ChapmanOpticalDepth):
            return self.param.base.bottom_radius / c.scale_heights.max(-1).values >= self.integrator.min_x
        return torch.ones(c.scale_heights.shape[0], dtype=torch.bool, device=c.scale_heights.device)

    def predict(self, X: Tensor) -> list[Tensor]:
        """Each observation's predicted channels (B, n_i, C_i), exposure applied."""
        phys = self.physical(X)
        c = self.coefficients(phys)
        out: list[list[Tensor]] = [[] for _ in self.problem.observations]
        for geo in self.geoms:
            i = geo.obs
            spec = self._radiance(geo, c) * geo.solar_scale
            pred = spec @ geo.matrix
            out[i].append(pred * self._nuisance(phys, "exposure", i)[:, None, None])
        return [torch.cat(p, 1) for p in out]

    def _nuisance(self, phys, name, i) -> Tensor:
        v = phys[name]
        return v[:, i] if v.ndim == 2 else v

    def __call__(self, X: Tensor) -> Tensor:
        """log-likelihood of each row of X (B, P), shape (B,); -inf where the integrator refuses the layers."""
        phys = self.physical(X)
        c = self.coefficients(phys)
        ok = self.layers_ok(c)
        total = X.new_zeros(X.shape[0])
        for geo in self.geoms:
            i = geo.obs
            spec = self._radiance(geo, c) * geo.solar_scale
            pred = (spec @ geo.matrix) * self._nuisance(phys, "exposure", i)[:, None, None]
            s = self._nuisance(phys, "noise_scale", i)[:, None, None]
            val = self.problem.loss(pred, geo.values, geo.sigma, noise_scale=s, reduction="none")
            total = total + val.sum((1, 2))
        return torch.where(ok, -total, torch.full_like(total, -math.inf))


def per_walker_loglike(problem: FitProblem, X: Tensor) -> Tensor:
    """Reference: ``-n_elements * objective(x)`` for each row of X (B, P), one forward pass per walker.

    A point the integrator refuses (ValueError) gets -inf, as the optimiser's line search treats it.
    """
    out = []
    with torch.no_grad():
        for x in X:
            try:
                out.append(-problem.n_elements * float(problem.objective(x)))
            except ValueError:
                out.append(-math.inf)
    return torch.tensor(out, dtype=X.dtype, device=X.device)


def check_batched(batched: BatchedLikelihood, problem: FitProblem, X: Sequence[Tensor] | Tensor, rtol: float = 1e-9) -> float:
    """Largest relative difference between the batched and the per-walker log-likelihood at X (B, P)."""
    X = torch.as_tensor(X)
    with torch.no_grad():
        a = batched(X)
    b = per_walker_loglike(problem, X)
    fin = torch.isfinite(a) & torch.isfinite(b)
    if not bool((torch.isfinite(a) == torch.isfinite(b)).all()):
        return math.inf
    if not bool(fin.any()):
        return 0.0
    return float(((a[fin] - b[fin]).abs() / b[fin].abs().clamp_min(1.0)).max())
