"""Export of Bruneton's precomputed tables as 2-D images (OpenEXR or npz) plus ``lut.json``.

Layout (docs/luts.md has the shader formulas): every table is a 2-D image of float32
channels; row 0 is the first row of the file.

=========================  ===================  ==================  =========================================
file                       height (rows)        width (columns)     channels
=========================  ===================  ==================  =========================================
``transmittance``          n_r (i_r)            n_mu (i_mu)         ``T<nm>`` (or R, G, B) and the optical
                                                                    lengths ``column_rayleigh``, ``column_mie``,
                                                                    ``column_ozone`` [m]
``scattering_rayleigh``,   R * MU               NU * MU_S           ``L<nm>`` (or R, G, B)
``scattering_mie``,        (i_r * MU + i_mu)    (i_nu * MU_S
``scattering_multiple``                          + i_mu_s)
``direct_irradiance``,     n_r (i_r)            n_mu_s (i_mu_s)     ``E<nm>`` (or R, G, B)
``irradiance``
=========================  ===================  ==================  =========================================

The scattering layout is Bruneton 2017's 3-D texture (width NU * MU_S, height MU,
depth R) with its R depth slices stacked vertically. ``scattering_multiple`` is absent
when orders = 1.
"""
from __future__ import annotations

import contextlib
import json
import math
import os
import shutil
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from ..atmosphere import Atmosphere
from ..io.atomic import current_umask, make_temp_dir
from ..scattering.bruneton_tables import TableSizes, extinction_matrix3
from ..scattering.multiple import PrecomputedAtmosphere, Quadrature

FORMATS = ("exr", "npz")
LUT_VERSION = 1
_SCATTERING = ("single_rayleigh", "single_mie", "multiple")
_FILES = {"single_rayleigh": "scattering_rayleigh", "single_mie": "scattering_mie", "multiple": "scattering_multiple",
          "direct_irradiance": "direct_irradiance", "irradiance": "irradiance", "transmittance": "transmittance"}


class LutError(ValueError):
    """A LUT directory that cannot be written or read."""


# -- packing -------------------------------------------------------------------
def pack_scattering(t: Tensor) -> np.ndarray:
    """(R, MU, MU_S, NU, C) -> (R * MU, NU * MU_S, C): row i_r MU + i_mu, column i_nu MU_S + i_mu_s."""
    R, MU, MUS, NU, C = t.shape
    return t.detach().cpu().permute(0, 1, 3, 2, 4).reshape(R * MU, NU * MUS, C).numpy()


def unpack_scattering(a: np.ndarray, sizes: TableSizes) -> np.ndarray:
    """Inverse of :func:`pack_scattering`."""
    R, MU, MUS, NU = sizes.scattering_shape
    return a.reshape(R, MU, NU, MUS, a.shape[-1]).transpose(0, 1, 3, 2, 4)


def rgb_matrix(wavelengths_nm: Tensor) -> Tensor:
    """(W, 3) matrix M with linear sRGB = spectrum @ M: CIE 1931 XYZ (683 lm/W) then XYZ -> sRGB (D65)."""
    from ..render.colour import xyz_to_srgb_matrix, spectral_to_xyz_matrix

    lam = wavelengths_nm.detach().cpu().double()
    return spectral_to_xyz_matrix(lam) @ torch.as_tensor(xyz_to_srgb_matrix(), dtype=torch.float64).T


def _names(prefix: str, lam: list[float]) -> list[str]:
    names = [f"{prefix}{v:g}" for v in lam]
    if len(set(names)) != len(names):
        raise LutError("wavelengths closer than the channel names resolve (format :g); use a coarser grid")
    return names


# -- writing -------------------------------------------------------------------
def _write_image(path: Path, channels: dict[str, np.ndarray], fmt: str, meta: dict) -> None:
    if fmt == "exr":
        from ..io import write_exr

        write_exr(path, channels, meta)
    else:
        with open(path, "wb") as f:
            np.savez(f, **{k: np.ascontiguousarray(v, dtype=np.float32) for k, v in channels.items()})


def _lut_json(tables: PrecomputedAtmosphere, atm: Atmosphere, fmt: str, rgb: bool, files: dict, m: Tensor | None) -> dict:
    s = tables.sizes
    Rb, Rt = atm.bottom_radius, atm.top_radius
    lam = atm.wavelengths.detach().cpu().tolist()
    return {
        "skyfit_lut": LUT_VERSION,
        "format": fmt,
        "channels": "rgb" if rgb else "spectral",
        "wavelengths_nm": lam,
        "rgb_conversion": None if m is None else {
            "description": "linear sRGB (D65) = spectrum @ matrix; CIE 1931 2 deg, 683 lm/W, so G-weighted Y is cd/m^2 "
                           "for radiance in W/(m^2 sr nm); transmittance R,G,B weighted by the solar spectrum (approximate)",
            "matrix_W_by_3": m.tolist(),
        },
        "orders": tables.orders,
        "files": files,
        "sizes": {k: getattr(s, k) for k in s.__dataclass_fields__},
        "quadrature": {k: getattr(tables.quadrature, k) for k in tables.quadrature.__dataclass_fields__},
        "parametrisation": {
            "source": "Bruneton 2017, precomputed_atmospheric_scattering/functions.glsl",
            "bottom_radius_m": Rb,
            "top_radius_m": Rt,
            "H_m": math.sqrt(Rt * Rt - Rb * Rb),
            "mu_s_min": tables.mu_s_min,
            "texel_centres": "unit value x in [0, 1] -> continuous texel index x (n - 1); GPU u = (x (n - 1) + 0.5) / n; "
                             "linear filtering, clamp to edge",
            "rho": "sqrt(r^2 - bottom^2)",
            "transmittance": "x_r = rho / H; x_mu = (d - (top - r)) / (rho + H - (top - r)), d = -r mu + sqrt(r^2 (mu^2 - 1) + top^2)",
            "scattering_r": "x_r = rho / H",
            "scattering_mu_ground": "ray hits the ground: d = -r mu - sqrt(r^2 (mu^2 - 1) + bottom^2); "
                                    "x = (d - (r - bottom)) / (rho - (r - bottom)); i_mu = (MU/2 - 1) (1 - x)",
            "scattering_mu_sky": "otherwise: d = -r mu + sqrt(r^2 (mu^2 - 1) + top^2); x = (d - (top - r)) / (rho + H - (top - r)); "
                                 "i_mu = MU/2 + (MU/2 - 1) x",
            "scattering_mu_s": "d = -bottom mu_s + sqrt(bottom^2 (mu_s^2 - 1) + top^2); a = (d - (top - bottom)) / (H - (top - bottom)); "
                               "A = -2 mu_s_min bottom / (H - (top - bottom)); x = max(1 - a / A, 0) / (1 + a)",
            "scattering_nu": "x = (nu + 1) / 2",
            "irradiance": "x_r = (r - bottom) / (top - bottom); x_mu_s = (mu_s + 1) / 2",
            "scattering_packing": "row = i_r * MU + i_mu, column = i_nu * MU_S + i_mu_s (2017's 3-D texture, depth slices "
                                  "stacked vertically); interpolate linearly in i_nu between two columns blocks",
        },
        "units": {
            "transmittance": "1", "column_*": "m (optical length divided by the sea-level density)",
            "scattering_rayleigh": "W/(m^2 nm) without phase function (multiply by the Rayleigh phase [1/sr])",
            "scattering_mie": "W/(m^2 nm) without phase function (multiply by the Mie phase [1/sr])",
            "scattering_multiple": "W/(m^2 sr nm), orders 2..N, phase functions included",
            "direct_irradiance": "W/(m^2 nm) on a horizontal surface, order 0",
            "irradiance": "W/(m^2 nm) on a horizontal surface, orders 1..N-1",
            "rgb": "the same quantities through the matrix of rgb_conversion (nm-integrated, photometric via 683 lm/W)",
        },
        "phase": {"rayleigh": "3 / (16 pi) (1 + nu^2)", "mie": atm.mie_phase, "mie_g": float(atm.mie_g),
                  **({"mie_g2": float(atm.mie_g2), "mie_hg_weight": float(atm.mie_hg_weight),
                      "mie_formula": "f HG(mie_g) + (1 - f) HG(mie_g2), f = mie_hg_weight"}
                     if atm.mie_phase == "two_term_hg" else {}),
                  **({"mie_median_radius_m": float(atm.mie_median_radius), "mie_geometric_sigma": float(atm.mie_geometric_sigma),
                      "mie_refractive_index": list(atm.mie_refractive_index),
                      **({"mie_coarse_radius_m": float(atm.mie_coarse_radius), "mie_coarse_sigma": float(atm.mie_coarse_sigma),
                          "mie_fine_fraction": float(atm.mie_fine_fraction)} if atm.mie_coarse_mode is not None else {}),
                      "mie_formula": "per wavelength: the Mie phase of a log-normal size distribution "
                                     "(skyfit.scattering.lognormal_mie_phase; docs/aerosol.md); mie_g is its asymmetry "
                                     "at 550 nm, and an RGB channel has no single phase"}
                     if atm.mie_phase == "lognormal_mie" else {})},
        "mie_profile": {"name": atm.mie_profile,
                        **({"mixing_height_m": float(atm.mie_mixing_height),
                            "density": "1 for h <= mixing_height_m, exp(-(h - mixing_height_m) / mie_scale_height) above"}
                           if atm.mie_profile == "boundary_layer" else {"density": "exp(-h / mie_scale_height)"})},
        "extinction_1_per_m": {"rayleigh": atm.rayleigh_scattering.detach().cpu().tolist(),
                               "mie": atm.mie_extinction.detach().cpu().tolist(),
                               "ozone": extinction_matrix3(atm)[2].detach().cpu().tolist()},
        "atmosphere": atm.summary(),
    }


@contextlib.contextmanager
def lut_folder(out: str | Path) -> Iterator[Path]:
    """A temporary folder beside ``out`` to write a set of LUT files into, all or nothing.

    On success it becomes ``out`` (a new folder, with the umask's mode), or its files replace those
    of an existing ``out`` one by one, ``lut.json`` last; on any failure nothing of it remains and
    ``out`` is untouched. Its name lets a killed run's be recognised and removed (:mod:`skyfit.io.atomic`).

    Raises:
        LutError: one line naming ``out``.
    """
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise LutError(f"--out {out} exists and is not a directory")
    try:
        tmp = make_temp_dir(out)
    except (OSError, ValueError) as e:
        raise LutError(f"cannot write LUTs to {out}: {getattr(e, 'strerror', None) or e}") from None
    try:
        yield tmp
        if not out.exists():
            os.chmod(tmp, 0o777 & ~current_umask())  # mkdtemp's 0700 -> a plain mkdir's mode
            os.replace(tmp, out)
        else:
            names = sorted(p.name for p in tmp.iterdir() if p.name != "lut.json")
            for f in names + (["lut.json"] if (tmp / "lut.json").exists() else []):
                os.replace(tmp / f, out / f)
    except LutError:
        raise
    except OSError as e:
        raise LutError(f"cannot write LUTs to {out}: {e.strerror or e}") from None
    except Exception as e:  # ExrError and the like: already one line
        raise LutError(f"cannot write LUTs to {out}: {e}") from None
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)


def export_luts(tables: PrecomputedAtmosphere, atm: Atmosphere | None, out_dir: str | Path, format: str = "exr",
                rgb: bool = False) -> Path:
    """Write the tables of ``tables`` as float32 images and ``lut.json`` into ``out_dir`` (docs/luts.md).

    Everything is written into a temporary directory beside ``out_dir`` and moved into place
    only when complete, ``lut.json`` last, so a failure leaves no partial output.

    Args:
        tables: from :func:`skyfit.scattering.multiple.precompute`.
        atm: the atmosphere for the metadata and transmittance (None: ``tables.atm``).
        out_dir: target directory (created; existing LUT files in it are replaced).
        format: "exr" (OpenEXR, one multi-channel file per table) or "npz".
        rgb: store linear sRGB channels R, G, B (:func:`rgb_matrix`) instead of one channel per wavelength.

    Returns:
        ``out_dir``.
    """
    tables.check_every_sun("an engine's LUT")
    if format not in FORMATS:
        raise LutError(f"unknown LUT format {format!r}; valid: {', '.join(FORMATS)}")
    atm = tables.atm if atm is None else atm
    out = Path(out_dir)
    lam = atm.wavelengths.detach().cpu().tolist()
    m = rgb_matrix(atm.wavelengths.detach().cpu()) if rgb else None  # numpy below: tables from any device

    def chans(t: np.ndarray, prefix: str) -> dict[str, np.ndarray]:
        t = np.asarray(t, dtype=np.float64)
        if m is not None:
            t = t @ m.numpy()
            return {c: t[..., k] for k, c in enumerate("RGB")}
        return {n: t[..., k] for k, n in enumerate(_names(prefix, lam))}

    images: dict[str, dict[str, np.ndarray]] = {}
    with torch.no_grad():
        cols = tables.transmittance_columns.detach().cpu().double()
        ext = extinction_matrix3(atm).detach().cpu().double()
        trans = torch.exp(-cols @ ext).numpy()
        if m is not None:  # sun-weighted mean transmittance per channel (not exact: T is not linear in the spectrum)
            w = atm.solar_irradiance.detach().cpu().double().numpy()[:, None] * m.numpy()
            tc = (trans @ w) / w.sum(0)
            images["transmittance"] = {c: tc[..., k] for k, c in enumerate("RGB")}
        else:
            images["transmittance"] = {n: trans[..., k] for k, n in enumerate(_names("T", lam))}
        for k, n in enumerate(("rayleigh", "mie", "ozone")):
            images["transmittance"][f"column_{n}"] = cols[..., k].numpy()
        for name in _SCATTERING:
            t = getattr(tables, name)
            if t is not None:
                images[name] = chans(pack_scattering(t.double()), "L")
        for name in ("direct_irradiance", "irradiance"):
            images[name] = chans(getattr(tables, name).detach().cpu().double().numpy(), "E")
    for name, ch in images.items():
        bad = [k for k, v in ch.items() if not np.isfinite(v).all()]
        if bad:
            raise LutError(f"table {name} has non-finite values in {bad}; nothing written")
    files = {name: f"{_FILES[name]}.{format}" for name in images}
    meta = _lut_json(tables, atm, format, rgb, files, m)
    with lut_folder(out) as tmp:
        for name, ch in images.items():
            _write_image(tmp / files[name], ch, format, {"table": name, "skyfit_lut": LUT_VERSION})
        (tmp / "lut.json").write_text(json.dumps(meta, indent=2))
    return out


# -- reading -------------------------------------------------------------------
def _read_image(path: Path, fmt: str) -> dict[str, np.ndarray]:
    if not path.is_file():
        raise LutError(f"LUT file missing: {path}")
    if fmt == "exr":
        from ..io import read_exr

        return read_exr(path)[0]
    try:
        with np.load(path) as z:
            return {k: z[k] for k in z.files}
    except (OSError, ValueError) as e:
        raise LutError(f"cannot read {path}: {e}") from None


def _atmosphere_from_summary(d: dict, dtype, device) -> Atmosphere:
    T = lambda v: None if v is None else torch.as_tensor(v, dtype=dtype, device=device)  # noqa: E731
    kw = {}
    for k, v in d.items():
        if k in ("bottom_radius", "top_radius", "sun_angular_radius"):
            kw[k] = float(v)
        elif k in ("ozone_layer_m", "mie_refractive_index"):
            kw[k] = None if v is None else tuple(float(x) for x in v)
        elif k in ("mie_phase", "mie_profile", "name"):
            kw[k] = v
        else:
            kw[k] = T(v)
    return Atmosphere(**kw)


def load_luts(lut_dir: str | Path, dtype: torch.dtype = torch.float64, device="cpu") -> PrecomputedAtmosphere:
    """Read a directory written by :func:`export_luts` (spectral channels) into a PrecomputedAtmosphere.

    The atmosphere is rebuilt from ``lut.json``, the tables from the images (float32 values,
    cast to ``dtype``), so :func:`skyfit.scattering.multiple.sky_radiance` and the table's
    lookup methods sample them exactly as the in-memory tables. RGB exports are meant for
    shaders and are refused here.
    """
    d = Path(lut_dir)
    p = d / "lut.json"
    try:
        meta = json.loads(p.read_text())
    except FileNotFoundError:
        raise LutError(f"not a LUT directory (no lut.json): {d}") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise LutError(f"{p}: unreadable ({type(e).__name__})") from None
    if not isinstance(meta, dict) or meta.get("skyfit_lut") != LUT_VERSION:
        raise LutError(f"{p}: not a skyfit LUT description (version {LUT_VERSION})")
    if meta.get("channels") != "spectral":
        raise LutError(f"{p}: load_luts reads spectral exports; this one holds {meta.get('channels')!r} channels")
    fmt = meta["format"]
    sizes = TableSizes(**meta["sizes"])
    atm = _atmosphere_from_summary(meta["atmosphere"], dtype, device)
    lam = [float(v) for v in meta["wavelengths_nm"]]
    T = lambda a: torch.as_tensor(np.ascontiguousarray(a), dtype=dtype, device=device)  # noqa: E731

    def stack(name: str, prefix: str) -> np.ndarray:
        ch = _read_image(d / meta["files"][name], fmt)
        try:
            return np.stack([ch[n] for n in _names(prefix, lam)], axis=-1)
        except KeyError as e:
            raise LutError(f"{d / meta['files'][name]}: channel {e} missing") from None

    tr = _read_image(d / meta["files"]["transmittance"], fmt)
    cols = np.stack([tr[f"column_{n}"] for n in ("rayleigh", "mie", "ozone")], axis=-1)
    scat = {n: T(unpack_scattering(stack(n, "L"), sizes)) for n in _SCATTERING if n in meta["files"]}
    return PrecomputedAtmosphere(
        atm=atm, orders=int(meta["orders"]), sizes=sizes, quadrature=Quadrature(**meta["quadrature"]),
        mu_s_min=float(meta["parametrisation"]["mu_s_min"]), transmittance_columns=T(cols),
        direct_irradiance=T(stack("direct_irradiance", "E")), irradiance=T(stack("irradiance", "E")),
        single_rayleigh=scat["single_rayleigh"], single_mie=scat["single_mie"], multiple=scat.get("multiple"),
    )


# -- RESULT.json -> Atmosphere -------------------------------------------------------------
