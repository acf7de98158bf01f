"""Log-likelihood of a whole ensemble of parameter vectors in one batched forward pass.

emcee's stretch move (Goodman & Weare 2010; Foreman-Mackey et al. 2013, Sec. 3) with
``vectorize=True`` asks for log p of an array X (B, P): half the ensemble per call.
:class:`BatchedLikelihood` evaluates it as one torch computation over a leading walker
axis B, reusing everything that does not depend on the parameters.

The physics (columns with the scale height as a batched argument, the rays' fixed
geometry, the batched single-scattering radiance) is :mod:`skyfit.scattering.batched`;
this module maps parameter vectors to its coefficients and adds the fit's channels,
exposure and loss.

What the parameters do not touch (precomputed once per observation, see
:class:`skyfit.scattering.batched.RayGeometry`): the view-ray sample positions r_j and their sun cosines
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
fixed sun offsets (they move the geometry), with the one-lobed Mie phases and the exponential
aerosol profile (not ``two_term_hg``, ``lognormal_mie`` nor ``boundary_layer``, docs/aerosol.md). Anything else: :meth:`BatchedLikelihood.supported`
says why, and :class:`~skyfit.fit.sample.LogPosterior` loops over the walkers instead.

``torch.func.vmap`` over :meth:`FitProblem.objective` is not an option: the objective
reads Python numbers from tensors (``Atmosphere.validate``'s ``bool(...)`` checks,
Chapman's ``float(scale_heights.max())`` regime check, the chunk-size arithmetic),
which vmap refuses ("data-dependent control flow").
"""
from __future__ import annotations

import math
from typing import Sequence

import torch
from torch import Tensor

from ..scattering.batched import BatchCoefficients, RayGeometry, batched_single_scattering
from ..transmittance.chapman import ChapmanOpticalDepth
from ..transmittance.quadrature import QuadratureOpticalDepth
from .model import FitProblem
from .parameters import CAMERA_RESPONSE, ORIENTATION, PARAMETERS


class _ObsGeometry(RayGeometry):
    """One observation's used samples (a slice ``rays`` of them): their :class:`RayGeometry`, values and noise."""

    def __init__(self, problem: FitProblem, i: int, integrator, view_samples: int, rule: str, fixed_heights,
                 rays: slice = slice(None)):
        atm = problem.param.base
        o = problem.observations[i]
        phys0 = problem.param.to_physical(problem.param.initial_vector(atm.dtype, atm.device))
        sun = problem.sun_vectors(phys0, i)
        if sun.ndim == 2:
            sun = sun[o.mask][rays]
        view = problem.view_directions(phys0, i)[rays].to(atm.dtype)
        super().__init__(atm, view, sun, o.altitude_m, integrator, view_samples, rule, fixed_heights)
        self.obs = i
        o_val, o_sig = o.values[o.mask][rays], o.sigma[o.mask][rays]
        self.values, self.sigma = o_val.to(atm.dtype), o_sig.to(atm.dtype)
        self.matrix = problem.matrices[i]
        self.solar_scale = problem.solar_scale[i]


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
        touched = free | set(problem.param._overridden)
        if problem.param.base.mie_phase == "two_term_hg" or touched & {"mie_g2", "mie_hg_weight"}:
            return "the two-term Henyey-Greenstein phase (the batched Mie phase is one-lobed)"
        if problem.param.lognormal_mie():
            return "the lognormal_mie phase (the batched Mie phase is one Henyey-Greenstein lobe for every wavelength)"
        if problem.param.boundary_layer():
            return "the boundary-layer aerosol profile (the batched columns are exponential)"
        if free & set(ORIENTATION):
            return f"free {sorted(free & set(ORIENTATION))} move the view geometry"
        response = {n for n in CAMERA_RESPONSE if n in free or problem.param.values[n] != problem.param.defaults[n]}
        if response and any(o.kind == "rgb" for o in problem.observations):
            return f"{sorted(response)} of RGB data (the camera's gains and vignetting are not batched)"
        if any(o.censored is not None for o in problem.observations):
            return "censored values"
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
        return batched_single_scattering(geo, c, self.solar)

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
