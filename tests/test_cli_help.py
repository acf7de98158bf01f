"""The command line's self-description: every flag of every subcommand has a help text that shows its
default, ``skyfit --version`` prints the installed version, and the renamed fit setting still reads."""
from __future__ import annotations

import argparse
import importlib.metadata
import re

import pytest

import skyfit
from skyfit.cli import build_parser, main
from skyfit.fit.problem import FitError, fit_settings

PARSER = build_parser()
SUB = next(a for a in PARSER._actions if isinstance(a, argparse._SubParsersAction))


def _expanded(parser: argparse.ArgumentParser, action: argparse.Action) -> str:
    """The help text as ``--help`` prints it (``%(default)s`` and the like filled in), on one line."""
    return " ".join(parser._get_formatter()._expand_help(action).split())


def _shows(help_text: str, default) -> bool:
    """Whether ``help_text`` says ``default ...`` with this value (numbers compared as numbers: 1e-3 == 0.001)."""
    for m in re.finditer(r"default:?\s+([^\s,;)]+)", help_text):
        token = m.group(1).rstrip(".")
        if token == str(default):
            return True
        if isinstance(default, (int, float)):
            try:
                if float(token) == float(default):
                    return True
            except ValueError:
                pass
    return False


def _walk():
    for name, sub in SUB.choices.items():
        for action in sub._actions:
            if not isinstance(action, argparse._HelpAction):
                yield name, sub, action


def test_walk_sees_every_command():
    assert {"render", "fit", "evaluate", "sample", "envmap", "export-lut", "demo", "batch", "bench",
            "calibrate-integrator"} <= set(SUB.choices)
    assert sum(1 for _ in _walk()) > 150


def test_every_flag_has_help_and_shows_its_default():
    missing, unshown = [], []
    for name, sub, action in _walk():
        flag = action.option_strings[0] if action.option_strings else action.dest
        if action.help == argparse.SUPPRESS:  # a hidden deprecated alias: another, visible flag has its dest
            if not any(a is not action and a.dest == action.dest and a.help != argparse.SUPPRESS for a in sub._actions):
                missing.append(f"{name} {flag} (hidden, and no visible flag for {action.dest})")
            continue
        if not action.help or not action.help.strip():
            missing.append(f"{name} {flag}")
            continue
        d = action.default
        if d is None or action.nargs == 0 or isinstance(d, bool):  # switches: the default is "off"
            continue
        if not _shows(_expanded(sub, action), d):
            unshown.append(f"{name} {flag} (default {d!r}): {_expanded(sub, action)}")
    assert not missing, "flags without help:\n" + "\n".join(missing)
    assert not unshown, "defaults not shown in the help:\n" + "\n".join(unshown)


def test_the_checker_can_fail():
    p = argparse.ArgumentParser()
    a = p.add_argument("--size", type=int, default=256, help="image size (default 128)")
    b = p.add_argument("--tol", type=float, default=1e-3, help="tolerance (default 1e-3)")
    c = p.add_argument("--rule", default="gauss", help="rule (default %(default)s)")
    assert not _shows(_expanded(p, a), a.default)
    assert _shows(_expanded(p, b), b.default) and _shows(_expanded(p, c), c.default)


def test_version(capsys):
    with pytest.raises(SystemExit) as e:
        main(["--version"])
    assert e.value.code == 0
    out = capsys.readouterr().out.strip()
    assert out == f"skyfit {importlib.metadata.version('skyfit')}"
    assert re.fullmatch(r"skyfit \d+\.\d+\.\d+\S*", out)
    assert importlib.metadata.version("skyfit") == skyfit.__version__  # pyproject reads __version__


def test_license_metadata():
    md = importlib.metadata.metadata("skyfit")
    assert md["License-Expression"] == "Apache-2.0"
    assert "LICENSE" in (md.get_all("License-File") or [])


def test_sun_mask_setting_and_its_old_name():
    assert fit_settings({"sun_mask_deg": 4.0}).sun_mask_deg == 4.0
    old = fit_settings({"sun_disc_deg": 5.0})  # configs and RESULT.json files written before the rename
    assert old.sun_mask_deg == 5.0 and old.sun_disc_deg == 5.0
    assert fit_settings(None, {"sun_mask_deg": 6.0}).sun_mask_deg == 6.0
    with pytest.raises(FitError, match="fit.sun_disc_deg must be in"):  # reported under the name the user wrote
        fit_settings({"sun_disc_deg": -5})
    with pytest.raises(FitError, match="old name"):
        fit_settings({"sun_disc_deg": 5.0, "sun_mask_deg": 4.0})
    sub = SUB.choices["fit"]
    assert sub.parse_args(["d.exr", "--config", "earth", "--out", "r.json", "--sun-mask", "3"]).sun_mask == 3.0
