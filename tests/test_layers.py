"""The layers of docs/architecture.md hold in the imports: the contract (schemas) imports no
service code; the shared libraries (services/lib) only the contract and each other, without a
cycle; a service (services/<name>) only the contract, the libraries and itself; the tools
(services/tools) anything below them, and each other only downwards (the registry and the recorder,
then evaluation, then the viewer, then the launcher). Read with `ast`, so an import inside a function counts too."""
from __future__ import annotations

import ast
import shutil
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
TOOL_ORDER = {"registry": 0, "recorder": 1, "evaluation": 2, "viz": 3, "launcher": 4}


def _imports(path: Path, package: list[str]) -> set[str]:
    """The modules a file imports, by absolute name; `package`: the file's package, for relative
    imports (`from ..voxels import grid` in services/lib/tracks.py is services.lib.voxels.grid)."""
    names: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = package[:len(package) - node.level + 1] if node.level else []
            module = ".".join([*base, *([node.module] if node.module else [])])
            names.add(module)
            if node.level or module in ("services", "services.lib", "services.tools"):  # `from services import x`
                names.update(f"{module}.{alias.name}" for alias in node.names)
    return names


def _unit(module: str) -> tuple[str, str] | None:
    """(layer, unit) of a project module: ("schemas", ""), ("lib", package), ("service", name),
    ("tools", package); None for anything else (the standard library, third parties, the
    `services` packages themselves)."""
    parts = module.split(".")
    if parts[0] == "schemas":
        return "schemas", ""
    if parts[0] != "services" or len(parts) < 2:
        return None
    if parts[1] in ("lib", "tools"):
        return (parts[1], parts[2].removesuffix(".py")) if len(parts) > 2 else None
    return "service", parts[1]


def _unit_of_file(root: Path, path: Path) -> tuple[str, str] | None:
    return _unit(".".join(path.relative_to(root).with_suffix("").parts))


def reverse_imports(root: Path) -> list[str]:
    """Every import against the direction under `root` (a tree holding schemas/ and services/),
    and every cycle between library packages, as 'importer -> imported: why' lines."""
    wrong, library_edges = [], set()
    for path in sorted([*(root / "schemas").rglob("*.py"), *(root / "services").rglob("*.py")]):
        own = _unit_of_file(root, path)
        if own is None:
            continue
        parts = list(path.relative_to(root).with_suffix("").parts)
        for module in sorted(_imports(path, parts[:-1])):
            other = _unit(module)
            if other is None or other == own:
                continue
            why = _against(own, other)
            if why:
                wrong.append(f"{path.relative_to(root)} -> {module}: {why}")
            elif own[0] == other[0] == "lib":
                library_edges.add((own[1], other[1]))
    wrong.extend(f"library cycle: {' -> '.join(cycle)}" for cycle in _cycles(library_edges))
    return wrong


def _against(own: tuple[str, str], other: tuple[str, str]) -> str | None:
    rank = {"schemas": 0, "lib": 1, "service": 2, "tools": 3}
    if rank[other[0]] > rank[own[0]]:
        return f"the {own[0]} layer imports the {other[0]} layer above it"
    if own[0] == other[0] == "service":
        return "a service imports another service (share it through services/lib)"
    if own[0] == other[0] == "tools" and TOOL_ORDER.get(other[1], 9) >= TOOL_ORDER.get(own[1], 9):
        return f"tool {own[1]!r} imports tool {other[1]!r}, which is not below it"
    return None


def _cycles(edges: set[tuple[str, str]]) -> list[list[str]]:
    graph: dict[str, set[str]] = {}
    for a, b in edges:
        graph.setdefault(a, set()).add(b)
    found, state = [], {}

    def visit(node: str, trail: list[str]) -> None:
        state[node] = "open"
        for nxt in sorted(graph.get(node, ())):
            if state.get(nxt) == "open":
                found.append(trail[trail.index(nxt):] + [node, nxt] if nxt in trail else [node, nxt])
            elif nxt not in state:
                visit(nxt, trail + [node])
        state[node] = "done"

    for node in sorted(graph):
        if node not in state:
            visit(node, [])
    return found


def test_every_import_goes_down_the_layers():
    assert reverse_imports(ROOT) == []


def test_the_layer_check_sees_a_planted_reverse_import(tmp_path):
    """The check itself: a copy of the tree with one import against the direction of each kind."""
    shutil.copytree(ROOT / "schemas", tmp_path / "schemas", ignore=shutil.ignore_patterns("__pycache__"))
    shutil.copytree(ROOT / "services", tmp_path / "services", ignore=shutil.ignore_patterns("__pycache__"))
    plants = {"services/lib/geometry.py": "from services.lib.lidar import rays",
              "services/lib/voxels/grid.py": "def f():\n    from services.planner import core",
              "services/planner/core.py": "from services.tracker.core import TrackerCore",
              "services/planner/node.py": "from ..job_manager import core",
              "services/tools/recorder/record.py": "from services.tools.launcher import cli",
              "schemas/keys.py": "import services.lib.runtime.clock"}
    for relative, line in plants.items():
        with open(tmp_path / relative, "a") as f:
            f.write("\n" + line + "\n")
    found = "\n".join(reverse_imports(tmp_path))
    assert "services/lib/voxels/grid.py -> services.planner: the lib layer imports the service layer above it" in found
    assert "services/planner/core.py -> services.tracker.core: a service imports another service" in found
    assert "services/planner/node.py -> services.job_manager: a service imports another service" in found  # relative
    assert "services/tools/recorder/record.py -> services.tools.launcher: tool 'recorder' imports tool 'launcher'" in found
    assert "schemas/keys.py -> services.lib.runtime.clock: the schemas layer imports the lib layer" in found
    assert "library cycle: geometry -> lidar -> geometry" in found  # lidar/rays.py imports geometry
