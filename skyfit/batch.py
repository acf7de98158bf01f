"""Many skies: one fit per item on a Dask cluster, resumable, with a results table and a time series.

``skyfit.batch(items, config, out=...)`` (and ``skyfit batch DATA... --config C --out DIR``; CONTRACT.md,
"Many skies"; docs/batch.md) expands ``items`` (.exr files, Kider capture folders, folders of either,
globs) into one fit per item and runs each in a Dask worker with the call ``skyfit fit`` makes
(:func:`skyfit.fit.run.run_fit`, one torch thread per task), so that a batch's numbers are those of
``skyfit fit`` run one by one. The client writes, atomically, as each item finishes:

- ``DIR/<item>/RESULT.json``: what ``skyfit fit --no-plots`` writes, plus a ``batch`` entry (item,
  wall and CPU seconds, worker);
- at the end ``DIR/results.parquet`` and ``DIR/results.csv`` (one row per item, :func:`result_row`),
  ``DIR/timeseries.png`` (:func:`plot_timeseries`).

A failing item is recorded with its one-line error and the batch goes on; a worker that dies
mid-item has the item rescheduled by Dask up to ``retries`` times, then it is recorded as failed
(``KilledWorker``). ``resume=True`` skips every item with a complete RESULT.json of that item.

dask.distributed, pandas and matplotlib are imported inside the functions that use them: about a
second of imports that ``import skyfit`` and the other commands need not pay.
"""
from __future__ import annotations

import dataclasses
import glob
import hashlib
import json
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
from .fit.data import DataError, expand_data_paths
from .fit.losses import make_loss
from .fit.parameters import PARAMETERS
from .fit.problem import fit_settings, make_model
from .fit.report import dumps, save_fig
from .fit.results import check_result, save_result
from .fit.run import run_fit
from .io.atomic import atomic_path, check_writable, write_text_atomic

RESULT_NAME = "RESULT.json"
TABLE_NAMES = ("results.parquet", "results.csv")
TIMESERIES_NAME = "timeseries.png"
SERIES = ("mie_aod_550", "mie_angstrom_alpha", "mie_g", "rayleigh_scale")
"""The time series' quantities (timeseries.png, the summary): aerosol optical depth at 550 nm, Ångström
alpha, the Mie phase's g and the Rayleigh scale factor (docs/fitting.md)."""
DEFAULT_RETRIES = 2
"""Reschedules of an item whose worker died (Dask's ``distributed.scheduler.allowed-failures``) before it is
recorded as failed."""


class BatchError(ValueError):
    """A batch that cannot start: no items, an unwritable output folder, an unreachable scheduler."""


@dataclasses.dataclass(frozen=True)
class BatchItem:
    """One fit of a batch.

    Attributes:
        key: the item's folder name under the output folder (the capture or file name; unique in the batch).
        path: the absolute path of the capture folder or file.
        kind: ``kider`` or ``exr``.
    """

    key: str
    path: str
    kind: str


# -- items ------------------------------------------------------------------------------------------
def _is_glob(text: str) -> bool:
    return any(c in text for c in "*?[")


def batch_items(items: str | Path | Sequence[str | Path]) -> list[BatchItem]:
    """The fits of ``items``: .exr files, Kider capture folders, folders of either, or globs of those.

    Each capture folder and each file is one item (:func:`skyfit.fit.data.expand_data_paths`), in the
    order given (a glob's and a folder's matches sorted by name), duplicates dropped. The key is the
    folder or file name (its stem for files), with a short hash of the path where two items share a name.
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
    try:
        expanded = expand_data_paths(paths)
    except DataError as e:
        raise BatchError(str(e)) from None
    seen: dict[str, str] = {}
    for kind, p in expanded:
        seen.setdefault(str(Path(p).absolute()), kind)
    names = {path: (Path(path).name if kind == "kider" else Path(path).stem) for path, kind in seen.items()}
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


def warm_start_values(previous: dict | None) -> dict:
    """The free parameters' fitted values of ``previous`` (a RESULT dict), one value each: a fit's ``fit.initial``."""
    if not previous:
        return {}
    return {n: _scalar(previous["parameters"][n]) for n in previous.get("free", []) if n in previous["parameters"]}


def fit_item(path: str, config: dict, overrides: dict, config_source: str = "", kider_site: dict | None = None,
             laplace: bool = False, threads: int = 1, previous: dict | None = None, device: str = "cpu",
             force: bool = False) -> dict:
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
    """
    if torch.get_num_threads() != threads:
        torch.set_num_threads(threads)
    w0, c0 = time.perf_counter(), time.thread_time()
    start = (previous or {}).get("result") or (previous or {}).get("carry")
    if start:
        initial = {**((config.get("fit") or {}).get("initial") or {}), **(overrides.get("initial") or {}),
                   **warm_start_values(start)}
        overrides = {**overrides, "initial": initial}
    result, status = None, "ok"
    try:
        with tempfile.TemporaryDirectory(prefix="skyfit-batch-") as tmp:  # run_fit writes; the client keeps the copy
            result = run_fit([path], config, Path(tmp) / RESULT_NAME, overrides=overrides, config_source=config_source,
                             kider_site=kider_site, plots=False, progress=False, laplace=laplace,
                             device=resolve_device(device), force=force)
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
    """One row of results.parquet: item, time, location, sun, every parameter (``sigma_<name>`` with Laplace),
    metrics, convergence, wall/CPU seconds, worker, status (``ok`` or the one-line error)."""
    row: dict = {"item": item.key, "path": item.path, "status": info.get("status", "ok"), "time": None,
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
        m, c = result.get("metrics") or {}, result.get("convergence") or {}
        row.update(rmse=m.get("rmse"), rmse_units=m.get("rmse_units"), delta_e=m.get("delta_e"), loss=m.get("loss"),
                   n_samples=m.get("n_samples"), converged=c.get("converged"), iterations=c.get("iterations"),
                   free=",".join(result.get("free", [])))
    row.update(wall_s=info.get("wall_s"), cpu_s=info.get("cpu_s"), worker=info.get("worker"),
               result=str(Path(item.key) / RESULT_NAME) if result is not None else None)
    return row


def results_table(rows: Sequence[dict]):
    """The rows as a pandas DataFrame (item order; sigma columns no item has are dropped)."""
    import pandas as pd  # ~0.3 s of import, only for a batch

    df = pd.DataFrame(list(rows))
    if len(df):
        df = df.drop(columns=[c for c in df.columns if c.startswith("sigma_") and df[c].isna().all()])
    for c in ("wall_s", "cpu_s", "rmse", "delta_e", "loss", *PARAMETERS):
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
    items have no time), with ±1 sigma bands where Laplace sigmas exist and failed items marked."""
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
def batch(items, config: str | Path | dict = "earth", *, out: str | Path | None = None, client=None,
          scheduler: str | None = None, workers: int | None = None, threads_per_worker: int = 1,
          resume: bool = False, laplace: bool = False, progress: bool = False, retries: int = DEFAULT_RETRIES,
          free: Sequence[str] | None = None, kider_site: dict | None = None, plot: bool = True,
          warm_start: str | None = None, device: str = "cpu", force: bool = False, dashboard_address: str | None = ":8787",
          log: Callable[[str], None] | None = None, **settings):
    """Fit each item on its own, in parallel on Dask; a pandas DataFrame with one row per item.

    Args:
        items: .exr files, Kider capture folders, folders of either, or globs (:func:`batch_items`).
        config: a shipped name, a YAML path or a dict with an optional ``fit:`` section, as for ``skyfit.fit``.
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
    todo = batch_items(items)
    cfg, source = read_config(config)
    overrides = {**settings, "free": free}
    s = fit_settings(cfg.get("fit"), overrides)  # bad settings fail here, before any fit or file is made
    make_model(s)
    make_loss(s.loss)
    out_dir = check_out_dir(out) if out is not None else None
    if resume and out_dir is None:
        raise BatchError("resume needs out: the folder of the batch to continue")

    rows: dict[str, dict] = {}
    finished: dict[str, dict] = {}
    if resume and out_dir is not None:
        for it in todo:
            res = finished_result(out_dir, it)
            if res is not None:
                rows[it.key] = result_row(it, res, {"status": "ok", **res["batch"]})
                finished[it.key] = res
    pending = [it for it in todo if it.key not in rows]
    resumed = len(rows)
    if rows:
        say(f"resume: {len(rows)} of {len(todo)} items already done, {len(pending)} to fit")

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
                 {"device": str(device), "force": force})
            run_s = time.perf_counter() - t2
        finally:
            for r in owned:
                r.close()
    df = results_table([rows[it.key] for it in todo])
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


def _run(c, pending, rows, out_dir, cfg, overrides, source, kider_site, laplace, progress, warm=None,
         options: dict | None = None) -> None:
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
                     key=f"skyfit-fit-{it.key}-{os.urandom(4).hex()}", pure=False)
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
                save_result(res, result_path(out_dir, it))
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
