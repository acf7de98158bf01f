"""Bad input generated from the CLI's own grammar (issue 18; docs/reliability.md, "The fuzz suite").

``skyfit.cli.build_parser()`` is walked: for every command, every flag and every file argument,
values of the kinds a careless or unlucky user gives (wrong type, empty, NaN, infinite, out of
range, huge, an unknown choice, a value to a switch; missing, empty, corrupt and wrong-kind
files; outputs that cannot be written) are put into an otherwise valid, cheap command line. Each
case runs in-process and must end as CONTRACT.md says: exit status 2, exactly one stderr line
naming the problem (the flag, the value or the file), no traceback, and nothing new beside the
target. Every case fails before any rendering or fitting, so the whole file runs in well under a
minute on 2 cores (its count and time are in docs/reliability.md).
"""
from __future__ import annotations

import argparse
import json
import math
import re
from pathlib import Path

import numpy as np
import pytest

from skyfit.cli import FLAG_RANGES, build_parser, main
from skyfit.io import read_exr, write_exr

# -- the grammar -------------------------------------------------------------------------------
PARSER = build_parser()
COMMANDS: dict[str, argparse.ArgumentParser] = next(
    a for a in PARSER._actions if isinstance(a, argparse._SubParsersAction)).choices

BASE: dict[str, list[str]] = {
    # a valid, cheap command line per command: {in} is the shared inputs folder, {w} the case's own folder
    "render": ["render", "earth", "--out", "{w}/x.exr", "--sun-zenith", "30", "--size", "8", "--view-samples", "4",
               "--wavelengths", "450:650:100"],
    "demo": ["demo", "--quick", "--out", "{w}/demo"],
    "fit": ["fit", "{in}/sky.exr", "--config", "earth", "--out", "{w}/R.json", "--no-plots", "--integrator", "chapman",
            "--view-samples", "4", "--starts", "1", "--max-iter", "3", "--adam-steps", "0"],
    "evaluate": ["evaluate", "{in}/RESULT.json", "{in}/sky.exr", "--json"],
    "sample": ["sample", "{in}/sky.exr", "--config", "earth", "--init", "{in}/RESULT.json", "--out", "{w}/s",
               "--walkers", "4", "--steps", "2", "--no-plots"],
    "batch": ["batch", "{in}/sky.exr", "--config", "earth", "--out", "{w}/batch"],
    "bench": ["bench", "--quick", "--out", "{w}/bench"],
    "calibrate-integrator": ["calibrate-integrator", "earth", "--quick", "--out", "{w}/c.json"],
    "export-lut": ["export-lut", "{in}/RESULT.json", "--out", "{w}/lut", "--orders", "1", "--table-sizes", "4,4,4,2"],
    "envmap": ["envmap", "earth", "--out", "{w}/e.exr", "--size", "8", "--sun-zenith", "30", "--orders", "1"],
    # every case fails before its photo is read: the photo need not exist
    "calibrate-camera": ["calibrate-camera", "{in}/photo.jpg", "--time", "2024-06-01T10:00:00+02:00", "--location", "48.1,11.6",
                         "--out", "{w}/camera.yaml", "--config", "earth"],
}
"""Commands whose flags are checked beyond argparse only when every check runs before the work: batch
(a Dask cluster) gets only the cases refused before it starts (types, ranges, outputs)."""
EARLY_ONLY = {"batch"}

EXTRA_RANGES: dict[tuple[str, str], tuple[float, float, str]] = {
    ("render", "size"): (2, 8192, "[]"), ("envmap", "size"): (2, 8192, "[]"),
}
"""Ranges a command checks itself (beyond skyfit.cli.FLAG_RANGES)."""
HUGE: set[tuple[str, str]] = {
    ("render", "view_samples"), ("render", "orders"), ("fit", "view_samples"), ("fit", "starts"), ("fit", "max_iter"),
    ("fit", "adam_steps"), ("sample", "walkers"), ("sample", "steps"), ("sample", "view_samples"),
    ("export-lut", "orders"), ("envmap", "orders"),
}
"""Sizes for which 10^9 cannot fit in memory or would run for days: refused by the estimates (skyfit.resources)."""

STRINGS: dict[str, list[str]] = {
    # dest: values that are wrong for every command that has the flag
    "wavelengths": ["", "blue", "700:400:10", "400:700:0", "100:200:10", "550,550", "400:700:0.0001", "nan:700:10",
                    "400:inf:10"],
    "integrator": ["", "rk45", "taylor:zzz=3", "trapezoid:samples", "taylor:a=abc", "trapezoid:samples=-3",
                   "gauss:samples=1000000000"],
    "table_sizes": ["8,31,8", "a,b,c,d", "0,0,0,0", "8,31,8,4"],
    "free": ["bogus", "mie_g,mie_g", "mie_g,ozone_colum"],
    "per_observation": ["bogus", "mie_g"],
    "loss": ["l1", "huber:delta=abc"],
    "rule": ["simpsons"],
    "accuracy": ["banana", "de=-1", "rel=abc", "de=nan"],
    "location": ["abc", "91,0", "0,400", "nan,0", "1,2,3,4"],
    "time": ["yesterday", "2013-13-45T00:00:00-04:00", "2013-05-27T09:30:00"],
    "kb_coeffs": ["1,2,3", "a,b,c,d"],
    "center": ["1", "a,b", "nan,0"],
    "tilt": ["1", "95,0", "a,b"],
    "device": ["bogus", "cuda:x", ""],
    "sun_zenith": ["abc", "nan", "200"],
}
STRING_SKIP = {("render", "time"), ("envmap", "time")}
"""(command, dest) pairs whose STRINGS need another flag to be wrong (``--time`` needs ``--location``): given as pairs below."""
PAIRS: list[tuple[str, list[str], str]] = [
    # (command, flags, a word the message must hold); "-FLAG" first drops FLAG and its value from BASE
    ("render", ["--sun-zenith", "30", "--time", "2013-05-27T09:30:00-04:00", "--location", "1,2"], "not both"),
    ("render", ["-" "--sun-zenith", "--time", "yesterday", "--location", "1,2"], "yesterday"),
    ("render", ["-" "--sun-zenith", "--time", "2013-05-27T09:30:00-04:00"], "--location"),
    ("render", ["--orders", "2", "--table-sizes", "1000000000,128,32,8"], "1000000000x128x32x8 texels"),
    ("envmap", ["--orders", "2", "--table-sizes", "1000000000,128,32,8"], "1000000000x128x32x8 texels"),
    ("envmap", ["--size", "8193"], "--size"),
    ("render", ["--focal", "10", "--radius", "4"], "--focal"),
    ("render", ["--kb-coeffs", "0,0,0,0"], "--kb-coeffs"),
    ("envmap", ["-" "--sun-zenith", "--time", "2013-05-27T09:30:00", "--location", "1,2"], "UTC offset"),
    ("bench", ["--study", "integrators", "--frontier-out", "{w}/f.json"], "--frontier-out"),
    ("export-lut", ["--layout", "bruneton2017", "--format", "npz"], "--format"),
    ("export-lut", ["--precision", "f16"], "--precision"),
    ("fit", ["--orders", "2", "--multiple", "bruneton", "--integrator", "gauss:samples=0"], "samples"),
    ("fit", ["--free", "mie_beta_550,mie_aod_550"], "mie_aod_550"),
    # the photo flags on an EXR with skyfit's header (not a photo)
    ("fit", ["--camera", "{w}/camera.yaml"], "--camera"),
    ("fit", ["--mask", "{w}/mask.png"], "--mask"),
    ("fit", ["--exposures", "0.01,0.1"], "--exposures"),
    ("fit", ["--response", "srgb"], "--response"),
    ("batch", ["--smooth", "abc"], "--smooth"),
]

# -- files -------------------------------------------------------------------------------------
FILES: dict[str, str] = {
    # kind: how it is made (by _make_inputs)
    "missing": "a path that does not exist",
    "folder": "an empty folder",
    "unreadable": "a file whose read fails (/proc/self/mem: EIO, also for root, whom permissions do not stop)",
    "empty": "an empty file",
    "garbage": "random bytes",
    "yaml_list": "YAML that is not a mapping",
    "exr": "a valid fisheye EXR (the wrong kind for a config or a result)",
    "json_other": "JSON that is not a RESULT.json",
    "result_nan": "a RESULT.json with a NaN parameter",
    "result_range": "a RESULT.json with a negative scale height",
    "exr_zero": "an EXR whose pixels are all 0",
    "exr_truncated": "half an EXR",
    "exr_bare": "an EXR without skyfit metadata",
    "exr_nan": "an EXR with a NaN pixel",
}
SLOTS: list[tuple[str, str, list[str]]] = [
    # (command, how the file is given: "pos:N" replaces the N-th positional, "--flag" replaces a flag's value, kinds)
    ("render", "pos:0", ["missing", "folder", "unreadable", "empty", "garbage", "yaml_list", "exr"]),
    ("calibrate-integrator", "pos:0", ["missing", "folder", "unreadable", "empty", "garbage", "yaml_list", "exr"]),
    ("fit", "--config", ["missing", "folder", "unreadable", "empty", "garbage", "yaml_list", "exr"]),
    ("fit", "pos:0", ["missing", "folder", "unreadable", "empty", "garbage", "yaml_list", "json_other", "exr_zero", "exr_truncated",
                      "exr_bare", "exr_nan"]),
    ("evaluate", "pos:0", ["missing", "folder", "unreadable", "empty", "garbage", "yaml_list", "exr", "json_other", "result_nan",
                           "result_range"]),
    ("evaluate", "pos:1", ["missing", "folder", "unreadable", "empty", "garbage", "json_other", "exr_zero", "exr_truncated",
                           "exr_bare", "exr_nan"]),
    ("sample", "--init", ["missing", "folder", "unreadable", "empty", "garbage", "exr", "json_other", "result_nan", "result_range"]),
    ("sample", "--config", ["missing", "unreadable", "garbage", "yaml_list", "folder"]),
    ("sample", "pos:0", ["missing", "unreadable", "empty", "garbage", "exr_zero", "exr_truncated"]),
    ("export-lut", "pos:0", ["missing", "folder", "unreadable", "empty", "garbage", "exr", "json_other", "result_nan", "result_range"]),
    ("envmap", "pos:0", ["missing", "folder", "unreadable", "garbage", "result_nan", "result_range"]),
    ("calibrate-camera", "--config", ["missing", "folder", "unreadable", "empty", "garbage", "yaml_list", "exr"]),
]
SUFFIX = {"missing": "nothing.yaml", "folder": "afolder", "unreadable": "mem", "empty": "empty.yaml", "garbage": "garbage.yaml",
          "yaml_list": "list.yaml", "exr": "sky.exr", "json_other": "other.json", "result_nan": "nan.json",
          "result_range": "range.json", "exr_zero": "zero.exr", "exr_truncated": "trunc.exr", "exr_bare": "bare.exr",
          "exr_nan": "nanpix.exr"}
# where a result is expected the corrupt files are .json, where DATA is expected .exr
JSON_SLOTS = {("evaluate", "pos:0"), ("sample", "--init"), ("export-lut", "pos:0"), ("envmap", "pos:0")}
DATA_SLOTS = {("fit", "pos:0"), ("evaluate", "pos:1"), ("sample", "pos:0")}

OUTS: list[tuple[str, str, list[str]]] = [
    # (command, flag, kinds): existing folder where a file goes, existing file where a folder goes, a path under a
    # file, a place no one can write (/proc), the wrong suffix
    ("render", "--out", ["dir", "under_file", "proc", "suffix:.png"]),
    ("fit", "--out", ["dir", "under_file", "proc", "suffix:.txt"]),
    ("calibrate-integrator", "--out", ["dir", "under_file", "proc", "suffix:.txt"]),
    ("envmap", "--out", ["dir", "under_file", "proc", "suffix:.png"]),
    ("sample", "--out", ["file", "under_file", "proc"]),
    ("bench", "--out", ["file", "under_file", "proc"]),
    ("demo", "--out", ["file", "under_file", "proc"]),
    ("export-lut", "--out", ["file", "under_file", "proc"]),
    ("batch", "--out", ["file", "under_file", "proc"]),
    ("bench", "--frontier-out", ["dir", "under_file", "proc"]),
    ("calibrate-camera", "--out", ["dir", "under_file", "proc", "suffix:.txt"]),
]


def _opt(action: argparse.Action) -> str:
    return action.option_strings[0]


def _range_values(kind: type, lo: float, hi: float, brackets: str) -> list[tuple[str, str]]:
    out = []
    if lo != -math.inf:
        v = (lo - 1 if kind is int else lo - 0.5) if brackets[0] == "[" else lo
        out.append(("below", str(int(v)) if kind is int else repr(float(v))))
    if hi != math.inf:
        v = (hi + 1 if kind is int else hi + 0.5) if brackets[1] == "]" else hi
        out.append(("above", str(int(v)) if kind is int else repr(float(v))))
    return out


def generate() -> list[tuple[str, str, list[str], list[str], dict]]:
    """Every case: (id, command, extra argv, needles (one must be in the message), setup)."""
    cases = []
    for cmd, sub in COMMANDS.items():
        assert cmd in BASE, f"a new command {cmd!r}: give it a cheap valid command line in BASE"
        early = cmd in EARLY_ONLY
        for a in sub._actions:
            if not a.option_strings or isinstance(a, argparse._HelpAction):
                continue
            flag, dest = _opt(a), a.dest
            if isinstance(a, (argparse._StoreTrueAction, argparse._StoreFalseAction, argparse.BooleanOptionalAction)):
                cases.append((f"{cmd}{flag}=value-to-a-switch", cmd, [f"{flag}=yes"], [flag], {}))
                continue
            if a.choices is not None:
                cases.append((f"{cmd}{flag}-unknown-choice", cmd, [flag, "bogus"], [flag], {}))
                continue
            if a.type in (int, float):
                bad = [("wrong-type", "abc"), ("empty", "")]
                bad += [("fraction", "1.5")] if a.type is int else [("nan", "nan"), ("inf", "inf"), ("-inf", "-inf")]
                rng = FLAG_RANGES.get(dest) or EXTRA_RANGES.get((cmd, dest))
                if rng is not None:
                    bad += _range_values(a.type, *rng)
                if (cmd, dest) in HUGE:
                    bad.append(("huge", "1000000000"))
                for label, v in bad:
                    cases.append((f"{cmd}{flag}-{label}", cmd, [flag, v], [flag, v] if label == "huge" else [flag], {}))
                continue
            if early or (cmd, dest) in STRING_SKIP or dest not in STRINGS:
                continue
            for i, v in enumerate(STRINGS[dest]):
                needles = [flag, flag.lstrip("-").replace("-", "_")] + ([v] if v else []) + (
                    ["1000000000 inner samples"] if "1000000000" in v else [])
                cases.append((f"{cmd}{flag}-bad{i}", cmd, [flag, v], needles, {}))
    for i, (cmd, extra, needle) in enumerate(PAIRS):
        cases.append((f"{cmd}-combination{i}", cmd, extra, [needle], {}))
    for cmd, slot, kinds in SLOTS:
        for kind in kinds:
            cases.append((f"{cmd}-{slot}-{kind}", cmd, [], ["{file}"], {"file": (slot, kind)}))
    for cmd, flag, kinds in OUTS:
        for kind in kinds:
            cases.append((f"{cmd}{flag}-{kind}", cmd, [], ["{target}"], {"out": (flag, kind)}))
    return cases


CASES = generate()
RESOURCE_DEST = {"wavelengths", "table_sizes", "integrator"}


# -- fixtures ----------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    """The valid inputs of BASE and the bad files of FILES, made once."""
    d = tmp_path_factory.mktemp("fuzz_inputs")
    assert main(["render", "earth", "--out", str(d / "sky.exr"), "--size", "10", "--sun-zenith", "40", "--sun-azimuth",
                 "120", "--wavelengths", "450:650:100", "--integrator", "chapman", "--view-samples", "4", "--spectral",
                 "--dtype", "float64"]) == 0
    assert main(["fit", str(d / "sky.exr"), "--config", "earth", "--out", str(d / "RESULT.json"), "--free",
                 "mie_g,exposure", "--no-plots", "--integrator", "chapman", "--view-samples", "4", "--starts", "1",
                 "--max-iter", "3", "--adam-steps", "0"]) == 0
    bad = d / "bad"
    bad.mkdir()
    (bad / "afolder").mkdir()
    chans, meta = read_exr(d / "sky.exr")
    res = json.loads((d / "RESULT.json").read_text())
    for ext in (".yaml", ".json", ".exr"):
        (bad / f"empty{ext}").write_bytes(b"")
        (bad / f"garbage{ext}").write_bytes(np.random.default_rng(0).bytes(512))
        (bad / f"list{ext}").write_text("- a\n- list\n")
        (bad / f"other{ext}").write_text(json.dumps({"hello": "world"}))
    write_exr(bad / "sky.exr", chans, meta)
    write_exr(bad / "zero.exr", {k: np.zeros_like(v) for k, v in chans.items()}, meta)
    (bad / "trunc.exr").write_bytes((d / "sky.exr").read_bytes()[:300])
    write_exr(bad / "bare.exr", chans)
    nanpix = {k: v.copy() for k, v in chans.items()}
    nanpix["L550"][5, 5] = np.nan
    write_exr(bad / "nanpix.exr", nanpix, meta)
    (bad / "nan.json").write_text(json.dumps({**res, "parameters": {**res["parameters"], "mie_g": float("nan")}}))
    (bad / "range.json").write_text(json.dumps({**res, "parameters": {**res["parameters"], "mie_scale_height": -1200.0}}))
    return d


def _file_for(slot: tuple[str, str], cmd: str, bad: Path) -> Path:
    where, kind = slot
    if kind == "unreadable":
        return Path("/proc/self/mem")
    name = SUFFIX[kind]
    if (cmd, where) in JSON_SLOTS and name.endswith(".yaml"):
        name = name[:-5] + ".json"
    if (cmd, where) in DATA_SLOTS and name.endswith((".yaml", ".json")) and kind in ("empty", "garbage"):
        name = name.rsplit(".", 1)[0] + ".exr"
    return bad / name


def _listing(folder: Path) -> list[str]:
    return sorted(str(p.relative_to(folder)) for p in folder.rglob("*"))


@pytest.mark.parametrize("case", CASES, ids=[c[0] for c in CASES])
def test_bad_input_is_one_line_exit_2_and_writes_nothing(case, inputs, tmp_path, capsys):
    case_id, cmd, extra, needles, setup = case
    w = tmp_path / "w"
    w.mkdir()
    argv = [a.format(**{"in": inputs, "w": w}) for a in BASE[cmd]]
    extra = [a.format(w=w) for a in extra]
    for drop in [a[1:] for a in extra if a.startswith("---")]:
        i = argv.index(drop)
        del argv[i:i + 2]
    extra = [a for a in extra if not a.startswith("---")]
    fill = {}
    if "file" in setup:
        where, kind = setup["file"]
        f = _file_for(setup["file"], cmd, inputs / "bad")
        if where.startswith("pos:"):  # the N-th positional: BASE puts them right after the command
            argv[1 + int(where[4:])] = str(f)
        else:
            argv[argv.index(where) + 1] = str(f)
        fill["file"] = f.name
    if "out" in setup:
        flag, kind = setup["out"]
        if flag in argv:
            target = Path(argv[argv.index(flag) + 1])
        else:
            target = w / "frontier.json"
            argv += [flag, str(target)]
            if cmd == "bench":
                argv += ["--study", "trade"]
        if kind == "dir":
            target.mkdir()
        elif kind == "file":
            target.write_text("keep me")
        elif kind == "under_file":
            (w / "afile").write_text("keep me")
            target = w / "afile" / target.name
        elif kind == "proc":
            target = Path("/proc") / f"skyfit_fuzz_{target.name}"
        else:  # a wrong suffix
            target = target.with_suffix(kind.split(":")[1])
        argv[argv.index(flag) + 1] = str(target)
        fill["target"] = target.name
    before = _listing(w)
    try:
        rc = main(argv + extra)
    except SystemExit as e:  # argparse
        rc = e.code
    out, err = capsys.readouterr()
    lines = err.strip().splitlines()
    assert rc == 2, f"{case_id}: exit {rc}\n{err}"
    assert len(lines) == 1 and "Traceback" not in err, f"{case_id}: {err}"
    assert re.match(r"skyfit( [a-z-]+)?: error: ", lines[0]), lines[0]  # argparse names the subcommand
    wanted = [n.format(**fill) for n in needles]
    assert any(n in lines[0] for n in wanted), f"{case_id}: none of {wanted} in {lines[0]!r}"
    assert _listing(w) == before, f"{case_id}: new files {sorted(set(_listing(w)) - set(before))}"


UNCOVERED = {("batch", f) for f in ("--accuracy", "--config", "--device", "--free", "--integrator", "--location", "--loss",
                                     "--per-observation", "--rule", "--scheduler", "--wavelengths")}
UNCOVERED |= {("batch", f) for f in ("--photo-timezone", "--times", "--mask", "--camera", "--response")}
"""(command, flag) pairs no case varies: batch checks these once its Dask cluster runs (EARLY_ONLY); the photo
flags only when there are photo items (tests/test_batch.py covers their bad values)."""


def test_the_fuzz_suite_covers_every_command_and_flag():
    assert len(CASES) >= 300
    varied = {(c[1], a.split("=")[0]) for c in CASES for a in c[2] if a.startswith("--")}
    varied |= {(cmd, where) for cmd, where, _ in SLOTS} | {(cmd, flag) for cmd, flag, _ in OUTS}
    missing = {(cmd, _opt(a)) for cmd, sub in COMMANDS.items() for a in sub._actions
               if a.option_strings and not isinstance(a, argparse._HelpAction)} - varied
    assert missing == UNCOVERED
