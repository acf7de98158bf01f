"""Imports run one way (docs/architecture.md): no cycle, nothing below the CLI imports it, layers in order.

The checker (tests/_layers.py) reads the imports with ast. It is run on the package as it is, and on
copies of the package with a back-import injected, each of which it must reject.
"""
from __future__ import annotations

import shutil
from pathlib import Path

import pytest

import _layers as L

PACKAGE = Path(__file__).resolve().parents[1] / "skyfit"


def test_every_module_has_a_layer():
    for mod in L.modules(PACKAGE):
        L.layer_of(mod)  # raises for a module docs/architecture.md does not place


def test_no_import_against_the_layer_order():
    assert L.layer_violations(L.imports(PACKAGE)) == []


def test_no_import_cycle():
    assert L.cycles(L.imports(PACKAGE)) == []


def test_nothing_below_the_cli_imports_it():
    graph = L.imports(PACKAGE)
    assert sorted(a for a, targets in graph.items() if "skyfit.cli" in targets) == []


def test_architecture_doc_lists_the_layers():
    doc = (PACKAGE.parent / "docs" / "architecture.md").read_text()
    positions = [doc.find(f"`{name}`") for name, _ in L.LAYERS]
    assert all(p >= 0 for p in positions), [name for (name, _), p in zip(L.LAYERS, positions) if p < 0]
    assert positions == sorted(positions), "docs/architecture.md lists the layers in another order"


INJECTED = [
    # (module file, line appended inside a function, what the checker must report)
    ("atmosphere/params.py", "from ..fit.model import SkyModel", "skyfit.atmosphere.params (atmosphere) -> skyfit.fit.model (fit)"),
    ("fit/data.py", "from ..cli import parse_wavelengths", "skyfit.fit.data (fit) -> skyfit.cli (cli)"),
    ("render/colour.py", "from ..camera import FisheyeCamera", "skyfit.render.colour (render) -> skyfit.camera (camera)"),
    ("transmittance/quadrature.py", "import skyfit.scattering.single", "(transmittance) -> skyfit.scattering.single (scattering)"),
]


@pytest.mark.parametrize("path, line, expected", INJECTED, ids=[i[0] for i in INJECTED])
def test_checker_rejects_an_injected_back_import(tmp_path, path, line, expected):
    copy = tmp_path / "skyfit"
    shutil.copytree(PACKAGE, copy, ignore=shutil.ignore_patterns("__pycache__", "data", "configs"))
    f = copy / path
    f.write_text(f.read_text() + f"\n\ndef _injected():\n    {line}\n")
    problems = L.layer_violations(L.imports(copy))
    assert any(expected in p for p in problems), problems


def test_checker_finds_a_cycle_within_a_layer(tmp_path):
    copy = tmp_path / "skyfit"
    shutil.copytree(PACKAGE, copy, ignore=shutil.ignore_patterns("__pycache__", "data", "configs"))
    (copy / "fit" / "losses.py").write_text((copy / "fit" / "losses.py").read_text()
                                            + "\n\ndef _injected():\n    from .optimise import fit\n")
    assert L.layer_violations(L.imports(copy)) == []  # same layer: allowed by the order ...
    found = L.cycles(L.imports(copy))
    assert any({"skyfit.fit.losses", "skyfit.fit.optimise"} <= set(c) for c in found), found  # ... but a circle


def test_checker_resolves_relative_and_absolute_imports(tmp_path):
    pkg = tmp_path / "skyfit"
    (pkg / "a").mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "a" / "__init__.py").write_text("from .b import x\n")
    (pkg / "a" / "b.py").write_text("import skyfit.c\nfrom .. import c\nx = 1\n")
    (pkg / "c.py").write_text("def f():\n    from skyfit.a.b import x\n")
    g = L.imports(pkg)
    assert g == {"skyfit": set(), "skyfit.a": {"skyfit.a.b"}, "skyfit.a.b": {"skyfit.c"}, "skyfit.c": {"skyfit.a.b"}}
    assert L.cycles(g) == [["skyfit.a.b", "skyfit.c"]]
    assert L.in_function_imports(pkg) == 1
