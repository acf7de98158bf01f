"""NumPy transcription of ``atmosphere.glsl`` (:mod:`skyfit.export.glsl`): what a GPU computes from the
``--layout bruneton2017`` files.

Written independently of skyfit's torch sampler (:mod:`skyfit.scattering.bruneton_tables`):
the textures are fetched as OpenGL does with ``GL_LINEAR`` and ``GL_CLAMP_TO_EDGE`` (texel
coordinate ``u n - 1/2``, the two neighbours weighted, indices clamped; OpenGL 4.6 core,
Sec. 8.14.2, eq. 8.9-8.11), from the files as they are stored (float16 values where the
export wrote half floats), and every GLSL function is a method of the same name, vectorised
over rays. Lengths in km, as the shader. The arithmetic is float64 (a GPU's float32 arithmetic
is not emulated; texture precision is).

Used by tests/test_bruneton2017.py and scripts/bruneton2017_accuracy.py to measure how well the
exported files reproduce ``skyfit render`` (docs/luts.md).
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np


def texture2d(img: np.ndarray, u, v) -> np.ndarray:
    """GL ``texture(sampler2D, vec2(u, v))``, linear, clamp to edge: img (height, width, C), u along the width."""
    h, w = img.shape[:2]
    x, y = np.asarray(u, float) * w - 0.5, np.asarray(v, float) * h - 0.5
    x0, y0 = np.floor(x), np.floor(y)
    fx, fy = (x - x0)[..., None], (y - y0)[..., None]
    xi = [np.clip(x0 + k, 0, w - 1).astype(int) for k in (0, 1)]
    yi = [np.clip(y0 + k, 0, h - 1).astype(int) for k in (0, 1)]
    return ((1 - fy) * ((1 - fx) * img[yi[0], xi[0]] + fx * img[yi[0], xi[1]])
            + fy * ((1 - fx) * img[yi[1], xi[0]] + fx * img[yi[1], xi[1]]))


def texture3d(vol: np.ndarray, u, v, w) -> np.ndarray:
    """GL ``texture(sampler3D, vec3(u, v, w))``, linear, clamp to edge: vol (depth, height, width, C)."""
    d = vol.shape[0]
    z = np.asarray(w, float) * d - 0.5
    z0 = np.floor(z)
    fz = (z - z0)[..., None]
    out = 0.0
    for k, wt in ((0, 1 - fz), (1, fz)):
        zi = np.clip(z0 + k, 0, d - 1).astype(int)
        h, wd = vol.shape[1:3]
        x, y = np.asarray(u, float) * wd - 0.5, np.asarray(v, float) * h - 0.5
        x0, y0 = np.floor(x), np.floor(y)
        fx, fy = (x - x0)[..., None], (y - y0)[..., None]
        xi = [np.clip(x0 + j, 0, wd - 1).astype(int) for j in (0, 1)]
        yi = [np.clip(y0 + j, 0, h - 1).astype(int) for j in (0, 1)]
        s = ((1 - fy) * ((1 - fx) * vol[zi, yi[0], xi[0]] + fx * vol[zi, yi[0], xi[1]])
             + fy * ((1 - fx) * vol[zi, yi[1], xi[0]] + fx * vol[zi, yi[1], xi[1]]))
        out = out + wt * s
    return out


def _smoothstep(e0, e1, x):
    t = np.clip((x - e0) / (e1 - e0), 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


class Bruneton2017Shader:
    """The GLSL functions of ``atmosphere.glsl`` on the exported textures.

    Args:
        textures: ``transmittance`` (n_r, n_mu, 3), ``scattering`` (R MU, NU MU_S, 4),
            ``single_mie_scattering`` (R MU, NU MU_S, 3), ``irradiance`` (n_r, n_mu_s, 3), as stored.
        constants: ``lut.json``'s ``constants`` (SI units; converted to km here).
        combined: the shader's ``COMBINED_SCATTERING_TEXTURES`` (single Mie from the alpha channel).
    """

    def __init__(self, textures: dict, constants: dict, combined: bool = True):
        c = constants
        km = 1000.0
        self.s = c["sizes"]
        self.BOTTOM_RADIUS, self.TOP_RADIUS = c["bottom_radius_m"] / km, c["top_radius_m"] / km
        self.MU_S_MIN, self.SUN_ANGULAR_RADIUS, self.MIE_G = c["mu_s_min"], c["sun_angular_radius_rad"], c["mie_g"]
        self.HG = c["mie_phase"] == "henyey_greenstein"
        self.SOLAR_IRRADIANCE = np.asarray(c["solar_irradiance"], float)
        self.RAYLEIGH_SCATTERING = np.asarray(c["rayleigh_scattering"], float) * km
        self.MIE_SCATTERING = np.asarray(c["mie_scattering"], float) * km
        self.GROUND_ALBEDO = np.asarray(c["ground_albedo"], float)
        self.SKY_K = np.asarray(c["sky_spectral_radiance_to_luminance"], float)
        self.SUN_K = np.asarray(c["sun_spectral_radiance_to_luminance"], float)
        self.combined = combined
        f = lambda a: np.asarray(a, np.float64)  # noqa: E731  (stored float16/32 values, exactly)
        R, MU = self.s["SCATTERING_TEXTURE_R_SIZE"], self.s["SCATTERING_TEXTURE_MU_SIZE"]
        self.transmittance_texture = f(textures["transmittance"])
        self.irradiance_texture = f(textures["irradiance"])
        sc = f(textures["scattering"])
        self.scattering_texture = sc.reshape(R, MU, sc.shape[1], sc.shape[2])
        sm = f(textures["single_mie_scattering"])
        self.single_mie_scattering_texture = sm.reshape(R, MU, sm.shape[1], sm.shape[2])

    @classmethod
    def from_dir(cls, lut_dir: str | Path, combined: bool = True) -> "Bruneton2017Shader":
        """From an ``export-lut --layout bruneton2017`` directory (the EXR files)."""
        from .bruneton2017 import read_bruneton2017

        tex, meta = read_bruneton2017(lut_dir)
        return cls(tex, meta["constants"], combined)

    # -- functions.glsl's helpers ------------------------------------------------------------------
    def distance_to_top(self, r, mu):
        return np.maximum(-r * mu + np.sqrt(np.maximum(r * r * (mu * mu - 1.0) + self.TOP_RADIUS ** 2, 0.0)), 0.0)

    def distance_to_bottom(self, r, mu):
        return np.maximum(-r * mu - np.sqrt(np.maximum(r * r * (mu * mu - 1.0) + self.BOTTOM_RADIUS ** 2, 0.0)), 0.0)

    def ray_intersects_ground(self, r, mu):
        return (mu < 0.0) & (r * r * (mu * mu - 1.0) + self.BOTTOM_RADIUS ** 2 >= 0.0)

    @staticmethod
    def coord(x, n: int):
        """GetTextureCoordFromUnitRange."""
        return 0.5 / n + x * (1.0 - 1.0 / n)

    # -- transmittance -----------------------------------------------------------------------------
    def transmittance_uv(self, r, mu):
        b, t = self.BOTTOM_RADIUS, self.TOP_RADIUS
        H = math.sqrt(t * t - b * b)
        rho = np.sqrt(np.maximum(r * r - b * b, 0.0))
        d = self.distance_to_top(r, mu)
        d_min, d_max = t - r, rho + H
        return (self.coord((d - d_min) / (d_max - d_min), self.s["TRANSMITTANCE_TEXTURE_WIDTH"]),
                self.coord(rho / H, self.s["TRANSMITTANCE_TEXTURE_HEIGHT"]))

    def transmittance_to_top(self, r, mu):
        u, v = self.transmittance_uv(r, mu)
        return texture2d(self.transmittance_texture, u, v)

    def transmittance(self, r, mu, d, hits):
        r_d = np.clip(np.sqrt(d * d + 2.0 * r * mu * d + r * r), self.BOTTOM_RADIUS, self.TOP_RADIUS)
        mu_d = np.clip((r * mu + d) / r_d, -1.0, 1.0)
        ground = self.transmittance_to_top(r_d, -mu_d) / self.transmittance_to_top(r, -mu)
        sky = self.transmittance_to_top(r, mu) / self.transmittance_to_top(r_d, mu_d)
        return np.minimum(np.where(hits[..., None], ground, sky), 1.0)

    def transmittance_to_sun(self, r, mu_s):
        sin_h = self.BOTTOM_RADIUS / r
        cos_h = -np.sqrt(np.maximum(1.0 - sin_h * sin_h, 0.0))
        w = sin_h * self.SUN_ANGULAR_RADIUS
        return self.transmittance_to_top(r, mu_s) * _smoothstep(-w, w, mu_s - cos_h)[..., None]

    # -- phase functions ---------------------------------------------------------------------------
    @staticmethod
    def rayleigh_phase(nu):
        return 3.0 / (16.0 * math.pi) * (1.0 + nu * nu)

    def mie_phase(self, g, nu):
        if self.HG:
            return (1.0 - g * g) / (4.0 * math.pi * (1.0 + g * g - 2.0 * g * nu) ** 1.5)
        k = 3.0 / (8.0 * math.pi) * (1.0 - g * g) / (2.0 + g * g)
        return k * (1.0 + nu * nu) / (1.0 + g * g - 2.0 * g * nu) ** 1.5

    # -- scattering --------------------------------------------------------------------------------
    def scattering_uvwz(self, r, mu, mu_s, nu, hits):
        b, t = self.BOTTOM_RADIUS, self.TOP_RADIUS
        s = self.s
        H = math.sqrt(t * t - b * b)
        rho = np.sqrt(np.maximum(r * r - b * b, 0.0))
        u_r = self.coord(rho / H, s["SCATTERING_TEXTURE_R_SIZE"])
        r_mu = r * mu
        disc = r_mu * r_mu - r * r + b * b
        half = s["SCATTERING_TEXTURE_MU_SIZE"] // 2
        d_g = -r_mu - np.sqrt(np.maximum(disc, 0.0))
        dmin_g, dmax_g = r - b, rho
        same = dmax_g == dmin_g
        x_g = np.where(same, 0.0, (d_g - dmin_g) / np.where(same, 1.0, dmax_g - dmin_g))
        d_t = -r_mu + np.sqrt(np.maximum(disc + H * H, 0.0))
        x_t = (d_t - (t - r)) / (rho + H - (t - r))
        u_mu = np.where(hits, 0.5 - 0.5 * self.coord(x_g, half), 0.5 + 0.5 * self.coord(x_t, half))
        d = self.distance_to_top(b, mu_s)
        d_min, d_max = t - b, H
        a = (d - d_min) / (d_max - d_min)
        A = (self.distance_to_top(b, self.MU_S_MIN) - d_min) / (d_max - d_min)
        u_mu_s = self.coord(np.maximum(1.0 - a / A, 0.0) / (1.0 + a), s["SCATTERING_TEXTURE_MU_S_SIZE"])
        u_nu = (nu + 1.0) / 2.0
        return u_nu, u_mu_s, u_mu, u_r

    def extrapolated_single_mie(self, sc):
        r = sc[..., :1]
        ok = r > 0.0
        k = (self.RAYLEIGH_SCATTERING[0] / self.MIE_SCATTERING[0]) * (self.MIE_SCATTERING / self.RAYLEIGH_SCATTERING)
        return np.where(ok, sc[..., :3] * sc[..., 3:4] / np.where(ok, r, 1.0) * k, 0.0)

    def combined_scattering(self, r, mu, mu_s, nu, hits):
        """(scattering RGB, single Mie RGB), each (..., 3) (GetCombinedScattering)."""
        nn = self.s["SCATTERING_TEXTURE_NU_SIZE"]
        u_nu, u_mu_s, u_mu, u_r = self.scattering_uvwz(r, mu, mu_s, nu, hits)
        tex_coord_x = u_nu * (nn - 1)
        tex_x = np.floor(tex_coord_x)
        lerp = (tex_coord_x - tex_x)[..., None]
        x0, x1 = (tex_x + u_mu_s) / nn, (tex_x + 1.0 + u_mu_s) / nn
        fetch = lambda vol: (texture3d(vol, x0, u_mu, u_r) * (1 - lerp) + texture3d(vol, x1, u_mu, u_r) * lerp)  # noqa: E731
        comb = fetch(self.scattering_texture)
        mie = self.extrapolated_single_mie(comb) if self.combined else fetch(self.single_mie_scattering_texture)
        return comb[..., :3], mie

    # -- irradiance --------------------------------------------------------------------------------
    def irradiance(self, r, mu_s):
        b, t = self.BOTTOM_RADIUS, self.TOP_RADIUS
        u = self.coord(mu_s * 0.5 + 0.5, self.s["IRRADIANCE_TEXTURE_WIDTH"])
        v = self.coord((r - b) / (t - b), self.s["IRRADIANCE_TEXTURE_HEIGHT"])
        return texture2d(self.irradiance_texture, u, v)

    # -- the API -----------------------------------------------------------------------------------
    def sky_luminance(self, camera, view_ray, sun_direction):
        """GetSkyLuminance: (luminance (N, 3) [cd/m^2], transmittance (N, 3)); camera (N, 3) in km from the centre."""
        camera = np.array(camera, float, copy=True)
        view_ray = np.asarray(view_ray, float)
        sun = np.asarray(sun_direction, float)
        r = np.linalg.norm(camera, axis=-1)
        rmu = (camera * view_ray).sum(-1)
        with np.errstate(invalid="ignore"):
            dist = -rmu - np.sqrt(rmu * rmu - r * r + self.TOP_RADIUS ** 2)
        move = dist > 0.0
        camera = np.where(move[..., None], camera + view_ray * np.where(move, dist, 0.0)[..., None], camera)
        space = ~move & (r > self.TOP_RADIUS)
        rmu = np.where(move, rmu + np.where(move, dist, 0.0), rmu)
        r = np.where(move, self.TOP_RADIUS, r)
        mu = rmu / r
        mu_s = (camera * sun).sum(-1) / r
        nu = (view_ray * sun).sum(-1)
        hits = self.ray_intersects_ground(r, mu)
        trans = np.where(hits[..., None], 0.0, self.transmittance_to_top(r, mu))
        scattering, mie = self.combined_scattering(r, mu, mu_s, nu, hits)
        lum = (scattering * self.rayleigh_phase(nu)[..., None] + mie * self.mie_phase(self.MIE_G, nu)[..., None]) * self.SKY_K
        return np.where(space[..., None], 0.0, lum), np.where(space[..., None], 1.0, trans)

    def sun_and_sky_illuminance(self, p, normal, sun_direction):
        """GetSunAndSkyIlluminance: (sun, sky) illuminance [lux], each (N, 3)."""
        r = np.linalg.norm(p, axis=-1)
        mu_s = (p * sun_direction).sum(-1) / r
        sky = self.irradiance(r, mu_s) * ((1.0 + (normal * p).sum(-1) / r) * 0.5)[..., None] * self.SKY_K
        cos = np.maximum((normal * sun_direction).sum(-1), 0.0)
        return self.SOLAR_IRRADIANCE * self.transmittance_to_sun(r, mu_s) * cos[..., None] * self.SUN_K, sky

    def sky_and_ground_luminance(self, camera, view_ray, sun_direction):
        """GetSkyAndGroundLuminance [cd/m^2], (N, 3): the sky, plus the lit ground for rays that hit it."""
        camera = np.asarray(camera, float)
        view_ray = np.asarray(view_ray, float)
        sky, _ = self.sky_luminance(camera, view_ray, sun_direction)
        r = np.linalg.norm(camera, axis=-1)
        mu = (camera * view_ray).sum(-1) / r
        hits = self.ray_intersects_ground(r, mu) & (r <= self.TOP_RADIUS)
        d = self.distance_to_bottom(r, mu)
        p = camera + view_ray * d[..., None]
        normal = p / np.linalg.norm(p, axis=-1, keepdims=True)
        sun_e, sky_e = self.sun_and_sky_illuminance(self.BOTTOM_RADIUS * normal, normal, np.asarray(sun_direction, float))
        ground = self.GROUND_ALBEDO / math.pi * (sun_e + sky_e)
        return sky + np.where(hits[..., None], self.transmittance(r, mu, d, hits) * ground, 0.0)

    def solar_luminance(self):
        """GetSolarLuminance [cd/m^2], (3,)."""
        return self.SOLAR_IRRADIANCE / (math.pi * self.SUN_ANGULAR_RADIUS ** 2) * self.SUN_K


# -- accuracy against skyfit's own render -----------------------------------------------------------------------
BANDS_DEG = ((0.0, 30.0), (30.0, 60.0), (60.0, 80.0), (80.0, 85.0), (85.0, 88.0), (88.0, 90.0), (90.0, 180.0))
"""View-zenith bands of the accuracy table [deg]; the last is the ground."""


def view_grid(zenith_step_deg: float = 0.5, azimuth_step_deg: float = 15.0) -> np.ndarray:
    """Unit ENU view directions: zenith (k + 1/2) step, k = 0.., up to 180 deg, times azimuths 0, step, ..., (N, 3)."""
    th = np.radians(np.arange(0.5 * zenith_step_deg, 180.0, zenith_step_deg))
    ph = np.radians(np.arange(0.0, 360.0, azimuth_step_deg))
    TH, PH = np.meshgrid(th, ph, indexing="ij")
    return np.stack([np.sin(TH) * np.sin(PH), np.sin(TH) * np.cos(PH), np.cos(TH)], -1).reshape(-1, 3)


def skyfit_luminance(tables, view: np.ndarray, sun: np.ndarray, altitude_m: float = 0.0) -> np.ndarray:
    """skyfit's render (``sky_radiance`` on the in-memory tables, ground included) as linear sRGB [cd/m^2], (N, 3)."""
    import torch

    from ..scattering.multiple import sky_radiance
    from .lut import rgb_matrix

    atm = tables.atm
    v = torch.as_tensor(view, dtype=torch.float64)
    s = torch.as_tensor(sun, dtype=torch.float64)
    r = torch.full_like(v[:, 2], atm.bottom_radius + altitude_m)
    with torch.no_grad():
        L = sky_radiance(tables, None, r, v[:, 2], s[2].expand_as(r), v @ s)
    return L.cpu().double().numpy() @ rgb_matrix(atm.wavelengths).numpy()


def relative_errors(shader: Bruneton2017Shader, tables, view: np.ndarray, sun_zenith_deg: float,
                    altitude_m: float = 0.0, sun_azimuth_deg: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """|shader - skyfit| / skyfit per direction and channel (N, 3), and skyfit's values (N, 3), for one sun."""
    z, a = math.radians(sun_zenith_deg), math.radians(sun_azimuth_deg)
    sun = np.array([math.sin(z) * math.sin(a), math.sin(z) * math.cos(a), math.cos(z)])
    ref = skyfit_luminance(tables, view, sun, altitude_m)
    cam = np.tile([0.0, 0.0, (tables.atm.bottom_radius + altitude_m) / 1000.0], (view.shape[0], 1))
    got = shader.sky_and_ground_luminance(cam, view, sun)
    return np.abs(got - ref) / np.maximum(ref, 1e-300), ref


def band_table(errors: np.ndarray, view: np.ndarray, bands=BANDS_DEG) -> list[dict]:
    """Median, 99th percentile and max of per-channel relative errors in each view-zenith band."""
    zen = np.degrees(np.arccos(np.clip(view[:, 2], -1.0, 1.0)))
    rows = []
    for lo, hi in bands:
        sel = (zen >= lo) & (zen < hi)
        e = errors[sel].ravel()
        rows.append({"band_deg": [lo, hi], "n": int(sel.sum()), "median": float(np.median(e)),
                     "p99": float(np.percentile(e, 99)), "max": float(e.max())})
    return rows
