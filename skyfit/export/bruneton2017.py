"""``export-lut --layout bruneton2017``: the textures an unmodified Bruneton 2017 shader samples.

E. Bruneton, *Precomputed Atmospheric Scattering: a New Implementation* (2017),
github.com/ebruneton/precomputed_atmospheric_scattering: ``atmosphere/model.cc`` (what is
stored), ``atmosphere/functions.glsl`` (how it is sampled), ``atmosphere/demo/webgl`` (the
raw ``.dat`` files its WebGL demo loads). Bruneton & Neyret 2008 (Sec. 4, eq. 16) is the
method; docs/luts.md has the formulas. What the textures hold, as 2017's *precomputed
illuminance* mode (``num_precomputed_wavelengths > 3``) stores them:

- ``scattering`` (R * MU rows x NU * MU_S columns, RGBA; 2017's 3-D texture with its depth
  slices stacked): RGB = single Rayleigh (no phase function) + multiple scattering of orders
  2..N divided by the Rayleigh phase at the texel's nu (``kComputeMultipleScatteringShader``:
  ``delta_multiple_scattering / RayleighPhaseFunction(nu)``); A = the red channel of single
  Mie (no phase function), 2017's ``COMBINED_SCATTERING_TEXTURES`` layout.
- ``single_mie_scattering`` (same size, RGB): single Mie without phase function, for shaders
  built without ``COMBINED_SCATTERING_TEXTURES``.
- ``irradiance`` (16 x 64, RGB): indirect irradiance on a horizontal surface, orders 1..N-1
  (2017 keeps the direct sun out of it).
- ``transmittance`` (64 x 256, RGB): transmittance to the top of the atmosphere at
  lambda = 680, 550, 440 nm (2017's kLambdaR, G, B; ``Model::Init`` recomputes it there
  after the luminance passes).

Colour and units: the spectral tables are integrated against the CIE 1931 colour matching
functions and converted to linear sRGB (D65), without the 683 lm/W factor, so that half
floats do not overflow: ``SKY_SPECTRAL_RADIANCE_TO_LUMINANCE = 683`` restores luminance
(2017's Model constructor does exactly this in precomputed illuminance mode). Scattering
and irradiance textures are thus in "W/m^2 of sRGB-weighted light" [lm/m^2 / 683]; times a
phase function [1/sr] and 683 they give cd/m^2. ``SUN_SPECTRAL_RADIANCE_TO_LUMINANCE`` is the
linear sRGB luminance of the solar spectrum per unit of its value at kLambdaR, G, B [lm/W].

Precision: ``f16`` stores the scattering textures as half floats (2017's
``half_precision``); transmittance and irradiance stay float32, as 2017 keeps them
(``NewTexture2d`` is always RGBA32F: "16F precision for the transmittance gives artifacts").

The mu_s axis: upstream's current mapping takes ``A = (D - d_min) / (d_max - d_min)`` with D
the distance to the top at mu_s_min; the first 2017 release (and skyfit's tables) take
``A = -2 mu_s_min bottom / (d_max - d_min)``. Both are x = max(1 - a / A, 0) / (1 + a), so
skyfit's tables at ``mu_s_min = m`` are upstream's at :func:`upstream_mu_s_min` (m), texel for
texel: the export writes that value as the shader's MU_S_MIN and resamples nothing. The CLI
precomputes at :func:`skyfit_mu_s_min` (-0.2), so that MU_S_MIN is -0.2.
"""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import torch

from ..atmosphere import Atmosphere
from ..scattering.bruneton_tables import extinction_matrix3, scattering_texel_params
from ..scattering.multiple import PrecomputedAtmosphere
from ..scattering.phase import rayleigh_phase
from .lut import LutError, lut_folder, pack_scattering, rgb_matrix

LAMBDAS_RGB_NM = (680.0, 550.0, 440.0)
"""2017's kLambdaR, kLambdaG, kLambdaB [nm] (model.h): the wavelengths of the transmittance texture."""

MAX_LUMINOUS_EFFICACY = 683.0
"""[lm/W], 2017's MAX_LUMINOUS_EFFICACY (constants.h); divided out of the stored values."""

PRECISIONS = ("f16", "f32")
LENGTH_UNIT_M = 1000.0
"""Length unit of the GLSL constants and of the shader's positions [m] (2017's demo: kLengthUnitInMeters)."""

_FILES = {"transmittance": "transmittance", "scattering": "scattering", "single_mie_scattering": "single_mie_scattering",
          "irradiance": "irradiance"}
_DAT = {"transmittance": "transmittance.dat", "scattering": "scattering.dat", "irradiance": "irradiance.dat"}


def check_precision(precision: str) -> str:
    if precision not in PRECISIONS:
        raise LutError(f"unknown precision {precision!r}; valid: {', '.join(PRECISIONS)}")
    return precision


# -- the mu_s mapping ----------------------------------------------------------------------------------------------
def _distance_to_top(r, mu, top):
    return -r * mu + math.sqrt(max(r * r * (mu * mu - 1.0) + top * top, 0.0))


def upstream_mu_s_min(skyfit_mu_s_min: float, bottom: float, top: float) -> float:
    """The upstream 2017 ``mu_s_min`` whose mu_s mapping equals skyfit's tables' mapping at ``skyfit_mu_s_min``. [1]

    Both mappings are x = max(1 - a / A, 0) / (1 + a) with a = (d(mu_s) - d_min) / (d_max - d_min);
    skyfit (the first 2017 release) takes A = -2 mu_s_min bottom / (d_max - d_min), upstream
    A = (D - d_min) / (d_max - d_min) with D the distance to the top at mu_s_min. Equal A, equal
    texels: D = d_min + A (d_max - d_min), mu_s_min = (H^2 - D^2) / (2 bottom D).
    """
    H = math.sqrt(top * top - bottom * bottom)
    D = (top - bottom) - 2.0 * skyfit_mu_s_min * bottom  # d_min + A (d_max - d_min)
    return (H * H - D * D) / (2.0 * bottom * D)


def skyfit_mu_s_min(upstream: float, bottom: float, top: float) -> float:
    """Inverse of :func:`upstream_mu_s_min`: the ``precompute(mu_s_min=...)`` whose tables an upstream shader with
    ``mu_s_min = upstream`` samples exactly. [1]"""
    if not -1.0 < upstream < 0.0:
        raise LutError(f"mu_s_min must be in (-1, 0), got {upstream}")
    return -(_distance_to_top(bottom, upstream, top) - (top - bottom)) / (2.0 * bottom)


UPSTREAM_MU_S_MIN = -0.2
"""The ``mu_s_min`` of the bruneton2017 export (the shader's MU_S_MIN): sun zenith up to 101.5 deg. [1]"""


# -- the textures --------------------------------------------------------------------------------------------------
def _rgb_extinction(atm: Atmosphere, atm_rgb: Atmosphere | None) -> tuple[np.ndarray, dict, str]:
    """Extinction rows (3, 3) at 680/550/440 nm and the GLSL constants there; how they were obtained."""
    if atm_rgb is not None:
        lam = [float(v) for v in atm_rgb.wavelengths.tolist()]
        if lam != list(LAMBDAS_RGB_NM):
            raise LutError(f"the 2017 atmosphere must be on {LAMBDAS_RGB_NM} nm, got {lam}")
        ext = extinction_matrix3(atm_rgb).detach().cpu().double().numpy()
        get = lambda name: getattr(atm_rgb, name).detach().cpu().double().numpy()  # noqa: E731
        how = "exact: the atmosphere rebuilt on 680, 550, 440 nm"
    else:  # linear interpolation on the tables' wavelength grid (constant beyond its ends)
        grid = atm.wavelengths.detach().cpu().double().numpy()
        order = np.argsort(grid)
        lerp = lambda v: np.array([np.interp(l_, grid[order], np.asarray(v, float)[order]) for l_ in LAMBDAS_RGB_NM])  # noqa: E731
        ext = np.stack([lerp(row) for row in extinction_matrix3(atm).detach().cpu().double().numpy()])
        get = lambda name: lerp(getattr(atm, name).detach().cpu().double().numpy())  # noqa: E731
        how = "interpolated linearly in wavelength from the tables' grid"
    consts = {k: get(k) for k in ("solar_irradiance", "rayleigh_scattering", "mie_scattering", "mie_extinction",
                                  "ground_albedo")}
    return ext, consts, how


def bruneton2017_textures(tables: PrecomputedAtmosphere, atm_rgb: Atmosphere | None = None) -> tuple[dict, dict]:
    """The four 2017 textures as float64 arrays and the constants of the shader.

    Args:
        tables: from :func:`skyfit.scattering.multiple.precompute` (any wavelength grid).
        atm_rgb: the same atmosphere on :data:`LAMBDAS_RGB_NM` (transmittance and shader
            constants exact there); None: interpolated from the tables' grid.

    Returns:
        (textures, constants): ``scattering`` (R MU, NU MU_S, 4), ``single_mie_scattering``
        (R MU, NU MU_S, 3), ``irradiance`` (n_r, n_mu_s, 3), ``transmittance`` (n_r, n_mu, 3);
        constants for the GLSL header and lut.json (SI units).
    """
    tables.check_every_sun("2017's texture set")
    atm = tables.atm
    if atm.mie_phase not in ("cornette_shanks", "henyey_greenstein"):
        raise ValueError(f"Bruneton 2017's shader evaluates a one-lobe Mie phase (Cornette-Shanks or Henyey-Greenstein, "
                         f"one MIE_G); the {atm.mie_phase} phase has no place in its layout: export skyfit's own layout "
                         "(export-lut without --format bruneton2017), whose tables keep the phase out")
    m = rgb_matrix(atm.wavelengths).numpy() / MAX_LUMINOUS_EFFICACY  # (W, 3): spectrum -> sRGB without 683
    s = tables.sizes
    with torch.no_grad():
        tex = scattering_texel_params(atm.bottom_radius, atm.top_radius, tables.mu_s_min, s, torch.float64, "cpu")
        p_r = rayleigh_phase(tex.nu).numpy()[..., None]  # (R, MU, MU_S, NU, 1) at the texels' (clamped) nu
        ray = tables.single_rayleigh.detach().cpu().double().numpy() @ m
        mie = tables.single_mie.detach().cpu().double().numpy() @ m
        if tables.multiple is not None:
            ray = ray + (tables.multiple.detach().cpu().double().numpy() @ m) / p_r
        pack = lambda t: pack_scattering(torch.as_tensor(t))  # noqa: E731
        scattering = np.concatenate([pack(ray), pack(mie)[..., :1]], -1)
        irradiance = tables.irradiance.detach().cpu().double().numpy() @ m
        ext, consts, how = _rgb_extinction(atm, atm_rgb)
        cols = tables.transmittance_columns.detach().cpu().double().numpy()
        transmittance = np.exp(-cols @ ext)
        e_sun = atm.solar_irradiance.detach().cpu().double().numpy()
    sun_k = (e_sun @ rgb_matrix(atm.wavelengths).numpy()) / consts["solar_irradiance"]
    constants = {
        "lambdas_nm": list(LAMBDAS_RGB_NM), "constants_from": how,
        "bottom_radius_m": atm.bottom_radius, "top_radius_m": atm.top_radius,
        "mu_s_min": upstream_mu_s_min(tables.mu_s_min, atm.bottom_radius, atm.top_radius),
        "skyfit_mu_s_min": tables.mu_s_min,
        "sun_angular_radius_rad": atm.sun_angular_radius, "mie_g": float(atm.mie_g), "mie_phase": atm.mie_phase,
        **{f"{k}": v.tolist() for k, v in consts.items()},
        "sky_spectral_radiance_to_luminance": [MAX_LUMINOUS_EFFICACY] * 3,
        "sun_spectral_radiance_to_luminance": sun_k.tolist(),
        "sizes": {"TRANSMITTANCE_TEXTURE_WIDTH": s.transmittance_mu, "TRANSMITTANCE_TEXTURE_HEIGHT": s.transmittance_r,
                  "SCATTERING_TEXTURE_R_SIZE": s.scattering_r, "SCATTERING_TEXTURE_MU_SIZE": s.scattering_mu,
                  "SCATTERING_TEXTURE_MU_S_SIZE": s.scattering_mu_s, "SCATTERING_TEXTURE_NU_SIZE": s.scattering_nu,
                  "IRRADIANCE_TEXTURE_WIDTH": s.irradiance_mu_s, "IRRADIANCE_TEXTURE_HEIGHT": s.irradiance_r},
        "orders": tables.orders,
    }
    textures = {"scattering": scattering, "single_mie_scattering": pack(mie), "irradiance": irradiance,
                "transmittance": transmittance}
    return textures, constants


def stored(textures: dict, precision: str) -> dict:
    """The values as written: the scattering textures rounded to float16 for ``f16``, the rest float32 (2017)."""
    check_precision(precision)
    out = {}
    for k, v in textures.items():
        half = precision == "f16" and k in ("scattering", "single_mie_scattering")
        if half and np.nanmax(np.abs(v)) >= 65504.0:
            raise LutError(f"texture {k} exceeds the float16 range (max {np.nanmax(np.abs(v)):.4g}); use --precision f32")
        out[k] = v.astype(np.float16 if half else np.float32)
    return out


# -- files ---------------------------------------------------------------------------------------------------------
def _dat(a: np.ndarray) -> bytes:
    """2017's WebGL demo format (precompute.cc SaveTexture): RGBA float32 little endian, x fastest, then y, then z."""
    rgba = np.zeros(a.shape[:-1] + (4,), dtype="<f4")
    rgba[..., : a.shape[-1]] = a.astype(np.float32)
    return rgba.tobytes()


def _glsl_float(x) -> str:
    """A GLSL float literal (always with a point or an exponent)."""
    t = f"{float(x):.9g}"
    return t if any(c in t for c in ".en") else t + ".0"


def _glsl_vec3(v) -> str:
    return "vec3(" + ", ".join(_glsl_float(x) for x in v) + ")"


def glsl_source(c: dict) -> str:
    """The GLSL 3.30 lookup functions for the exported textures, with this atmosphere's constants."""
    from .glsl import TEMPLATE

    km = LENGTH_UNIT_M
    sizes = "\n".join(f"const int {k} = {v};" for k, v in c["sizes"].items())
    return TEMPLATE.substitute(
        sizes=sizes, bottom=_glsl_float(c["bottom_radius_m"] / km), top=_glsl_float(c["top_radius_m"] / km),
        mu_s_min=_glsl_float(c["mu_s_min"]), sun_radius=_glsl_float(c["sun_angular_radius_rad"]), mie_g=_glsl_float(c["mie_g"]),
        solar=_glsl_vec3(c["solar_irradiance"]), rayleigh=_glsl_vec3(np.asarray(c["rayleigh_scattering"]) * km),
        mie=_glsl_vec3(np.asarray(c["mie_scattering"]) * km), albedo=_glsl_vec3(c["ground_albedo"]),
        sky_k=_glsl_vec3(c["sky_spectral_radiance_to_luminance"]), sun_k=_glsl_vec3(c["sun_spectral_radiance_to_luminance"]),
        hg="1" if c["mie_phase"] == "henyey_greenstein" else "0", orders=c["orders"],
    )


def export_bruneton2017(tables: PrecomputedAtmosphere, out_dir: str | Path, *, precision: str = "f16",
                        atm_rgb: Atmosphere | None = None) -> Path:
    """Write the 2017 textures (EXR and the WebGL demo's raw .dat), ``atmosphere.glsl`` and ``lut.json``.

    Everything goes into a temporary directory beside ``out_dir``, moved into place when complete
    (``lut.json`` last), so a failure leaves nothing behind.

    Args:
        tables: from :func:`skyfit.scattering.multiple.precompute`.
        out_dir: target directory.
        precision: ``f16`` (scattering textures as half floats, 2017's default) or ``f32``.
        atm_rgb: the atmosphere on 680, 550, 440 nm (see :func:`bruneton2017_textures`).
    """
    from ..io import write_exr

    textures, consts = bruneton2017_textures(tables, atm_rgb)
    vals = stored(textures, precision)
    for k, v in vals.items():
        if not np.isfinite(v).all():
            raise LutError(f"texture {k} has non-finite values; nothing written")
    out = Path(out_dir)
    files = {k: f"{v}.exr" for k, v in _FILES.items()}
    meta = {
        "skyfit_lut": 1, "layout": "bruneton2017", "precision": precision,
        "source": "E. Bruneton, Precomputed Atmospheric Scattering: a New Implementation (2017), "
                  "github.com/ebruneton/precomputed_atmospheric_scattering (model.cc, functions.glsl, demo/webgl)",
        "files": {**files, "dat": dict(_DAT), "glsl": "atmosphere.glsl"},
        "channels": {"scattering": "R, G, B: single Rayleigh + multiple / RayleighPhase(nu); A: single Mie red",
                     "single_mie_scattering": "R, G, B", "irradiance": "R, G, B", "transmittance": "R, G, B at 680, 550, 440 nm"},
        "units": {"scattering": "linear sRGB / 683 of W/(m^2) (phase function not applied): x phase [1/sr] x 683 -> cd/m^2",
                  "irradiance": "linear sRGB / 683 of W/(m^2), horizontal surface, orders 1..N-1: x 683 -> lux",
                  "transmittance": "1", "lengths_in_glsl": "km"},
        "texture_layout": "2-D images: row 0 first (GL's t = 0); the 3-D scattering texture (width NU * MU_S, height MU, "
                          "depth R) with its depth slices stacked vertically: row = i_r * MU + i_mu, column = i_nu * MU_S + i_mu_s",
        "dat_format": "RGBA float32 little endian, x fastest then y then z (2017 demo/webgl/precompute.cc); "
                      "the demo's demo.js expects 2017's default sizes",
        "precision_note": "scattering textures in half floats for f16; transmittance and irradiance always float32 (2017)",
        "mu_s_mapping": "upstream: A = (D - d_min) / (d_max - d_min), D = distance to the top at mu_s_min "
                        "(constants.mu_s_min; the tables were computed at skyfit's equivalent constants.skyfit_mu_s_min)",
        "constants": consts,
    }
    with lut_folder(out) as tmp:
        for k, v in vals.items():
            ch = {c: v[..., i] for i, c in enumerate("RGBA"[: v.shape[-1]])}
            write_exr(tmp / files[k], ch, {"table": k, "layout": "bruneton2017", "precision": precision})
        for k, name in _DAT.items():
            (tmp / name).write_bytes(_dat(vals[k]))
        (tmp / "atmosphere.glsl").write_text(glsl_source(consts))
        (tmp / "lut.json").write_text(json.dumps(meta, indent=2))
    return out


def read_bruneton2017(lut_dir: str | Path) -> tuple[dict, dict]:
    """The textures (float32 arrays as stored, RGB[A] last) and ``lut.json`` of a bruneton2017 export."""
    from ..io import read_exr

    d = Path(lut_dir)
    try:
        meta = json.loads((d / "lut.json").read_text())
    except (OSError, ValueError) as e:
        raise LutError(f"{d}: not a LUT directory ({type(e).__name__})") from None
    if meta.get("layout") != "bruneton2017":
        raise LutError(f"{d / 'lut.json'}: not a bruneton2017 export")
    tex = {}
    for k in _FILES:
        ch, _ = read_exr(d / meta["files"][k])
        tex[k] = np.stack([ch[c] for c in "RGBA" if c in ch], -1)
    return tex, meta
