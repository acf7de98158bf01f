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
                     "--view-samples", "4", "--rule", "trapezoid", "--spacing", "uniform",  # the fit's renderer (FAST_FLAGS)
                     "--dtype", "float64", "--spectral", "--out", str(d / f"{name}.exr")]) == 0
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
        assert row["corrected_mie_g"] == pytest.approx(one.corrected["values"]["mie_g"], rel=1e-9)
        assert row["sigma_corrected_mie_g"] == pytest.approx(one.corrected["sigma"]["mie_g"], rel=1e-9)
        for n, d in one.corrected["derived"].items():  # derived quantities of the free ones, if any
            assert row[f"corrected_{n}"] == pytest.approx(d["value"], rel=1e-9)
        assert abs(row["mie_g"] - g) < 2e-3  # noise-free data: the truth of each sky comes back
        res = json.loads((out / key / "RESULT.json").read_text())
        assert res["parameters"] == pytest.approx(one.parameters, rel=1e-12)
        assert res["batch"]["item"] == str(data / f"{key}.exr") and res["batch"]["wall_s"] > 0


def test_a_row_carries_the_corrected_estimate_and_its_derived_quantities():
    """results.parquet's corrected_<name> / sigma_corrected_<name>: RESULT.json's laplace.corrected, its free values
    and its derived ones (the AOD), beside the fitted value and the total sigma."""
    from skyfit.batch import BatchItem, result_row

    res = {"parameters": {"mie_beta_550": 2e-5, "exposure": 1.1}, "free": ["mie_beta_550", "exposure"],
           "laplace": {"sigma": {"mie_beta_550": 3e-6, "exposure": 0.02},
                       "derived": {"mie_aod_550": {"value": 0.03, "sigma": 0.004}},
                       "corrected": {"values": {"mie_beta_550": 2.4e-5, "exposure": 1.05},
                                     "sigma": {"mie_beta_550": 1e-6, "exposure": 0.01},
                                     "derived": {"mie_aod_550": {"value": 0.036, "sigma": 0.0015}}}}}
    row = result_row(BatchItem("a", "/a.exr", "exr"), res, {})
    assert (row["mie_beta_550"], row["sigma_mie_beta_550"]) == (2e-5, 3e-6) and row["sigma_mie_aod_550"] == 0.004
    assert (row["corrected_mie_beta_550"], row["sigma_corrected_mie_beta_550"]) == (2.4e-5, 1e-6)
    assert (row["corrected_exposure"], row["sigma_corrected_exposure"]) == (1.05, 0.01)
    assert (row["corrected_mie_aod_550"], row["sigma_corrected_mie_aod_550"]) == (0.036, 0.0015)
    assert not [k for k in result_row(BatchItem("b", "/b.exr", "exr"), {**res, "laplace": {}}, {}) if "corrected" in k]


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


# -- photos as items --------------------------------------------------------------------------------------
def _jpeg(path: Path, when: str | None = None, offset: str | None = None, rgb=None) -> Path:
    """A JPEG (8 x 8 grey unless ``rgb``) with EXIF DateTimeOriginal (tag 36867, 'YYYY:MM:DD HH:MM:SS') and
    OffsetTimeOriginal (36881) when given, written by PIL as a camera writes them (in the Exif sub-IFD)."""
    import numpy as np
    from PIL import Image

    path.parent.mkdir(parents=True, exist_ok=True)
    ex = Image.Exif()
    sub = ex.get_ifd(0x8769)
    if when is not None:
        sub[36867] = when
    if offset is not None:
        sub[36881] = offset
    img = Image.fromarray(np.full((8, 8, 3), 120, np.uint8) if rgb is None else rgb)
    img.save(path, quality=95, exif=ex)
    return path


def test_a_folder_of_frames_is_one_bracket_or_one_photo_each(tmp_path):
    for i, sec in enumerate((0, 1, 3)):  # an auto-bracket: three frames within 3 s
        _jpeg(tmp_path / "day" / "b1030" / f"f{i}.jpg", f"2024:06:01 10:30:0{sec}")
    for i, minute in enumerate((0, 20, 40)):  # a time series: minutes apart
        _jpeg(tmp_path / "day" / "series" / f"s{i}.jpg", f"2024:06:01 11:{minute:02d}:00")
    for i in range(2):  # no EXIF times, marked as a bracket
        _jpeg(tmp_path / "day" / "marked" / f"m{i}.jpg")
    (tmp_path / "day" / "marked" / ".bracket").write_text("")
    for i in range(2):  # no EXIF times, no mark: photos
        _jpeg(tmp_path / "day" / "plain" / f"n{i}.jpg")
    _jpeg(tmp_path / "day" / "loose.jpg", "2024:06:01 12:00:00")

    assert [(i.key, i.kind) for i in B.batch_items([tmp_path / "day" / "b1030"])] == [("b1030", "bracket")]
    assert [(i.key, i.kind) for i in B.batch_items([tmp_path / "day" / "series"])] == [
        ("s0", "photo"), ("s1", "photo"), ("s2", "photo")]
    assert [(i.key, i.kind) for i in B.batch_items([tmp_path / "day" / "marked"])] == [("marked", "bracket")]
    assert [i.kind for i in B.batch_items([tmp_path / "day" / "plain"])] == ["photo", "photo"]
    got = [(i.key, i.kind) for i in B.batch_items([tmp_path / "day"])]  # the subfolders by the same rule
    assert got == [("b1030", "bracket"), ("loose", "photo"), ("marked", "bracket"), ("n0", "photo"), ("n1", "photo"),
                   ("s0", "photo"), ("s1", "photo"), ("s2", "photo")]
    glob_items = B.batch_items([str(tmp_path / "day" / "series" / "s*.jpg")])
    assert [i.key for i in glob_items] == ["s0", "s1", "s2"] and {i.kind for i in glob_items} == {"photo"}


def test_a_photo_time_from_exif_its_offset_a_zone_or_the_times_file(tmp_path):
    a = _jpeg(tmp_path / "a.jpg", "2024:06:01 10:00:00", "+05:30")
    b = _jpeg(tmp_path / "b.jpg", "2024:01:15 10:00:00")
    c = _jpeg(tmp_path / "c.jpg")
    for i in range(3):  # a bracket whose frames are not in time order by name
        _jpeg(tmp_path / "br" / f"f{i}.jpg", f"2024:06:01 09:00:0{5 - i}")
    item = {p.stem: B.BatchItem(p.stem, str(p), "photo") for p in (a, b, c)}
    bracket = B.BatchItem("br", str(tmp_path / "br"), "bracket")
    assert B.photo_time(item["a"], None, "Europe/Berlin") == ("2024-06-01T10:00:00+05:30", "exif")  # EXIF's offset wins
    assert B.photo_time(item["b"], None, "Europe/Berlin") == ("2024-01-15T10:00:00+01:00", "exif+zone")  # winter time
    assert B.photo_time(item["b"], None, "-4") == ("2024-01-15T10:00:00-04:00", "exif+zone")
    assert B.photo_time(bracket, None, "+02:00") == ("2024-06-01T09:00:03+02:00", "exif+zone")  # its first frame
    with pytest.raises(ValueError, match=r"^photo .*b\.jpg: EXIF DateTimeOriginal 2024-01-15T10:00:00 has no UTC offset"):
        B.photo_time(item["b"])
    with pytest.raises(ValueError, match=r"^photo .*c\.jpg: no time: no EXIF DateTimeOriginal, and no row in --times$"):
        B.photo_time(item["c"], None, "UTC")

    csv = tmp_path / "times.csv"
    csv.write_text("file,time\n# a comment\nc.jpg,2024-06-01T12:00:00Z\nsub/a.jpg,2024-06-01T13:00:00 Europe/Berlin\n"
                   "b.jpg,2024-06-01T08:00:00\n")
    t = B.read_times(csv)
    assert B.photo_time(item["c"], t) == ("2024-06-01T12:00:00+00:00", "times")
    assert B.photo_time(item["a"], t) == ("2024-06-01T13:00:00+02:00", "times")  # by name: the row wins over EXIF
    assert B.photo_time(item["b"], t, "+01:00") == ("2024-06-01T08:00:00+01:00", "times")
    with pytest.raises(ValueError, match="in --times has no UTC offset"):
        B.photo_time(item["b"], t)
    csv.write_text("c.jpg,2024-06-01T12:00:00Z\nb.jpg,yesterday\n")
    with pytest.raises(B.BatchError, match=r"times\.csv line 2: cannot parse time 'yesterday'"):
        B.read_times(csv)
    with pytest.raises(B.BatchError, match="--photo-timezone Mars/Olympus"):
        B.check_photo_timezone("Mars/Olympus")


@pytest.fixture(scope="module")
def photo_day(tmp_path_factory):
    """Three 64 x 64 sRGB JPEGs of the earth sky at Munich, 20 min apart (EXIF DateTimeOriginal without an offset),
    one copy without EXIF, and the camera file of the equidistant lens that took them."""
    import numpy as np
    import torch

    from skyfit.camera import FisheyeCamera
    from skyfit.camera.srgb import srgb_encode

    d = tmp_path_factory.mktemp("photos")
    cam = FisheyeCamera(64, projection="equidistant", radius=30)
    atm = skyfit.load_atmosphere("earth")
    for i, hm in enumerate(("10:00", "10:20", "10:40")):
        sky = skyfit.render(atm, cam, time=f"2024-06-01T{hm}:00+02:00", location=(48.1, 11.6, 500), accuracy="de=1")
        rgb = np.nan_to_num(sky.rgb.numpy())
        rgb = np.clip(rgb / np.percentile(rgb[sky.valid.numpy()], 99) * 0.8, 0, 1)
        code = (srgb_encode(torch.as_tensor(rgb)).numpy() * 255).round().astype(np.uint8)
        _jpeg(d / "day" / f"sky{i}.jpg", f"2024:06:01 {hm}:00", rgb=code)
        if i == 0:
            _jpeg(d / "day" / "untimed.jpg", rgb=code)
    (d / "camera.yaml").write_text("projection: equidistant\ncx: 31.5\ncy: 31.5\nradius_px: 30.0\nup_azimuth_deg: 0.0\n"
                                   "tilt_deg: [0.0, 0.0]\n")
    return d


PHOTO_FLAGS = ["--orders", "1", "--integrator", "gauss:samples=8", "--view-samples", "4", "--max-iter", "5",
               "--adam-steps", "0"]


def test_a_batch_of_photos_times_from_exif_one_row_each(photo_day, cluster, tmp_path, capsys):
    """The photos fitted as `skyfit fit PHOTO` fits them (cheap settings), the untimed one failing alone; a warm
    start passes each photo's aerosol on; the table holds RESULT.json's values; --smooth adds its columns."""
    out = tmp_path / "out"
    rc, so, se = _run(["batch", photo_day / "day", "--out", out, "--location", "48.1,11.6,500", "--photo-timezone",
                       "Europe/Berlin", "--camera", photo_day / "camera.yaml", "--scheduler", cluster.scheduler_address,
                       "--warm-start", "previous", "--smooth", "0.2", *PHOTO_FLAGS, "--json", "--no-progress"], capsys)
    assert rc == 0, se
    s = json.loads(so)
    assert (s["items"], s["ok"], s["failed"]) == (4, 3, 1)
    df = pd.read_csv(out / "results.csv")
    assert list(df["item"]) == ["sky0", "sky1", "sky2", "untimed"] and set(df["kind"]) == {"photo"}
    bad = df.set_index("item").loc["untimed"]
    assert bad["status"] == (f"photo {photo_day / 'day' / 'untimed.jpg'}: no time: no EXIF DateTimeOriginal, "
                             "and no row in --times")
    assert not (out / "untimed").exists()
    ok = df[df["status"] == "ok"]
    assert list(ok["time"]) == ["2024-06-01T10:00:00+02:00", "2024-06-01T10:20:00+02:00", "2024-06-01T10:40:00+02:00"]
    assert set(ok["time_source"]) == {"exif+zone"}
    for _, row in ok.iterrows():
        res = json.loads((out / row["item"] / "RESULT.json").read_text())
        a = res["aerosol"]
        assert res["time"] == row["time"] and res["batch"]["time_source"] == "exif+zone"
        for col, key in (("mie_aod_550", "aod_550"), ("mie_angstrom_alpha", "angstrom_alpha"), ("mie_g", "g")):
            assert row[col] == pytest.approx(a[key], rel=1e-12)
            if a["sigma"][key] is not None:
                # RESULT.json keeps 12 digits of laplace.sigma
                assert row[f"sigma_{col}"] == pytest.approx(a["sigma"][key], rel=1e-9, abs=1e-300)
        assert row["rmse_rel"] == pytest.approx(res["metrics"]["rmse_rel"], rel=1e-12)
        assert row["camera_up_azimuth_deg"] == pytest.approx(res["camera"]["up_azimuth_deg"], rel=1e-12)
        assert row["camera_projection"] == "equidistant" and row["pixels_used"] == res["pixels"]["used"]
        assert res["settings"]["max_iter"] == 5 and res["settings"]["orders"] == 1  # the flags reached the photo fit
    r0, r1 = (json.loads((out / k / "RESULT.json").read_text()) for k in ("sky0", "sky1"))
    # one worker, two threads: chains [sky0, sky1] and [sky2]; sky1 starts from sky0's aerosol, not its camera nuisances
    assert {k: r1["settings"]["initial"][k] for k in ("mie_aod_550", "mie_angstrom_alpha", "mie_g")} == \
        {k: r0["parameters"][k] for k in ("mie_aod_550", "mie_angstrom_alpha", "mie_g")}
    assert "exposure" not in r1["settings"]["initial"]
    assert r1["batch"]["warm_start_from"] == str(photo_day / "day" / "sky0.jpg")
    for n in ("aod_550", "angstrom_alpha", "g"):
        assert ok[f"{n}_smooth"].notna().all() and (ok[f"sigma_{n}_smooth"] > 0).all(), n
    assert (out / "timeseries.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


@pytest.mark.parametrize("case", ["no location", "zone", "smooth", "smooth name", "times file", "camera"])
def test_cli_photo_batch_bad_input_is_one_line_and_exit_2(case, tmp_path, capsys):
    photo = _jpeg(tmp_path / "p.jpg", "2024:06:01 10:00:00", "+02:00")
    out = tmp_path / "out"
    args = ["batch", photo, "--out", out, "--location", "48.1,11.6"]
    extra, expect = {"no location": ([], "give --location"),
                     "zone": (["--photo-timezone", "Mars/Olympus"], "--photo-timezone Mars/Olympus"),
                     "smooth": (["--smooth", "-1"], "--smooth: aod_550 must be > 0"),
                     "smooth name": (["--smooth", "aod=0.1"], "--smooth: unknown series 'aod'"),
                     "times file": (["--times", tmp_path / "none.csv"], "none.csv: cannot read it"),
                     "camera": (["--camera", tmp_path / "none.yaml"], "camera file")}[case]
    if case == "no location":
        args = args[:-2]
    rc, so, se = _run(args + extra, capsys)
    assert rc == 2
    assert se.count("\n") == 1 and se.startswith("skyfit: error: ") and expect in se, se
    assert so == "" and not out.exists()


# -- the smoothing pass ------------------------------------------------------------------------------------
def _series(seed=3, n=36, outlier=14):
    """A smooth truth of (log AOD, alpha, g) every 10 min, Gaussian noise of the stated sigma, and one outlier."""
    import numpy as np

    rng = np.random.default_rng(seed)
    t = np.arange(n) * 600.0
    h = t / 3600.0
    truth = np.stack([np.log(0.12 + 0.04 * np.sin(h / 1.5)), 1.3 + 0.2 * np.cos(h / 2.0), 0.72 + 0.01 * h], 1)
    sd = np.array([0.08, 0.12, 0.02])
    y = truth + rng.normal(size=truth.shape) * sd
    y[outlier] += np.array([1.2, -0.9, 0.15])  # a cloudy frame: far off in every quantity
    cov = np.broadcast_to(np.diag(sd ** 2), (n, 3, 3)).copy()
    return t, truth, y, cov, sd


def test_block_tridiagonal_solve_equals_the_dense_inverse():
    import numpy as np

    rng = np.random.default_rng(0)
    T, K = 7, 3
    A = np.stack([m @ m.T + 2 * np.eye(K) for m in rng.normal(size=(T, K, K))])
    Bm = 0.3 * rng.normal(size=(T - 1, K, K))
    H = np.zeros((T * K, T * K))
    for t in range(T):
        H[t * K:(t + 1) * K, t * K:(t + 1) * K] = A[t]
    for t in range(T - 1):
        H[t * K:(t + 1) * K, (t + 1) * K:(t + 2) * K] = Bm[t]
        H[(t + 1) * K:(t + 2) * K, t * K:(t + 1) * K] = Bm[t].T
    b = rng.normal(size=(T, K))
    x, S = B._block_tridiagonal_solve(A, Bm, b)
    Hi = np.linalg.inv(H)  # numpy's dense LU: independent of the block recursion
    torch_close(x.ravel(), np.linalg.solve(H, b.ravel()), 1e-12)
    torch_close(S, np.stack([Hi[t * K:(t + 1) * K, t * K:(t + 1) * K] for t in range(T)]), 1e-12)


def torch_close(a, b, tol):
    """torch.testing.assert_close on numpy arrays (shapes must match: no broadcasting)."""
    import numpy as np
    import torch

    torch.testing.assert_close(torch.as_tensor(np.array(a)), torch.as_tensor(np.array(b)), rtol=tol, atol=tol)


def test_smoothing_is_closer_to_the_truth_and_down_weights_the_outlier():
    import numpy as np

    t, truth, y, cov, sd = _series()
    sm = B.smooth_series(t, y, cov, [0.1, 0.1, 0.02])
    raw_err = np.sqrt(((y - truth) ** 2).mean(0))
    sm_err = np.sqrt(((sm.mean - truth) ** 2).mean(0))
    assert (sm_err < 0.5 * raw_err).all(), (raw_err, sm_err)
    assert sm.weight[14] < 0.1 and np.median(np.delete(sm.weight, 14)) > 0.8
    assert abs(sm.mean[14, 0] - truth[14, 0]) < 2 * sd[0]  # the cloudy frame did not throw the series
    cover = np.abs(sm.mean - truth) < 2 * sm.sd  # the band: about 95 % of the truth inside +-2 sd
    assert cover.mean() > 0.85
    gauss = B.smooth_series(t, y, cov, [0.1, 0.1, 0.02], nu=None)  # without the Student-t weights it is pulled
    assert abs(gauss.mean[14, 0] - truth[14, 0]) > abs(sm.mean[14, 0] - truth[14, 0])


def test_smoothing_limits_raw_values_and_the_weighted_mean():
    import numpy as np

    t, truth, y, cov, sd = _series()
    y[5] = np.nan  # a failed item
    raw = B.smooth_series(t, y, cov, np.inf)
    keep = np.isfinite(y).all(1)
    torch_close(raw.mean[keep], y[keep], 1e-9)
    torch_close(raw.sd[keep], np.broadcast_to(sd, y[keep].shape), 1e-9)
    assert np.isnan(raw.mean[5]).all()  # nothing ties a failed item to the others without a walk
    flat = B.smooth_series(t, y, cov, 1e-6, nu=None)
    w = 1.0 / sd ** 2  # inverse-variance weighted mean of each quantity over the measured items
    mean = (y[keep] * w).sum(0) / (w * keep.sum())
    torch_close(flat.mean, np.broadcast_to(mean, y.shape), 1e-4)  # a walk of 1e-6 / sqrt(h) over 6 h: ~1e-5 left
    torch_close(flat.sd[0], sd / np.sqrt(keep.sum()), 1e-3)
    robust = B.smooth_series(t, y, cov, 1e-6)  # with the weights: still one constant
    assert np.ptp(robust.mean, axis=0).max() < 1e-5


def test_smooth_table_columns_log_aod_and_failed_items(tmp_path):
    import numpy as np

    t, truth, y, cov, sd = _series(n=12, outlier=4)
    times = pd.Timestamp("2024-06-01T10:00:00+02:00") + pd.to_timedelta(t, unit="s")
    df = pd.DataFrame({"item": [f"p{i}" for i in range(12)], "status": ["ok"] * 12,
                       "time": [x.isoformat() for x in times], "free": "mie_aod_550,mie_angstrom_alpha,mie_g,exposure",
                       "mie_aod_550": np.exp(y[:, 0]), "sigma_mie_aod_550": np.exp(y[:, 0]) * sd[0],
                       "mie_angstrom_alpha": y[:, 1], "sigma_mie_angstrom_alpha": sd[1], "mie_g": y[:, 2],
                       "sigma_mie_g": 0.0, "rmse_rel": 0.05})  # g's sigma 0: a Hessian that was not positive definite
    df.loc[7, ["status", "mie_aod_550", "mie_angstrom_alpha", "mie_g"]] = ["RuntimeError: diverged", np.nan, np.nan, np.nan]
    out = B.smooth_table(df, np.inf)
    ok = out["status"] == "ok"
    torch_close(out.loc[ok, "aod_550_smooth"].to_numpy(), df.loc[ok, "mie_aod_550"].to_numpy(), 1e-9)
    torch_close(out.loc[ok, "sigma_aod_550_smooth"].to_numpy(), df.loc[ok, "sigma_mie_aod_550"].to_numpy(), 1e-9)
    assert np.isnan(out.loc[7, "aod_550_smooth"]) and np.isnan(out.loc[7, "smooth_weight"])
    d = np.diff(y[ok.to_numpy(), 2])  # no item has a sigma of g: the robust scatter of consecutive values
    fallback = 1.4826 * np.median(np.abs(d - np.median(d))) / np.sqrt(2)
    torch_close(out.loc[ok, "sigma_g_smooth"].to_numpy(), np.full(int(ok.sum()), fallback), 1e-9)
    sm = B.smooth_table(df, {"aod_550": 0.1, "angstrom_alpha": 0.1})
    assert sm.attrs["smooth"]["series"] == ["aod_550", "angstrom_alpha"] and "g_smooth" not in sm
    assert np.isfinite(sm.loc[7, "aod_550_smooth"]) and sm.loc[7, "aod_550_smooth"] > 0  # a failed item: interpolated
    assert sm.loc[4, "smooth_weight"] < 0.2
    df.loc[4, "rmse_rel"] = 0.5  # ten times the batch's misfit: its covariance x 100 (Gaussian: no Student-t weight)
    gauss = B.smooth_table(df, {"aod_550": 0.1}, nu=None)["smooth_weight"]
    assert gauss[4] == pytest.approx(0.01, rel=1e-12) and (gauss.drop([4, 7]) == 1.0).all()
    assert B.plot_timeseries(sm, tmp_path / "ts.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_photo_places_from_exif_gps_when_no_location(tmp_path):
    from PIL import Image
    from _files import exif_when_where

    import numpy as np

    img = Image.fromarray(np.full((8, 8, 3), 120, np.uint8))
    img.save(tmp_path / "gps.jpg", exif=exif_when_where("2024:06:01 10:00:00", "+02:00", -33.8752, 151.2014, -12.0))
    img.save(tmp_path / "nogps.jpg", exif=exif_when_where("2024:06:01 10:05:00", "+02:00"))
    items = {it.key: it for it in B.batch_items([tmp_path / "gps.jpg", tmp_path / "nogps.jpg"])}
    args, fail = B._photo_arguments(list(items.values()), {}, {}, None, None, None, None, None, False, None)
    lat, lon, elev = (float(v) for v in args[next(k for k in args)]["location"].split(","))
    assert (lat, lon, elev) == (pytest.approx(-33.8752, abs=1e-6), pytest.approx(151.2014, abs=1e-6), -12.0)
    assert list(fail.values()) == [f"photo {items[next(iter(fail))].path}: no place: no EXIF GPS position, and no --location"]
    with pytest.raises(B.BatchError, match="none has an EXIF GPS position"):
        B._photo_arguments([items[k] for k in fail], {}, {}, None, None, None, None, None, False, None)
