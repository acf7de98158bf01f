"""Monte Carlo reference for multiple scattering, independent of the Bruneton tables.

Nothing here is used by the renderer: it is a slow, careful numpy path tracer to
measure :mod:`skyfit.scattering.multiple` against (tests, scripts/multiple_accuracy.py).
It shares no code with the tables: geometry in 3D Cartesian coordinates, phase
functions, optical depths (Gauss-Legendre along each segment) and sampling are
written here from the definitions.

Model (the one the tables solve, Bruneton & Neyret 2008 Sec. 2-3): a spherical shell
between ``bottom_radius`` and ``top_radius`` with Rayleigh and Mie exponential layers
and an ozone tent layer, a Lambertian ground of spectral albedo alpha, and the sun as a
distant source of irradiance E_sun whose visible fraction above the horizon is 2017's
smoothstep (``sun_visible_fraction``) and whose cosine on the ground is 2017's average
over the disc (``ComputeDirectIrradiance``).

Estimator (backward path tracing with next-event estimation, per scattering order):
from the camera, each segment to the ground or the top gets one vertex, sampled on a
piecewise-linear approximation of the optical depth of the spectrally averaged
extinction (forced inside the segment when it ends at the top; when it ends on the
ground, the ground is chosen with the approximate segment transmittance). At vertex n
(n = 1, 2, ...) the sun is connected deterministically (transmittance by Gauss-Legendre
quadrature), which tallies the radiance of paths with exactly n bounces (scattering
events or ground reflections), the counting of 2008 eq. 12. The next direction is drawn
from a mixture of the Rayleigh phase and Henyey-Greenstein (the Cornette-Shanks phase is
reached by the weight P_CS / pdf, bounded by 1.5), or cosine-weighted at the ground.
All weights use the exact pdf of what was sampled, so the estimator is unbiased up to the
Gauss-Legendre optical depths (relative error < 1e-6 for the default 48 nodes).
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np

from ..atmosphere import Atmosphere


@dataclasses.dataclass
class MCResult:
    """Per-order radiance estimates, shape (orders, W), and their standard errors. [W/(m^2 sr nm)]"""

    mean: np.ndarray
    stderr: np.ndarray
    paths: int


def _np(x) -> np.ndarray:
    return np.asarray(x.detach().cpu().numpy() if hasattr(x, "detach") else x, dtype=np.float64)


class _Model:
    def __init__(self, atm: Atmosphere):
        self.Rb = float(atm.bottom_radius)
        self.Rt = float(atm.top_radius)
        self.bR = _np(atm.rayleigh_scattering)
        self.bM = _np(atm.mie_scattering)
        self.eM = _np(atm.mie_extinction)
        self.oz = _np(atm.ozone_absorption) if atm.ozone_absorption is not None else np.zeros_like(self.bR)
        self.HR = float(_np(atm.rayleigh_scale_height))
        self.HM = float(_np(atm.mie_scale_height))
        self.g = float(_np(atm.mie_g))
        self.phase = atm.mie_phase
        self.albedo = _np(atm.ground_albedo)
        self.esun = _np(atm.solar_irradiance)
        self.layer = tuple(float(v) for v in atm.ozone_layer_m)
        self.alpha_s = float(atm.sun_angular_radius)
        self.ext = np.stack([self.bR, self.eM, self.oz])  # (3, W)

    def densities(self, radius: np.ndarray) -> np.ndarray:
        h = radius - self.Rb
        lo, pk, hi = self.layer
        oz = np.clip(np.minimum((h - lo) / (pk - lo), (hi - h) / (hi - pk)), 0.0, 1.0)
        return np.stack([np.exp(-h / self.HR), np.exp(-h / self.HM), oz], axis=-1)

    def mie_phase(self, c: np.ndarray) -> np.ndarray:
        g = self.g
        den = (1.0 + g * g - 2.0 * g * c) ** 1.5
        if self.phase == "cornette_shanks":
            return 3.0 / (8.0 * math.pi) * (1 - g * g) * (1 + c * c) / ((2 + g * g) * den)
        return (1 - g * g) / (4.0 * math.pi * den)

    def hg(self, c: np.ndarray) -> np.ndarray:
        g = self.g
        return (1 - g * g) / (4.0 * math.pi * (1.0 + g * g - 2.0 * g * c) ** 1.5)


def _rayleigh(c):
    return 3.0 / (16.0 * math.pi) * (1.0 + c * c)


def _dot(a, b):
    return np.sum(a * b, axis=-1)


def _exit_distance(p: np.ndarray, w: np.ndarray, Rb: float, Rt: float) -> tuple[np.ndarray, np.ndarray]:
    """Distance along (p, w) to the ground or the top, and whether it is the ground."""
    b = _dot(p, w)
    c_b = _dot(p, p) - Rb * Rb
    disc_b = b * b - c_b
    hits = (b < 0) & (disc_b >= 0) & (c_b > -1e-3 * Rb)
    t_g = -b - np.sqrt(np.maximum(disc_b, 0.0))
    disc_t = b * b - (_dot(p, p) - Rt * Rt)
    t_t = -b + np.sqrt(np.maximum(disc_t, 0.0))
    return np.where(hits, np.maximum(t_g, 0.0), np.maximum(t_t, 0.0)), hits


def _columns(m: _Model, p: np.ndarray, w: np.ndarray, length: np.ndarray, x: np.ndarray, wt: np.ndarray) -> np.ndarray:
    """Columns (P, 3) of the three profiles on [0, length] by Gauss-Legendre (nodes x, weights wt on [0, 1])."""
    s = length[:, None] * x[None, :]  # (P, G)
    pts = p[:, None, :] + s[..., None] * w[:, None, :]
    dens = m.densities(np.linalg.norm(pts, axis=-1))  # (P, G, 3)
    return np.einsum("pgk,g->pk", dens, wt) * length[:, None]


def _sun_factor(m: _Model, y: np.ndarray, s: np.ndarray, x, wt, ground: bool) -> np.ndarray:
    """E_sun T(y, sun) times the sun's visible fraction (volume) or average cosine (ground), (P, W)."""
    r = np.linalg.norm(y, axis=-1)
    mu_s = _dot(y, s) / r
    a = m.alpha_s
    if ground:
        f = np.where(mu_s < -a, 0.0, np.where(mu_s > a, mu_s, (mu_s + a) ** 2 / (4 * a)))
    else:
        sin_h = np.minimum(m.Rb / r, 1.0)
        cos_h = -np.sqrt(np.maximum(1.0 - sin_h * sin_h, 0.0))
        ww = sin_h * a
        z = np.clip((mu_s - cos_h + ww) / (2 * ww), 0.0, 1.0)
        f = z * z * (3 - 2 * z)
    # Column to the top along the sun direction, ignoring the ground (inside the penumbra
    # the ray dips at most ~100 m below it); only where the sun is at least partly visible.
    t = np.zeros((y.shape[0], m.ext.shape[1]))
    lit = f > 0
    if lit.any():
        yl = y[lit]
        sv = np.broadcast_to(s, yl.shape)
        b = _dot(yl, sv)
        length = -b + np.sqrt(np.maximum(b * b - (_dot(yl, yl) - m.Rt * m.Rt), 0.0))
        t[lit] = np.exp(-_columns(m, yl, sv, length, x, wt) @ m.ext)
    return m.esun * t * f[:, None]


def _frame(w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors orthogonal to each row of w."""
    a = np.where(np.abs(w[:, 2:3]) < 0.9, np.array([[0.0, 0.0, 1.0]]), np.array([[1.0, 0.0, 0.0]]))
    u = np.cross(w, a)
    u /= np.linalg.norm(u, axis=-1, keepdims=True)
    v = np.cross(w, u)
    return u, v


def _rotate(w: np.ndarray, cos_t: np.ndarray, phi: np.ndarray) -> np.ndarray:
    u, v = _frame(w)
    sin_t = np.sqrt(np.maximum(1.0 - cos_t * cos_t, 0.0))
    out = w * cos_t[:, None] + (u * np.cos(phi)[:, None] + v * np.sin(phi)[:, None]) * sin_t[:, None]
    return out / np.linalg.norm(out, axis=-1, keepdims=True)


def _sample_rayleigh(xi: np.ndarray) -> np.ndarray:
    """Inverse CDF of 3/8 (1 + c^2) on [-1, 1]: root of c^3 + 3c + 4 - 8 xi = 0 (Cardano)."""
    q = 4.0 - 8.0 * xi
    d = np.sqrt(q * q / 4.0 + 1.0)
    return np.cbrt(-q / 2.0 + d) + np.cbrt(-q / 2.0 - d)


def _sample_hg(xi: np.ndarray, g: float) -> np.ndarray:
    if abs(g) < 1e-6:
        return 2.0 * xi - 1.0
    t = (1.0 - g * g) / (1.0 - g + 2.0 * g * xi)
    return np.clip((1.0 + g * g - t * t) / (2.0 * g), -1.0, 1.0)


def mc_radiance(
    atm: Atmosphere,
    r: float,
    mu: float,
    mu_s: float,
    nu: float,
    orders: int = 4,
    paths: int = 20000,
    seed: int = 0,
    batch: int = 5000,
    proposal_nodes: int = 128,
    gauss_nodes: int = 48,
) -> MCResult:
    """Radiance reaching an observer at radius r from direction (mu, mu_s, nu), per order.

    Args:
        atm: the atmosphere (read as float64 numpy).
        r: observer radius, inside the atmosphere. [m]
        mu, mu_s, nu: view zenith, sun zenith and view-sun cosines (a valid triple). [1]
        orders: number of orders tallied (1 = single scattering).
        paths: number of camera paths.
        seed: numpy Generator seed.

    Returns:
        MCResult with mean and standard error of each order, shapes (orders, W).
    """
    m = _Model(atm)
    rng = np.random.default_rng(seed)
    xg, wg = np.polynomial.legendre.leggauss(gauss_nodes)
    xg, wg = 0.5 * (xg + 1.0), 0.5 * wg
    sin_v = math.sqrt(max(1.0 - mu * mu, 0.0))
    w0 = np.array([sin_v, 0.0, mu])
    sx = (nu - mu * mu_s) / sin_v if sin_v > 1e-12 else math.sqrt(max(1.0 - mu_s * mu_s, 0.0))
    sy = math.sqrt(max(1.0 - sx * sx - mu_s * mu_s, 0.0))
    s = np.array([sx, sy, mu_s])
    s /= np.linalg.norm(s)
    n_w = m.bR.shape[0]
    ref = lambda v: float(np.mean(v))  # noqa: E731  spectral average for the proposals
    ext_ref = np.array([ref(m.bR), ref(m.eM), ref(m.oz)])
    sca_ref = np.array([ref(m.bR), ref(m.bM)])
    sums = np.zeros((orders, n_w))
    sq = np.zeros((orders, n_w))
    tk = np.linspace(0.0, 1.0, proposal_nodes + 1)
    done = 0
    while done < paths:
        P = min(batch, paths - done)
        done += P
        p = np.tile(np.array([0.0, 0.0, r]), (P, 1))
        w = np.tile(w0, (P, 1))
        wt = np.ones((P, n_w))
        tally = np.zeros((orders, P, n_w))
        for n in range(orders):
            length, hits = _exit_distance(p, w, m.Rb, m.Rt)
            # Piecewise-linear optical depth of the spectral-mean extinction (proposal only).
            tt = length[:, None] * tk[None, :]
            pts = p[:, None, :] + tt[..., None] * w[:, None, :]
            sig = m.densities(np.linalg.norm(pts, axis=-1)) @ ext_ref  # (P, K+1)
            dtau = 0.5 * (sig[:, 1:] + sig[:, :-1]) * np.diff(tt, axis=1)
            tau = np.concatenate([np.zeros((P, 1)), np.cumsum(dtau, axis=1)], axis=1)
            tau_l = tau[:, -1]
            # Vertex: the ground with probability exp(-tau_l) when the segment ends on it;
            # otherwise a point drawn from the mixture (1/2) exponential-like proposal on
            # the approximate optical depth + (1/2) uniform in distance (defensive, for
            # shadowed low layers at twilight).
            p_gnd = np.where(hits, np.exp(-tau_l), 0.0)
            to_ground = rng.random(P) < p_gnd
            znorm = -np.expm1(-tau_l)
            xi = rng.random(P)
            tau_star = -np.log1p(-xi * znorm)
            k = np.clip(np.sum(tau[:, 1:] <= tau_star[:, None], axis=1), 0, proposal_nodes - 1)
            rows = np.arange(P)
            dt_cell = np.diff(tt, axis=1)
            slope = np.maximum(dtau[rows, k] / np.maximum(dt_cell[rows, k], 1e-30), 1e-300)
            t_exp = np.clip(tt[rows, k] + (tau_star - tau[rows, k]) / slope, 0.0, length)
            t_uni = rng.random(P) * length
            t = np.where(rng.random(P) < 0.5, t_exp, t_uni)
            # mixture density at t (find t's cell on the proposal grid)
            kc = np.clip((t / np.maximum(length, 1e-30) * proposal_nodes).astype(int), 0, proposal_nodes - 1)
            slope_c = np.maximum(dtau[rows, kc] / np.maximum(dt_cell[rows, kc], 1e-30), 1e-300)
            tau_t = tau[rows, kc] + slope_c * (t - tt[rows, kc])
            q_exp = slope_c * np.exp(-tau_t) / np.maximum(znorm, 1e-300)
            pdf_vol = (1.0 - p_gnd) * (0.5 * q_exp + 0.5 / np.maximum(length, 1e-30))
            t = np.where(to_ground, length, t)
            y = p + t[:, None] * w
            cols = _columns(m, p, w, t, xg, wg)
            trans = np.exp(-cols @ m.ext)  # (P, W)
            pdf = np.where(to_ground, p_gnd, pdf_vol)
            wt = wt * trans / pdf[:, None]
            # ground vertices
            g_idx = np.nonzero(to_ground)[0]
            v_idx = np.nonzero(~to_ground)[0]
            new_w = w.copy()
            if g_idx.size:
                yg = y[g_idx]
                yg = yg / np.linalg.norm(yg, axis=-1, keepdims=True) * m.Rb
                y[g_idx] = yg
                normal = yg / m.Rb
                tally[n, g_idx] = wt[g_idx] * (m.albedo / math.pi) * _sun_factor(m, yg, s, xg, wg, ground=True)
                # cosine-weighted continuation: weight *= albedo
                u1, u2 = rng.random(g_idx.size), rng.random(g_idx.size)
                new_w[g_idx] = _rotate(normal, np.sqrt(u1), 2 * math.pi * u2)
                wt[g_idx] = wt[g_idx] * m.albedo
            if v_idx.size:
                yv = y[v_idx]
                wv = w[v_idx]
                dens = m.densities(np.linalg.norm(yv, axis=-1))
                sR = dens[:, 0:1] * m.bR  # (V, W)
                sM = dens[:, 1:2] * m.bM
                c_sun = _dot(wv, s)
                jsun = sR * _rayleigh(c_sun)[:, None] + sM * m.mie_phase(c_sun)[:, None]
                tally[n, v_idx] = wt[v_idx] * jsun * _sun_factor(m, yv, s, xg, wg, ground=False)
                # continuation: mixture of Rayleigh and HG, weights by the reference scattering
                aR = dens[:, 0] * sca_ref[0]
                aM = dens[:, 1] * sca_ref[1]
                cR = aR / np.maximum(aR + aM, 1e-300)
                pick_r = rng.random(v_idx.size) < cR
                xi2 = rng.random(v_idx.size)
                cos_t = np.where(pick_r, _sample_rayleigh(xi2), _sample_hg(xi2, m.g))
                phi = 2 * math.pi * rng.random(v_idx.size)
                wn = _rotate(wv, cos_t, phi)
                c = _dot(wv, wn)
                pdf_dir = cR * _rayleigh(c) + (1 - cR) * m.hg(c)
                f = sR * _rayleigh(c)[:, None] + sM * m.mie_phase(c)[:, None]
                wt[v_idx] = wt[v_idx] * f / pdf_dir[:, None]
                new_w[v_idx] = wn
            p, w = y, new_w
        sums += tally.sum(axis=1)
        sq += (tally**2).sum(axis=1)
    mean = sums / paths
    var = np.maximum(sq / paths - mean**2, 0.0)
    return MCResult(mean=mean, stderr=np.sqrt(var / paths), paths=paths)
