"""The package layout's dependency rules, read from the source (an AST scan of every import, deferred ones
included), so that they hold as the code grows. DEVELOPERS.md states the same rules in words."""
from __future__ import annotations

import ast
import functools
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SUBPACKAGES = ("io", "camera", "lidar", "solvers", "simulation", "analysis", "pipeline")
PIPELINE = {"estimators.calibration", "estimators.rig_calibration"}  # and estimators.pipeline's stages
CLI = "estimators.cli"  # a package: the parser, the commands, the printing

# What each subpackage may never import (prefix match on the imported module).
FORBIDDEN = {
    "io": ("estimators.solvers", "estimators.analysis", "estimators.simulation", "estimators.calibration",
           "estimators.cli"),
    "camera": ("estimators.io", "estimators.solvers", "estimators.analysis", "estimators.simulation",
               "estimators.calibration", "estimators.cli"),
    "lidar": ("estimators.io", "estimators.solvers", "estimators.analysis", "estimators.simulation",
              "estimators.calibration", "estimators.cli"),
    "solvers": ("estimators.io", "estimators.analysis", "estimators.calibration", "estimators.cli"),
    "simulation": ("estimators.solvers", "estimators.analysis", "estimators.calibration", "estimators.cli"),
    "analysis": ("estimators.cli",),
    "pipeline": ("estimators.calibration", "estimators.rig_calibration", "estimators.cli"),
}
# The upward edges: ``RigResult.report()`` is a convenience of the result record that draws the report; it
# imports it inside the method, so importing the pipeline never loads ``analysis``. The engine asks the layout
# analysis for the next pose of its weakest pair in the same way.
DEFERRED_UPWARD = {("estimators.pipeline.rig_result", "estimators.analysis.rig_report"),
                   ("estimators.rig_calibration", "estimators.analysis.rig_layout")}


def module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def imports_of(path: Path) -> list[tuple[str, bool]]:
    """(imported module, at module level?) for every import in ``path``; relative imports resolved. For
    ``from pkg import name`` both ``pkg`` and ``pkg.name`` are listed (``name`` may be a module)."""
    tree = ast.parse(path.read_text(), filename=str(path))
    me = module_name(path)
    package = me if path.name == "__init__.py" else me.rpartition(".")[0]
    top_level = {id(node) for node in tree.body}
    for node in tree.body:  # imports under a module-level ``if``/``try`` still run at import time
        if isinstance(node, (ast.If, ast.Try)):
            top_level |= {id(n) for n in ast.walk(node)}
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found += [(a.name, id(node) in top_level) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[:len(base) - (node.level - 1)]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module
            found.append((target, id(node) in top_level))
            found += [(f"{target}.{a.name}", id(node) in top_level) for a in node.names]
    return found


def sources(folder: str) -> list[Path]:
    return sorted((ROOT / folder).rglob("*.py"))


def existing(module: str) -> bool:
    path = ROOT / module.replace(".", "/")
    return path.with_suffix(".py").exists() or (path / "__init__.py").exists()


@functools.lru_cache(maxsize=1)
def edges() -> tuple[tuple[str, str, bool], ...]:
    """(importer, imported, at module level) for every import between modules of the project (read once per test
    process: the scan takes seconds)."""
    return tuple((module_name(p), target, level) for folder in ("estimators", "geometry") for p in sources(folder)
            for target, level in imports_of(p)
            if target.split(".")[0] in ("estimators", "geometry") and existing(target))


def subpackage(module: str) -> str | None:
    parts = module.split(".")
    return parts[1] if len(parts) > 2 and parts[0] == "estimators" and parts[1] in SUBPACKAGES else None


def test_the_scan_sees_the_imports():
    """The scanner resolves relative imports (a rule over an empty edge list could never fail)."""
    found = edges()
    assert ("estimators.calibration", "estimators.solvers.refinement", True) in found
    assert ("estimators.pipeline.rig_result", "estimators.analysis.rig_report", False) in found
    assert ("estimators.solvers.posterior", "estimators.solvers.refinement", True) in found
    assert ("estimators.analysis.study", "estimators.calibration", False) in found
    assert len(found) > 100


def test_every_module_lives_in_a_subpackage_or_is_a_top_level_role():
    top = {module_name(p) for p in (ROOT / "estimators").glob("*.py")}
    # The pipelines (a camera-LiDAR pair, a rig), the per-frame records, the errors and the API; the CLI is a
    # package of its own.
    assert top == {"estimators", "estimators.__main__", "estimators.calibration",
                   "estimators.rig_calibration", "estimators.measurements", "estimators.errors"}
    assert (ROOT / "estimators" / "cli" / "__init__.py").is_file()
    for sub in SUBPACKAGES:
        init = ROOT / "estimators" / sub / "__init__.py"
        doc = ast.get_docstring(ast.parse(init.read_text()))
        assert doc and "May import" in doc, f"{init} needs a docstring saying what it holds and may import"


def test_geometry_imports_nothing_from_estimators():
    bad = [(a, b) for a, b, _ in edges() if a.startswith("geometry") and b.startswith("estimators")]
    assert not bad


@pytest.mark.parametrize("sub", SUBPACKAGES)
def test_subpackage_imports_only_downwards(sub):
    bad = [(a, b) for a, b, _ in edges() if subpackage(a) == sub and b.startswith(FORBIDDEN[sub])]
    assert not bad, f"{sub} must not import these: {bad}"


def test_nothing_imports_the_cli():
    bad = [(a, b) for a, b, _ in edges() if (b == CLI or b.startswith(CLI + "."))
           and not (a == "estimators.__main__" or a == CLI or a.startswith(CLI + "."))]
    assert not bad


def test_records_and_errors_import_no_subpackage():
    bad = [(a, b) for a, b, _ in edges() if a in ("estimators.errors", "estimators.measurements")
           and subpackage(b)]
    assert not bad


def in_pipeline(module: str) -> bool:
    return module in PIPELINE or subpackage(module) == "pipeline"


def test_the_pipeline_reaches_analysis_only_through_the_deferred_report():
    upward = {(a, b) for a, b, _ in edges() if in_pipeline(a) and subpackage(b) == "analysis"}
    assert upward <= DEFERRED_UPWARD
    assert not [(a, b) for a, b, level in edges() if (a, b) in DEFERRED_UPWARD and level]


def test_no_import_cycle_between_subpackages():
    graph = {s: set() for s in SUBPACKAGES}
    for a, b, _ in edges():
        if subpackage(a) and subpackage(b) and subpackage(a) != subpackage(b) and (a, b) not in DEFERRED_UPWARD:
            graph[subpackage(a)].add(subpackage(b))
    state: dict[str, int] = {}

    def visit(node, path):
        state[node] = 1
        for nxt in graph[node]:
            assert state.get(nxt) != 1, f"import cycle: {' -> '.join(path + [nxt])}"
            if nxt not in state:
                visit(nxt, path + [nxt])
        state[node] = 2

    for s in SUBPACKAGES:
        if s not in state:
            visit(s, [s])
    assert graph["analysis"] and graph["solvers"]  # the graph is not empty: the check above has edges to walk


def test_no_import_cycle_between_modules():
    """No two modules import each other, directly or round a loop, deferred imports included (a deferred import
    hides a loop from the interpreter, not from a reader). A package importing its own submodules is not a
    loop, nor are the deferred upward edges above (a result record drawing its report)."""
    graph: dict[str, set[str]] = {}
    for a, b, _ in edges():
        if a != b and not b.startswith(a + ".") and (a, b) not in DEFERRED_UPWARD:
            graph.setdefault(a, set()).add(b)
    order: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    loops = []

    def visit(node):  # Tarjan's strongly connected components
        order[node] = low[node] = len(order)
        stack.append(node)
        for nxt in graph.get(node, ()):
            if nxt not in order:
                visit(nxt)
                low[node] = min(low[node], low[nxt])
            elif nxt in stack:
                low[node] = min(low[node], order[nxt])
        if low[node] == order[node]:
            component = []
            while not component or component[-1] != node:
                component.append(stack.pop())
            if len(component) > 1:
                loops.append(sorted(component))

    for node in list(graph):
        if node not in order:
            visit(node)
    assert len(graph) > 30 and not loops, loops


def test_the_module_map_names_every_module_once():
    """DEVELOPERS.md's module map has a line per module of ``geometry`` and ``estimators`` (``__main__`` and the
    subpackages' ``__init__`` aside) and names no module that does not exist."""
    import re

    text = (ROOT / "DEVELOPERS.md").read_text()
    listed = re.findall(r"^\| `((?:estimators|geometry)/[\w/]+\.py)` \|", text, flags=re.M)
    assert len(listed) == len(set(listed)), sorted(p for p in listed if listed.count(p) > 1)
    mapped_packages = ("cli", "estimators")  # packages whose __init__ holds code of its own
    modules = {str(p.relative_to(ROOT)) for folder in ("estimators", "geometry") for p in sources(folder)
               if p.name != "__main__.py" and (p.name != "__init__.py" or p.parent.name in mapped_packages)}
    assert sorted(modules - set(listed)) == [], "modules missing from DEVELOPERS.md's module map"
    assert sorted(set(listed) - modules) == [], "DEVELOPERS.md's module map names modules that do not exist"


def test_every_line_of_code_fits_in_120_columns():
    """The code's width: no line of the package, tests or benchmarks is longer."""
    long = [f"{p.relative_to(ROOT)}:{k}" for folder in ("estimators", "geometry", "tests", "benchmarks")
            for p in sorted((ROOT / folder).rglob("*.py"))
            for k, line in enumerate(p.read_text().splitlines(), 1) if len(line) > 120]
    assert not long, f"lines over 120 columns: {long}"
