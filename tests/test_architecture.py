"""The import picture of ``src/rtsgt`` (docs/architecture.md#layers), checked on every run.

From the source text alone (``ast``, nothing imported): no import cycle between modules; no
import inside a function except the optional extras (and the command line's lazy imports,
which keep its start fast, tests/test_cli_startup.py); no private name imported from another
module; each package imports only packages of its own layer or below; the numeric core free
of ``io``, ``report``, ``app`` and ``cli``; ``cli`` imported by nothing but ``cli``. What the
code still does against a rule is listed below, each with the reason, and must be there.
The checker itself is tested on a small package written by the test.
"""

from __future__ import annotations

import ast
from dataclasses import dataclass
from pathlib import Path

from _paths import REPO

SRC = REPO / "src"

#: The packages (top-level modules) of rtsgt by layer, lowest first: a module may import its
#: own layer and those below it (docs/architecture.md#layers).
LAYERS: tuple[tuple[str, ...], ...] = (
    ("rtsgt", "errors", "parallel", "allocator", "choices", "stats", "measurement",
     "geometry"),
    ("types",),
    ("pose", "noise", "filtering"),
    ("interpolation",),
    ("options", "calibration", "shared"),
    ("checks", "clocks", "joint", "deployment", "record"),
    ("stages",),
    ("pipeline", "evaluation"),
    ("planning",),
    ("io", "report", "simulation"),
    ("app", "batch"),
    ("cli",),
)
#: The numeric core, which never imports these (STYLE.md: reading files, plotting and the
#: command line sit around it).
CORE = ("evaluation", "pose", "interpolation", "noise", "calibration", "measurement",
        "geometry", "checks", "filtering", "shared", "joint")
EDGES = ("io", "report", "app", "cli")
#: Optional extras, imported where they are used so that rtsgt runs without them.
EXTRAS = ("plotly", "rosbags", "dask", "distributed", "evo")

#: Known departures, (importer, imported), each with its reason; the tests fail when one is
#: gone too, so that this list stays the truth.
LAYER_EXCEPTIONS: set[tuple[str, str]] = set()
PRIVATE_EXCEPTIONS: set[tuple[str, str, str]] = set()
#: Imports inside a function outside ``cli`` beyond the extras: matplotlib (through the
#: report's figures) only when a report is asked for, so that ``rtsgt run`` starts without
#: it (tests/test_cli_startup.py).
LAZY_EXCEPTIONS = {
    ("rtsgt.app.run", "rtsgt.report.html"),
}
#: Known import cycles between modules.
CYCLE_EXCEPTIONS: set[frozenset[str]] = set()


@dataclass(frozen=True)
class Import:
    """One imported name: the importing ``module`` and ``line``; ``target``, the imported
    module (the rtsgt module it resolves to, else the dotted name as written); ``name``, the
    name taken from it (None for ``import x``); ``lazy`` inside a function; ``typing`` under
    ``if TYPE_CHECKING``."""

    module: str
    line: int
    target: str
    name: str | None
    lazy: bool
    typing: bool


def find_modules(src: Path) -> dict[str, Path]:
    """The modules of the packages under ``src`` by dotted name (a package by its own)."""
    found = {}
    for path in sorted(src.rglob("*.py")):
        parts = list(path.relative_to(src).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts.pop()
        found[".".join(parts)] = path
    return found


def find_imports(modules: dict[str, Path]) -> list[Import]:
    """Every imported name of ``modules`` (:func:`find_modules`)."""
    out: list[Import] = []
    for module, path in modules.items():
        package = module if path.name == "__init__.py" else module.rpartition(".")[0]
        _visit(ast.parse(path.read_text(encoding="utf-8")), module, package, modules,
               False, False, out)
    return out


def _visit(node, module, package, modules, lazy, typing, out) -> None:
    for child in ast.iter_child_nodes(node):
        if isinstance(child, ast.Import):
            out += [Import(module, child.lineno, a.name, None, lazy, typing) for a in child.names]
        elif isinstance(child, ast.ImportFrom):
            base = child.module or ""
            if child.level:
                up = package.split(".")[:len(package.split(".")) - child.level + 1]
                base = ".".join(up + ([base] if base else []))
            for a in child.names:
                sub = f"{base}.{a.name}"
                target = sub if sub in modules else base
                name = None if sub in modules else a.name
                out.append(Import(module, child.lineno, target, name, lazy, typing))
        inner_lazy = lazy or isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef))
        inner_typing = typing or (isinstance(child, ast.If)
                                  and "TYPE_CHECKING" in ast.unparse(child.test))
        _visit(child, module, package, modules, inner_lazy, inner_typing, out)


def package_of(module: str) -> str:
    """``rtsgt.io.config`` -> ``io``; ``rtsgt`` -> ``rtsgt``."""
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else parts[0]


def cycles(imports: list[Import], modules: dict[str, Path]) -> list[frozenset[str]]:
    """The import cycles between modules (strongly connected components of more than one
    module, or a module importing itself) of the imports run at import time or later (not
    those under ``TYPE_CHECKING``)."""
    graph: dict[str, set[str]] = {m: set() for m in modules}
    for imp in imports:
        if imp.target in modules and not imp.typing:
            graph[imp.module].add(imp.target)
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    found: list[frozenset[str]] = []
    for root in graph:  # Tarjan's algorithm, iteratively
        if root in index:
            continue
        work = [(root, iter(sorted(graph[root])))]
        index[root] = low[root] = len(index)
        stack.append(root)
        while work:
            v, it = work[-1]
            w = next(it, None)
            if w is None:
                work.pop()
                if work:
                    low[work[-1][0]] = min(low[work[-1][0]], low[v])
                if low[v] == index[v]:
                    comp = stack[stack.index(v):]
                    del stack[stack.index(v):]
                    if len(comp) > 1 or v in graph[v]:
                        found.append(frozenset(comp))
            elif w not in index:
                index[w] = low[w] = len(index)
                stack.append(w)
                work.append((w, iter(sorted(graph[w]))))
            elif w in stack:
                low[v] = min(low[v], index[w])
    return found


def layer_breaks(imports: list[Import], modules: dict[str, Path],
                 layers: tuple[tuple[str, ...], ...]) -> set[tuple[str, str]]:
    """(importer, imported module) of each import of a package from a higher layer, of the
    numeric core's imports of the edges, and of imports of ``cli`` from outside it."""
    level = {p: i for i, layer in enumerate(layers) for p in layer}
    out = set()
    for imp in imports:
        if imp.target not in modules:
            continue
        mine, theirs = package_of(imp.module), package_of(imp.target)
        if (level[theirs] > level[mine] or mine in CORE and theirs in EDGES
                or theirs == "cli" and mine != "cli"):
            out.add((imp.module, imp.target))
    return out


def private_imports(imports: list[Import]) -> set[tuple[str, str, str]]:
    """(importer, module, name) of each private name (``_x``, not ``__x__``) imported from
    another module."""
    return {(i.module, i.target, i.name) for i in imports
            if i.name and i.name.startswith("_") and not i.name.endswith("__")
            and i.target != i.module}


def lazy_imports(imports: list[Import]) -> set[tuple[str, str]]:
    """(importer, imported) of each import inside a function, other than the extras and
    those of the command line (``rtsgt.cli``, which imports the library when a command runs
    so that ``rtsgt --help`` starts at once)."""
    return {(i.module, i.target) for i in imports
            if i.lazy and i.target.split(".")[0] not in EXTRAS
            and package_of(i.module) != "cli"}


MODULES = find_modules(SRC)
IMPORTS = find_imports(MODULES)


def test_every_package_has_a_layer():
    packages = {package_of(m) for m in MODULES if m.startswith("rtsgt")}
    assert packages == {p for layer in LAYERS for p in layer}


def test_no_import_cycle():
    assert set(cycles(IMPORTS, MODULES)) == CYCLE_EXCEPTIONS


def test_no_import_from_a_higher_layer_core_free_of_the_edges_cli_imported_by_nothing():
    assert layer_breaks(IMPORTS, MODULES, LAYERS) == LAYER_EXCEPTIONS


def test_no_private_name_imported_across_modules():
    assert private_imports(IMPORTS) == PRIVATE_EXCEPTIONS


def test_no_import_inside_a_function_but_the_extras():
    assert lazy_imports(IMPORTS) == LAZY_EXCEPTIONS


def test_the_checker_finds_each_kind_of_break(tmp_path):
    """A small package with one break of each rule: each found, and nothing else."""
    files = {
        "rtsgt/__init__.py": "",
        "rtsgt/geometry/__init__.py": "from rtsgt.geometry.a import f\n",
        "rtsgt/geometry/a.py": "from rtsgt.geometry.b import _g\n\ndef f():\n    pass\n",
        "rtsgt/geometry/b.py": ("from rtsgt.geometry import a\nfrom rtsgt.io.x import h\n"
                                "def _g():\n    import numpy\n    import dask\n"),
        "rtsgt/io/__init__.py": "",
        "rtsgt/io/x.py": ("from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n"
                          "    from rtsgt.cli import c\ndef h():\n    pass\n"),
        "rtsgt/cli/__init__.py": "", "rtsgt/cli/c.py": "def main():\n    from .. import io\n",
    }
    for rel, text in files.items():
        (tmp_path / rel).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / rel).write_text(text)
    modules = find_modules(tmp_path)
    imports = find_imports(modules)
    layers = (("rtsgt", "geometry"), ("io",), ("cli",))
    assert cycles(imports, modules) == [frozenset({"rtsgt.geometry.a", "rtsgt.geometry.b"})]
    assert layer_breaks(imports, modules, layers) == {
        ("rtsgt.geometry.b", "rtsgt.io.x"), ("rtsgt.io.x", "rtsgt.cli.c")}
    assert private_imports(imports) == {("rtsgt.geometry.a", "rtsgt.geometry.b", "_g")}
    assert lazy_imports(imports) == {("rtsgt.geometry.b", "numpy")}
    relative = [i for i in imports if i.module == "rtsgt.cli.c"]
    assert [(i.target, i.lazy) for i in relative] == [("rtsgt.io", True)]
