"""Command-line interface: the only place that reads files and flags (CONTRACT.md).

Every user mistake ends in one line on stderr and exit status 2; outputs are
written atomically, so a failed command leaves no partial file.
"""
from __future__ import annotations

import argparse
import contextlib
import dataclasses
import io
import json
import math
import re
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import torch

from . import __version__
from .api import envmap, render_model, resolve_device
from .batch import batch as run_batch
from .batch import summary_lines
from .atmosphere import ConfigError, load_atmosphere, read_config
from .atmosphere.wavelengths import DEFAULT_WAVELENGTHS, parse_wavelengths
from .camera import PROJECTIONS, FisheyeCamera, parse_location, parse_time, render_fisheye, sun_position
from .export import FORMATS, bruneton2017, export_luts
from .export.unreal import export_unreal
from .fit.budget import DISCREPANCY_MODELS, SIGMA_MODES
from .fit.problem import DTYPES, FitSettings
from .fit.report import dumps
from .fit.results import atmosphere_from_result, read_result
from .fit.run import run_evaluate, run_fit
from .fit.select import format_table
from .io import ExrError, write_exr
from .io.atomic import check_writable, write_text_atomic
from .fit.data import DataWarning
from .resources import Estimate, check, single_scattering_estimate, tables_estimate
from .quadrature import RULES
from .render.auto import RENDER_DEFAULTS, choose, describe, parse_accuracy
from .scattering.bruneton_tables import TableSizes
from .scattering.hillaire import hillaire_lut
from .scattering.multiple import ACCURATE_QUADRATURE, SunBelowTables, precompute
from .scattering.single import SPACINGS
from .tools.bench import machine_info, run_bench
from .tools.integrator_calibration import CALIBRATE_QUICK, calibrate_integrators
from .tools.trade import run_trade_study
from .transmittance import parse_integrator
from .transmittance.spline import SPLINE_KINDS

EXIT_USAGE = 2


class UserError(ValueError):
    """A mistake in the command line or its inputs."""


def _check_device(device: str) -> str:
    """``--device``: cpu, cuda, cuda:N or auto -> the device name; one line when it is unknown or absent here."""
    try:
        return str(resolve_device(device))
    except ValueError as e:
        raise UserError(f"--device: {e}") from None


# -- commands ------------------------------------------------------------------
def _floats(text: str | None, n: int, flag: str) -> list[float] | None:
    """``A,B,...`` -> n finite floats (None passes through)."""
    if text is None:
        return None
    try:
        vals = [float(v) for v in text.split(",")]
    except ValueError:
        vals = []
    if len(vals) != n or not all(math.isfinite(v) for v in vals):
        raise UserError(f"{flag} takes {n} comma-separated finite numbers, got {text!r}")
    return vals


def _camera_from_args(args, size, projection):
    """The render command's camera options -> FisheyeCamera (docs/camera.md); absent options take defaults."""
    get = lambda name: getattr(args, name, None)  # noqa: E731  (demo passes a Namespace without them)
    kb = _floats(get("kb_coeffs"), 4, "--kb-coeffs")
    if kb is not None and projection != "kannala_brandt":
        raise UserError(f"--kb-coeffs needs --projection kannala_brandt, got --projection {projection}")
    centre = _floats(get("center"), 2, "--center") or [None, None]
    tilt = _floats(get("tilt"), 2, "--tilt") or [0.0, 0.0]
    if not 0.0 <= tilt[0] < 90.0:
        raise UserError(f"--tilt ZENITH,AZIMUTH: the optical axis's zenith angle must be in [0, 90) degrees, got {tilt[0]}")
    if get("focal") is not None and get("radius") is not None:
        raise UserError("give --focal or --radius, not both")
    b = math.radians(tilt[1])
    return FisheyeCamera(
        size, projection=projection, cx=centre[0], cy=centre[1], radius=get("radius"), focal=get("focal"), kb_coeffs=kb,
        up_azimuth_deg=get("up_azimuth") or 0.0, tilt_deg=(tilt[0] * math.sin(b), tilt[0] * math.cos(b)),
        max_zenith_deg=90.0 if get("max_zenith") is None else get("max_zenith"),
    )


def _render_image(args, atm, integrator, sun_zenith, sun_azimuth, size, projection):
    """The fisheye of ``render``, and the header of the Bruneton tables it built (None where it built none here)."""
    cam = _camera_from_args(args, size, projection)
    extra, header = {}, None
    if args.orders == 1:
        extra["spacing"] = _spacing(args)
    else:
        extra["multiple"] = getattr(args, "multiple", "bruneton")
        if extra["multiple"] == "bruneton" and getattr(args, "accuracy", None):  # the trade study's setting as measured
            extra["table_sizes"] = _table_sizes(args.table_sizes)
        elif extra["multiple"] == "bruneton":
            extra["tables"], header = _sun_tables(args, atm, sun_zenith)
        elif getattr(args, "hillaire_lut", None):  # N_H,N_MU_S,DIRECTIONS,SAMPLES (set by --accuracy)
            nh, nm, nd, ns = (int(v) for v in args.hillaire_lut.split(","))
            extra["tables"] = hillaire_lut(atm, size=(nh, nm), directions=nd, samples=ns)
    try:
        return render_fisheye(
            atm, cam, sun_zenith, sun_azimuth, integrator, altitude=args.altitude, view_samples=args.view_samples,
            rule=args.rule, orders=args.orders, sun_disk=args.sun_disk, **extra,
        ), header
    except SunBelowTables as e:  # the library's advice names Python arguments the CLI has not
        lowest = math.degrees(math.acos(e.mu_s_min))
        raise UserError(f"--sun-zenith {sun_zenith:g}: Bruneton's multiple-scattering tables (--orders {args.orders}) "
                        f"hold suns down to {lowest:.1f} deg from the zenith at the observer (mu_s_min {e.mu_s_min:g}), "
                        f"this one is at {math.degrees(math.acos(e.mu_s)):.1f} deg; render it with --orders 1 or "
                        "--multiple hillaire") from None


def _sun_tables(args, atm, sun_zenith: float):
    """Bruneton tables for ``render --orders N``: :func:`skyfit.render`'s renderer (one sun's mu_s window, Gauss view
    rays, split density bands; docs/multiple_scattering.md, "One sun's mu_s window") at ``--table-sizes``, if given;
    and their settings for the EXR header."""
    model = render_model(None, args.orders, "bruneton", sun_zenith, args.altitude)
    sizes = _table_sizes(getattr(args, "table_sizes", None))
    if sizes is not None:
        model = dataclasses.replace(model, table_sizes=dataclasses.astuple(sizes))
    tables = model.sun_tables(atm, sun_zenith, args.altitude)
    rng = tables.mu_s_range
    return tables, {"table_sizes": list(dataclasses.astuple(tables.sizes)), "ray_rule": model.ray_rule,
                    "density_directions": list(model.density_directions),
                    "mu_s_range": None if rng is None else [float(v) for v in rng]}


def _spacing(args) -> str:
    """The view-ray spacing a render uses: ``--spacing`` for single scattering; Hillaire's single-scattering
    part is uniformly spaced and Bruneton's tables have no view samples."""
    return args.spacing if args.orders == 1 else "uniform"


def _table_sizes(text: str | None):
    """``R,MU,MUS,NU`` scattering-table sizes for --orders >= 2 (None: Bruneton 2017's 32,128,32,8)."""
    try:
        return TableSizes.parse(text) if text else None
    except ValueError as e:
        raise UserError(f"--table-sizes: {e}") from None


def _exr_payload(img, atm, integrator, args, sun_zenith, sun_azimuth, spectral: bool):
    rgb = img.rgb.detach().cpu().numpy()
    chans = {"R": rgb[..., 0], "G": rgb[..., 1], "B": rgb[..., 2], "Y": img.xyz[..., 1].detach().cpu().numpy()}
    if spectral:
        spec = img.spectral.detach().cpu().numpy()
        for k, lam in enumerate(atm.wavelengths.cpu().tolist()):
            name = f"L{lam:g}"
            if name in chans:
                raise UserError(f"wavelengths closer than the channel names resolve ({name} twice); use a coarser grid")
            chans[name] = spec[..., k]
    meta = {
        "skyfit_version": __version__,
        "camera": img.camera.metadata(),
        "sun": {"zenith_deg": sun_zenith, "azimuth_deg": sun_azimuth},
        "observer_altitude_m": args.altitude,
        "units": {
            "L<nm>": "W/(m^2 sr nm)",
            "R,G,B": "linear sRGB of XYZ with 683 lm/W (Y in cd/m^2)",
            "Y": "cd/m^2",
        },
        "wavelengths_nm": atm.wavelengths.cpu().tolist(),
        "integrator": integrator.settings(),
        "view_samples": args.view_samples,
        "rule": args.rule,
        "spacing": _spacing(args),
        "orders": args.orders,
        "atmosphere": atm.summary(),
    }
    return chans, meta


def _sun_from_args(args) -> tuple[float, float, dict]:
    """Sun zenith and azimuth [deg] from --sun-zenith/--sun-azimuth or --time/--location (NREL SPA).

    Returns also a dict for the EXR header (time, location, Earth-Sun distance when dated).
    """
    if args.time or args.location:
        if not (args.time and args.location):
            raise UserError("--time and --location go together (ISO 8601 time with offset, LAT,LON[,ELEV])")
        if args.sun_zenith is not None:
            raise UserError("give the sun either by --sun-zenith/--sun-azimuth or by --time/--location, not both")
        lat, lon, elev = parse_location(args.location)
        when = parse_time(args.time)
        sp = sun_position(when, lat, lon, elev)
        # The renderer has no refraction, so it takes the geometric (airless) sun direction.
        zen, az = float(sp.zenith_geometric), float(sp.azimuth)
        info = {"time": when.isoformat(), "location": {"latitude_deg": lat, "longitude_deg": lon, "elevation_m": elev},
                "distance_au": float(sp.distance_au), "apparent_zenith_deg": float(sp.zenith)}
        return zen, az, info
    if args.sun_zenith is None:
        raise UserError("give the sun with --sun-zenith DEG [--sun-azimuth DEG], or --time ISO8601 --location LAT,LON[,ELEV]")
    if not (0.0 <= args.sun_zenith <= 180.0):
        raise UserError(f"--sun-zenith must be in [0, 180] degrees, got {args.sun_zenith}")
    if not math.isfinite(args.sun_azimuth):
        raise UserError(f"--sun-azimuth must be a finite angle in degrees, got {args.sun_azimuth}")
    return float(args.sun_zenith), float(args.sun_azimuth), {}


def _check_render_numbers(args) -> None:
    if not math.isfinite(args.up_azimuth):
        raise UserError(f"--up-azimuth must be a finite angle in degrees, got {args.up_azimuth}")
    if not (0.0 <= args.altitude < math.inf):
        raise UserError(f"--altitude must be >= 0 m above the ground, got {args.altitude}")


def cmd_render(args) -> int:

    out = Path(args.out)
    if out.suffix.lower() != ".exr":
        raise UserError(f"--out must name an .exr file, got {out}")
    if args.size < 2 or args.size > 8192:
        raise UserError(f"--size must be in 2..8192, got {args.size}")
    if args.view_samples < 1:
        raise UserError(f"--view-samples must be >= 1, got {args.view_samples}")
    if args.orders < 1:
        raise UserError(f"--orders must be >= 1 (1 = single scattering), got {args.orders}")
    sun_zenith, sun_azimuth, sun_info = _sun_from_args(args)
    _check_render_numbers(args)
    lam = parse_wavelengths(args.wavelengths)
    auto = _apply_accuracy(args, sun_zenith) if args.accuracy else None
    try:
        integrator = parse_integrator(args.integrator)
    except ValueError as e:
        raise UserError(f"--integrator {args.integrator}: {e}") from None
    device = _check_device(args.device)
    check_resources(args, len(lam), integrator)
    if args.preview:
        from .export.envmap import preview_path

        check_writable(preview_path(out), what="--preview")  # before the render; creates nothing
    atm = load_atmosphere(args.config, lam, dtype=DTYPES[args.dtype], device=device, sun_distance_au=sun_info.get("distance_au"))
    t0 = time.perf_counter()
    with torch.no_grad():
        img, tables_header = _render_image(args, atm, integrator, sun_zenith, sun_azimuth, args.size, args.projection)
    elapsed = time.perf_counter() - t0
    chans, meta = _exr_payload(img, atm, integrator, args, sun_zenith, sun_azimuth, args.spectral)
    meta["sun"].update(sun_info)
    if tables_header:  # Bruneton's tables of --orders >= 2 (their mu_s axis for this sun)
        meta["multiple_tables"] = tables_header
    bad = sorted(k for k, v in chans.items() if not np.isfinite(v).all())
    if bad:  # never write an image of NaN/Inf (a parameter the checks above missed, or a renderer bug)
        raise UserError(f"render of {args.config} produced non-finite values in channel(s) {bad}; nothing written")
    write_exr(out, chans, meta)
    info = {"out": str(out), "seconds": round(elapsed, 4), "size": args.size, "channels": sorted(chans)}
    if args.preview:
        info["preview"] = str(_write_render_preview(out, chans, img))
    if auto is not None:
        info["accuracy"] = auto.summary()
    text = f"wrote {out} ({args.size}x{args.size}, {len(chans)} channels) in {elapsed:.2f} s"
    if auto is not None:
        text += f"; --accuracy {auto.tolerance}: {describe(auto.setting)} (measured {auto.predicted_error:.3g})"
    print(json.dumps(info) if args.json else text)
    return 0


def _write_render_preview(out: Path, chans: dict, img) -> Path:
    """``render --preview``: the fisheye as an 8-bit sRGB PNG beside ``out`` (atomic), exposed on the sky's
    90th percentile; pixels outside the image circle black."""
    from .export.envmap import preview_path, write_preview

    rgb = np.stack([chans["R"], chans["G"], chans["B"]], -1).astype(np.float64)
    valid = img.valid.detach().cpu().numpy().astype(bool)
    y = rgb.mean(-1)[valid]
    ref = float(np.percentile(y[y > 0], 90)) if np.any(y > 0) else 1.0
    return write_preview(preview_path(out), np.where(valid[..., None], rgb, 0.0), exposure=1.0 / max(ref, 1e-12))


def _apply_accuracy(args, sun_zenith: float):
    """``--accuracy``: replace the renderer flags by the cheapest measured setting meeting it (skyfit.render.auto)."""
    try:
        choice = choose(parse_accuracy(args.accuracy), sun_zenith, args.altitude, orders=args.orders, dtype=args.dtype)
    except ValueError as e:
        raise UserError(f"--accuracy {args.accuracy}: {e}") from None
    st = choice.setting
    if st["multiple"] == "bruneton":
        args.orders, args.multiple, args.table_sizes = int(st["orders"]), "bruneton", st["table_sizes"]
    else:
        args.integrator, args.view_samples, args.rule = st["integrator"], int(st["view_samples"]), st["rule"]
        args.spacing = "uniform"  # the trade study measured every setting with uniform spacing
        if st["multiple"] == "hillaire":
            args.orders, args.multiple, args.hillaire_lut = max(args.orders, 2), "hillaire", st["hillaire_lut"]
    return choice


def cmd_demo(args) -> int:
    """The main job on an embedded default: render, noise, fit, uncertainty, LUTs, truth vs recovered (skyfit.tools.demo)."""
    # The demo samples (emcee, through scipy.stats) and writes PNGs (skimage): ~2 s of imports the others need not pay.
    from .tools.demo import run_demo

    _threads(args)
    summary = run_demo(args.out, quick=args.quick, progress=_progress(args),
                       log=(lambda *a, **k: None) if args.json else print, device=_check_device(args.device))
    if args.json:
        print(json.dumps(summary))
    return 0


def _kider_site(args) -> dict:
    site: dict = {}
    if args.location:
        site["latitude"], site["longitude"], site["elevation"] = parse_location(args.location)
    if args.timezone is not None:
        if not (math.isfinite(args.timezone) and -14 <= args.timezone <= 14):
            raise UserError(f"--timezone must be a UTC offset in hours in [-14, 14], got {args.timezone}")
        site["utc_offset_hours"] = args.timezone
    return site


def _progress(args) -> bool:
    return (sys.stderr.isatty() and not args.json) if args.progress is None else bool(args.progress)


def _threads(args) -> None:
    """--threads N: torch's intra-op threads for this process (small fits on a busy machine: 1 is fastest)."""
    if args.threads is not None:
        if args.threads < 1:
            raise UserError(f"--threads must be >= 1, got {args.threads}")
        torch.set_num_threads(args.threads)


def _photo_input(data) -> bool:
    """True when DATA is one photo or bracket folder (not an EXR with skyfit's header, not Kider captures)."""
    from .io.photo import is_photo_path

    return len(data) == 1 and is_photo_path(data[0])


def _exposures(text: str | None) -> list[float] | None:
    if text is None:
        return None
    try:
        vals = [float(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise UserError(f"--exposures must be a comma list of seconds, got {text!r}") from None
    if not vals or not all(v > 0 and math.isfinite(v) for v in vals):
        raise UserError(f"--exposures must be positive finite seconds, got {text!r}")
    return vals


@contextlib.contextmanager
def _photo_named(photo, out=None):
    """A photo command's errors name the photo (the image tests' CalibrationError does not), and a failed or
    interrupted fit leaves no RESULT.png without its RESULT.json (run_photo_fit writes the plot first)."""
    from .camera.autocal import CalibrationError

    png = Path(out).with_suffix(".png") if out else None
    had = png is not None and png.exists()
    try:
        yield
    except CalibrationError as e:
        msg = str(e)
        _drop_orphan_png(png, had, out)
        raise (e if str(photo) in msg else UserError(f"photo {photo}: {msg}")) from None
    except BaseException:
        _drop_orphan_png(png, had, out)
        raise


def _drop_orphan_png(png, had: bool, out) -> None:
    if png is not None and not had and png.exists() and not Path(out).exists():
        png.unlink()


def cmd_fit_photo(args) -> int:
    from .fit.photo import run_photo_fit

    if args.select:
        raise UserError("--select applies to EXR and Kider data, not photos")
    cfg, source = read_config(args.config or "earth")
    overrides = {k: v for k, v in {**_fit_overrides(args), "dtype": args.dtype}.items() if v is not None}
    with _photo_named(args.data[0], args.out):
        res = run_photo_fit(args.data[0], cfg, args.out, time=args.time, location=args.location, camera=args.camera,
                            mask=args.mask, exposures=_exposures(args.exposures), linear=args.linear, response=args.response,
                            overrides=overrides, plots=not args.no_plots, progress=_progress(args), laplace=True,
                            device=_check_device(args.device))
    a, sun, px = res["aerosol"], res["sun"], res["pixels"]
    summary = {"out": str(args.out), "aerosol": a, "camera": {k: res["camera"][k] for k in
               ("projection", "cx", "cy", "radius_px", "up_azimuth_deg", "tilt_deg")}, "sun": sun,
               "rmse_rel": res["metrics"]["rmse_rel"], "pixels": px, "notes": res["notes"],
               "seconds": round(res["seconds"], 3), "converged": res["convergence"]["converged"]}
    if args.json:
        print(dumps(summary, indent=None))
    else:
        sig = a["sigma"]
        for k in ("aod_550", "angstrom_alpha", "g"):
            print(f"{k:16s} {a[k]:.4g}" + (f" +- {sig[k]:.2g}" if sig.get(k) is not None else ""))
        cam = summary["camera"]
        print(f"camera: {cam['projection']}, centre ({cam['cx']:.1f}, {cam['cy']:.1f}) px, radius {cam['radius_px']:.1f} px, "
              f"up azimuth {cam['up_azimuth_deg']:.2f} deg, tilt {cam['tilt_deg'][0]:.2f}/{cam['tilt_deg'][1]:.2f} deg")
        if sun["detected_px"] is not None:
            how = {"registration": "by its saturated region", "centroid": "at its centroid"}.get(sun.get("detected_by"), "")
            print(f"sun: detected {how} at ({sun['detected_px'][0]:.1f}, {sun['detected_px'][1]:.1f}) px, the fitted camera "
                  f"puts it at ({sun['model_px'][0]:.1f}, {sun['model_px'][1]:.1f}) px: {sun['separation_deg']:.2f} deg apart")
        for n in res["notes"]:
            print(f"note: {n}")
        print(f"relative rms {res['metrics']['rmse_rel']:.4f} over {px['used']} px ({px['masked']} masked, "
              f"{px['censored']} censored), {res['seconds']:.1f} s")
        print(f"wrote {args.out}")
    return 0


def cmd_fit(args) -> int:
    _threads(args)
    if _photo_input(args.data):
        return cmd_fit_photo(args)
    for flag in ("time", "camera", "mask", "exposures", "response"):
        if getattr(args, flag) is not None:
            raise UserError(f"--{flag} applies to a photo; {args.data[0]} is not one")
    if args.config is None:
        raise UserError("--config is required for EXR and Kider data")
    cfg, source = read_config(args.config)
    overrides = {**_fit_overrides(args), "select_sigma": args.select_sigma, "select_heldout": args.heldout,
                 "dtype": args.dtype}
    try:
        res = run_fit(args.data, cfg, args.out, overrides=overrides, config_source=source, kider_site=_kider_site(args),
                      plots=not args.no_plots, progress=_progress(args), laplace=args.laplace, select=args.select,
                      device=_check_device(args.device), force=args.force)
    except ConfigError as e:
        raise ConfigError(f"config {source}: {e}") from None
    m, c = res["metrics"], res["convergence"]
    summary = {"out": str(args.out), "free": {n: res["parameters"][n] for n in res["free"]}, "loss": m["loss"],
               "rmse": m["rmse"], "rmse_units": m["rmse_units"], "delta_e": m["delta_e"], "n_samples": m["n_samples"],
               "converged": c["converged"], "reason": c["reason"], "seconds": round(res["seconds"], 3),
               "plots": res.get("plots", []), "notes": res.get("notes", [])}
    if "laplace" in res:
        summary["laplace_sigma"] = res["laplace"]["sigma"]
        if "corrected" in res["laplace"]:
            summary["laplace_corrected"] = {k: res["laplace"]["corrected"][k] for k in ("values", "sigma")}
    if "selection" in res:
        summary["selection"] = {k: res["selection"][k] for k in ("chosen", "components", "heldout_choice", "heldout_agrees", "why")}
    if args.json:
        print(dumps(summary, indent=None))
    else:
        if "selection" in res:
            print(format_table(res["selection"]))
            print(f"chosen: {res['selection']['why']}")
        sig = res.get("laplace", {}).get("sigma", {})
        edge = set(res.get("laplace", {}).get("at_bound") or [])
        kind = {"total": "total sigma", "noise": "noise sigma"}.get(res.get("laplace", {}).get("sigma_mode"), "Laplace")
        for n, v in summary["free"].items():
            print(f"{n:22s} {v}" + (f" +- {sig[n]:.3g} ({kind})" if sig.get(n) is not None else "")
                  + ("  (on its bound: no Gaussian sigma; see laplace.interval95)" if n in edge else ""))
        cor = res.get("laplace", {}).get("corrected")
        if cor and any(cor["values"][n] != v for n, v in summary["free"].items()):
            # the numerically corrected estimate beside the fitted one (docs/uncertainty.md)
            print("corrected for the fit's setting (laplace.corrected; which to read: docs/uncertainty.md): " + ", ".join(
                f"{n} {cor['values'][n]:.6g}" + (f" +- {cor['sigma'][n]:.3g}" if cor["sigma"].get(n) is not None else "")
                for n in summary["free"]))
        print(f"loss {m['loss']:.6g}  rmse {m['rmse']:.4g} {m['rmse_units']}  delta_e {m['delta_e']:.3g}  "
              f"({m['n_samples']} samples; {c['reason']} after {c['iterations']} L-BFGS iterations, {res['seconds']:.1f} s)")
        for n in res.get("notes", []):
            print(f"note: {n}")
        print(f"wrote {args.out}")
    return 0


def cmd_evaluate(args) -> int:
    _threads(args)
    if _photo_input(args.data):
        from .fit.photo import evaluate_photo

        refit = ["exposure"] + (["sun_azimuth_offset", "gain_red", "gain_blue"] if args.refit_nuisance else [])
        with _photo_named(args.data[0]):
            res = evaluate_photo(read_result(args.result), args.data[0], time=args.time, location=args.location, refit=refit,
                                 device=_check_device(args.device), progress=_progress(args))
        if args.json:
            print(dumps(res, indent=None))
        else:
            print(f"relative rms {res['rmse_rel']:.4f}  delta_e {res['delta_e']:.3g}  ({res['pixels']['used']} px; "
                  f"refitted {', '.join(res['refitted'])})")
        return 0
    res = run_evaluate(args.result, args.data, refit_nuisance=args.refit_nuisance, kider_site=_kider_site(args),
                       progress=_progress(args), device=_check_device(args.device), force=args.force)
    if args.json:
        print(dumps(res, indent=None))
    else:
        print(f"rmse {res['rmse']:.4g} {res['rmse_units']}  delta_e {res['delta_e']:.3g}  ({res['n_samples']} samples)")
    return 0


def cmd_sample(args) -> int:
    from .fit.sample import run_sample

    _threads(args)
    if args.walkers is not None and args.walkers < 2:
        raise UserError(f"--walkers must be >= 2, got {args.walkers}")
    if args.steps is not None and args.steps < 1:
        raise UserError(f"--steps must be >= 1, got {args.steps}")
    read_result(args.init)  # before the data: a missing, malformed or out-of-range RESULT.json is one line
    cfg, source = read_config(args.config)
    overrides = {"walkers": args.walkers, "steps": args.steps, "seed": args.seed, "integrator": args.integrator,
                 "view_samples": args.view_samples, "checkpoint_seconds": args.checkpoint_seconds, "accuracy": args.accuracy,
                 "batched": False if args.no_batch else None}
    try:
        res = run_sample(args.data, cfg, args.init, args.out, overrides=overrides, kider_site=_kider_site(args),
                         resume=args.resume, progress=_progress(args), plots=not args.no_plots,
                         device=_check_device(args.device), force=args.force, config_source=source)
    except ConfigError as e:
        raise ConfigError(f"config {source}: {e}") from None
    d = res["diagnostics"]
    short = {"out": str(args.out), "parameters": {n: {k: v[k] for k in ("median", "p16", "p84", "std")} for n, v in res["parameters"].items()},
             "tau_max": d["tau_max"], "acceptance": d["acceptance_fraction"]["mean"], "steps": d["steps"],
             "long_enough": d["long_enough"], "warning": d["warning"]}
    if args.json:
        print(dumps(short, indent=None))
    else:
        for n, v in res["parameters"].items():
            print(f"{n:22s} {v['median']:.6g} +{v['p84'] - v['median']:.3g} -{v['median'] - v['p16']:.3g}")
        print(f"{d['steps']} steps x {d['walkers']} walkers, tau max {d['tau_max']:.1f}, acceptance "
              f"{d['acceptance_fraction']['mean']:.2f}, burn-in {d['burn_in']}, thin {d['thin']}")
        print(f"wrote {args.out}")
    return 0


FIT_FLAGS = {
    "free": "free", "per_observation": "per_observation", "integrator": "integrator", "orders": "orders",
    "multiple": "multiple", "view_samples": "view_samples", "rule": "rule", "loss": "loss", "starts": "starts",
    "max_iter": "max_iter", "adam_steps": "adam_steps", "seed": "seed", "wavelengths": "wavelengths",
    "min_elevation": "min_elevation_deg", "sun_mask": "sun_mask_deg", "max_samples": "max_samples",
    "sigma_relative": "sigma_relative", "accuracy": "accuracy", "sigma": "sigma", "optimiser": "optimiser",
    "sigma_discrepancy": "sigma_discrepancy", "ms_follow": "ms_follow", "sigma_phase": "sigma_phase",
}
"""The per-fit flags of ``fit`` and ``batch`` (argparse dest -> FitSettings field)."""


def _fit_overrides(args) -> dict:
    """The per-fit flags as FitSettings overrides (None: not given)."""
    return {field: getattr(args, dest) for dest, field in FIT_FLAGS.items()}


def _add_fit_options(p, D) -> None:
    """The per-fit flags shared by ``fit`` and ``batch``; their help states ``D``'s (FitSettings') defaults."""
    p.add_argument("--free", help="comma list of fitted parameters (docs/fitting.md), e.g. mie_beta_550,mie_g,exposure")
    p.add_argument("--per-observation", help="comma list of nuisance parameters with one value per observation")
    p.add_argument("--integrator", help=f"NAME[:key=value,...] (default {D.integrator})")
    p.add_argument("--orders", type=int, help="scattering orders (1 = single scattering, the default; >= 2 adds multiple scattering)")
    p.add_argument("--multiple", choices=("hillaire", "bruneton", "bruneton_lagged"),
                   help="with --orders >= 2: Hillaire 2020's LUT (default, rebuilt per evaluation), Bruneton's tables (reduced "
                        "sizes, rebuilt per evaluation) or bruneton_lagged (Bruneton's orders >= 2 as a factor on the live single "
                        "scattering, frozen per fit and refreshed at its result; docs/fitting.md)")
    p.add_argument("--view-samples", type=int, help=f"samples of the view-ray integral (default {D.view_samples})")
    p.add_argument("--rule", help=f"outer quadrature rule (default {D.rule})")
    p.add_argument("--accuracy", help="auto (model error <= 1/3 of the data's median relative sigma), de=X or rel=X: "
                   "the cheapest measured renderer setting meeting it replaces --integrator/--view-samples/--rule")
    p.add_argument("--loss", help=f"squared, log, relative, huber, cauchy [:residual=...,delta=...] (default {D.loss})")
    p.add_argument("--starts", type=int, help=f"multi-start points (default {D.starts})")
    p.add_argument("--max-iter", type=int, help=f"optimiser iterations per start (default {D.max_iter})")
    p.add_argument("--optimiser", choices=("auto", "lm", "lbfgs"),
                   help=f"auto: Levenberg-Marquardt for squared losses, else Adam + L-BFGS (lbfgs: always, as "
                        f"earlier versions; default {D.optimiser})")
    p.add_argument("--adam-steps", type=int, help=f"Adam warm-start steps per start of L-BFGS (default {D.adam_steps})")
    p.add_argument("--seed", type=int, help=f"seed of the multi-start spread (default {D.seed})")
    p.add_argument("--wavelengths", help="model grid for RGB data, START:STOP:STEP or a list [nm]")
    p.add_argument("--min-elevation", type=float, help=f"horizon mask: lowest elevation used [deg] (default {D.min_elevation_deg:g})")
    p.add_argument("--sun-mask", type=float, help=f"images: radius of the disk around the sun left out [deg] (default {D.sun_mask_deg:g})")
    p.add_argument("--fast-multiple", dest="ms_follow", action="store_false", default=None,
                   help="photos: hold the multiple-scattering factor fixed between refreshes instead of following it in "
                        "the aerosol optical depth (one build per refresh instead of two, but more refreshes: no faster on the "
                        "synthetic photos since the saturations, and biased low on hazy skies; for speed on clear "
                        "skies --orders 3; docs/photos.md)")
    p.add_argument("--max-samples", type=int, help="images: use every k-th pixel so that at most this many remain")
    p.add_argument("--sigma-relative", type=float, help=f"images: relative noise when the header has none (default {D.sigma_relative:g})")
    p.add_argument("--sigma", choices=SIGMA_MODES,
                   help=f"--laplace sigma: total (noise + numerical model error + discrepancy floor) or noise only "
                        f"(default {D.sigma}; docs/uncertainty.md)")
    p.add_argument("--sigma-discrepancy", choices=DISCREPANCY_MODELS,
                   help=f"--sigma total's discrepancy term: a white relative error floor, a cluster-robust sandwich over "
                        f"sky regions, or the larger of the two (default {D.sigma_discrepancy}; docs/uncertainty.md)")
    p.add_argument("--sigma-phase", dest="sigma_phase", action=argparse.BooleanOptionalAction, default=None,
                   help="--sigma total: the phase term, the spread and shift of a two-term Henyey-Greenstein refit "
                        "(one-term HG fits with g free; one more fit; on by default, --no-sigma-phase for the faster, "
                        "narrower sigma of a one-lobed aerosol; docs/uncertainty.md, \"The phase term\")")
    p.add_argument("--location", help="LAT,LON[,ELEV] [deg, deg, m]: a photo's place (default: its EXIF GPS position), "
                   "Kider data's site (default: the Kider site)")
    p.add_argument("--timezone", type=float, help="Kider data: UTC offset of the folder times [h] (default -4)")


def _add_sun_flags(p) -> None:
    """The sun of ``render`` and ``envmap``: zenith and azimuth, or a time and a place (NREL SPA)."""
    p.add_argument("--sun-zenith", type=float, help="sun zenith angle [deg]")
    p.add_argument("--sun-azimuth", type=float, default=180.0, help="sun azimuth, clockwise from North [deg] (default %(default)g)")
    p.add_argument("--time", help="ISO 8601 timestamp with a UTC offset or an IANA time zone name (daylight saving "
                   "time from the tz database), e.g. 2013-05-27T09:30:00-04:00, '2013-05-27T09:30:00 America/New_York' "
                   "or 2013-05-27T09:30:00[America/New_York] (sun by NREL SPA)")
    p.add_argument("--location", help="LAT,LON[,ELEV]: degrees North, degrees East, metres (with --time)")


def _add_photo_options(p) -> None:
    """The flags of a photo (``fit PHOTO``; ``evaluate RESULT PHOTO`` takes --time and --location)."""
    p.add_argument("--time", help="photo: when it was taken, ISO 8601 with its UTC offset or a zone name "
                   "(2024-06-01T14:05:00+02:00); default: EXIF DateTimeOriginal with its OffsetTimeOriginal")
    p.add_argument("--camera", help="photo: CAMERA.yaml (projection, cx, cy, radius_px or focal_px, up_azimuth_deg, tilt_deg, "
                   "vignetting, gains, saturation_red/blue, spectral_sensitivities CSV); default: estimated from the image and the sun")
    p.add_argument("--mask", help="photo: an image of the photo's size, non-zero = ignore (added to the automatic masks)")
    p.add_argument("--exposures", help="bracket folder: exposure times of the frames in file-name order, comma list [s] "
                   "(default: from EXIF, else estimated from the frames' overlap)")
    p.add_argument("--linear", action="store_true", help="photo: pixel values are linear (no sRGB decoding)")
    p.add_argument("--response", help="photo: camera response srgb, linear, gamma:G, estimate (a bracket: from the frames), "
                   "debevec or robertson (a bracket: calibrated from its frames), or file:TABLE.csv (rows code,X or "
                   "code,R,G,B; codes 0..1)")


def _add_fit_parsers(sub) -> None:
    D = FitSettings()  # the help states the defaults of the one definition
    f = sub.add_parser("fit", help="fit an atmosphere to fisheye EXR images or Kider captures (docs/fitting.md)")
    f.add_argument("data", nargs="+", help="an .exr fisheye, a Kider capture folder, or a folder of either (several: joint fit); "
                   "or one photo: JPEG/PNG/TIFF, camera RAW, Radiance .hdr, EXR without skyfit metadata, or a folder "
                   "of one scene's bracketed exposures (with --time and --location, or EXIF DateTimeOriginal + OffsetTimeOriginal and "
                   "GPS; docs/photos.md)")
    f.add_argument("--config", help="atmosphere config YAML with an optional fit: section (or a shipped name); "
                   "required for EXR and Kider data, default earth for a photo")
    _add_photo_options(f)
    f.add_argument("--out", required=True, help="RESULT.json (plots are written beside it)")
    _add_fit_options(f, D)
    f.add_argument("--no-plots", action="store_true", help="do not write PNG plots")
    f.add_argument("--laplace", action="store_true", help="add a Hessian (Laplace) covariance: sigma and correlation per parameter")
    f.add_argument("--select", action="store_true",
                   help="choose the model by a ladder of nested models, BIC and held-out pixels (docs/selection.md)")
    f.add_argument("--select-sigma", choices=("scaled", "known"),
                   help="--select: data sigma known up to a fitted common factor (default) or exactly")
    f.add_argument("--heldout", type=float, help=f"--select: fraction of samples held out of the fits (default {D.select_heldout:g})")
    f.add_argument("--threads", type=int, help="torch intra-op threads (default: torch's; 1 is fastest for small fits on a busy machine; "
                   "a photo fit with 2 or more runs its independent branches side by side, one process each)")
    f.add_argument("--progress", action=argparse.BooleanOptionalAction, default=None, help="tqdm bar (default: on a terminal)")
    f.add_argument("--device", default="cpu", help="cpu, cuda, cuda:N or auto (CUDA when present); default cpu")
    f.add_argument("--dtype", choices=("float32", "float64"), help=f"working precision (default {D.dtype})")
    f.add_argument("--json", action="store_true", help="print the summary as one line of JSON")
    f.set_defaults(func=cmd_fit)

    e = sub.add_parser("evaluate", help="how well a fitted atmosphere predicts DATA (its own sun position)")
    e.add_argument("result", help="RESULT.json of skyfit fit")
    e.add_argument("data", nargs="+", help="an .exr fisheye, a Kider capture folder, or a folder of either")
    e.add_argument("--time", help="photo: when it was taken, ISO 8601 with its UTC offset or a zone name (default: EXIF "
                   "DateTimeOriginal with its OffsetTimeOriginal)")
    e.add_argument("--refit-nuisance", action="store_true", help="re-estimate exposure and the orientation the fit modelled (sun offsets, camera tilts; default the sun azimuth and zenith offsets) on DATA, atmosphere fixed")
    e.add_argument("--location", help="LAT,LON[,ELEV] [deg, deg, m]: a photo's place (default: its EXIF GPS position, "
                   "else the fit's), Kider data's site (default: the Kider site)")
    e.add_argument("--timezone", type=float, help="Kider data: UTC offset of the folder times [h] (default -4)")
    e.add_argument("--progress", action=argparse.BooleanOptionalAction, default=None, help="tqdm bar (default: on a terminal)")
    e.add_argument("--threads", type=int, help="torch intra-op threads (default: torch's)")
    e.add_argument("--device", default="cpu", help="cpu, cuda, cuda:N or auto (CUDA when present); default cpu")
    e.add_argument("--json", action="store_true", help="print the summary as one line of JSON")
    e.set_defaults(func=cmd_evaluate)

    sm = sub.add_parser("sample", help="emcee posterior around a fit: chain, summary.json, corner/trace plots (docs/uncertainty.md)")
    sm.add_argument("data", nargs="+", help="the DATA the fit used (.exr, Kider folders)")
    sm.add_argument("--config", required=True, help="atmosphere config (or shipped name); optional sample: section (priors...)")
    sm.add_argument("--init", required=True, help="RESULT.json of skyfit fit: free set, settings and the starting point")
    sm.add_argument("--out", required=True, help="output folder: chain.h5, summary.json, plots")
    sm.add_argument("--walkers", type=int, help="ensemble size, even and >= 2 x free parameters (default 32)")
    sm.add_argument("--steps", type=int, help="chain length per walker (default 2000); with --resume the total to reach")
    sm.add_argument("--seed", type=int, help="random seed (default 0)")
    sm.add_argument("--resume", action="store_true", help="continue DIR/chain.h5 from its last checkpoint")
    sm.add_argument("--integrator", help="optical-depth integrator while sampling (default: the fit's); its bias is measured")
    sm.add_argument("--view-samples", type=int, help="view-ray samples while sampling (default: the fit's)")
    sm.add_argument("--accuracy", help="auto (model error <= 1/3 of the data's median relative sigma), de=X or rel=X: "
                    "the cheapest measured renderer setting meeting it while sampling (default: the fit's renderer)")
    sm.add_argument("--checkpoint-seconds", type=float, help="wall time between chain checkpoints (default 10)")
    sm.add_argument("--no-batch", action="store_true", help="evaluate the walkers one at a time (for comparison)")
    sm.add_argument("--no-plots", action="store_true", help="do not write PNG plots")
    sm.add_argument("--location", help="Kider data: LAT,LON[,ELEV] (default: the Kider site)")
    sm.add_argument("--timezone", type=float, help="Kider data: UTC offset of the folder times [h] (default -4)")
    sm.add_argument("--threads", type=int, help="torch intra-op threads (default: torch's)")
    sm.add_argument("--progress", action=argparse.BooleanOptionalAction, default=None, help="tqdm bar with running tau (default: on a terminal)")
    sm.add_argument("--device", default="cpu", help="cpu, cuda, cuda:N or auto (CUDA when present); default cpu")
    sm.add_argument("--json", action="store_true", help="print the summary as one line of JSON")
    sm.set_defaults(func=cmd_sample)


def cmd_bench(args) -> int:
    if args.threads is not None and args.threads < 1:
        raise UserError(f"--threads must be >= 1, got {args.threads}")
    device = _check_device(args.device)
    if args.frontier_out and args.study == "integrators":
        raise UserError("--frontier-out needs --study trade or all (the trade study writes it)")
    if args.study == "integrators":
        run_bench(out=Path(args.out), quick=args.quick, device=device, as_json=args.json, threads=args.threads)
        return 0
    trade = lambda as_json: run_trade_study(out=Path(args.out), quick=args.quick, device=device, as_json=as_json,  # noqa: E731
                                            threads=args.threads, frontier_out=args.frontier_out and Path(args.frontier_out),
                                            command="skyfit " + " ".join(sys.argv[1:]) if sys.argv[1:2] == ["bench"] else None)
    if args.study == "trade":
        trade(args.json)
        return 0
    if not args.json:
        run_bench(out=Path(args.out), quick=args.quick, device=device, threads=args.threads)
        trade(False)
        return 0
    with contextlib.redirect_stdout(io.StringIO()) as a:
        run_bench(out=Path(args.out), quick=args.quick, device=device, as_json=True, threads=args.threads)
    with contextlib.redirect_stdout(io.StringIO()) as b:
        trade(True)
    print(json.dumps({"integrators": json.loads(a.getvalue()), "trade": json.loads(b.getvalue())}))
    return 0


def _write_json_atomic(path: Path, data: dict) -> None:
    """Write ``data`` as strict JSON (NaN refused) to a temporary file beside ``path``, then rename it."""
    write_text_atomic(path, json.dumps(data, indent=2, allow_nan=False) + "\n")


def cmd_calibrate_integrator(args) -> int:

    out = Path(args.out)
    if out.suffix.lower() != ".json":
        raise UserError(f"--out must name a .json file, got {out}")
    if not out.parent.is_dir():
        raise UserError(f"--out: directory {out.parent} does not exist")
    for flag, v in (("--tolerance", args.tolerance), ("--transmittance-tolerance", args.transmittance_tolerance)):
        if not 0.0 < v < 1.0:
            raise UserError(f"{flag} must be in (0, 1), got {v}")
    lam = parse_wavelengths(args.wavelengths)
    atm = load_atmosphere(args.config, lam, dtype=torch.float64, device=_check_device(args.device))
    settings = dict(CALIBRATE_QUICK) if args.quick else {}
    t0 = time.perf_counter()
    res = calibrate_integrators(atm, tolerance=args.tolerance, transmittance_tolerance=args.transmittance_tolerance,
                                metric=args.metric, d_spacing=args.d_spacing, view_rule=args.view_rule,
                                spline_kind=args.spline_kind, **settings)
    res = {"atmosphere": res.pop("atmosphere"), "config": str(args.config), **res}
    res["run"] = {"seconds": round(time.perf_counter() - t0, 2), "quick": bool(args.quick), "skyfit_version": __version__,
                  "machine": machine_info("cpu")}
    _write_json_atomic(out, res)
    t = res["taylor"]
    spline = res.get("spline", {})
    summary = {"out": str(out), "a": t["a"], "b": t["b"], "taylor_error": t["error"], "default_error": t["default_error"],
               "spline": [spline.get("height_points"), spline.get("distance_points")], "view_samples": res["view_samples"]}
    if args.json:
        print(json.dumps(summary))
    else:
        print(f"wrote {out}: taylor a={t['a']:.4f} b={t['b']:.4f} error {t['error']:.3g} (default 0.45/0.45: {t['default_error']:.3g}); "
              f"spline {summary['spline'][0]}x{summary['spline'][1]}; view samples {res['view_samples']} ({res['run']['seconds']:.1f} s)")
    return 0


def cmd_export_lut(args) -> int:
    """Precompute Bruneton's tables for a fitted atmosphere and write them as LUTs (docs/luts.md)."""
    device = _check_device(args.device)
    if args.orders < 1:
        raise UserError(f"--orders must be >= 1 (1 = single scattering), got {args.orders}")
    if args.layout == "bruneton2017" and args.format != "exr":
        raise UserError(f"--layout bruneton2017 writes EXR and raw .dat textures; --format {args.format} is for --layout skyfit")
    if args.precision is not None and args.layout != "bruneton2017":
        raise UserError("--precision applies to --layout bruneton2017 (the other layouts are float32)")
    if args.layout == "unreal" and args.format != "exr":
        raise UserError(f"--layout unreal writes EXR LUTs and unreal.json; --format {args.format} is for --layout skyfit")
    if args.sun_zenith is not None and args.layout != "unreal":
        raise UserError("--sun-zenith applies to --layout unreal (the sky-view LUTs)")
    sky_view_suns = _floats(args.sun_zenith, len(args.sun_zenith.split(",")), "--sun-zenith") if args.sun_zenith else [45.0]
    if not all(0.0 <= z <= 180.0 for z in sky_view_suns):
        raise UserError(f"--sun-zenith angles must be in [0, 180] degrees, got {args.sun_zenith}")
    res = read_result(args.result)
    if args.wavelengths is not None:
        lam = parse_wavelengths(args.wavelengths)
    else:
        lam = np.asarray(res["model"].get("wavelengths_nm") or parse_wavelengths(DEFAULT_WAVELENGTHS), float)
    sizes = _table_sizes(args.table_sizes) or TableSizes()
    out = check_writable(args.out, directory=True)  # before the (long) precomputation; creates nothing
    try:
        atm = atmosphere_from_result(res, lam, device=device)
    except (KeyError, TypeError) as e:
        raise UserError(f"{args.result}: malformed result ({e})") from None
    t0 = time.perf_counter()
    if args.layout == "bruneton2017":
        b17 = bruneton2017
        with torch.no_grad():
            tables = precompute(atm, orders=args.orders, sizes=sizes, quadrature=ACCURATE_QUADRATURE,
                                mu_s_min=b17.skyfit_mu_s_min(b17.UPSTREAM_MU_S_MIN, atm.bottom_radius, atm.top_radius))
        b17.export_bruneton2017(tables, out, precision=args.precision or "f32",
                                atm_rgb=atmosphere_from_result(res, list(b17.LAMBDAS_RGB_NM), device=device))
    elif args.layout == "unreal":
        export_unreal(atm, atmosphere_from_result(res, list(bruneton2017.LAMBDAS_RGB_NM), device=device), out,
                      sun_zeniths=sky_view_suns)
    else:
        with torch.no_grad():
            tables = precompute(atm, orders=args.orders, sizes=sizes, quadrature=ACCURATE_QUADRATURE)
        export_luts(tables, atm, out, format=args.format, rgb=args.rgb)
    info = {"out": str(out), "format": args.format, "orders": args.orders, "seconds": round(time.perf_counter() - t0, 3),
            "channels": "rgb" if args.rgb or args.layout != "skyfit" else "spectral", "layout": args.layout,
            "wavelengths_nm": [float(v) for v in lam]}
    if args.layout == "bruneton2017":
        info["precision"] = args.precision or "f32"
    print(json.dumps(info) if args.json else f"wrote {out} ({args.format}, {args.orders} orders) in {info['seconds']:.1f} s")
    return 0


# -- one camera from several photos ----------------------------------------------
def cmd_calibrate_camera(args) -> int:
    """``skyfit calibrate-camera PHOTO... --time T ... --location L --out CAMERA.yaml`` (skyfit.fit.photo_calibration)."""
    from .fit.photo_calibration import calibrate_camera, write_camera

    times = list(args.time or [])
    for t in times:  # before any photo is read: a bad time is the flag's error
        try:
            parse_time(t)
        except ValueError as e:
            msg = str(e).splitlines()[0] if str(e) else type(e).__name__
            raise UserError(f"--time {t}: {msg}") from None
    if len(times) != len(args.photos):
        raise UserError(f"--time: give one per photo, in order: {len(args.photos)} photo(s), {len(times)} --time")
    if Path(args.out).suffix.lower() not in (".yaml", ".yml"):
        raise UserError(f"--out must name a .yaml file, got {args.out}")
    cfg, source = read_config(args.config or "earth")
    cam = calibrate_camera(args.photos, times, args.location, cfg, linear=args.linear, device=_check_device(args.device))
    write_camera(cam, args.out)
    summary = {"out": str(args.out), **{k: cam[k] for k in ("projection", "size", "cx", "cy", "radius_px", "up_azimuth_deg",
                                                            "tilt_deg", "vignetting", "gain_red", "gain_blue", "saturation_red", "saturation_blue")
                                        if k in cam},
               "spread": cam["_spread"], "photos": len(cam["photos"])}
    if args.json:
        print(dumps(summary, indent=None))
    else:
        sp = cam["_spread"]
        print(f"projection {cam['projection']} ({sp['projection']})")
        print(f"centre ({cam['cx']:.2f}, {cam['cy']:.2f}) px +- {max(sp['cx']['max_abs_dev'], sp['cy']['max_abs_dev']):.2g}, "
              f"radius {cam['radius_px']:.2f} px +- {sp['radius_px']['max_abs_dev']:.2g}")
        print(f"up azimuth {cam['up_azimuth_deg']:.2f} deg +- {sp['up_azimuth_deg']['max_abs_dev']:.2g}, tilt "
              f"{cam['tilt_deg'][0]:.2f}/{cam['tilt_deg'][1]:.2f} deg (East/North)")
        print(f"wrote {args.out} ({len(cam['photos'])} photo(s))")
    return 0


def _add_calibrate_camera_parser(sub) -> None:
    c = sub.add_parser("calibrate-camera", help="one CAMERA.yaml (projection, centre, radius, heading, tilt, vignetting, "
                       "gains) from sky photos of known time and place, for fit PHOTO --camera (docs/photos.md)")
    c.add_argument("photos", nargs="+", help="photos of one camera (JPEG/PNG/TIFF, RAW, .hdr, EXR, or bracket folders), "
                   "all of one image size")
    c.add_argument("--time", action="append", help="when each photo was taken, ISO 8601 with its UTC offset or a zone name; "
                   "one --time per photo, in the photos' order (required)")
    c.add_argument("--location", required=True, help="LAT,LON[,ELEV] [deg, deg, m] of the photos")
    c.add_argument("--out", required=True, help="CAMERA.yaml to write (atomically)")
    c.add_argument("--config", help="atmosphere config YAML with an optional fit: section (or a shipped name); default earth")
    c.add_argument("--linear", action="store_true", help="pixel values are linear (no sRGB decoding)")
    c.add_argument("--device", default="cpu", help="cpu, cuda, cuda:N or auto (CUDA when present); default cpu")
    c.add_argument("--json", action="store_true", help="print the summary as one line of JSON")
    c.set_defaults(func=cmd_calibrate_camera)


# -- many skies ------------------------------------------------------------------
def cmd_batch(args) -> int:
    """``skyfit batch``: a thin layer over :func:`skyfit.batch.batch` (CONTRACT.md, "Many skies"; docs/batch.md)."""
    if args.scheduler and (args.workers is not None or args.threads_per_worker is not None):
        raise UserError("--workers and --threads-per-worker size the local cluster; a --scheduler's cluster has its own workers")
    overrides = _fit_overrides(args)
    free = overrides.pop("free")
    # a local cluster runs on this machine: its --device is checked here; a scheduler's workers resolve it themselves
    device = args.device if args.scheduler else _check_device(args.device)
    say = (lambda line: print(line, file=sys.stderr)) if args.json else print
    df = run_batch(args.data, args.config, out=args.out, scheduler=args.scheduler, workers=args.workers,
                   threads_per_worker=args.threads_per_worker or 1, resume=args.resume, laplace=args.laplace,
                   progress=_progress(args), retries=args.retries, free=free, kider_site=_kider_site(args),
                   plot=not args.no_plots, warm_start=args.warm_start, device=device,
                   force=getattr(args, "force", False), log=say, location=args.location, times=args.times,
                   photo_timezone=args.photo_timezone, camera=args.camera, mask=args.mask, linear=args.linear,
                   response=args.response, smooth=args.smooth,
                   **{k: v for k, v in overrides.items() if v is not None})
    a = df.attrs
    n_ok = int((df["status"] == "ok").sum())
    if args.json:
        print(dumps({"out": str(args.out), "items": len(df), "ok": n_ok, "failed": len(df) - n_ok,
                     "resumed": a["resumed"], "seconds": round(a["seconds"], 3), "startup_s": round(a["startup_s"], 3),
                     "run_s": round(a["run_s"], 3), "dashboard": a["dashboard"], "workers": a["workers"],
                     "files": a["files"]}, indent=None))
    else:
        print("\n".join(summary_lines(df, a["seconds"])))
        print(f"wrote {args.out} ({', '.join(Path(f).name for f in a['files'])} and one RESULT.json per item)")
    return 0


def _add_batch_parser(sub) -> None:
    D = FitSettings()
    b = sub.add_parser("batch", help="one fit per item (captures, photos, folders, globs) on Dask: RESULT.json per item, "
                                     "results.parquet/.csv, timeseries.png (docs/batch.md)")
    b.add_argument("data", nargs="+", help="Kider capture folders, .exr files, photos (JPEG/PNG/TIFF/RAW/.hdr/EXR without "
                   "skyfit metadata), bracket folders, folders of any of these, or globs (quoted). A folder of image "
                   "frames is one bracket when it holds a file named .bracket or its frames' EXIF times lie within "
                   "10 s; otherwise each frame is one photo (docs/batch.md)")
    b.add_argument("--config", help="atmosphere config YAML with an optional fit: section (or a shipped name); "
                   "required for EXR and Kider data, default earth when every item is a photo")
    b.add_argument("--out", required=True, help="output folder: <item>/RESULT.json, results.parquet, results.csv, timeseries.png")
    b.add_argument("--scheduler", metavar="ADDRESS", help="a running Dask scheduler, tcp://HOST:PORT (default: a local cluster)")
    b.add_argument("--workers", type=int, help="local cluster: worker processes (default: one per CPU)")
    b.add_argument("--threads-per-worker", type=int, help="local cluster: fits at once per worker, one torch thread each (default 1)")
    b.add_argument("--retries", type=int, default=2, help="reschedules of an item whose worker died before it is recorded as failed (default 2)")
    b.add_argument("--resume", action="store_true", help="skip the items with a complete RESULT.json in --out")
    b.add_argument("--laplace", action="store_true", help="Laplace sigma per free parameter (sigma_<name> columns, bands in timeseries.png)")
    b.add_argument("--warm-start", choices=("previous",),
                   help="previous: start each fit from the item before it (in order; contiguous chains, one per worker "
                   "thread; a photo passes on only its aerosol)")
    b.add_argument("--smooth", metavar="SIGMA",
                   help="after the fits, smooth AOD 550 (in log), Ångström α and g over time jointly: a random walk "
                   "of SIGMA per sqrt(hour) (0.1 = 10%% AOD change / 0.1 in α, g per sqrt(h)) or "
                   "aod_550=S,angstrom_alpha=S,g=S; Student-t weights for outliers; adds <name>_smooth, "
                   "sigma_<name>_smooth, smooth_weight columns (docs/batch.md)")
    _add_fit_options(b, D)
    b.add_argument("--times", metavar="CSV", help="photos: rows file,time (ISO 8601); a photo's row wins over its EXIF "
                   "DateTimeOriginal (paths relative to the CSV, or file names)")
    b.add_argument("--photo-timezone", metavar="ZONE", help="photos: the zone of times without a UTC offset (EXIF "
                   "DateTimeOriginal without OffsetTimeOriginal, naive --times rows): +02:00, -4 or an IANA name "
                   "such as Europe/Berlin (daylight saving applied)")
    b.add_argument("--camera", help="photos: CAMERA.yaml of the camera that took them all (default: each photo's camera "
                   "estimated from the image and the sun)")
    b.add_argument("--mask", help="photos: an image of the photos' size, non-zero = ignore (added to the automatic masks)")
    b.add_argument("--linear", action="store_true", help="photos: pixel values are linear (no sRGB decoding)")
    b.add_argument("--response", help="photos: camera response srgb, linear, gamma:G, estimate, debevec or robertson "
                   "(brackets: calibrated from their frames), or file:TABLE.csv (rows code,X or code,R,G,B; codes 0..1)")
    b.add_argument("--no-plots", action="store_true", help="do not write timeseries.png")
    b.add_argument("--device", default="cpu", help="cpu, cuda, cuda:N or auto (resolved on each worker); default cpu")
    b.add_argument("--progress", action=argparse.BooleanOptionalAction, default=None, help="tqdm bar over the items (default: on a terminal)")
    b.add_argument("--json", action="store_true", help="print the summary as one line of JSON")
    b.set_defaults(func=cmd_batch)


def _envmap_atmosphere(source: str, wavelengths: str | None, sun_distance_au: float | None, device="cpu"):
    """``skyfit envmap``'s SOURCE: a RESULT.json (the fitted atmosphere) or a config (name or YAML)."""
    if Path(source).suffix.lower() == ".json":
        res = read_result(source)
        lam = parse_wavelengths(wavelengths) if wavelengths else None
        try:
            return atmosphere_from_result(res, lam, device=device)
        except (KeyError, TypeError) as e:
            raise UserError(f"{source}: malformed result ({e})") from None
    return load_atmosphere(source, parse_wavelengths(wavelengths or DEFAULT_WAVELENGTHS), sun_distance_au=sun_distance_au,
                           device=device)


def cmd_envmap(args) -> int:
    """An HDR environment map (lat-long or cubemap) of a fitted sky or a config (docs/envmap.md)."""
    from .export.envmap import MAX_SIZE, check_output, preview_path, write_envmap

    try:
        out = check_output(args.out, spectral=args.spectral)
    except ValueError as e:
        raise UserError(str(e)) from None
    if not (2 <= args.size <= MAX_SIZE and args.size % 2 == 0):
        raise UserError(f"--size must be an even number of pixels in 2..{MAX_SIZE}, got {args.size}")
    if args.orders < 1:
        raise UserError(f"--orders must be >= 1 (1 = single scattering), got {args.orders}")
    if not (0.0 <= args.altitude < math.inf):
        raise UserError(f"--altitude must be >= 0 m above the ground, got {args.altitude}")
    check_writable(out)  # before the (long) precomputation; creates nothing
    if args.preview:
        check_writable(preview_path(out), what="--preview")
    sun_zenith, sun_azimuth, sun_info = _sun_from_args(args)
    sizes = _table_sizes(args.table_sizes)
    atm = _envmap_atmosphere(args.source, args.wavelengths, sun_info.get("distance_au"), _check_device(args.device))
    t0 = time.perf_counter()
    env = envmap(atm, (sun_zenith, sun_azimuth), size=args.size, layout=args.format, sun_disk=args.sun_disk,
                 orders=args.orders, multiple=args.multiple, table_sizes=sizes, altitude=args.altitude,
                 spectral=args.spectral)
    written = write_envmap(env, out, preview=args.preview,
                           extra_meta={"sun": {**env.sun, **sun_info}, "source": str(args.source), "skyfit_version": __version__})
    rgb_e = env.irradiance()
    info = {"out": str(out), "preview": str(preview_path(out)) if args.preview else None, "format": args.format,
            "size": env.size, "shape": list(env.image().shape[:2]), "sun": {**env.sun, **sun_info},
            "seconds": round(time.perf_counter() - t0, 3),
            "horizontal_illuminance_lux": float(rgb_e @ np.linalg.inv(_xyz_to_srgb())[1])}
    text = (f"wrote {', '.join(str(p) for p in written)} ({args.format}, {info['shape'][0]}x{info['shape'][1]}) in "
            f"{info['seconds']:.1f} s; horizontal illuminance {info['horizontal_illuminance_lux']:.4g} lx")
    print(json.dumps(info) if args.json else text)
    return 0


def _xyz_to_srgb() -> np.ndarray:
    from .render.colour import xyz_to_srgb_matrix

    return xyz_to_srgb_matrix()


def _add_envmap_parser(sub) -> None:
    from .export.envmap import LAYOUTS

    v = sub.add_parser("envmap", help="an HDR environment map (lat-long or cubemap) of a fitted sky (docs/envmap.md)")
    v.add_argument("source", help="RESULT.json of skyfit fit, or an atmosphere config (shipped name or YAML)")
    v.add_argument("--out", required=True, help="output .exr (R, G, B, Y [+ L<nm>]) or .hdr (Radiance RGBE) file")
    v.add_argument("--format", choices=LAYOUTS, default="latlong",
                   help="latlong: H x 2H, row 0 straight up, column 0's left edge North, East at W/4; "
                        "cubemap: faces +X,-X,+Y,-Y,+Z,-Z of (x=East, y=Up, z=South) as an N x 6N strip (default latlong)")
    v.add_argument("--size", type=int, default=512, help="lat-long height H (width 2H) or cube face edge N, even [px] (default 512)")
    _add_sun_flags(v)
    v.add_argument("--sun-disk", action="store_true", help="add the attenuated solar disk (its flux exact at any size)")
    v.add_argument("--preview", action="store_true", help="also write a tone-mapped PNG beside --out (same name, .png)")
    v.add_argument("--spectral", action="store_true", help="also write one channel L<nm> per wavelength (.exr only)")
    v.add_argument("--orders", type=int, default=4, help="scattering orders (1 = single scattering; default 4)")
    v.add_argument("--multiple", choices=("bruneton", "hillaire"), default="bruneton",
                   help="with --orders >= 2: Bruneton's precomputed tables or Hillaire 2020's LUT (default bruneton)")
    v.add_argument("--table-sizes", help="R,MU,MUS,NU Bruneton scattering-table sizes (default 2017's 32,128,32,8; "
                                         "minutes of precomputation on a 2-core CPU)")
    v.add_argument("--wavelengths", help="START:STOP:STEP or comma list [nm] (default: the fit's, or "
                                         f"{DEFAULT_WAVELENGTHS} for a config)")
    v.add_argument("--altitude", type=float, default=0.0, help="observer altitude above the ground [m] (default 0)")
    v.add_argument("--device", default="cpu", help="cpu, cuda, cuda:N or auto (CUDA when present); default cpu")
    v.add_argument("--json", action="store_true", help="print a JSON summary")
    v.set_defaults(func=cmd_envmap)


# -- checks before any work (docs/reliability.md) --------------------------------
_INF = math.inf
FLAG_RANGES: dict[str, tuple[float, float, str]] = {
    # dest: (lo, hi, "[]" / "[)" / "()" / "(]"); a flag a command does not have is skipped, as is None
    "view_samples": (1, _INF, "[)"), "orders": (1, _INF, "[)"), "threads": (1, _INF, "[)"),
    "walkers": (2, _INF, "[)"), "steps": (1, _INF, "[)"), "seed": (0, _INF, "[)"), "starts": (1, _INF, "[)"),
    "max_iter": (1, _INF, "[)"), "adam_steps": (0, _INF, "[)"), "max_samples": (1, _INF, "[)"),
    "checkpoint_seconds": (0, _INF, "()"), "sun_mask": (0, 180, "[)"), "min_elevation": (-90, 90, "[)"),
    "sigma_relative": (0, _INF, "[)"), "heldout": (0, 1, "[)"), "timezone": (-14, 14, "[]"),
    "sun_zenith": (0, 180, "[]"), "altitude": (0, _INF, "[)"), "focal": (0, _INF, "()"), "radius": (0, _INF, "()"),
    "max_zenith": (0, 180, "(]"), "tolerance": (0, 1, "()"), "transmittance_tolerance": (0, 1, "()"),
    "workers": (1, _INF, "[)"), "threads_per_worker": (1, _INF, "[)"), "retries": (0, _INF, "[)"),
}
"""Ranges of the numeric flags, checked for every command before any work; every float flag must
also be finite (``nan`` and ``inf`` parse as floats)."""
FLAG_WHAT = {"heldout": "the held-out fraction", "timezone": "a UTC offset in hours"}
"""What a flag is, where its name alone does not say, for the range messages."""
OUTPUTS: dict[str, tuple[tuple[str, bool], ...]] = {
    # command: (dest, is a folder) of each output path
    "render": (("out", False),), "fit": (("out", False),), "calibrate-integrator": (("out", False),),
    "envmap": (("out", False),), "sample": (("out", True),), "bench": (("out", True), ("frontier_out", False)),
    "demo": (("out", True),), "export-lut": (("out", True),), "batch": (("out", True),),
    "calibrate-camera": (("out", False),),
}
"""Output paths, checked for writability (and file vs folder) before any work."""
FORCE_COMMANDS = ("render", "fit", "sample", "evaluate", "export-lut", "envmap", "batch")
"""Commands with ``--force``: run although the memory or time estimate says no (skyfit.resources)."""


def _flag(dest: str) -> str:
    return "--" + dest.replace("_", "-")


def check_flags(parser: argparse.ArgumentParser, args) -> None:
    """UserError naming the flag for a numeric flag out of :data:`FLAG_RANGES` or a float flag not finite."""
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction)).choices[args.command]
    for action in sub._actions:
        v = getattr(args, action.dest, None)
        if action.type not in (int, float) or v is None or isinstance(v, bool):
            continue
        flag = action.option_strings[0] if action.option_strings else action.dest
        if action.type is float and not math.isfinite(v):
            raise UserError(f"{flag} must be a finite number, got {v}")
        if action.dest in FLAG_RANGES:
            lo, hi, b = FLAG_RANGES[action.dest]
            if not ((lo <= v if b[0] == "[" else lo < v) and (v <= hi if b[1] == "]" else v < hi)):
                rng = (f">= {lo:g}" if b[0] == "[" else f"> {lo:g}") if hi == _INF else f"in {b[0]}{lo:g}, {hi:g}{b[1]}"
                what = f" ({FLAG_WHAT[action.dest]})" if action.dest in FLAG_WHAT else ""
                raise UserError(f"{flag}{what} must be {rng}, got {v:g}")


SPECS = {"wavelengths": parse_wavelengths, "table_sizes": TableSizes.parse, "location": parse_location, "time": parse_time}
"""Flags holding a spec string, parsed before any work even where the command would not use it (e.g.
--wavelengths for spectral data, --table-sizes with --orders 1): a malformed value is always an error."""


def check_specs(args) -> None:
    """UserError naming the flag and its value for a spec flag of :data:`SPECS` that does not parse."""
    for dest, parse in SPECS.items():
        v = getattr(args, dest, None)
        if v is None or not isinstance(v, str):
            continue
        try:
            parse(v)
        except ValueError as e:
            msg = str(e).splitlines()[0] if str(e) else type(e).__name__
            raise UserError(msg if _flag(dest) in msg else f"{_flag(dest)} {v}: {msg}") from None


def check_outputs(args) -> None:
    """OutputError (one line) unless every output path of the command can be written: a file target is not a
    folder, a folder target not a file, and the place is writable; nothing is created (skyfit.io.atomic)."""
    for dest, folder in OUTPUTS.get(args.command, ()):
        path = getattr(args, dest, None)
        if path:
            check_writable(path, directory=folder, what=_flag(dest))


def _render_estimate(args, n_wavelengths: int, integrator=None, device: str = "cpu") -> Estimate:
    """Memory and time of ``skyfit render`` (or ``envmap``) with these flags (skyfit.resources)."""
    nbytes = 8 if getattr(args, "dtype", "float32") == "float64" else 4
    if args.command == "envmap":
        rays = float(args.size) * (2 * args.size if args.format == "latlong" else 6 * args.size)
    else:
        rays = float(args.size) ** 2 * math.pi / 4  # the fisheye's circle
    orders = int(getattr(args, "orders", 1))
    what = f"{args.command} {args.size}x{args.size}" if args.command == "render" else f"{args.command} of size {args.size}"
    if orders > 1 and getattr(args, "multiple", "bruneton") == "bruneton":
        sizes = _table_sizes(getattr(args, "table_sizes", None)) or TableSizes()
        est = tables_estimate(sizes.scattering_shape, n_wavelengths, orders, dtype_bytes=nbytes, device=device, what=what)
        look = single_scattering_estimate(rays, n_wavelengths, 1, None, dtype_bytes=nbytes, device=device)
        return Estimate(what, max(est.memory_bytes, look.memory_bytes), est.seconds + look.seconds, est.detail)
    settings = integrator.settings() if integrator is not None else None
    return single_scattering_estimate(rays, n_wavelengths, int(getattr(args, "view_samples", 32) or 32), settings,
                                      dtype_bytes=nbytes, device=device, what=what)


def check_resources(args, n_wavelengths: int, integrator=None) -> None:
    """ResourceError (one line, with the estimate) for a render, envmap or export-lut too large for this
    machine or too long to run unasked; ``--force`` skips it."""
    device = _check_device(args.device) if getattr(args, "device", None) else "cpu"  # auto -> the device it means
    if args.command == "export-lut":
        sizes = _table_sizes(args.table_sizes) or TableSizes()
        est = tables_estimate(sizes.scattering_shape, n_wavelengths, args.orders, device=device, what="export-lut")
        hint = "reduce --table-sizes, --orders or --wavelengths, or add --force"
    else:
        est = _render_estimate(args, n_wavelengths, integrator, device)
        hint = "reduce --size, --view-samples, the --integrator's samples, --wavelengths, --orders or --table-sizes, or add --force"
    check(est, force=bool(getattr(args, "force", False)), hint=hint, device=device)


def _export_lut_wavelengths(args) -> int:
    """How many wavelengths ``export-lut`` will tabulate (its --wavelengths, else the fit's)."""
    if args.wavelengths is not None:
        return len(parse_wavelengths(args.wavelengths))
    res = read_result(args.result)
    lam = (res.get("model") or {}).get("wavelengths_nm")
    return len(lam) if isinstance(lam, list) and lam else len(parse_wavelengths(DEFAULT_WAVELENGTHS))


def _before_work(parser: argparse.ArgumentParser, args) -> None:
    """Every check that needs no data: flag ranges, output paths, and the resource estimates that the
    flags alone determine (export-lut, envmap; render checks after ``--accuracy`` settles its flags)."""
    if getattr(args, "device", None) is not None and not getattr(args, "scheduler", None):
        _check_device(args.device)  # a flag alone decides it: before anything is read (a scheduler's workers resolve theirs)
    check_flags(parser, args)
    check_specs(args)
    check_outputs(args)
    if args.command == "export-lut":
        check_resources(args, _export_lut_wavelengths(args))
    elif args.command == "envmap":
        if args.wavelengths is not None or Path(args.source).suffix.lower() != ".json":
            n = len(parse_wavelengths(args.wavelengths or DEFAULT_WAVELENGTHS))
        else:
            n = len((read_result(args.source).get("model") or {}).get("wavelengths_nm") or [0] * 16)
        check_resources(args, n)


class _OneLineWarnings:
    """Library warnings as one stderr line each, ``skyfit: warning: ...`` (a DataWarning says what data
    was left out and why; docs/reliability.md), instead of Python's two-line form with the source line."""

    def __enter__(self):
        self._cm = warnings.catch_warnings()
        self._cm.__enter__()
        warnings.showwarning = self._show
        return self

    def __exit__(self, *exc):
        return self._cm.__exit__(*exc)

    @staticmethod
    def _show(message, category, filename, lineno, file=None, line=None):
        text = " ".join(str(message).split())
        kind = "" if issubclass(category, (DataWarning, UserWarning)) else f"{category.__name__}: "
        print(f"skyfit: warning: {kind}{text}", file=sys.stderr)


# -- entry point ---------------------------------------------------------------
class _Parser(argparse.ArgumentParser):
    """argparse with CONTRACT.md's error form: one line on stderr, exit status 2 (no usage block)."""

    def error(self, message: str):
        self.exit(EXIT_USAGE, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def _installed_version() -> str:
    """The installed distribution's version (importlib.metadata; pyproject reads it from ``__version__``),
    ``__version__`` when skyfit runs from a source tree that is not installed."""
    import importlib.metadata

    try:
        return importlib.metadata.version("skyfit")
    except importlib.metadata.PackageNotFoundError:
        return __version__


def build_parser() -> argparse.ArgumentParser:
    p = _Parser(prog="skyfit", description="Fit a physically based atmosphere to measured skies.")
    p.add_argument("--version", action="version", version=f"skyfit {_installed_version()}",
                   help="print skyfit's version (the installed distribution's) and exit")
    sub = p.add_subparsers(dest="command", required=True)

    r = sub.add_parser("render", help="render a fisheye sky to OpenEXR")
    r.add_argument("config", help="atmosphere config YAML (or a shipped name: earth, earth_clear_sky_eval, earth_hazy, mars)")
    r.add_argument("--out", required=True, help="output .exr file")
    r.add_argument("--size", type=int, default=256, help="image size in pixels (default 256)")
    r.add_argument("--projection", choices=PROJECTIONS, default="equidistant", help="fisheye model (docs/camera.md; default %(default)s)")
    r.add_argument("--kb-coeffs", metavar="K1,K2,K3,K4", help="kannala_brandt: r = f (t + k1 t^3 + k2 t^5 + k3 t^7 + k4 t^9)")
    r.add_argument("--focal", type=float, help="focal length, dr/dtheta at the centre [px/rad]")
    r.add_argument("--radius", type=float, help="radius of the 90 deg circle [px] (default size/2)")
    r.add_argument("--center", metavar="CX,CY", help="image position of the optical axis [px] (default the middle)")
    r.add_argument("--up-azimuth", type=float, default=0.0, help="azimuth of the image's up direction [deg] (default %(default)g)")
    r.add_argument("--tilt", metavar="DEG,DEG", help="optical axis's zenith angle and the azimuth it leans toward [deg]")
    r.add_argument("--max-zenith", type=float, help="field of view: largest angle from the optical axis [deg] (default 90)")
    _add_sun_flags(r)
    r.add_argument("--altitude", type=float, default=0.0, help="observer altitude above the ground [m] (default %(default)g)")
    # The defaults: within 1 % of the converged radiance above 5° elevation (docs/accuracy.md, "Render defaults").
    r.add_argument("--integrator", default=RENDER_DEFAULTS["integrator"],
                   help="NAME[:key=value,...], e.g. trapezoid:samples=64, taylor:a=0.45,b=0.45 (default %(default)s)")
    r.add_argument("--view-samples", type=int, default=RENDER_DEFAULTS["view_samples"],
                   help="samples of the outer (view-ray) integral (default %(default)s)")
    r.add_argument("--rule", choices=RULES, default=RENDER_DEFAULTS["rule"], help="outer quadrature rule (default %(default)s)")
    r.add_argument("--spacing", choices=SPACINGS, default=RENDER_DEFAULTS["spacing"],
                   help="single scattering: view-ray nodes uniform in distance, or geometric (dense where the "
                        "thinnest layer is; docs/accuracy.md) (default %(default)s)")
    r.add_argument("--orders", type=int, default=1, help="scattering orders (1 = single scattering; >= 2: Bruneton's precomputed tables; default %(default)s)")
    r.add_argument("--multiple", choices=("bruneton", "hillaire"), default="bruneton",
                   help="with --orders >= 2: Bruneton's full orders, or Hillaire 2020's cheaper approximation (default %(default)s)")
    r.add_argument("--table-sizes", help="R,MU,MUS,NU scattering-table sizes for --orders >= 2 (default 32,128,32,8; "
                   "MUS is unused: the tables' mu_s axis spans the sun's zenith angle +- 5 deg in texels 2 deg apart, "
                   "docs/multiple_scattering.md)")
    r.add_argument("--wavelengths", default=DEFAULT_WAVELENGTHS, help="START:STOP:STEP or comma list [nm] (default %(default)s)")
    r.add_argument("--spectral", action="store_true", help="also write one channel L<nm> per wavelength")
    r.add_argument("--preview", action="store_true", help="also write an 8-bit sRGB PNG of the fisheye beside --out "
                   "(same name, .png; auto-exposed)")
    r.add_argument("--sun-disk", action="store_true", help="add the attenuated solar disk")
    r.add_argument("--dtype", choices=("float32", "float64"), default="float32", help="working precision (default %(default)s)")
    r.add_argument("--accuracy", help="auto (= de=1), de=X (mean ΔE) or rel=X (relative radiance error): the cheapest "
                   "measured setting meeting it replaces --integrator/--view-samples/--rule (and with --orders >= 2 "
                   "--multiple/--table-sizes); docs/benchmarks.md, 'Automatic settings'")
    r.add_argument("--device", default="cpu", help="cpu, cuda, cuda:N or auto (CUDA when present); default cpu")
    r.add_argument("--json", action="store_true", help="print the summary as one line of JSON")
    r.set_defaults(func=cmd_render)

    d = sub.add_parser("demo", help="the main job on a known sky: render, add noise, fit, uncertainty, export LUTs, "
                                    "truth vs recovered +- sigma (skyfit/tools/demo.py)")
    d.add_argument("--out", default="demo_out", help="report folder (default demo_out)")
    d.add_argument("--quick", action="store_true", help="48x48, 6 wavelengths, Laplace only: within a minute on 2 CPU cores")
    d.add_argument("--threads", type=int, help="torch intra-op threads (default: torch's)")
    d.add_argument("--progress", action=argparse.BooleanOptionalAction, default=None, help="tqdm bars (default: on a terminal)")
    d.add_argument("--device", default="cpu", help="cpu, cuda, cuda:N or auto (CUDA when present); default cpu")
    d.add_argument("--json", action="store_true", help="print the summary as one line of JSON")
    d.set_defaults(func=cmd_demo)
    _add_fit_parsers(sub)
    _add_batch_parser(sub)
    _add_calibrate_camera_parser(sub)

    b = sub.add_parser("bench", help="speed/accuracy table of the transmittance integrators")
    b.add_argument("--out", default="bench_out", help="report folder (default %(default)s)")
    b.add_argument("--quick", action="store_true", help="a reduced table for CI")
    b.add_argument("--device", default="cpu", help="cpu, cuda, cuda:N or auto (CUDA when present); default cpu")
    b.add_argument("--threads", type=int, help="torch CPU threads (default: the bench's own choice, 2; trade study 1)")
    b.add_argument("--study", choices=("integrators", "trade", "all"), default="all",
                   help="integrators: Gałaj 2021 Table 3 (bench.md); trade: every renderer setting on fixed scenes "
                        "(trade.md, frontier.json for --accuracy); all: both (default %(default)s)")
    b.add_argument("--frontier-out", help="also write the trade study's frontier.json here (skyfit/data/auto_settings.json "
                                          "is the one --accuracy reads)")
    b.add_argument("--json", action="store_true", help="print the summary as one line of JSON")
    b.set_defaults(func=cmd_bench)

    c = sub.add_parser("calibrate-integrator", help="fit Taylor a, b; pick spline grid and view samples for an atmosphere")
    c.add_argument("config", help="atmosphere config YAML (or a shipped name: earth, mars, ...)")
    c.add_argument("--out", required=True, help="output .json file (docs/integrator_calibration.md)")
    c.add_argument("--tolerance", type=float, default=1e-3, help="relative single-scattering radiance tolerance (default 1e-3)")
    c.add_argument("--transmittance-tolerance", type=float, default=1e-3, help="spline transmittance tolerance (default 1e-3)")
    c.add_argument("--metric", choices=("transmittance", "column", "radiance"), default="transmittance", help="Taylor fit error metric (docs/integrator_calibration.md; default %(default)s)")
    c.add_argument("--d-spacing", choices=("view", "paper"), default="view", help="line distances of the (d, t) domain (default %(default)s)")
    c.add_argument("--view-rule", choices=RULES, default="trapezoid", help="outer quadrature rule of the view samples (default %(default)s)")
    c.add_argument("--spline-kind", choices=SPLINE_KINDS, default="natural_cubic", help="spline kind of the grid search (default %(default)s)")
    c.add_argument("--wavelengths", default=DEFAULT_WAVELENGTHS, help="START:STOP:STEP or comma list [nm] (default %(default)s)")
    c.add_argument("--quick", action="store_true", help="coarser domain, fewer rays and candidates (seconds, for CI)")
    c.add_argument("--device", default="cpu", help="cpu, cuda, cuda:N or auto (CUDA when present); default cpu")
    c.add_argument("--json", action="store_true", help="print the summary as one line of JSON")
    c.set_defaults(func=cmd_calibrate_integrator)

    e = sub.add_parser("export-lut", help="precompute a fitted atmosphere's tables and write them as LUTs (docs/luts.md)")
    e.add_argument("result", help="RESULT.json written by skyfit fit")
    e.add_argument("--out", required=True, help="output directory")
    e.add_argument("--format", choices=FORMATS, default="exr", help="exr (OpenEXR, float32) or npz (default %(default)s)")
    e.add_argument("--orders", type=int, default=4, help="scattering orders in the tables (default 4)")
    e.add_argument("--table-sizes", help="R,MU,MUS,NU scattering-table sizes (default 32,128,32,8)")
    e.add_argument("--wavelengths", help="START:STOP:STEP or comma list [nm] (default: the fit's model wavelengths)")
    e.add_argument("--rgb", action="store_true", help="linear sRGB channels instead of one per wavelength")
    e.add_argument("--layout", choices=("skyfit", "bruneton2017", "unreal"), default="skyfit",
                   help="skyfit: spectral tables with multiple scattering apart; bruneton2017: the RGB "
                        "textures, .dat files and GLSL an unmodified Bruneton 2017 shader samples; unreal: Unreal "
                        "SkyAtmosphere parameters and Hillaire 2020's LUTs (docs/luts.md; default %(default)s)")
    e.add_argument("--precision", choices=("f16", "f32"),
                   help="--layout bruneton2017: scattering textures in half or single floats (default f32)")
    e.add_argument("--sun-zenith", help="--layout unreal: sun zenith angle(s) of the sky-view LUTs, comma list [deg] "
                                        "(default 45)")
    e.add_argument("--device", default="cpu", help="cpu, cuda, cuda:N or auto (CUDA when present); default cpu")
    e.add_argument("--json", action="store_true", help="print the summary as one line of JSON")
    e.set_defaults(func=cmd_export_lut)
    _add_envmap_parser(sub)
    for name in FORCE_COMMANDS:
        sub.choices[name].add_argument("--force", action="store_true", help="run even when the memory or time estimate "
                                       "says the job does not fit this machine (docs/reliability.md)")
    return p


def _os_error(e: OSError) -> str:
    """An OSError as one line naming the file: ``FILE: reason`` (not a bare errno)."""
    reason = e.strerror or str(e) or type(e).__name__
    return f"{e.filename}: {reason}" if e.filename else reason


_NEGATIVE_LIST = re.compile(r"^-\d[^,\s]*(,[^,\s]*)+$")


def _join_negative_lists(argv: list[str]) -> list[str]:
    """``--location -33.9,151.2`` as ``--location=-33.9,151.2``: argparse takes a value that starts with '-' and is
    not a plain number for an option, so a southern or western place would be refused. Only a comma list that starts
    with a negative number, right after a long option, is joined (its items are checked by the option's own parser,
    so ``-33.9,abc`` gets the location's message, not argparse's "expected one argument"; written by hand: argparse
    has no switch for it)."""
    out: list[str] = []
    for tok in argv:
        if out and out[-1].startswith("--") and "=" not in out[-1] and _NEGATIVE_LIST.match(tok):
            out[-1] = f"{out[-1]}={tok}"
        else:
            out.append(tok)
    return out


def main(argv: list[str] | None = None) -> int:
    """The command line: one line and exit status 2 for any bad input, 130 on Ctrl-C (docs/reliability.md)."""
    try:
        parser = build_parser()
        args = parser.parse_args(_join_negative_lists(list(sys.argv[1:] if argv is None else argv)))
        with _OneLineWarnings():
            _before_work(parser, args)
            return int(args.func(args) or 0)
    except (UserError, ConfigError, ExrError) as e:
        print(f"skyfit: error: {e}", file=sys.stderr)
        return EXIT_USAGE
    except ValueError as e:  # parameter validation inside the library
        print(f"skyfit: error: {e}", file=sys.stderr)
        return EXIT_USAGE
    except OSError as e:  # an unreadable input, a full disk: one line naming the file
        print(f"skyfit: error: {_os_error(e)}", file=sys.stderr)
        return EXIT_USAGE
    except MemoryError:  # a size the estimates let through (or --force): one line, not a traceback
        print("skyfit: error: out of memory; reduce the sizes (docs/reliability.md)", file=sys.stderr)
        return EXIT_USAGE
    except RuntimeError as e:
        if "allocate" not in str(e) and "out of memory" not in str(e):
            raise
        print(f"skyfit: error: out of memory ({str(e).splitlines()[0][:200]}); reduce the sizes (docs/reliability.md)",
              file=sys.stderr)
        return EXIT_USAGE
    except KeyboardInterrupt:
        print("skyfit: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
