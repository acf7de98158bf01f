"""The import-layer checker of docs/architecture.md: reads the package's imports with ast (no third-party tool).

Every ``import`` and ``from ... import`` in a module counts, at module level or inside a function
(an import inside a function still ties the two modules together). ``from pkg import name``
is an edge to ``pkg.name`` when that is a module, else to ``pkg``.
"""
from __future__ import annotations

import ast
from pathlib import Path

LAYERS: tuple[tuple[str, tuple[str, ...]], ...] = (
    ("base", ("skyfit.geometry", "skyfit.quadrature", "skyfit.resources")),
    ("atmosphere", ("skyfit.atmosphere",)),
    ("transmittance", ("skyfit.transmittance",)),
    ("scattering", ("skyfit.scattering",)),
    ("render", ("skyfit.render",)),
    ("camera", ("skyfit.camera",)),
    ("io", ("skyfit.io",)),
    ("fit", ("skyfit.fit",)),
    ("export", ("skyfit.export",)),
    ("api", ("skyfit.api", "skyfit.batch", "skyfit")),
    ("tools", ("skyfit.tools",)),
    ("cli", ("skyfit.cli", "skyfit.__main__")),
)
"""Layers, lowest first, as docs/architecture.md lists them: each is matched by the longest module-name prefix.
The package root ``skyfit`` (its ``__init__``) is the API's facade."""


def modules(package_dir: Path) -> dict[str, Path]:
    """Dotted module name -> file, for every .py file of the package (a package is its ``__init__``)."""
    root = package_dir.parent
    out = {}
    for p in sorted(package_dir.rglob("*.py")):
        parts = list(p.relative_to(root).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        out[".".join(parts)] = p
    return out


def imports(package_dir: Path) -> dict[str, set[str]]:
    """Module -> the package's modules it imports (anywhere in its body)."""
    mods = modules(package_dir)
    top = package_dir.name
    graph: dict[str, set[str]] = {m: set() for m in mods}
    for mod, path in mods.items():
        pkg = mod if path.name == "__init__.py" else mod.rpartition(".")[0]
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                if node.level:
                    base = pkg.split(".")[: len(pkg.split(".")) - (node.level - 1)]
                    target = ".".join(base + ([node.module] if node.module else []))
                else:
                    target = node.module or ""
                targets = [f"{target}.{a.name}" if f"{target}.{a.name}" in mods else target for a in node.names]
            else:
                continue
            for t in targets:
                while t and t not in mods and "." in t:  # import skyfit.fit.data.x -> the module skyfit.fit.data
                    t = t.rpartition(".")[0]
                if t in mods and (t == top or t.startswith(top + ".")) and t != mod:
                    graph[mod].add(t)
    return graph


def layer_of(mod: str) -> int:
    """Index in :data:`LAYERS` of the longest prefix matching ``mod``; ValueError for a module in no layer."""
    best, best_len = None, -1
    for i, (_, prefixes) in enumerate(LAYERS):
        for pre in prefixes:
            if (mod == pre or mod.startswith(pre + ".")) and len(pre) > best_len:
                best, best_len = i, len(pre)
    if best is None:
        raise ValueError(f"module {mod} is in no layer of docs/architecture.md")
    return best


def layer_violations(graph: dict[str, set[str]]) -> list[str]:
    """'a -> b' for each import of a higher layer, and for any import of skyfit.cli below the CLI."""
    out = []
    for a, targets in sorted(graph.items()):
        for b in sorted(targets):
            la, lb = layer_of(a), layer_of(b)
            if lb > la:
                out.append(f"{a} ({LAYERS[la][0]}) -> {b} ({LAYERS[lb][0]})")
    return out


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan's algorithm), each sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    out: list[list[str]] = []
    counter = [0]

    def visit(v: str) -> None:  # recursion depth is bounded by the package's ~80 modules
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in graph.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


class _LazyImports(ast.NodeVisitor):
    def __init__(self):
        self.depth = self.count = 0

    def visit_FunctionDef(self, node):
        self.depth += 1
        self.generic_visit(node)
        self.depth -= 1

    visit_AsyncFunctionDef = visit_FunctionDef

    def visit_Import(self, node):
        self.count += self.depth > 0

    visit_ImportFrom = visit_Import


def in_function_imports(package_dir: Path) -> int:
    """Number of import statements inside function bodies (lazy imports) in the package."""
    v = _LazyImports()
    for path in modules(package_dir).values():
        v.visit(ast.parse(path.read_text(), str(path)))
    return v.count
