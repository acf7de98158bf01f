"""Many skies: one fit per item on a Dask cluster, resumable, with a results table and a time series.

``skyfit.batch(items, config, out=...)`` (and ``skyfit batch DATA... --config C --out DIR``; CONTRACT.md,
"Many skies"; docs/batch.md) expands ``items`` (.exr files, Kider capture folders, photos,
photo brackets, folders of any of these, globs) into one fit per item and runs each in a Dask worker with
the call ``skyfit fit`` makes (:func:`skyfit.fit.run.run_fit`; for a photo
:func:`skyfit.fit.photo.run_photo_fit`, its time from EXIF or a times file; one torch thread per task), so
that a batch's numbers are those of ``skyfit fit`` run one by one. The client writes, atomically, as each item finishes:

- ``DIR/<item>/RESULT.json``: what ``skyfit fit --no-plots`` writes, plus a ``batch`` entry (item,
  wall and CPU seconds, worker);
- at the end ``DIR/results.parquet`` and ``DIR/results.csv`` (one row per item, :func:`result_row`),
  ``DIR/timeseries.png`` (:func:`plot_timeseries`).

A failing item is recorded with its one-line error and the batch goes on; a worker that dies
mid-item has the item rescheduled by Dask up to ``retries`` times, then it is recorded as failed
(``KilledWorker``). ``resume=True`` skips every item with a complete RESULT.json of that item.

``smooth=SIGMA`` adds a smoothing pass over the finished items (:func:`smooth_series`): the per-item
posteriors of log AOD 550, Ångström alpha and g, as Gaussians (the Laplace approximation), joined by a
Gaussian random walk of SIGMA per square-root hour, with Student-t weights for outliers.

dask.distributed, pandas and matplotlib are imported inside the functions that use them: about a
second of imports that ``import skyfit`` and the other commands need not pay.
"""
from __future__ import annotations

import csv
import dataclasses
import datetime as _dt
import glob
import hashlib
import json
import math
import os
import socket
import tempfile
import time
from pathlib import Path
from typing import Callable, Sequence
from urllib.parse import urlparse

import numpy as np
import torch

from .api import resolve_device
from .atmosphere import read_config
from .camera.sun import parse_location, parse_time
from .fit.losses import make_loss
from .fit.parameters import PARAMETERS
from .fit.problem import fit_settings, make_model
from .fit.report import dumps, save_fig
from .fit.results import check_result, save_result
from .fit.run import run_fit
from .io.atomic import atomic_path, check_writable, write_text_atomic
from .io.kider import is_kider_capture_name
from .io.photo import EXIF_OFFSET as _OFFSET
from .io.photo import (EXR_EXTENSIONS, HDR_EXTENSIONS, PHOTO_EXTENSIONS, exif_location, exif_stamps, exif_time,
                       is_photo_path)

RESULT_NAME = "RESULT.json"
TABLE_NAMES = ("results.parquet", "results.csv")
TIMESERIES_NAME = "timeseries.png"
SERIES = ("mie_aod_550", "mie_angstrom_alpha", "mie_g", "rayleigh_scale")
"""The time series' quantities (timeseries.png, the summary): aerosol optical depth at 550 nm, Ångström
alpha, the Mie phase's g and the Rayleigh scale factor (docs/fitting.md)."""
PHOTO_KINDS = ("photo", "bracket")
"""Item kinds fitted by the photo fit (:func:`skyfit.fit.photo.run_photo_fit`)."""
BRACKET_MARKER = ".bracket"
"""A (hidden, possibly empty) file of this name in a folder of image frames makes the folder one bracket."""
BRACKET_SPAN_S = 10.0
"""A folder of >= 2 image frames whose EXIF DateTimeOriginal all lie within this span is one bracket;
otherwise each frame is a photo of its own. [s] (An auto-bracket takes well under a second to a few
seconds; a sky time series is minutes apart.)"""
PHOTO_WARM_START = ("mie_aod_550", "mie_angstrom_alpha", "mie_g", "mie_beta_550", "rayleigh_scale")
"""The fitted values a photo passes on with ``warm_start="previous"``: the atmosphere's, not the camera's
nuisances (the exposure is profiled anyway, the heading is relative to each photo's own calibration)."""
SMOOTH_SERIES = (("aod_550", "mie_aod_550", True), ("angstrom_alpha", "mie_angstrom_alpha", False),
                 ("g", "mie_g", False))
"""(short name, table column, smoothed in log) of the smoothing pass: AOD 550 in log (a random walk of
relative changes; it stays positive), alpha and g as they are."""
STUDENT_NU = 4.0
"""Degrees of freedom of the smoothing's Student-t item weights (small: heavy tails, outliers down-weighted)."""
MIN_STEP_S = 1.0
"""Items closer in time than this are one second apart for the random walk (two photos of one instant). [s]"""
DEFAULT_RETRIES = 2
"""Reschedules of an item whose worker died (Dask's ``distributed.scheduler.allowed-failures``) before it is
recorded as failed."""


class BatchError(ValueError):
    """A batch that cannot start: no items, an unwritable output folder, an unreachable scheduler."""


@dataclasses.dataclass(frozen=True)
class BatchItem:
    """One fit of a batch.

    Attributes:
        key: the item's folder name under the output folder (the capture, bracket or file name; unique in the batch).
        path: the absolute path of the capture folder, bracket folder or file.
        kind: ``kider``, ``exr`` (an EXR with skyfit's metadata), ``photo`` (one image file) or ``bracket``
            (a folder of one scene's exposures).
    """

    key: str
    path: str
    kind: str


# -- items ------------------------------------------------------------------------------------------
def _is_glob(text: str) -> bool:
    return any(c in text for c in "*?[")


def _entries(folder: Path) -> list[Path]:
    return sorted(q for q in folder.iterdir() if not q.name.startswith("."))


def _file_kind(p: Path) -> str:
    """``photo`` for an image/RAW/.hdr file or an EXR without skyfit's metadata; ``exr`` otherwise (its fit
    reports what the file is)."""
    ext = p.suffix.lower()
    if ext in EXR_EXTENSIONS:
        return "photo" if is_photo_path(p) else "exr"
    return "photo" if ext in PHOTO_EXTENSIONS else "exr"


def photo_folder_items(folder: str | Path) -> list[tuple[str, Path]]:
    """A folder holding only image frames: ``[("bracket", folder)]`` or ``[("photo", file), ...]``.

    The rule (docs/batch.md): the folder is one bracket when it holds a file named :data:`BRACKET_MARKER`
    (hidden files are not frames), or when it holds >= 2 frames, none of them .hdr/.exr, whose EXIF
    DateTimeOriginal all exist and lie within :data:`BRACKET_SPAN_S`; otherwise every file is a photo.
    """
    folder = Path(folder)
    files = [q for q in _entries(folder) if q.is_file()]
    if (folder / BRACKET_MARKER).exists():
        return [("bracket", folder)]
    linear = any(q.suffix.lower() in HDR_EXTENSIONS + EXR_EXTENSIONS for q in files)
    if len(files) >= 2 and not linear:
        times = [exif_time(q)[0] for q in files]
        if all(t is not None for t in times) and (max(times) - min(times)).total_seconds() <= BRACKET_SPAN_S:
            return [("bracket", folder)]
    return [("photo", q) for q in files]


def _expand(p: Path) -> list[tuple[str, Path]]:
    """(kind, path) of one DATA path: a file, a Kider capture, a bracket, or a folder of any of these."""
    if p.is_file():
        return [(_file_kind(p), p)]
    if not p.is_dir():
        raise BatchError(f"data not found: {p}")
    if is_kider_capture_name(p.name):
        return [("kider", p)]
    if is_photo_path(p):  # only image frames: one bracket, or one photo per frame
        return photo_folder_items(p)
    caps, exrs, photos = [], [], []
    for q in _entries(p):
        if q.is_dir() and is_kider_capture_name(q.name):
            caps.append(("kider", q))
        elif q.is_dir() and is_photo_path(q):
            photos += photo_folder_items(q)
        elif q.is_file() and (q.suffix.lower() in PHOTO_EXTENSIONS or q.suffix.lower() == ".exr"):
            (exrs if _file_kind(q) == "exr" else photos).append((_file_kind(q), q))
    if not (caps or exrs or photos):
        raise BatchError(f"{p}: a folder with no Kider captures (YYYY-MM-DD___HH.MM.SS), .exr files or photos")
    return caps + exrs + photos


def batch_items(items: str | Path | Sequence[str | Path]) -> list[BatchItem]:
    """The fits of ``items``: .exr files, Kider capture folders, photos, bracket folders, folders of any of
    these, or globs.

    Each Kider capture, bracket and file is one item, in the order given (a glob's and a folder's matches
    sorted by name: a folder's Kider captures, then its .exr files with skyfit's metadata, then its photos),
    duplicates dropped. A folder of image frames is one bracket or one photo per frame
    (:func:`photo_folder_items`); a folder's subfolders of image frames likewise. The key is the folder or
    file name (its stem for files), with a short hash of the path where two items share a name.
    BatchError when a glob matches nothing, a path does not exist or nothing remains.
    """
    if isinstance(items, (str, Path)):
        items = [items]
    paths: list[str] = []
    for it in items:
        text = os.path.expanduser(str(it))
        if _is_glob(text):
            found = sorted(glob.glob(text, recursive=True))
            if not found:
                raise BatchError(f"no items match {it}")
            paths += found
        else:
            paths.append(text)
    if not paths:
        raise BatchError("no items given")
    seen: dict[str, str] = {}
    for p in paths:
        for kind, q in _expand(Path(p)):
            seen.setdefault(str(q.absolute()), kind)
    names = {path: (Path(path).name if kind in ("kider", "bracket") else Path(path).stem) for path, kind in seen.items()}
    counts: dict[str, int] = {}
    for n in names.values():
        counts[n] = counts.get(n, 0) + 1
    out = []
    for path, kind in seen.items():
        key = names[path]
        if counts[key] > 1:
            key = f"{key}-{hashlib.sha1(path.encode()).hexdigest()[:8]}"
        out.append(BatchItem(key, path, kind))
    return out


# -- a photo's time ---------------------------------------------------------------------------------------
def check_photo_timezone(zone: str | None) -> str | None:
    """``zone`` when it is a UTC offset (``+02:00``, ``-0400``, ``Z``, hours as ``-4`` or ``5.5``) or an IANA
    time zone name (``Europe/Berlin``); BatchError otherwise."""
    if zone is None:
        return None
    try:
        local_time("2000-01-01T12:00:00", zone)
    except ValueError as e:
        raise BatchError(f"--photo-timezone {zone}: {str(e).splitlines()[0]}") from None
    return zone


def local_time(text: str, zone: str) -> _dt.datetime:
    """A naive ISO 8601 local time in ``zone`` (see :func:`check_photo_timezone`) as an aware datetime
    (a zone name's offset is the one in force then, daylight saving included). ValueError when it does not parse."""
    z = zone.strip()
    try:
        hours = float(z)
    except ValueError:
        hours = None
    if hours is not None:
        return parse_time(text, utc_offset_hours=hours)
    if z in ("Z", "z") or _OFFSET.match(z):
        m = _OFFSET.match(z)
        return parse_time(text + ("+00:00" if m is None else f"{m.group(1)}{m.group(2)}:{m.group(3)}"))
    return parse_time(f"{text} {z}")


def read_times(path: str | Path) -> dict[str, str]:
    """A times file: CSV rows ``file,time`` (a header row ``file,time`` and ``#`` comments allowed) ->
    {absolute path (relative paths are relative to the CSV's folder): time text}. The time is ISO 8601,
    with a UTC offset or zone name, or naive (local time in ``photo_timezone``). BatchError naming the file
    and line for an unreadable file or a malformed row."""
    p = Path(path).expanduser()
    try:
        text = p.read_text()
    except (OSError, UnicodeDecodeError) as e:
        raise BatchError(f"--times {p}: cannot read it ({getattr(e, 'strerror', None) or e})") from None
    out: dict[str, str] = {}
    for n, row in enumerate(csv.reader(text.splitlines()), 1):
        cells = [c.strip() for c in row]
        if not cells or not any(cells) or cells[0].startswith("#"):
            continue
        if len(cells) != 2 or not cells[0] or not cells[1]:
            raise BatchError(f"--times {p} line {n}: expected 'file,time', got {','.join(row)!r}")
        if n == 1 and cells[1].lower() == "time":
            continue
        body = cells[1].split(" ")[0].split("[")[0]
        try:
            _dt.datetime.fromisoformat(body)
        except ValueError:
            raise BatchError(f"--times {p} line {n}: cannot parse time {cells[1]!r} (ISO 8601, e.g. "
                             "2024-06-01T14:05:00+02:00)") from None
        out[str((p.parent / cells[0]).absolute())] = cells[1]
    return out


def photo_time(item: BatchItem, times: dict[str, str] | None = None, zone: str | None = None) -> tuple[str, str]:
    """(ISO 8601 time with its UTC offset, source) of a photo or bracket item.

    In order: the item's row of ``times`` (:func:`read_times`; matched by path, else by file or folder name;
    source ``times``); else EXIF DateTimeOriginal (a bracket's earliest frame) with OffsetTimeOriginal
    (``exif``) or, without it, in ``zone`` (``exif+zone``). A naive time of ``times`` is also taken in
    ``zone``. ValueError, one line naming the item: no time, or no UTC offset and no ``zone``.
    """
    label = f"photo {item.path}"
    row = None
    if times:
        row = times.get(item.path)
        if row is None:
            by_name = [v for k, v in times.items() if Path(k).name == Path(item.path).name]
            row = by_name[0] if len(by_name) == 1 else None
    try:
        if row is not None:
            try:
                return parse_time(row).isoformat(), "times"
            except ValueError:
                if zone is None:
                    raise ValueError(f"{label}: its time {row!r} in --times has no UTC offset; give one, or "
                                     "--photo-timezone") from None
                return local_time(row, zone).isoformat(), "times"
        stamps = exif_stamps(item.path)
        if not stamps:
            raise ValueError(f"{label}: no time: no EXIF DateTimeOriginal, and no row in --times")
        when, offset = min(stamps, key=lambda s: s[0])
        iso = when.isoformat()
        if offset is not None:
            return parse_time(iso + offset).isoformat(), "exif"
        if zone is None:
            raise ValueError(f"{label}: EXIF DateTimeOriginal {iso} has no UTC offset (no OffsetTimeOriginal); "
                             "give --photo-timezone (e.g. +02:00 or Europe/Berlin) or --times")
        return local_time(iso, zone).isoformat(), "exif+zone"
    except ValueError as e:
        msg = str(e).splitlines()[0]
        raise ValueError(msg if msg.startswith(label) else f"{label}: {msg}") from None


def check_out_dir(out: str | Path) -> Path:
    """``out`` as a Path when it is, or can be made, a writable folder; OutputError (a ValueError) otherwise.
    Creates nothing (:func:`skyfit.io.atomic.check_writable`)."""
    return check_writable(Path(out).expanduser(), directory=True)


def result_path(out: str | Path, item: BatchItem) -> Path:
    """Where an item's RESULT.json goes: ``out/<key>/RESULT.json``."""
    return Path(out) / item.key / RESULT_NAME


def finished_result(out: str | Path, item: BatchItem) -> dict | None:
    """The item's RESULT.json when it is complete (a readable fit result written by a batch for this item); else None."""
    p = result_path(out, item)
    try:
        res = check_result(json.loads(p.read_text()), str(p))
    except (OSError, UnicodeDecodeError, ValueError):
        return None
    if (res.get("batch") or {}).get("item") != item.path or not isinstance(res.get("metrics"), dict):
        return None
    return res


# -- the task -----------------------------------------------------------------------------------------
def one_line(e: BaseException) -> str:
    """An exception as the one line a table cell and a terminal show (its type unless it is a ValueError)."""
    text = (str(e).strip().splitlines() or [""])[0]
    return text if isinstance(e, ValueError) and text else f"{type(e).__name__}: {text}".rstrip(": ")


def _worker_name() -> str:
    try:
        from distributed import get_worker  # present: this runs inside a Dask worker

        w = get_worker()
        return str(w.name if w.name is not None else w.address)
    except (ImportError, ValueError):
        return f"pid {os.getpid()}"


def warm_start_values(previous: dict | None, names: Sequence[str] | None = None) -> dict:
    """The free parameters' fitted values of ``previous`` (a RESULT dict), one value each: a fit's ``fit.initial``
    (only those in ``names`` when given)."""
    if not previous:
        return {}
    return {n: _scalar(previous["parameters"][n]) for n in previous.get("free", [])
            if n in previous["parameters"] and (names is None or n in names)}


def fit_item(path: str, config: dict, overrides: dict, config_source: str = "", kider_site: dict | None = None,
             laplace: bool = False, threads: int = 1, previous: dict | None = None, device: str = "cpu",
             force: bool = False, photo: dict | None = None) -> dict:
    """One item's fit as ``skyfit fit PATH --no-plots`` makes it (:func:`skyfit.fit.run.run_fit`): the task of a batch.

    Never raises for a failed fit: returns ``{"result": RESULT dict or None, "status": "ok" or the one-line
    error, "wall_s", "cpu_s", "worker", "pid", "carry", "warm_from"}``. ``cpu_s`` is the task thread's CPU
    time (torch runs on that thread when ``threads`` is 1). Sets torch's intra-op threads of the worker
    process to ``threads``.

    ``device`` and ``force`` are ``skyfit fit``'s (``device`` is resolved on the worker: ``auto`` takes
    its CUDA device when it has one).

    ``previous`` (warm start): the task's return of the previous item, or ``{"result": RESULT dict}``; the
    fit then starts from its fitted values (its ``carry``: the last item of the chain that was fitted),
    added to ``fit.initial`` (so that RESULT.json's settings say where it started).

    ``photo``: the item is a photo or bracket, fitted as ``skyfit fit PHOTO --no-plots`` does
    (:func:`skyfit.fit.photo.run_photo_fit`, Laplace sigmas always) with the keys ``time`` (ISO 8601 with
    offset), ``location`` ("LAT,LON[,ELEV]"), and optionally ``camera``, ``mask``, ``linear``, ``response``;
    a warm start then passes on only the atmosphere's values (:data:`PHOTO_WARM_START`).
    """
    if torch.get_num_threads() != threads:
        torch.set_num_threads(threads)
    w0, c0 = time.perf_counter(), time.thread_time()
    start = (previous or {}).get("result") or (previous or {}).get("carry")
    if start:
        initial = {**((config.get("fit") or {}).get("initial") or {}), **(overrides.get("initial") or {}),
                   **warm_start_values(start, PHOTO_WARM_START if photo is not None else None)}
        overrides = {**overrides, "initial": initial}
    result, status = None, "ok"
    try:
        with tempfile.TemporaryDirectory(prefix="skyfit-batch-") as tmp:  # run_fit writes; the client keeps the copy
            if photo is not None:
                from .fit.photo import run_photo_fit  # only photo items need the photo fit's imports

                result = run_photo_fit(path, config, Path(tmp) / RESULT_NAME, time=photo["time"],
                                       location=photo["location"], camera=photo.get("camera"), mask=photo.get("mask"),
                                       linear=bool(photo.get("linear")), response=photo.get("response"),
                                       overrides=overrides, plots=False, progress=False, laplace=True,
                                       device=resolve_device(device))
            else:
                result = run_fit([path], config, Path(tmp) / RESULT_NAME, overrides=overrides,
                                 config_source=config_source, kider_site=kider_site, plots=False, progress=False,
                                 laplace=laplace, device=resolve_device(device), force=force)
        result = json.loads(dumps(result))  # plain JSON values, as RESULT.json holds them
    except Exception as e:  # noqa: BLE001  (any failure of one item is recorded, never stops the batch)
        result, status = None, one_line(e)
    out = {"result": result, "status": status, "wall_s": time.perf_counter() - w0, "cpu_s": time.thread_time() - c0,
           "worker": _worker_name(), "pid": os.getpid()}
    if previous is not None:
        out["carry"] = result or start
        out["warm_from"] = ((start or {}).get("data") or [{}])[0].get("source")
    return out


# -- rows and the table ---------------------------------------------------------------------------------
def _scalar(v):
    if isinstance(v, list):
        return v[0] if len(v) == 1 else float(np.mean(v))
    return v


def result_row(item: BatchItem, result: dict | None, info: dict) -> dict:
    """One row of results.parquet: item, kind, time, location, sun, every parameter (``sigma_<name>`` with
    Laplace; with the total sigma also ``corrected_<name>`` and ``sigma_corrected_<name>``, RESULT.json's
    ``laplace.corrected``), metrics, convergence, wall/CPU seconds, worker, status (``ok`` or the one-line error).

    A photo's row adds ``time_source`` (``exif``, ``exif+zone`` or ``times``: :func:`photo_time`),
    ``rmse_rel`` (relative RMS over the pixels used), the fitted camera (``camera_projection``, heading
    ``camera_up_azimuth_deg``, ``camera_tilt_east_deg``/``_north_deg``), ``sun_separation_deg`` (computed
    vs detected sun) and ``pixels_used``; its aerosol is in ``mie_aod_550``, ``mie_angstrom_alpha``,
    ``mie_g`` (RESULT.json's ``aerosol``) with ``sigma_`` columns (its ``sigma``: the budget's and the photo path's
    validation term, :func:`skyfit.fit.photo.aerosol_summary`)."""
    row: dict = {"item": item.key, "path": item.path, "kind": item.kind, "status": info.get("status", "ok"), "time": None,
                 "latitude_deg": None, "longitude_deg": None, "elevation_m": None,
                 "sun_zenith_deg": None, "sun_azimuth_deg": None}
    for n in PARAMETERS:
        row[n] = None
    for n in PARAMETERS:
        row[f"sigma_{n}"] = None
    row.update({"rmse": None, "rmse_units": None, "delta_e": None, "loss": None, "n_samples": None,
                "converged": None, "iterations": None, "free": None})
    if result is not None:
        d = (result.get("data") or [{}])[0]
        loc = d.get("location") or {}
        sz, sa = d.get("sun_zenith_deg"), d.get("sun_azimuth_deg")
        row.update(time=d.get("time"), latitude_deg=loc.get("latitude_deg"), longitude_deg=loc.get("longitude_deg"),
                   elevation_m=loc.get("elevation_m"), sun_zenith_deg=sz.get("mean") if isinstance(sz, dict) else sz,
                   sun_azimuth_deg=sa.get("mean") if isinstance(sa, dict) else sa)
        for n, v in result["parameters"].items():
            row[n] = _scalar(v)
        lap = result.get("laplace") or {}
        for n, s in (lap.get("sigma") or {}).items():
            row[f"sigma_{n}"] = _scalar(s)
        for n, v in (lap.get("derived") or {}).items():
            if isinstance(v, dict) and f"sigma_{n}" in row and row[f"sigma_{n}"] is None:
                row[f"sigma_{n}"] = v.get("sigma")
        cor = lap.get("corrected") or {}  # the estimate corrected for the fit's renderer (docs/uncertainty.md)
        for n, v in (cor.get("values") or {}).items():
            row[f"corrected_{n}"], row[f"sigma_corrected_{n}"] = _scalar(v), _scalar((cor.get("sigma") or {}).get(n))
        for n, v in (cor.get("derived") or {}).items():
            if isinstance(v, dict) and f"corrected_{n}" not in row:
                row[f"corrected_{n}"], row[f"sigma_corrected_{n}"] = v.get("value"), v.get("sigma")
        m, c = result.get("metrics") or {}, result.get("convergence") or {}
        row.update(rmse=m.get("rmse"), rmse_units=m.get("rmse_units"), delta_e=m.get("delta_e"), loss=m.get("loss"),
                   n_samples=m.get("n_samples"), converged=c.get("converged"), iterations=c.get("iterations"),
                   free=",".join(result.get("free", [])))
    if item.kind in PHOTO_KINDS:
        row.update(time_source=info.get("time_source"), rmse_rel=None, camera_projection=None, camera_up_azimuth_deg=None,
                   camera_tilt_east_deg=None, camera_tilt_north_deg=None, sun_separation_deg=None, pixels_used=None)
        if result is not None:
            cam, tilt = result.get("camera") or {}, (result.get("camera") or {}).get("tilt_deg") or [None, None]
            row.update(rmse_rel=(result.get("metrics") or {}).get("rmse_rel"), camera_projection=cam.get("projection"),
                       camera_up_azimuth_deg=cam.get("up_azimuth_deg"), camera_tilt_east_deg=tilt[0],
                       camera_tilt_north_deg=tilt[1], sun_separation_deg=(result.get("sun") or {}).get("separation_deg"),
                       pixels_used=(result.get("pixels") or {}).get("used"))
            aer = result.get("aerosol") or {}
            for n, k in (("mie_aod_550", "aod_550"), ("mie_angstrom_alpha", "angstrom_alpha"), ("mie_g", "g")):
                if k in (aer.get("sigma") or {}):  # the photo's total: the budget's and the validation term
                    row[f"sigma_{n}"] = aer["sigma"][k]
            if row["time"] is None:
                row["time"] = result.get("time")
    row.update(wall_s=info.get("wall_s"), cpu_s=info.get("cpu_s"), worker=info.get("worker"),
               result=str(Path(item.key) / RESULT_NAME) if result is not None else None)
    return row


def laplace_correlation(result: dict | None) -> dict:
    """{(name_a, name_b): correlation} of a RESULT's Laplace covariance (empty without one, or when its
    Hessian was not positive definite): the smoothing's per-item covariance (:func:`smooth_table`)."""
    lap = (result or {}).get("laplace") or {}
    names, corr = lap.get("names"), lap.get("correlation")
    if not names or corr is None or lap.get("positive_definite") is False:
        return {}
    return {(a, b): float(corr[i][j]) for i, a in enumerate(names) for j, b in enumerate(names)}


def results_table(rows: Sequence[dict]):
    """The rows as a pandas DataFrame (item order; sigma columns no item has are dropped)."""
    import pandas as pd  # ~0.3 s of import, only for a batch

    df = pd.DataFrame(list(rows))
    if len(df):
        df = df.drop(columns=[c for c in df.columns if c.startswith("sigma_") and df[c].isna().all()])
    for c in ("wall_s", "cpu_s", "rmse", "delta_e", "loss", "rmse_rel", "camera_up_azimuth_deg", "camera_tilt_east_deg",
              "camera_tilt_north_deg", "sun_separation_deg", *PARAMETERS):
        if c in df:
            df[c] = pd.to_numeric(df[c], errors="coerce")
    return df


def write_tables(df, out: Path) -> list[Path]:
    """results.parquet and results.csv in ``out``, each written atomically."""
    paths = []
    with atomic_path(out / TABLE_NAMES[0], ".tmp.parquet") as tmp:
        df.to_parquet(tmp, index=False)
    paths.append(out / TABLE_NAMES[0])
    write_text_atomic(out / TABLE_NAMES[1], df.to_csv(index=False))
    paths.append(out / TABLE_NAMES[1])
    return paths


# -- smoothing --------------------------------------------------------------------------------------------
@dataclasses.dataclass
class Smoothed:
    """The smoothing pass's outcome (:func:`smooth_series`).

    Attributes:
        mean: posterior mean of each item's state, shape (T, K) (NaN where undetermined).
        sd: its posterior standard deviation, shape (T, K).
        weight: each item's Student-t weight, shape (T,): about 1 for an item as far from the curve as its
            covariance says, towards 0 for an outlier; NaN for an item without a measurement.
        scale: the common factor (>= 1) on every item's covariance estimated from the residuals.
        iterations: EM iterations run.
    """

    mean: np.ndarray
    sd: np.ndarray
    weight: np.ndarray
    scale: float
    iterations: int


def _block_tridiagonal_solve(A: np.ndarray, B: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Solve H x = b for a symmetric positive definite block-tridiagonal H, and H^-1's diagonal blocks.

    Args:
        A: the diagonal blocks H[t, t], shape (T, K, K).
        B: the blocks above the diagonal H[t, t+1], shape (T-1, K, K).
        b: shape (T, K).

    Returns:
        x (T, K) and the diagonal blocks of H^-1 (T, K, K): a block LDL^T sweep forward, back substitution
        and the selected-inverse recursion S_t = D_t^-1 + D_t^-1 B_t S_{t+1} B_t^T D_t^-1 (the RTS smoother
        in information form).
    """
    T, K = b.shape
    Dinv = np.empty_like(A)
    z = np.empty_like(b)
    Dinv[0] = np.linalg.inv(A[0])
    z[0] = b[0]
    for t in range(1, T):
        Bt = B[t - 1]
        D = A[t] - Bt.T @ Dinv[t - 1] @ Bt
        Dinv[t] = np.linalg.inv(0.5 * (D + D.T))
        z[t] = b[t] - Bt.T @ (Dinv[t - 1] @ z[t - 1])
    x = np.empty_like(b)
    S = np.empty_like(A)
    x[-1] = Dinv[-1] @ z[-1]
    S[-1] = Dinv[-1]
    for t in range(T - 2, -1, -1):
        G = Dinv[t] @ B[t]
        x[t] = Dinv[t] @ z[t] - G @ x[t + 1]
        S[t] = Dinv[t] + G @ S[t + 1] @ G.T
    return x, S


def smooth_series(t_s, y, cov, sigma_rw, *, nu: float | None = STUDENT_NU, max_iter: int = 200,
                  tol: float = 1e-10) -> Smoothed:
    """Join per-item Gaussian posteriors by a random walk: the smoothing pass of a batch (docs/batch.md).

    The model (the Laplace approximation of each item's fit, and a prior on how fast the state moves)::

        y_t ~ N(x_t, s^2 R_t / w_t)                    each item's fitted values and Laplace covariance
        x_t - x_{t-1} ~ N(0, diag(sigma_rw^2) dt_h)    a random walk, dt_h = hours between the items
        w_t ~ Gamma(nu/2, nu/2)                        Student-t noise with nu degrees of freedom

    solved by EM: for given weights the posterior of all x is Gaussian with a block-tridiagonal precision
    (solved exactly, :func:`_block_tridiagonal_solve`), then w_t = (nu + K) / (nu + d_t / s^2) with
    d_t = (y_t - m_t)^T R_t^-1 (y_t - m_t) + tr(R_t^-1 S_t), and s^2 = max(1, sum w_t d_t / (K n)): the
    Laplace covariances are taken as a lower bound, scaled up when the items scatter more than they say.
    There is no prior on x_1 itself (a flat one): the result does not depend on where the walk starts.

    Args:
        t_s: item times, shape (T,), any order (the walk runs in time order). [s]
        y: fitted values, shape (T, K); a row with a NaN is an item without a measurement (failed), whose
            state is interpolated by the walk.
        cov: each item's covariance of y, shape (T, K, K), positive definite where y is finite.
        sigma_rw: the walk's standard deviation per square-root hour, shape (K,) or scalar, > 0; ``inf``: no
            smoothing (each item its own value). [unit of y / sqrt(h)]
        nu: Student-t degrees of freedom; None: Gaussian (every weight 1, scale 1: the exact joint Gaussian).
        max_iter, tol: EM iterations and the convergence tolerance on the weights and scale.

    Returns:
        :class:`Smoothed`, in the order of the input rows.

    Raises:
        ValueError: shapes that disagree, a sigma_rw <= 0 or NaN, non-finite times, no measured item.
    """
    t_s = np.asarray(t_s, dtype=float)
    y = np.asarray(y, dtype=float)
    cov = np.asarray(cov, dtype=float)
    T, K = y.shape
    if t_s.shape != (T,) or cov.shape != (T, K, K):
        raise ValueError(f"smooth_series: times {t_s.shape}, values {y.shape} and covariances {cov.shape} disagree")
    sig = np.broadcast_to(np.asarray(sigma_rw, dtype=float), (K,)).copy()
    if not (sig > 0).all():  # NaN fails too
        raise ValueError(f"smooth_series: the random walk's sigma must be > 0 (inf: no smoothing), got {sig.tolist()}")
    if not np.isfinite(t_s).all():
        raise ValueError("smooth_series: every item needs a finite time")
    meas = np.isfinite(y).all(1)
    if not meas.any():
        raise ValueError("smooth_series: no item with a measurement")
    order = np.argsort(t_s, kind="stable")
    t, yy, R, m = t_s[order], y[order], cov[order], meas[order]
    Rinv = np.zeros_like(R)
    Rinv[m] = np.linalg.inv(R[m])
    yz = np.where(m[:, None], yy, 0.0)
    dt_h = np.maximum(np.diff(t), MIN_STEP_S) / 3600.0
    lam = 1.0 / (sig[None, :] ** 2 * dt_h[:, None])  # (T-1, K) the walk's precision per step; 0 for sigma inf
    typical = np.median(np.diagonal(R[m], axis1=1, axis2=2), axis=0)
    vague = 1e-12 / np.maximum(typical, 1e-300)  # a flat prior in effect (keeps H invertible where nothing ties a state)
    centre = np.array([np.median(yy[m, k]) for k in range(K)])
    B = np.zeros((T - 1, K, K))
    B[:, range(K), range(K)] = -lam
    walk = np.zeros((T, K))
    walk[1:] += lam
    walk[:-1] += lam
    w = np.where(m, 1.0, 0.0)
    s2 = 1.0
    it = 0
    for it in range(1, max_iter + 1):
        P = Rinv * (w / s2)[:, None, None]
        A = P.copy()
        A[:, range(K), range(K)] += walk + vague
        x, S = _block_tridiagonal_solve(A, B, np.einsum("tij,tj->ti", P, yz) + vague * centre)
        r = yz - x
        d = np.einsum("ti,tij,tj->t", r, Rinv, r) + np.einsum("tij,tji->t", Rinv, S)
        if nu is None:
            break
        w_new = np.where(m, (nu + K) / (nu + d / s2), 0.0)
        s2_new = max(1.0, float((w_new * d)[m].sum() / (K * m.sum())))
        done = np.abs(w_new - w).max() < tol and abs(s2_new - s2) < tol * s2
        w, s2 = w_new, s2_new
        if done:
            break
    sd = np.sqrt(np.diagonal(S, axis1=1, axis2=2))
    loose = sd ** 2 > 1e6 * typical  # only the vague prior holds it: not determined
    x = np.where(loose, np.nan, x)
    sd = np.where(loose, np.nan, sd)
    inv = np.empty(T, dtype=int)
    inv[order] = np.arange(T)
    return Smoothed(x[inv], sd[inv], np.where(m, w, np.nan)[inv], s2, it)


def parse_smooth(value) -> dict[str, float] | None:
    """``--smooth``'s value -> {short name of :data:`SMOOTH_SERIES`: sigma per sqrt(hour)}: one number for all
    (``0.1``), or ``aod_550=0.2,angstrom_alpha=0.1,g=0.05`` (names left out: not smoothed); a dict as
    that. BatchError for a value that is not > 0 or an unknown name. (AOD 550 is smoothed in log: its sigma
    is relative, 0.2 = 20 % per sqrt(hour).)"""
    if value is None:
        return None
    names = [n for n, _, _ in SMOOTH_SERIES]
    if isinstance(value, dict):
        pairs = list(value.items())
    elif isinstance(value, (int, float)):
        pairs = [(n, value) for n in names]
    else:
        text = str(value).strip()
        if "=" not in text:
            pairs = [(n, text) for n in names]
        else:
            pairs = [tuple(part.split("=", 1)) for part in text.split(",") if part.strip()]
            if any(len(pq) != 2 for pq in pairs):
                raise BatchError(f"--smooth {value}: expected SIGMA or NAME=SIGMA,... with names {', '.join(names)}")
    out = {}
    for name, v in pairs:
        name = str(name).strip()
        if name not in names:
            raise BatchError(f"--smooth: unknown series {name!r}; known: {', '.join(names)}")
        try:
            f = float(v)
        except (TypeError, ValueError):
            raise BatchError(f"--smooth: {name}={v!r} is not a number") from None
        if not f > 0:
            raise BatchError(f"--smooth: {name} must be > 0 per sqrt(hour) (inf: no smoothing), got {v}")
        out[name] = f
    return out


def _fallback_sigma(sig: np.ndarray, y: np.ndarray) -> float:
    """A component's sigma for items whose fit has none: the median of the others', else the robust scatter
    of consecutive values (1.4826 MAD / sqrt 2), else 1."""
    good = sig[np.isfinite(sig) & (sig > 0)]
    if good.size:
        return float(np.median(good))
    d = np.diff(y[np.isfinite(y)])
    mad = 1.4826 * float(np.median(np.abs(d - np.median(d)))) / math.sqrt(2.0) if d.size else 0.0
    return mad if mad > 0 else 1.0


def smooth_table(df, smooth, correlations: dict | None = None, nu: float | None = STUDENT_NU):
    """The table with the smoothing pass's columns: ``<name>_smooth``, ``sigma_<name>_smooth`` for each
    smoothed series of :data:`SMOOTH_SERIES` (``aod_550``, ``angstrom_alpha``, ``g``), and ``smooth_weight``.

    Each finished item (status ok) is a measurement of (log AOD 550, alpha, g) with covariance from its
    ``sigma_`` columns and ``correlations`` (item key -> :func:`laplace_correlation`); a missing, zero or
    non-finite sigma (no ``--laplace``, a Hessian that was not positive definite) takes
    :func:`_fallback_sigma`. An item whose rmse (``rmse_rel`` for photos) exceeds the batch's median by a
    factor k has its covariance multiplied by k^2. Failed items get the walk's interpolation. A series none of
    whose items fitted it (fixed) is not smoothed. Times from the ``time`` column; without times one item
    is one hour. ``df.attrs["smooth"]`` records sigma, nu, the covariance scale, the iterations and the
    series smoothed. ``sigma_aod_550_smooth`` is AOD x the sd of log AOD (the band is exp(log AOD +- sd)).
    """
    sig_rw = parse_smooth(smooth)
    df = df.copy()
    ok = (df["status"] == "ok").to_numpy()
    free_any = set(",".join(df.loc[ok, "free"].dropna()).split(",")) if ok.any() and "free" in df else set()
    if "mie_beta_550" in free_any:
        free_any.add("mie_aod_550")
    comps = [(n, col, lg) for n, col, lg in SMOOTH_SERIES if n in sig_rw and col in df and col in free_any]
    info_cols = [col for _, col, _ in comps]
    for n, col, _ in SMOOTH_SERIES:
        if n in sig_rw:
            df[f"{n}_smooth"] = df[col].astype(float) if (col in df and n not in [c[0] for c in comps]) else np.nan
            df[f"sigma_{n}_smooth"] = np.nan
    df["smooth_weight"] = np.nan
    info = {"sigma_per_sqrt_h": sig_rw, "nu": nu, "series": [c[0] for c in comps], "series_columns": info_cols,
            "scale": None, "iterations": 0}
    df.attrs["smooth"] = info
    if not comps or not ok.any():
        return df
    x, is_time = _times(df)
    t_s = ((np.asarray(x, dtype="datetime64[ns]") - np.datetime64(0, "ns")) / np.timedelta64(1, "s")) if is_time \
        else np.arange(len(df), dtype=float) * 3600.0
    T, K = len(df), len(comps)
    y = np.full((T, K), np.nan)
    sd = np.full((T, K), np.nan)
    for k, (_, col, lg) in enumerate(comps):
        v = df[col].to_numpy(dtype=float)
        s = df[f"sigma_{col}"].to_numpy(dtype=float) if f"sigma_{col}" in df else np.full(T, np.nan)
        if lg:
            s = np.where(v > 0, s / np.where(v > 0, v, 1.0), np.nan)
            v = np.where(v > 0, np.log(np.where(v > 0, v, 1.0)), np.nan)
        y[:, k], sd[:, k] = np.where(ok, v, np.nan), np.where(ok, s, np.nan)
    meas = np.isfinite(y).all(1)
    for k in range(K):
        bad = meas & ~(np.isfinite(sd[:, k]) & (sd[:, k] > 0))
        sd[bad, k] = _fallback_sigma(sd[meas & ~bad, k], y[meas, k]) if (meas & ~bad).any() else \
            _fallback_sigma(np.array([]), y[meas, k])
    misfit = df["rmse_rel"] if "rmse_rel" in df and df["rmse_rel"].notna().any() else df.get("rmse")
    inflate = np.ones(T)
    if misfit is not None:
        r = misfit.to_numpy(dtype=float)
        med = np.nanmedian(r[meas]) if np.isfinite(r[meas]).any() else np.nan
        if np.isfinite(med) and med > 0:
            inflate = np.where(np.isfinite(r), np.maximum(1.0, (r / med) ** 2), 1.0)
    cov = np.zeros((T, K, K))
    keys = df["item"].tolist()
    for i in range(T):
        c = (correlations or {}).get(keys[i]) or {}
        for a in range(K):
            for b in range(K):
                rho = 1.0 if a == b else c.get((comps[a][1], comps[b][1]), 0.0)
                cov[i, a, b] = rho * sd[i, a] * sd[i, b] * inflate[i]
        if meas[i] and np.linalg.eigvalsh(cov[i]).min() <= 0:  # a correlation of exactly +-1: keep the variances
            cov[i] = np.diag(np.diag(cov[i]))
    y[~meas] = np.nan
    sm = smooth_series(t_s, y, np.where(meas[:, None, None], cov, np.eye(K)), [sig_rw[c[0]] for c in comps], nu=nu)
    if is_time:  # an item without a time of its own (failed before its time was known) has no place on the curve
        import pandas as pd

        timed = pd.to_datetime(df["time"], utc=True, errors="coerce", format="ISO8601").notna().to_numpy()
        sm.mean[~timed], sm.sd[~timed] = np.nan, np.nan
    for k, (n, _, lg) in enumerate(comps):
        m, s = sm.mean[:, k], sm.sd[:, k]
        df[f"{n}_smooth"] = np.exp(m) if lg else m
        df[f"sigma_{n}_smooth"] = np.exp(m) * s if lg else s
    df["smooth_weight"] = sm.weight / inflate
    info.update(scale=sm.scale, iterations=sm.iterations)
    return df


# -- time series and summary -------------------------------------------------------------------------------
def _times(df):
    """x positions of the rows: times (UTC-aware datetimes, failed items placed by item order between their
    neighbours) when every finished item has one, else the item index; and whether they are times."""
    import pandas as pd  # only for a batch (module docstring)

    t = pd.to_datetime(df["time"], utc=True, errors="coerce", format="ISO8601")
    ok = t.notna().to_numpy()
    idx = np.arange(len(df), dtype=float)
    if ok.sum() >= 1 and ok[(df["status"] == "ok").to_numpy()].all():
        sec = (t[ok] - pd.Timestamp(0, tz="UTC")).dt.total_seconds().to_numpy()
        filled = np.interp(idx, idx[ok], sec) if ok.sum() > 1 else np.full(len(df), sec[0])
        return pd.to_datetime(filled, unit="s", utc=True), True
    return idx, False


def plot_timeseries(df, path: str | Path) -> Path:
    """timeseries.png: AOD 550, Ångström alpha, g and the Rayleigh scale against time (item order when the
    items have no time), with ±1 sigma bands where Laplace sigmas exist and failed items marked; with the
    smoothing pass's columns (:func:`smooth_table`) also the smoothed curve, its ±1 sigma band and the
    items it down-weighted."""
    import matplotlib  # matplotlib and pandas: ~1 s of imports, only for the plot of a batch

    matplotlib.use("Agg")
    import matplotlib.dates as mdates
    import matplotlib.pyplot as plt
    import pandas as pd

    x, is_time = _times(df)
    ok = (df["status"] == "ok").to_numpy()
    order = np.argsort(np.asarray(x, dtype="datetime64[ns]" if is_time else float), kind="stable")
    fig, axes = plt.subplots(len(SERIES), 1, figsize=(8, 2.1 * len(SERIES)), sharex=True)
    free_any = set(",".join(df.loc[ok, "free"].dropna()).split(",")) if ok.any() else set()
    if "mie_beta_550" in free_any:
        free_any.add("mie_aod_550")  # the AOD is the Mie extinction at 550 nm integrated over height
    labels = {"mie_aod_550": "AOD 550 nm", "mie_angstrom_alpha": "Ångström α", "mie_g": "g",
              "rayleigh_scale": "Rayleigh scale"}
    xs = np.asarray(x)[order]
    for ax, name in zip(axes, SERIES):
        v = df[name].to_numpy(dtype=float)[order] if name in df else np.full(len(df), np.nan)
        sel = ok[order] & np.isfinite(v)
        ax.plot(xs[sel], v[sel], "o-", ms=3, lw=1, color="C0",
                label=labels[name] + ("" if name in free_any else " (fixed)"))
        sc = f"sigma_{name}"
        if sc in df:
            s = df[sc].to_numpy(dtype=float)[order]
            band = sel & np.isfinite(s)
            if band.any():
                ax.fill_between(xs[band], (v - s)[band], (v + s)[band], color="C0", alpha=0.25, lw=0, label="±1σ (Laplace)")
        short = {col: n for n, col, _ in SMOOTH_SERIES}.get(name)
        smoothed = (df.attrs.get("smooth") or {}).get("series_columns", ())
        if short is not None and f"{short}_smooth" in df and name in smoothed:
            m = df[f"{short}_smooth"].to_numpy(dtype=float)[order]
            sm_sd = df[f"sigma_{short}_smooth"].to_numpy(dtype=float)[order]
            keep = np.isfinite(m)
            if short == "aod_550":  # smoothed in log: the band is exp(log AOD +- sd)
                rel = np.where(m > 0, sm_sd / np.where(m > 0, m, 1.0), np.nan)
                lo, hi = m * np.exp(-rel), m * np.exp(rel)
            else:
                lo, hi = m - sm_sd, m + sm_sd
            ax.plot(xs[keep], m[keep], "-", lw=1.5, color="C1", label="smoothed (random walk)")
            bk = keep & np.isfinite(lo) & np.isfinite(hi)
            ax.fill_between(xs[bk], lo[bk], hi[bk], color="C1", alpha=0.2, lw=0, label="±1σ smoothed")
            wgt = df["smooth_weight"].to_numpy(dtype=float)[order]
            low = sel & (wgt < 0.5)
            if low.any():
                ax.plot(xs[low], v[low], "o", ms=7, mfc="none", color="C3", label="down-weighted (w < 0.5)")
            fin = v[sel]
            if fin.size:  # the band of an interpolated gap can be wide: the data set the axis
                pad = 0.15 * (np.nanmax(fin) - np.nanmin(fin) or abs(np.nanmax(fin)) or 1.0)
                ax.set_ylim(min(np.nanmin(fin), np.nanmin(m[keep])) - pad, max(np.nanmax(fin), np.nanmax(m[keep])) + pad)
        bad = ~ok[order]
        if bad.any():
            for xb in xs[bad]:
                ax.axvline(xb, color="C3", lw=1, ls="--")
        ax.set_ylabel(labels[name])
        ax.grid(alpha=0.3)
    if (~ok).any():
        axes[0].plot([], [], color="C3", ls="--", label=f"failed ({int((~ok).sum())})")
    axes[0].legend(loc="best", fontsize=8)
    for ax in axes[1:]:
        if ax.get_legend_handles_labels()[0]:
            ax.legend(loc="best", fontsize=8)
    if is_time:
        first = df.loc[ok, "time"].dropna()
        tz = pd.Timestamp(first.iloc[0]).tz if len(first) else None  # the first item's UTC offset
        axes[-1].xaxis.set_major_formatter(mdates.DateFormatter("%H:%M", tz=tz))
        axes[-1].set_xlabel(f"time ({tz})" if tz is not None else "time (UTC)")
    else:
        axes[-1].set_xlabel("item")
    fig.suptitle(f"{int(ok.sum())} of {len(df)} items fitted")
    fig.tight_layout()
    return save_fig(fig, Path(path))


def summary_lines(df, seconds: float | None = None) -> list[str]:
    """A short terminal summary: items ok / failed, rate, each series' median and range, RMSE, the failures."""
    ok = df["status"] == "ok"
    n, n_ok = len(df), int(ok.sum())
    head = f"{n} items: {n_ok} ok, {n - n_ok} failed"
    if seconds:
        head += f" in {seconds:.1f} s ({n / seconds * 60:.1f} items/min)"
    lines = [head]
    for name in (*SERIES, "rmse"):
        if name in df and ok.any():
            v = df.loc[ok, name].astype(float)
            v = v[np.isfinite(v)]
            if len(v):
                unit = f" {df.loc[ok, 'rmse_units'].iloc[0]}" if name == "rmse" else ""
                lines.append(f"  {name:20s} median {v.median():.4g}  range {v.min():.4g} .. {v.max():.4g}{unit}")
    if "smooth_weight" in df and (df.attrs.get("smooth") or {}).get("series"):
        low = df.loc[df["smooth_weight"] < 0.5, "item"].tolist()
        lines.append(f"  smoothed {', '.join(df.attrs['smooth']['series'])}: {len(low)} item(s) down-weighted (w < 0.5)"
                     + (f": {', '.join(low[:10])}" + (" ..." if len(low) > 10 else "") if low else ""))
    for _, r in df.loc[~ok].head(10).iterrows():
        lines.append(f"  failed {r['item']}: {r['status']}")
    if n - n_ok > 10:
        lines.append(f"  ... and {n - n_ok - 10} more failures (results.csv)")
    return lines


# -- the cluster -------------------------------------------------------------------------------------------
def check_scheduler_address(address: str, timeout: float = 5.0) -> None:
    """BatchError unless something listens at a ``tcp://HOST:PORT`` (or ``HOST:PORT``) scheduler address."""
    u = urlparse(address if "://" in address else f"tcp://{address}")
    if u.scheme not in ("tcp", "tls", "ws", "wss") or not u.hostname or u.port is None:
        if u.scheme in ("inproc", "ucx"):
            return
        raise BatchError(f"--scheduler {address}: not a scheduler address (tcp://HOST:PORT)")
    try:
        with socket.create_connection((u.hostname, u.port), timeout=timeout):
            pass
    except OSError as e:
        raise BatchError(f"--scheduler {address}: unreachable ({e.strerror or e})") from None


def default_workers(threads_per_worker: int = 1) -> int:
    """Workers of the default LocalCluster: the CPUs this process may use, divided by the threads per worker."""
    try:
        cpus = len(os.sched_getaffinity(0))
    except AttributeError:
        cpus = os.cpu_count() or 1
    return max(1, cpus // max(1, threads_per_worker))


def _connect(client, scheduler, workers, threads_per_worker, retries, dashboard_address):
    """(client, owned resources to close): the user's client, a client of ``scheduler``, or a new LocalCluster."""
    import dask  # dask.distributed: ~1 s of imports, only for a batch (module docstring)
    from distributed import Client, LocalCluster

    if client is not None:
        return client, []
    if scheduler is not None:
        check_scheduler_address(scheduler)
        try:
            c = Client(scheduler, timeout="10s")
        except (OSError, TimeoutError) as e:
            raise BatchError(f"--scheduler {scheduler}: cannot connect ({one_line(e)})") from None
        return c, [c]
    with dask.config.set({"distributed.scheduler.allowed-failures": retries}):
        cluster = LocalCluster(n_workers=workers or default_workers(threads_per_worker),
                               threads_per_worker=threads_per_worker, processes=True,
                               dashboard_address=dashboard_address, silence_logs=40)
    c = Client(cluster)
    return c, [c, cluster]


# -- the batch ---------------------------------------------------------------------------------------------
def batch(items, config: str | Path | dict | None = None, *, out: str | Path | None = None, client=None,
          scheduler: str | None = None, workers: int | None = None, threads_per_worker: int = 1,
          resume: bool = False, laplace: bool = False, progress: bool = False, retries: int = DEFAULT_RETRIES,
          free: Sequence[str] | None = None, kider_site: dict | None = None, plot: bool = True,
          warm_start: str | None = None, device: str = "cpu", force: bool = False, dashboard_address: str | None = ":8787",
          log: Callable[[str], None] | None = None, location=None, times: str | Path | dict | None = None,
          photo_timezone: str | None = None, camera: str | Path | None = None, mask: str | Path | None = None,
          linear: bool = False, response: str | None = None, smooth=None, smooth_nu: float | None = STUDENT_NU,
          **settings):
    """Fit each item on its own, in parallel on Dask; a pandas DataFrame with one row per item.

    Args:
        items: .exr files, Kider capture folders, photos, bracket folders, folders of any of these, or globs
            (:func:`batch_items`; the bracket rule in :func:`photo_folder_items`).
        config: a shipped name, a YAML path or a dict with an optional ``fit:`` section, as for ``skyfit.fit``;
            None: ``earth`` when every item is a photo, required otherwise.
        out: a folder for ``<item>/RESULT.json``, results.parquet, results.csv and timeseries.png
            (None: nothing written, the results are only returned).
        client: a ``distributed.Client`` to run on (the caller keeps it open).
        scheduler: the address of a running Dask scheduler (``tcp://host:port``) instead.
        workers, threads_per_worker: size of the LocalCluster made when neither is given (default: one
            single-threaded worker process per CPU). Each task runs torch on one thread.
        resume: skip the items with a complete RESULT.json in ``out`` (their rows are read from it).
        laplace: Laplace sigmas of the free parameters (``sigma_<name>`` columns, the time series' bands).
        progress: a tqdm bar on stderr (items done, rate, ETA).
        retries: reschedules of an item whose worker died before it counts as failed (LocalCluster only:
            a running scheduler uses its own ``distributed.scheduler.allowed-failures``).
        free, kider_site, **settings: as for ``skyfit.fit`` (any :class:`~skyfit.fit.problem.FitSettings` field).
        plot: write timeseries.png (with ``out``).
        device, force: as for ``skyfit fit`` (cpu, cuda, cuda:N or auto, resolved on each worker; run fits
            whose memory or time estimate says no).
        warm_start: ``"previous"``: start each fit from the fitted values of the item before it (items in the
            order given, a folder's sorted by name: by time for captures and timestamped photos). The items
            are cut into as many contiguous chains as the cluster has threads; each chain runs in order and
            its first item starts from the config (or from the item before it when ``resume`` finds that
            one done). A failed item passes on the last fitted values. Results then depend on the
            order, unlike ``skyfit fit`` one by one; RESULT.json's ``settings.initial`` records the start.
        dashboard_address: of the LocalCluster (None: no dashboard).
        log: called with the dashboard address and progress notes (None: silent).
        location: a photo's place, "LAT,LON[,ELEV]" or (lat, lon[, elev]); None: each photo's EXIF GPS position (a
            photo without one fails; a batch of photos none of which has one is refused).
        times: a times CSV (``file,time`` rows, :func:`read_times`) or its dict; a photo's row wins over EXIF.
        photo_timezone: the zone of photo times without a UTC offset (EXIF DateTimeOriginal without
            OffsetTimeOriginal, naive rows of ``times``): ``+02:00``, hours (``-4``) or an IANA name.
        camera, mask, linear, response: as for ``skyfit fit PHOTO`` (one camera and mask for every photo).
            A photo whose time cannot be found fails alone, with its one-line error (no task is run).
        smooth: the smoothing pass (:func:`smooth_table`): the random walk's sigma per sqrt(hour), one number
            or per series (:func:`parse_smooth`); None: none.
        smooth_nu: the smoothing's Student-t degrees of freedom (None: Gaussian, no outlier weights).

    Returns:
        One row per item in item order (:func:`result_row`); ``df.attrs`` holds ``seconds`` (all of it),
        ``startup_s`` (connecting or starting the cluster), ``run_s`` (first submission to last result),
        ``resumed`` (items skipped by ``resume``),
        ``dashboard``, ``workers`` and, with ``out``, the written ``files``.
    """
    t0 = time.perf_counter()
    say = log or (lambda _line: None)
    if str(device) != "auto":
        try:
            torch.device(str(device))
        except (RuntimeError, TypeError):
            raise BatchError(f"unknown device {device!r}; use cpu, cuda, cuda:N or auto") from None
    if warm_start not in (None, "previous"):
        raise BatchError(f"warm_start must be None or 'previous', got {warm_start!r}")
    if retries < 0:
        raise BatchError(f"retries must be >= 0, got {retries}")
    if threads_per_worker < 1:
        raise BatchError(f"--threads-per-worker must be >= 1, got {threads_per_worker}")
    if workers is not None and workers < 1:
        raise BatchError(f"--workers must be >= 1, got {workers}")
    if sum(x is not None for x in (client, scheduler)) > 1:
        raise BatchError("give a client or a scheduler address, not both")
    sig_rw = parse_smooth(smooth)
    if smooth_nu is not None and not smooth_nu > 0:
        raise BatchError(f"smooth_nu must be > 0 (None: Gaussian), got {smooth_nu}")
    todo = batch_items(items)
    photos = [it for it in todo if it.kind in PHOTO_KINDS]
    if config is None:
        if len(photos) < len(todo):
            raise BatchError("--config is required for EXR and Kider data")
        config = "earth"
    cfg, source = read_config(config)
    overrides = {**settings, "free": free}
    if len(photos) < len(todo):
        s = fit_settings(cfg.get("fit"), overrides)  # bad settings fail here, before any fit or file is made
        make_model(s)
        make_loss(s.loss)
    photo_args, photo_fail = _photo_arguments(photos, cfg, overrides, location, times, photo_timezone, camera, mask,
                                              linear, response)
    out_dir = check_out_dir(out) if out is not None else None
    if resume and out_dir is None:
        raise BatchError("resume needs out: the folder of the batch to continue")

    rows: dict[str, dict] = {}
    finished: dict[str, dict] = {}
    correlations: dict[str, dict] = {}
    if resume and out_dir is not None:
        for it in todo:
            res = finished_result(out_dir, it)
            if res is not None:
                rows[it.key] = result_row(it, res, {"status": "ok", **res["batch"]})
                finished[it.key] = res
                correlations[it.key] = laplace_correlation(res)
    resumed = len(rows)
    for key, err in photo_fail.items():  # no time: recorded as failed, never submitted
        if key not in rows:
            rows[key] = result_row(next(it for it in todo if it.key == key), None, {"status": err})
    pending = [it for it in todo if it.key not in rows]
    if resumed:
        say(f"resume: {resumed} of {len(todo)} items already done, {len(pending)} to fit")

    dashboard, n_workers, startup, run_s = None, 0, 0.0, 0.0
    if pending:
        t1 = time.perf_counter()
        c, owned = _connect(client, scheduler, workers, threads_per_worker, retries, dashboard_address)
        try:
            info = c.scheduler_info()
            dashboard = c.dashboard_link if "dashboard" in (info.get("services") or {}) else None
            n_workers = len(info.get("workers", {}))
            say(f"dask: {n_workers} worker(s), dashboard {dashboard}")
            if out_dir is not None:
                out_dir.mkdir(parents=True, exist_ok=True)
            t2 = time.perf_counter()
            startup = t2 - t1
            warm = None
            if warm_start == "previous":
                warm = {b.key: finished.get(a.key) for a, b in zip(todo, todo[1:])}
            _run(c, pending, rows, out_dir, cfg, overrides, source, kider_site, laplace, progress, warm,
                 {"device": str(device), "force": force}, photo_args, correlations)
            run_s = time.perf_counter() - t2
        finally:
            for r in owned:
                r.close()
    df = results_table([rows[it.key] for it in todo])
    if sig_rw is not None:
        df = smooth_table(df, sig_rw, correlations, nu=smooth_nu)
    seconds = time.perf_counter() - t0
    df.attrs.update(seconds=seconds, startup_s=startup, run_s=run_s, resumed=resumed, dashboard=dashboard,
                    workers=n_workers, files=[])
    if out_dir is not None:
        out_dir.mkdir(parents=True, exist_ok=True)
        files = write_tables(df, out_dir)
        if plot:
            files.append(plot_timeseries(df, out_dir / TIMESERIES_NAME))
        df.attrs["files"] = [str(f) for f in files]
    return df


def _photo_arguments(photos, cfg, overrides, location, times, zone, camera, mask, linear, response):
    """({key: the photo arguments of :func:`fit_item`}, {key: one-line error}) of the photo items, after the
    batch-wide checks (BatchError: no --location, a bad times file, zone, camera file or setting)."""
    if not photos:
        return {}, {}
    from .fit.photo import photo_settings, read_camera  # only a batch with photos needs the photo fit's imports

    gps = {}
    if location is None:  # each photo's EXIF GPS position; a batch where none has one is refused as a whole
        gps = {it.key: exif_location(it.path) for it in photos}
        if all(g is None for g in gps.values()):
            raise BatchError(f"photo {photos[0].path}: give --location LAT,LON[,ELEV] (the place of the photos; "
                             "none has an EXIF GPS position)")
    else:
        try:
            lat, lon, elev = parse_location(location) if isinstance(location, str) else \
                (tuple(float(v) for v in location) + (0.0,))[:3]
        except (TypeError, ValueError) as e:
            raise BatchError(f"--location {location}: {one_line(e)}") from None
    zone = check_photo_timezone(zone)
    table = read_times(times) if isinstance(times, (str, Path)) else (
        {str(Path(k).absolute()): str(v) for k, v in times.items()} if times else None)
    try:
        cam = read_camera(camera) if camera is not None else None
        photo_settings(cfg, overrides, calibrated=cam is not None)  # bad settings fail before any fit
    except ValueError as e:
        raise BatchError(one_line(e)) from None
    if mask is not None and not Path(mask).expanduser().is_file():
        raise BatchError(f"mask {mask}: not found")
    args, fail = {}, {}
    for it in photos:
        try:
            when, source = photo_time(it, table, zone)
        except ValueError as e:
            fail[it.key] = one_line(e)
            continue
        if location is None:
            if gps[it.key] is None:
                fail[it.key] = f"photo {it.path}: no place: no EXIF GPS position, and no --location"
                continue
            lat, lon, elev = gps[it.key][0], gps[it.key][1], gps[it.key][2] or 0.0
        args[it.key] = {"time": when, "time_source": source, "location": f"{lat},{lon},{elev}", "camera": cam,
                        "mask": None if mask is None else str(Path(mask).expanduser()), "linear": linear,
                        "response": response}
    return args, fail


def _run(c, pending, rows, out_dir, cfg, overrides, source, kider_site, laplace, progress, warm=None,
         options: dict | None = None, photo_args: dict | None = None, correlations: dict | None = None) -> None:
    """Submit the pending items (a window a few times the cluster's threads), record each as it finishes.

    ``warm`` (warm start): item key -> the RESULT dict of the item before it when that one finished before
    this run (None for the others). The pending items are then cut into as many contiguous chains as the
    cluster has threads, each item a task that depends on the one before it in its chain."""
    from distributed import as_completed  # only for a batch (module docstring)
    from tqdm.auto import tqdm

    def window() -> int:
        try:
            threads = sum(c.nthreads().values())
        except Exception:  # noqa: BLE001  (a scheduler busy answering: keep a modest window)
            threads = 1
        return max(8, 4 * threads)

    by_key = {it.key: it for it in pending}
    queue = list(pending)
    ac = as_completed()
    futures: dict[str, str] = {}  # future key -> item key, while running
    live: dict = {}  # future key -> future, while running

    def submit(it: BatchItem, previous=None):
        f = c.submit(fit_item, it.path, cfg, overrides, source, kider_site, laplace, 1, previous, **(options or {}),
                     photo=(photo_args or {}).get(it.key), key=f"skyfit-fit-{it.key}-{os.urandom(4).hex()}", pure=False)
        futures[f.key] = it.key
        live[f.key] = f
        ac.add(f)
        return f

    if warm is not None:  # chains of dependent tasks, all submitted now
        n = max(1, min(len(queue), sum(c.nthreads().values())))
        for chunk in np.array_split(np.arange(len(queue)), n):
            prev = None
            for i in chunk:
                it = queue[int(i)]
                start = warm.get(it.key)
                prev = submit(it, prev if prev is not None else ({"result": start} if start else {}))
        queue = []
    limit = window()
    while queue and len(futures) < limit:
        submit(queue.pop(0))
    failed = 0
    bar = tqdm(total=len(pending), unit="item", desc="batch", disable=not progress, dynamic_ncols=True)
    last_window = time.monotonic()
    try:
        for f in ac:
            it = by_key[futures.pop(f.key)]
            live.pop(f.key, None)
            try:
                r = f.result()
            except Exception as e:  # noqa: BLE001  (KilledWorker after the retries, a lost scheduler...)
                r = {"result": None, "status": one_line(e), "wall_s": None, "cpu_s": None, "worker": None}
            finally:
                f.release()
            res = r.pop("result")
            if res is not None and out_dir is not None:
                res["batch"] = {"item": it.path, "key": it.key, "wall_s": r["wall_s"], "cpu_s": r["cpu_s"],
                                "worker": r["worker"]}
                if warm is not None:
                    res["batch"]["warm_start_from"] = r.get("warm_from")
                if it.key in (photo_args or {}):
                    res["batch"]["time_source"] = photo_args[it.key]["time_source"]
                save_result(res, result_path(out_dir, it))
            if it.key in (photo_args or {}):
                r["time_source"] = photo_args[it.key]["time_source"]
            if correlations is not None:
                correlations[it.key] = laplace_correlation(res)
            failed += r["status"] != "ok"
            rows[it.key] = result_row(it, res, r)
            bar.update(1)
            if failed:
                bar.set_postfix(failed=failed, refresh=False)
            if time.monotonic() - last_window > 10:
                limit, last_window = window(), time.monotonic()
            while queue and len(futures) < limit:
                submit(queue.pop(0))
    except BaseException:  # interrupted: nothing more is fitted; what finished is on disk for --resume
        c.cancel(list(live.values()))
        raise
    finally:
        bar.close()
