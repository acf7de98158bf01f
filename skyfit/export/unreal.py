"""``export-lut --layout unreal``: Unreal Engine SkyAtmosphere parameters and Hillaire 2020's LUT set.

S. Hillaire, "A Scalable and Production Ready Sky and Atmosphere Rendering Technique", EGSR 2020
(the method behind Unreal's SkyAtmosphere component; LUT parametrisations from its sample code,
github.com/sebh/UnrealEngineSkyAtmosphere, ``RenderSkyCommon.hlsl``). docs/luts.md has the
mapping table and the parametrisations.

SkyAtmosphere (``USkyAtmosphereComponent``, Engine/Classes/Components/SkyAtmosphereComponent.h)
takes lengths in km and coefficients in 1/km as ``Scale x Color``: a scalar scale and a linear
colour whose channels are the coefficient at the red, green and blue "wavelengths". Its defaults
are Bruneton 2017's Earth at 680, 550, 440 nm (RayleighScatteringScale 0.0331 x (0.175287,
0.409607, 1.0) = 5.802e-3, 13.558e-3, 33.1e-3 /km), so the fitted atmosphere is sampled at those
wavelengths, the colour normalised to a largest channel of 1. What the component cannot hold is
listed by :func:`unreal_parameters` for the atmosphere at hand (spectral detail between the three
samples, a Cornette-Shanks phase (Unreal's Mie is Henyey-Greenstein), a negative or >= 0.999 g,
an asymmetric ozone tent, a ground albedo finer than 8-bit sRGB, the solar spectrum).
"""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import torch

from ..atmosphere import Atmosphere
from ..atmosphere.profiles import profile_densities
from ..geometry import distance_to_top
from ..render.colour import spectral_to_xyz, xyz_to_linear_srgb
from ..scattering.bruneton_tables import extinction_matrix3
from ..scattering.hillaire import hillaire_lut, hillaire_sky_radiance
from ..transmittance import make_integrator
from .bruneton2017 import LAMBDAS_RGB_NM
from .lut import LutError, lut_folder, rgb_matrix

KM = 1000.0
TRANSMITTANCE_SIZE = (256, 64)
"""Hillaire's transmittance LUT (width x_mu, height x_r), as Unreal's default."""
MULTISCATTERING_SIZE = 32
"""Hillaire's multiple-scattering LUT, 32 x 32 (paper Sec. 5.5)."""
SKYVIEW_SIZE = (192, 108)
"""Hillaire's sky-view LUT (width: azimuth from the sun, height: view zenith), paper Sec. 5.3."""


def _xyz_to_srgb() -> np.ndarray:
    from ..render.colour import xyz_to_srgb_matrix

    return xyz_to_srgb_matrix()


def _srgb_encode(x: np.ndarray) -> np.ndarray:
    x = np.clip(x, 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)


def _srgb_decode(c: np.ndarray) -> np.ndarray:
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def _scale_color(v: np.ndarray) -> tuple[float, list[float]]:
    s = float(np.max(v))
    return (s, [float(x) for x in (v / s)]) if s > 0 else (0.0, [1.0, 1.0, 1.0])


def unreal_parameters(atm_rgb: Atmosphere) -> dict:
    """SkyAtmosphere component properties of an atmosphere given on 680, 550, 440 nm (SkyAtmosphereComponent.h).

    Returns:
        ``{"SkyAtmosphere": {property: value}, "DirectionalLight": {...}, "units": {...},
        "not_represented": [...]}``; colours as [R, G, B], GroundAlbedo as 8-bit sRGB [R, G, B, A].
    """
    lam = [float(v) for v in atm_rgb.wavelengths.tolist()]
    if lam != list(LAMBDAS_RGB_NM):
        raise LutError(f"the Unreal export samples the atmosphere on {LAMBDAS_RGB_NM} nm, got {lam}")
    g = lambda name: getattr(atm_rgb, name).detach().cpu().double().numpy()  # noqa: E731
    ray_s, ray_c = _scale_color(g("rayleigh_scattering") * KM)
    mie_sc = g("mie_scattering") * KM
    mie_s, mie_c = _scale_color(mie_sc)
    abs_s, abs_c = _scale_color((g("mie_extinction") * KM - mie_sc).clip(min=0.0))
    notes = ["spectral detail: the coefficients are sampled at 680, 550, 440 nm (Unreal's three channels)"]
    oz = atm_rgb.ozone_absorption
    o_s, o_c = _scale_color(oz.detach().cpu().double().numpy() * KM) if oz is not None else (0.0, [1.0, 1.0, 1.0])
    lo, peak, hi = (v / KM for v in atm_rgb.ozone_layer_m)
    width = 0.5 * ((peak - lo) + (hi - peak))
    if abs((peak - lo) - (hi - peak)) > 1e-9:
        notes.append(f"ozone tent {lo:g}-{peak:g}-{hi:g} km is asymmetric; Unreal's is symmetric: width {width:g} km")
    mg = float(atm_rgb.mie_g)
    if atm_rgb.mie_phase != "henyey_greenstein":
        notes.append(f"Mie phase {atm_rgb.mie_phase}: Unreal evaluates Henyey-Greenstein with the same g"
                     + (" (the forward lobe g1; the backward lobe is dropped)" if atm_rgb.mie_phase == "two_term_hg" else "")
                     + (" (the log-normal size distribution's asymmetry at 550 nm; its per-wavelength phase, Angstrom "
                        "exponent and albedo are sampled at the three channels)" if atm_rgb.mie_phase == "lognormal_mie" else ""))
    if atm_rgb.mie_profile != "exponential":
        notes.append(f"Mie profile {atm_rgb.mie_profile} (mixing height {float(atm_rgb.mie_mixing_height):g} m): "
                     "Unreal's aerosol is exponential from the ground with the same scale height")
    if not 0.0 <= mg <= 0.999:
        notes.append(f"mie_g {mg:.4g} outside Unreal's MieAnisotropy range [0, 0.999]: clamped")
    mg_u = min(max(mg, 0.0), 0.999)
    alb = g("ground_albedo")
    alb8 = np.round(_srgb_encode(alb) * 255.0).astype(int)
    if np.max(np.abs(_srgb_decode(alb8 / 255.0) - alb)) > 1e-6:
        notes.append(f"ground albedo {np.round(alb, 4).tolist()} rounded to 8-bit sRGB {alb8.tolist()} "
                     f"(linear {np.round(_srgb_decode(alb8 / 255.0), 4).tolist()})")
    notes.append("the sun: a directional light of the given top-of-atmosphere illuminance and colour; "
                 "Unreal has no solar spectrum")
    e_sun = g("solar_irradiance")
    params = {
        "TransformMode": "PlanetTopAtAbsoluteWorldOrigin",
        "BottomRadius": atm_rgb.bottom_radius / KM,
        "GroundAlbedo": [*alb8.tolist(), 255],
        "AtmosphereHeight": (atm_rgb.top_radius - atm_rgb.bottom_radius) / KM,
        "MultiScatteringFactor": 1.0,
        "RayleighScatteringScale": ray_s, "RayleighScattering": ray_c,
        "RayleighExponentialDistribution": float(atm_rgb.rayleigh_scale_height) / KM,
        "MieScatteringScale": mie_s, "MieScattering": mie_c,
        "MieAbsorptionScale": abs_s, "MieAbsorption": abs_c,
        "MieAnisotropy": mg_u,
        "MieExponentialDistribution": float(atm_rgb.mie_scale_height) / KM,
        "OtherAbsorptionScale": o_s, "OtherAbsorption": o_c,
        "OtherTentDistribution": {"TipAltitude": peak, "TipValue": 1.0 if oz is not None else 0.0, "Width": width},
    }
    return {
        "SkyAtmosphere": params,
        "DirectionalLight": {"solar_irradiance_W_m2_nm_at_680_550_440": e_sun.tolist(),
                             "sun_angular_diameter_deg": math.degrees(2 * atm_rgb.sun_angular_radius)},
        "units": {"BottomRadius, AtmosphereHeight, *ExponentialDistribution, TipAltitude, Width": "km",
                  "*Scale x *Color": "1/km, per channel R, G, B = 680, 550, 440 nm",
                  "GroundAlbedo": "FColor, 8-bit sRGB-encoded", "MieAnisotropy": "Henyey-Greenstein g"},
        "not_represented": notes,
    }


def atmosphere_from_unreal(params: dict, like: Atmosphere) -> Atmosphere:
    """The atmosphere an Unreal SkyAtmosphere with ``params`` describes, on 680, 550, 440 nm (Henyey-Greenstein).

    ``like`` (on the same wavelengths) gives what the component does not hold: the solar
    irradiance and the sun's angular radius.
    """
    p = params["SkyAtmosphere"] if "SkyAtmosphere" in params else params
    dt, dev = like.dtype, like.device
    T = lambda v: torch.as_tensor(v, dtype=dt, device=dev)  # noqa: E731
    sc = lambda s, c: T(np.asarray(c, float) * s / KM)  # noqa: E731  1/km -> 1/m
    mie_s = sc(p["MieScatteringScale"], p["MieScattering"])
    tent = p["OtherTentDistribution"]
    w = tent["Width"]
    return Atmosphere(
        wavelengths=T(list(LAMBDAS_RGB_NM)), bottom_radius=p["BottomRadius"] * KM,
        top_radius=(p["BottomRadius"] + p["AtmosphereHeight"]) * KM,
        rayleigh_scattering=sc(p["RayleighScatteringScale"], p["RayleighScattering"]),
        rayleigh_scale_height=T(p["RayleighExponentialDistribution"] * KM),
        mie_scattering=mie_s, mie_extinction=mie_s + sc(p["MieAbsorptionScale"], p["MieAbsorption"]),
        mie_scale_height=T(p["MieExponentialDistribution"] * KM), mie_g=T(p["MieAnisotropy"]),
        ground_albedo=T(_srgb_decode(np.asarray(p["GroundAlbedo"][:3], float) / 255.0)),
        solar_irradiance=like.solar_irradiance, ozone_absorption=sc(p["OtherAbsorptionScale"] * tent["TipValue"],
                                                                    p["OtherAbsorption"]),
        ozone_layer_m=(max(tent["TipAltitude"] - w, 0.0) * KM, tent["TipAltitude"] * KM, (tent["TipAltitude"] + w) * KM),
        sun_angular_radius=like.sun_angular_radius, mie_phase="henyey_greenstein", name="unreal",
    )


# -- Hillaire's LUTs -------------------------------------------------------------------------------------------------
def _columns(atm: Atmosphere, r: torch.Tensor, mu: torch.Tensor, samples: int = 500) -> torch.Tensor:
    """Optical lengths (Rayleigh, Mie, ozone) from (r, mu) to the top, trapezoid rule, shape (..., 3). [m]"""
    x = torch.linspace(0.0, 1.0, samples + 1, dtype=r.dtype, device=r.device)
    w = torch.full_like(x, 1.0 / samples)
    w[0] *= 0.5
    w[-1] *= 0.5
    rr, mm = r.reshape(-1, 1), mu.reshape(-1, 1)
    d = distance_to_top(rr, mm, atm.top_radius)
    s = d * x
    r_s = torch.sqrt(torch.clamp_min(s * s + 2.0 * rr * mm * s + rr * rr, 0.0))
    col = torch.einsum("nsk,s->nk", profile_densities(r_s - atm.bottom_radius, atm), w) * d
    return col.reshape(*r.shape, 3)


def transmittance_lut(atm: Atmosphere, size: tuple[int, int] = TRANSMITTANCE_SIZE) -> np.ndarray:
    """Hillaire's transmittance LUT, shape (height, width, W): T to the top at the texel centres. [1]

    Texel (row j, column i): x_mu = (i + 0.5) / width, x_r = (j + 0.5) / height (UvToLutTransmittanceParams,
    no sub-UV remapping); rho = H x_r, r = sqrt(rho^2 + bottom^2), d = d_min + x_mu (d_max - d_min) with
    d_min = top - r, d_max = rho + H, mu = (H^2 - rho^2 - d^2) / (2 r d).
    """
    nw, nh = size
    b, t = atm.bottom_radius, atm.top_radius
    H = math.sqrt(t * t - b * b)
    x_mu = (torch.arange(nw, dtype=atm.dtype) + 0.5) / nw
    x_r = (torch.arange(nh, dtype=atm.dtype) + 0.5) / nh
    rho = H * x_r[:, None]
    r = torch.sqrt(rho * rho + b * b)
    d_min, d_max = t - r, rho + H
    d = d_min + x_mu[None, :] * (d_max - d_min)
    mu = torch.clamp((H * H - rho * rho - d * d) / (2.0 * r * d), -1.0, 1.0)
    r, mu = torch.broadcast_tensors(r, mu)
    with torch.no_grad():
        return torch.exp(-_columns(atm, r, mu) @ extinction_matrix3(atm)).cpu().numpy()


def skyview_directions(size: tuple[int, int], sun_zenith_deg: float, altitude_m: float, bottom: float):
    """ENU view directions of the sky-view LUT texels (sun at azimuth 0), shape (height, width, 3).

    Hillaire's UvToSkyViewLutParams with his non-linear (squared) mapping: u, v = fromSubUvsToUnit
    (texel centres on 0 and 1); cos(azimuth from the sun) = -(2 u^2 - 1) (u = 0 towards the sun);
    v < 1/2: view zenith = Z (1 - (1 - 2 v)^2), v >= 1/2: Z + beta (2 v - 1)^2, with
    beta = acos(sqrt(r^2 - bottom^2) / r) the horizon's depression and Z = pi - beta.
    """
    nw, nh = size
    u = np.arange(nw) / (nw - 1)
    v = np.arange(nh) / (nh - 1)
    r = bottom + altitude_m
    beta = math.acos(math.sqrt(max(r * r - bottom * bottom, 0.0)) / r)
    zh = math.pi - beta
    zen = np.where(v < 0.5, zh * (1.0 - (1.0 - 2.0 * v) ** 2), zh + beta * (2.0 * v - 1.0) ** 2)
    cos_az = -(2.0 * u * u - 1.0)
    az = np.arccos(np.clip(cos_az, -1.0, 1.0))
    Z, A = np.meshgrid(zen, az, indexing="ij")
    return np.stack([np.sin(Z) * np.sin(A), np.sin(Z) * np.cos(A), np.cos(Z)], -1)


def skyview_lut(atm: Atmosphere, sun_zenith_deg: float, size: tuple[int, int] = SKYVIEW_SIZE, altitude_m: float = 0.0,
                view_samples: int = 32, lut=None) -> np.ndarray:
    """Hillaire's sky-view LUT of ``atm`` for one sun: linear sRGB luminance [cd/m^2], shape (height, width, 3).

    Rendered by skyfit with Hillaire 2020's model (single scattering integrated along each view ray,
    Gauss-Legendre optical depth, plus the Psi_ms term) on the atmosphere's wavelength grid.
    """
    d = torch.as_tensor(skyview_directions(size, sun_zenith_deg, altitude_m, atm.bottom_radius), dtype=atm.dtype)
    z = math.radians(sun_zenith_deg)
    sun = torch.tensor([0.0, math.sin(z), math.cos(z)], dtype=atm.dtype)
    flat = d.reshape(-1, 3)
    r = torch.full_like(flat[:, 2], atm.bottom_radius + altitude_m)
    with torch.no_grad():
        lut = lut or hillaire_lut(atm)
        rad = hillaire_sky_radiance(atm, r, flat[:, 2], sun[2].expand_as(r), flat @ sun, make_integrator("gauss", samples=16),
                                    view_samples, lut=lut)
        rgb = xyz_to_linear_srgb(spectral_to_xyz(rad, atm.wavelengths))
    return rgb.reshape(*d.shape[:2], 3).cpu().numpy()


def export_unreal(atm: Atmosphere, atm_rgb: Atmosphere, out_dir: str | Path, *, sun_zeniths=(45.0,),
                  altitude_m: float = 0.0) -> Path:
    """Write ``unreal.json`` (SkyAtmosphere properties) and Hillaire's LUTs as EXR into ``out_dir``.

    Args:
        atm: the fitted atmosphere on its spectral grid (for the sky-view LUTs, in sRGB).
        atm_rgb: the same atmosphere on 680, 550, 440 nm (parameters, transmittance and multi-scattering LUTs).
        sun_zeniths: one sky-view LUT per sun zenith angle. [deg]
        altitude_m: observer altitude of the sky-view LUTs. [m]
    """
    from ..io import write_exr

    zs = [float(z) for z in sun_zeniths]
    if not zs or not all(0.0 <= z <= 180.0 for z in zs):
        raise LutError(f"sun zenith angles for the sky-view LUTs must be in [0, 180] deg, got {sun_zeniths}")
    params = unreal_parameters(atm_rgb)

    sun_rgb = atm.solar_irradiance.detach().cpu().double().numpy() @ rgb_matrix(atm.wavelengths).numpy()  # lux per channel
    y = float(sun_rgb @ np.linalg.inv(_xyz_to_srgb())[1])
    params["DirectionalLight"].update({"illuminance_lux": y, "color_linear_srgb": (sun_rgb / sun_rgb.max()).tolist(),
                                       "note": "top-of-atmosphere; Unreal's SkyAtmosphere attenuates it (atmosphere sun light)"})
    with torch.no_grad():
        trans = transmittance_lut(atm_rgb)
        ms = hillaire_lut(atm_rgb, size=(MULTISCATTERING_SIZE, MULTISCATTERING_SIZE)).psi.cpu().numpy()
        lut_spec = hillaire_lut(atm)
    views = {f"skyview_sz{z:05.1f}.exr": skyview_lut(atm, z, altitude_m=altitude_m, lut=lut_spec) for z in zs}
    images = {"transmittance.exr": trans, "multiscattering.exr": ms, **views}
    for name, v in images.items():
        if not np.isfinite(v).all():
            raise LutError(f"{name} has non-finite values; nothing written")
    meta = {
        "skyfit_lut": 1, "layout": "unreal",
        "source": "Hillaire 2020 (EGSR), github.com/sebh/UnrealEngineSkyAtmosphere; Unreal SkyAtmosphereComponent.h",
        "files": {"parameters": "unreal.json", "transmittance": "transmittance.exr", "multiscattering": "multiscattering.exr",
                  "skyview": {f"{z:g}": n for z, n in zip(zs, views)}},
        "channels": {"transmittance": "R, G, B at 680, 550, 440 nm", "multiscattering": "R, G, B at 680, 550, 440 nm",
                     "skyview": "R, G, B linear sRGB (D65), Y in cd/m^2"},
        "units": {"transmittance": "1",
                  "multiscattering": "Psi_ms [1/sr] per unit solar irradiance and unit scattering coefficient: the "
                                     "multiple-scattering radiance added at a point y of a view ray is "
                                     "sigma_s(y) Psi_ms(h(y), mu_s(y)) E_sun (Hillaire 2020 eq. 10-11)",
                  "skyview": "cd/m^2 (sky luminance seen from the observer; sun's disc not included)"},
        "parametrisation": {
            "transmittance": "width 256 (x_mu), height 64 (x_r); texel centre u = (i + 0.5)/256, v = (j + 0.5)/64 used as "
                             "x_mu, x_r directly: rho = H x_r, r = sqrt(rho^2 + bottom^2), d = (top - r) + x_mu (rho + H - "
                             "(top - r)), mu = (H^2 - rho^2 - d^2) / (2 r d); H = sqrt(top^2 - bottom^2)",
            "multiscattering": "32 x 32, column: mu_s = 2 x - 1, row: h = x (top - bottom), x = i / 31 (texel centres on the "
                               "ends, fromSubUvsToUnit); lookup u = fromUnitToSubUvs(mu_s / 2 + 1/2), v = fromUnitToSubUvs(h / (top - bottom))",
            "skyview": "width 192, height 108, u, v = i / (n - 1) (fromSubUvsToUnit); cos(view azimuth - sun azimuth) = "
                       "-(2 u^2 - 1); v < 1/2: view zenith = Z (1 - (1 - 2 v)^2), else Z + beta (2 v - 1)^2, beta = "
                       "acos(sqrt(r^2 - bottom^2) / r), Z = pi - beta (Hillaire's non-linear mapping)",
        },
        "sky_view_observer_altitude_m": altitude_m,
        "bottom_radius_m": atm.bottom_radius, "top_radius_m": atm.top_radius,
    }
    out = Path(out_dir)
    with lut_folder(out) as tmp:
        for name, v in images.items():
            write_exr(tmp / name, {c: v[..., k] for k, c in enumerate("RGB")}, {"table": name, "layout": "unreal"})
        (tmp / "unreal.json").write_text(json.dumps(params, indent=2))
        (tmp / "lut.json").write_text(json.dumps(meta, indent=2))
    return out


def unreal_render_errors(atm_rgb: Atmosphere, view: torch.Tensor, sun_zenith_deg: float, tables=None,
                         hillaire_settings: dict | None = None, cache: dict | None = None) -> dict:
    """Relative errors at 680/550/440 nm of the exported parameters' sky against skyfit's own, per direction.

    ``unreal``: Hillaire 2020's model (skyfit's implementation) on :func:`atmosphere_from_unreal`
    (:func:`unreal_parameters` (atm_rgb)) against Bruneton's tables of ``atm_rgb``;
    ``mapping``: Bruneton's tables on both, so only what the parameters cannot hold differs.

    Args:
        atm_rgb: the fitted atmosphere on 680, 550, 440 nm.
        view: unit ENU directions of the sky, shape (N, 3).
        tables: Bruneton's tables of ``atm_rgb`` (precomputed at 2017's sizes by ACCURATE_QUADRATURE when None).
        cache: a dict kept between calls (several suns): the rebuilt atmosphere's tables and LUT.
    """
    from ..scattering.multiple import ACCURATE_QUADRATURE, precompute, sky_radiance

    cache = {} if cache is None else cache
    ua = cache.get("atmosphere") or atmosphere_from_unreal(unreal_parameters(atm_rgb), atm_rgb)
    cache["atmosphere"] = ua
    z = math.radians(sun_zenith_deg)
    sun = torch.tensor([0.0, math.sin(z), math.cos(z)], dtype=atm_rgb.dtype)
    r = torch.full_like(view[:, 2], atm_rgb.bottom_radius)
    args = (r, view[:, 2], sun[2].expand_as(r), view @ sun)
    with torch.no_grad():
        tables = tables or precompute(atm_rgb, quadrature=ACCURATE_QUADRATURE)
        ref = sky_radiance(tables, atm_rgb, *args)
        if "tables" not in cache:
            cache["tables"] = precompute(ua, orders=tables.orders, sizes=tables.sizes, quadrature=tables.quadrature,
                                         mu_s_min=tables.mu_s_min)
        mapped = sky_radiance(cache["tables"], ua, *args)
        hs = {"size": (32, 32), "directions": 64, "samples": 20, **(hillaire_settings or {})}
        if "lut" not in cache:
            cache["lut"] = hillaire_lut(ua, **hs)
        hil = hillaire_sky_radiance(ua, *args, make_integrator("gauss", samples=16), 32, lut=cache["lut"])
    rel = lambda a: ((a - ref).abs() / ref).cpu().numpy()  # noqa: E731
    return {"unreal": rel(hil), "mapping": rel(mapped)}
