"""The layering rules of docs/architecture.md, checked on the source: lower layers never
import higher ones (inside `rl` too, package by package), no two modules import each other even
through others (relative, function-local and `TYPE_CHECKING` imports included), and pymavlink
has exactly one importer."""

from __future__ import annotations

import ast
from collections.abc import Iterable, Mapping
from pathlib import Path

PACKAGE = Path(__file__).resolve().parent.parent / "sitl_bridge"

# Lowest first; modules in one group may import each other. Inside `rl` each package is a layer.
LAYERS = (
    ("errors", "data_paths", "frames", "jit", "compile_notice", "lifetime", "cores", "mavlink", "mavlink_kernels",
     "ports"),
    ("world",),
    ("physics",),
    ("sensors",),
    ("hil", "autopilot"),
    ("client",),
    ("session",),
    ("envs",),
    ("rl.common",),
    ("rl.learner",),
    ("rl.evaluation",),
    ("rl.training",),
    ("rl.analysis",),
    ("rl.experiments",),
    ("rl",),  # rl/__init__.py: the lazy `policy_from_checkpoint`
    ("bench", "commands", "cli", "__main__"),
)
RANK = {name: rank for rank, group in enumerate(LAYERS) for name in group}


def module_name(path: Path, root: Path = PACKAGE) -> str:
    """Dotted name of a source file (a package's `__init__.py` is the package)."""
    parts = path.relative_to(root.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def imported_names(path: Path, root: Path = PACKAGE) -> list[str]:
    """Every module name a file imports, anywhere in it (module level, inside functions, under
    `if TYPE_CHECKING:`), relative imports made absolute; `from a import b` gives `a` and `a.b`."""
    own = module_name(path, root).split(".")
    package = own if path.name == "__init__.py" else own[:-1]
    names: list[str] = []
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            names.extend(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                base = ".".join(package[: len(package) - node.level + 1] + ([base] if base else []))
            names.append(base)
            names.extend(f"{base}.{alias.name}" for alias in node.names)
    return names


def import_graph(root: Path = PACKAGE) -> dict[str, set[str]]:
    """Module -> the modules of the same package it imports (not its own parent packages)."""
    files = {module_name(path, root): path for path in sorted(root.rglob("*.py"))}
    graph: dict[str, set[str]] = {name: set() for name in files}
    for name, path in files.items():
        for target in imported_names(path, root):
            while target and target not in files:  # `from a import function` -> module a
                target = target.rpartition(".")[0]
            if target and target != name and not name.startswith(target + "."):
                graph[name].add(target)
    return graph


def cycles(graph: Mapping[str, Iterable[str]]) -> list[list[str]]:
    """Strongly connected components of more than one module (Tarjan's algorithm, iterative)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []
    for start in graph:
        if start in index:
            continue
        work = [(start, iter(sorted(graph[start])))]
        index[start] = low[start] = len(index)
        stack.append(start)
        on_stack.add(start)
        while work:
            node, successors = work[-1]
            for succ in successors:
                if succ not in index:
                    index[succ] = low[succ] = len(index)
                    stack.append(succ)
                    on_stack.add(succ)
                    work.append((succ, iter(sorted(graph.get(succ, ())))))
                    break
                if succ in on_stack:
                    low[node] = min(low[node], index[succ])
            else:
                work.pop()
                if work:
                    low[work[-1][0]] = min(low[work[-1][0]], low[node])
                if low[node] == index[node]:
                    component = []
                    while True:
                        member = stack.pop()
                        on_stack.discard(member)
                        component.append(member)
                        if member == node:
                            break
                    if len(component) > 1:
                        found.append(sorted(component))
    return found


def layer(module: str) -> str | None:
    """The layer of a module of the package: its top-level name, inside `rl` its package."""
    parts = module.split(".")[1:]
    if not parts:
        return None
    if parts[0] == "rl" and len(parts) > 1:
        return f"rl.{parts[1]}"
    return parts[0]


def test_every_module_has_a_layer() -> None:
    layers = {layer(name) for name in import_graph()} - {None}
    assert layers <= set(RANK), sorted(layers - set(RANK))


def test_lower_layers_never_import_higher_ones() -> None:
    violations = []
    for name, targets in import_graph().items():
        own = layer(name)
        for target in targets:
            other = layer(target)
            if own is not None and other is not None and RANK[other] > RANK[own]:
                violations.append(f"{name} imports {target}")
    assert not violations, "\n".join(sorted(violations))


def test_no_import_cycles() -> None:
    found = cycles(import_graph())
    assert not found, "\n".join(" <-> ".join(component) for component in found)


def test_the_cycle_finder_finds_a_planted_cycle(tmp_path: Path) -> None:
    """A cycle hidden the usual ways (a relative import, a function-local one, one under
    TYPE_CHECKING) is found; a chain without a way back is not a cycle."""
    pkg = tmp_path / "planted"
    (pkg / "sub").mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "sub" / "__init__.py").write_text("")
    (pkg / "a.py").write_text("from .sub import b\n")
    (pkg / "sub" / "b.py").write_text("def f():\n    from planted.c import g\n    return g\n")
    (pkg / "c.py").write_text("from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from . import a\ng = 1\n")
    (pkg / "d.py").write_text("import planted.a\n")
    graph = import_graph(pkg)
    assert graph["planted.a"] == {"planted.sub.b", "planted.sub"}
    assert cycles(graph) == [["planted.a", "planted.c", "planted.sub.b"]]
    (pkg / "c.py").write_text("g = 1\n")
    assert cycles(import_graph(pkg)) == []
    assert cycles({"x": {"y"}, "y": {"x"}, "z": {"z"}}) == [["x", "y"]]


def _sources() -> list[tuple[str, Path]]:
    """(layer, file) for every module but the package's __init__.py."""
    return [(layer(module_name(path)) or "", path) for path in sorted(PACKAGE.rglob("*.py"))
            if path != PACKAGE / "__init__.py"]


def _imports(path: Path) -> list[str]:
    return imported_names(path)


def test_pymavlink_has_one_importer() -> None:
    importers = {str(path.relative_to(PACKAGE.parent)) for _, path in _sources()
                 if any(m.split(".")[0] == "pymavlink" for m in _imports(path))}
    assert importers == {"sitl_bridge/mavlink.py"}


def test_the_session_only_composes() -> None:
    """session.py keeps only the session, and no module compares the autopilot kind's name
    (kinds are `AutopilotFleet` classes in `autopilot/registry.py`)."""
    assert len((PACKAGE / "session.py").read_text().splitlines()) < 400
    offenders = [str(path.relative_to(PACKAGE.parent)) for _, path in _sources()
                 if "autopilot ==" in path.read_text() and path.name != "registry.py"]
    assert not offenders
