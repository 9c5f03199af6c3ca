"""The layering rules of docs/architecture.md, checked on the source: lower layers never
import higher ones, and pymavlink has exactly one importer."""

from __future__ import annotations

import ast
from pathlib import Path

PACKAGE = Path(__file__).resolve().parent.parent / "sitl_bridge"

# Lowest first; modules in one group may import each other.
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
    ("rl",),
    ("bench", "commands", "cli", "__main__"),
)
RANK = {name: rank for rank, group in enumerate(LAYERS) for name in group}


def _imports(path: Path) -> list[str]:
    names: list[str] = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names.append(node.module)
        elif isinstance(node, ast.Import):
            names.extend(alias.name for alias in node.names)
    return names


def _sources() -> list[tuple[str, Path]]:
    """(top-level module name inside the package, file) for every module but __init__.py."""
    return [(path.relative_to(PACKAGE).parts[0].removesuffix(".py"), path)
            for path in sorted(PACKAGE.rglob("*.py")) if path != PACKAGE / "__init__.py"]


def test_every_module_has_a_layer() -> None:
    assert {top for top, _ in _sources()} <= set(RANK)


def test_lower_layers_never_import_higher_ones() -> None:
    violations = []
    for top, path in _sources():
        for module in _imports(path):
            parts = module.split(".")
            if parts[0] == "sitl_bridge" and len(parts) > 1 and RANK.get(parts[1], -1) > RANK[top]:
                violations.append(f"{path.relative_to(PACKAGE.parent)} imports {module}")
    assert not violations, "\n".join(violations)


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
