"""`skyfit batch` / `skyfit.batch` (CONTRACT.md, "Many skies"; docs/batch.md) on tiny synthetic EXR skies.

A batch's numbers must be those of fitting each item on its own (`skyfit.fit`, `skyfit fit`): the
expected values here come from those calls, not from the batch. The cluster is in-process
(`processes=False`, one worker, two threads) so that the tests take seconds; the worker-death test
starts worker processes and is marked slow.
"""
from __future__ import annotations

import json
import os
import shutil
import signal
import socket
import threading
import time
from pathlib import Path

import pandas as pd
import pytest

import skyfit
import skyfit.batch as B
from skyfit.cli import main
from _cli import run as _run

distributed = pytest.importorskip("distributed")

FAST = dict(integrator="gauss:samples=8", view_samples=4, rule="trapezoid", starts=1, max_iter=30)
FAST_FLAGS = ["--integrator", "gauss:samples=8", "--view-samples", "4", "--rule", "trapezoid", "--starts", "1",
              "--max-iter", "30"]
FREE = ["mie_g", "exposure"]
G = {"sky0": 0.65, "sky1": 0.7, "sky2": 0.75}
KIDER_DAY = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "kider2014" / "2013-05-27"


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    """Three 12 x 12 spectral fisheyes (g 0.65, 0.7, 0.75; a quarter hour apart at the Kider site) and a corrupt .exr."""
    d = tmp_path_factory.mktemp("day")
    base = (Path(skyfit.__file__).parent / "configs" / "earth.yaml").read_text()
    for i, (name, g) in enumerate(G.items()):
        text = base.replace("g: 0.8  ", f"g: {g}  ")
        assert f"g: {g}" in text
        (d / f"{name}.yaml").write_text(text)
        assert main(["render", str(d / f"{name}.yaml"), "--size", "12", "--time", f"2013-05-27T10:{15 * i:02d}:00-04:00",
                     "--location", "42.44,-76.48,250", "--wavelengths", "450:650:100", "--integrator", "gauss:samples=8",
                     "--view-samples", "4", "--dtype", "float64", "--spectral", "--out", str(d / f"{name}.exr")]) == 0
        (d / f"{name}.yaml").unlink()
    (d / "bad.exr").write_bytes(b"this is not an OpenEXR file")
    return d


@pytest.fixture(scope="module")
def cluster():
    with distributed.LocalCluster(n_workers=1, threads_per_worker=2, processes=False, protocol="tcp",
                                  dashboard_address=":0") as c:
        yield c


@pytest.fixture(scope="module")
def client(cluster):
    with distributed.Client(cluster) as c:
        yield c


@pytest.fixture(scope="module")
def done(data, client, tmp_path_factory):
    """The batch of the day folder (three skies and the corrupt file), with Laplace sigmas."""
    out = tmp_path_factory.mktemp("batch") / "out"
    df = skyfit.batch(data, "earth", out=out, client=client, laplace=True, free=FREE, **FAST)
    return out, df


def _drop_seconds(d):
    """A result dict without its timings (and the batch's own entry): what must be equal between two runs."""
    if isinstance(d, dict):
        return {k: _drop_seconds(v) for k, v in d.items() if "seconds" not in k and k != "batch"}
    if isinstance(d, list):
        return [_drop_seconds(v) for v in d]
    return d


# -- items -------------------------------------------------------------------------------------------
def test_items_from_folders_files_and_globs(data):
    items = B.batch_items([data])
    assert [i.key for i in items] == ["bad", "sky0", "sky1", "sky2"]
    assert all(Path(i.path).is_absolute() and i.kind == "exr" for i in items)
    same = B.batch_items([str(data / "sky*.exr"), data / "sky1.exr"])  # a glob, and a file it matched again
    assert [i.key for i in same] == ["sky0", "sky1", "sky2"]
    with pytest.raises(B.BatchError, match="no items match"):
        B.batch_items([str(data / "nothing*.exr")])


def test_items_with_one_name_get_distinct_keys(data, tmp_path):
    (tmp_path / "a").mkdir()
    shutil.copy(data / "sky0.exr", tmp_path / "a" / "sky0.exr")
    keys = [i.key for i in B.batch_items([data / "sky0.exr", tmp_path / "a" / "sky0.exr"])]
    assert len(set(keys)) == 2 and all(k.startswith("sky0-") for k in keys)


@pytest.mark.skipif(not KIDER_DAY.is_dir(), reason="Kider captures not in ../shared/data")
def test_a_folder_of_kider_captures_is_one_item_per_capture():
    items = B.batch_items([KIDER_DAY])
    assert len(items) == 15 and {i.kind for i in items} == {"kider"}
    assert items[0].key == "2013-05-27___09.30.00"


# -- the batch -----------------------------------------------------------------------------------------
def test_one_row_per_item_and_the_corrupt_one_fails_alone(done):
    out, df = done
    assert list(df["item"]) == ["bad", "sky0", "sky1", "sky2"]
    bad = df.set_index("item").loc["bad"]
    assert bad["status"].startswith("not an OpenEXR file") and "bad.exr" in bad["status"] and "\n" not in bad["status"]
    assert pd.isna(bad["rmse"]) and pd.isna(bad["result"])
    assert not (out / "bad").exists()
    ok = df[df["item"] != "bad"]
    assert (ok["status"] == "ok").all()
    for col in ("time", "latitude_deg", "mie_g", "sigma_mie_g", "sigma_exposure", "rmse", "delta_e",
                "wall_s", "cpu_s", "worker"):
        assert ok[col].notna().all(), col
    assert list(ok["latitude_deg"]) == pytest.approx([42.44] * 3) and list(ok["time"].str[11:16]) == ["10:00", "10:15", "10:30"]
    for name in ("results.parquet", "results.csv", "timeseries.png"):
        assert (out / name).is_file(), name
    assert (out / "timeseries.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    back = pd.read_parquet(out / "results.parquet")
    pd.testing.assert_frame_equal(back, df, check_dtype=False)
    csv = pd.read_csv(out / "results.csv")
    assert list(csv["status"]) == list(df["status"])
    assert not [p for p in out.rglob(".*")]  # no temporary file left


def test_batch_fits_are_those_of_skyfit_fit_one_by_one(done, data):
    out, df = done
    for key, g in G.items():
        one = skyfit.fit(data / f"{key}.exr", "earth", free=FREE, laplace=True, **FAST)
        row = df.set_index("item").loc[key]
        assert abs(row["rmse"] - one.metrics["rmse"]) <= 1e-9
        assert row["mie_g"] == pytest.approx(one.parameters["mie_g"], rel=1e-12, abs=0)
        assert row["sigma_mie_g"] == pytest.approx(one.sigma["mie_g"], rel=1e-9)
        assert abs(row["mie_g"] - g) < 2e-3  # noise-free data: the truth of each sky comes back
        res = json.loads((out / key / "RESULT.json").read_text())
        assert res["parameters"] == pytest.approx(one.parameters, rel=1e-12)
        assert res["batch"]["item"] == str(data / f"{key}.exr") and res["batch"]["wall_s"] > 0


def test_result_json_is_what_skyfit_fit_writes(done, data, tmp_path, capsys):
    out, _ = done
    cli = tmp_path / "RESULT.json"
    rc, _, se = _run(["fit", data / "sky1.exr", "--config", "earth", "--out", cli, "--free", ",".join(FREE),
                      "--laplace", "--no-plots", *FAST_FLAGS], capsys)
    assert rc == 0, se
    a = _drop_seconds(json.loads(cli.read_text()))
    b = _drop_seconds(json.loads((out / "sky1" / "RESULT.json").read_text()))
    assert a == b


def test_resume_refits_only_what_did_not_finish(done, data, client, tmp_path):
    first_out, first = done
    out = tmp_path / "out"
    shutil.copytree(first_out, out)
    (out / "sky2" / "RESULT.json").unlink()  # never finished
    (out / "sky1" / "RESULT.json").write_text('{"parameters": {')  # not a complete result
    kept = (out / "sky0" / "RESULT.json").stat().st_mtime_ns
    with distributed.get_task_stream(client) as ts:  # the tasks the scheduler ran
        df = skyfit.batch(data, "earth", out=out, client=client, laplace=True, resume=True, free=FREE, **FAST)
    calls = [t["key"].split("-")[2] for t in ts.data]
    assert sorted(calls) == ["bad", "sky1", "sky2"]
    assert (out / "sky0" / "RESULT.json").stat().st_mtime_ns == kept
    assert list(df["status"] == "ok") == [False, True, True, True]
    sky0 = df.set_index("item").loc["sky0"]
    assert sky0["wall_s"] == first.set_index("item").loc["sky0", "wall_s"]  # the row comes from its RESULT.json
    pd.testing.assert_series_equal(df["rmse"], first["rmse"], rtol=0, atol=1e-9)

    with distributed.get_task_stream(client) as ts:  # everything of sky0 finished: nothing is submitted
        skyfit.batch(data / "sky0.exr", "earth", out=out, client=client, laplace=True, resume=True, free=FREE, **FAST)
    calls = ts.data
    assert calls == []


def test_summary_names_the_failures_and_the_series(done):
    _, df = done
    lines = B.summary_lines(df, 12.0)
    assert lines[0] == "4 items: 3 ok, 1 failed in 12.0 s (20.0 items/min)"
    assert any(line.strip().startswith("mie_g") and "0.65" in line and "0.75" in line for line in lines)
    assert any(line.strip().startswith("failed bad: not an OpenEXR file") for line in lines)


def test_warm_start_previous_starts_each_fit_from_the_item_before(data, client, tmp_path):
    items = [data / "sky0.exr", data / "sky1.exr", data / "sky2.exr"]
    out = tmp_path / "warm"
    df = skyfit.batch(items, "earth", out=out, client=client, warm_start="previous", free=FREE, **FAST)
    assert (df["status"] == "ok").all()
    assert list(df["mie_g"]) == pytest.approx(list(G.values()), abs=2e-3)
    r = {k: json.loads((out / k / "RESULT.json").read_text()) for k in G}
    # one worker with two threads: two chains, [sky0, sky1] and [sky2]; a chain's first item starts from the config
    assert r["sky0"]["settings"]["initial"] == {} and r["sky0"]["batch"]["warm_start_from"] is None
    assert r["sky1"]["settings"]["initial"] == {n: r["sky0"]["parameters"][n] for n in FREE}
    assert r["sky1"]["batch"]["warm_start_from"] == str(items[0])
    assert r["sky2"]["settings"]["initial"] == {}

    (out / "sky1" / "RESULT.json").unlink()  # resumed, sky1 starts from sky0's result on disk
    skyfit.batch(items, "earth", out=out, client=client, warm_start="previous", resume=True, free=FREE, **FAST)
    again = json.loads((out / "sky1" / "RESULT.json").read_text())
    assert again["settings"]["initial"] == r["sky1"]["settings"]["initial"]
    assert again["parameters"] == r["sky1"]["parameters"]


# -- the command line -------------------------------------------------------------------------------------
def test_cli_batch_on_a_running_scheduler(data, cluster, tmp_path, capsys):
    out = tmp_path / "run"
    rc, so, se = _run(["batch", data / "sky*.exr", "--config", "earth", "--out", out, "--scheduler",
                       cluster.scheduler_address, "--free", ",".join(FREE), *FAST_FLAGS, "--json", "--no-progress"], capsys)
    assert rc == 0, se
    s = json.loads(so)
    assert (s["items"], s["ok"], s["failed"], s["workers"]) == (3, 3, 0, 1)
    assert sorted(p.name for p in out.iterdir()) == ["results.csv", "results.parquet", "sky0", "sky1", "sky2", "timeseries.png"]
    assert "dask: 1 worker(s)" in se


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.parametrize("case", ["no items", "out under a file", "out is a file", "scheduler", "free", "workers", "device"])
def test_cli_bad_input_is_one_line_and_exit_2(case, data, tmp_path, capsys):
    out = tmp_path / "out"
    args = ["batch", data / "sky0.exr", "--config", "earth", "--out", out]
    expect = {"no items": "no items match", "out under a file": "is not a directory", "out is a file": "is not a directory",
              "scheduler": "unreachable", "free": "unknown free parameter", "workers": "--workers must be >= 1",
              "device": "--device: unknown device 'tpu'"}[case]
    if case == "no items":
        args[1] = data / "nothing*.exr"
    elif case == "out under a file":
        args[5] = out = data / "sky0.exr" / "out"
    elif case == "out is a file":
        args[5] = out = data / "sky0.exr"
    elif case == "scheduler":
        args += ["--scheduler", f"tcp://127.0.0.1:{_free_port()}"]
    elif case == "free":
        args += ["--free", "mie_q"]
    elif case == "device":
        args += ["--device", "tpu"]
    else:
        args += ["--workers", "0"]
    rc, so, se = _run(args, capsys)
    assert rc == 2
    assert se.count("\n") == 1 and se.startswith("skyfit: error: ") and expect in se, se
    assert so == ""
    assert case == "out is a file" or not out.exists()


# -- worker death -------------------------------------------------------------------------------------------
@pytest.mark.slow
def test_a_worker_killed_mid_item_is_retried_then_recorded_failed(data, tmp_path):
    """SIGKILL the worker process running an item: Dask reschedules it and it is done once; with no
    reschedule allowed (retries 0) the item is recorded as failed (KilledWorker) and the batch goes on.

    Worker processes start cold: the first fit in each pays skyfit's imports (seconds), the window in
    which the test kills it. About 30 s, hence slow."""
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=":0") as cl, \
            distributed.Client(cl) as c:

        def kill_when_busy(killed):
            deadline = time.monotonic() + 60
            while time.monotonic() < deadline and not killed:
                busy = [w for w, tasks in c.processing().items() if tasks]
                if busy:
                    time.sleep(1.0)  # mid-item: the fit has started
                    os.kill(c.run(os.getpid, workers=[busy[0]])[busy[0]], signal.SIGKILL)
                    killed.append(busy[0])
                time.sleep(0.05)

        for allowed, item, status in ((2, "sky0", "ok"), (0, "sky1", "KilledWorker")):
            c.run_on_scheduler(lambda dask_scheduler, n=allowed: setattr(dask_scheduler, "allowed_failures", n))
            killed = []
            t = threading.Thread(target=kill_when_busy, args=(killed,))
            t.start()
            df = skyfit.batch([data / f"{item}.exr"], "earth", out=tmp_path / "out", client=c, free=FREE, **FAST)
            t.join()
            assert killed
            assert df["status"].iloc[0].startswith(status), df["status"].iloc[0]
            assert (tmp_path / "out" / item / "RESULT.json").is_file() == (status == "ok")
