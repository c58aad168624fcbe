"""The import graph of the `redsim` distribution: no circle, and no edge back down the layers.

Every module under redsim/, envs/ (installed as redsim.envs) and trainers/ (redsim.trainers) is
parsed with ``ast``; every import in it, at module level or inside a function, is an edge to
the modules it names (``from a import b`` names ``a.b`` when that is a module, else ``a``). Imports
under ``if TYPE_CHECKING:`` are left out: they never run.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
if not (ROOT / "redsim").is_dir():  # the tests copied beside an installed wheel: no source tree to read
    pytest.skip("needs the source checkout (redsim/, envs/, trainers/)", allow_module_level=True)
FOLDERS = {"redsim": ROOT / "redsim", "redsim.envs": ROOT / "envs", "redsim.trainers": ROOT / "trainers"}
TOP = ("redsim.cli", "redsim.bench", "redsim.benches", "redsim.__main__")
"""The command line (and ``python -m redsim``) and the benchmarks sit on top: nothing else imports them."""
UPPER = ("redsim.envs", "redsim.trainers", *TOP)
"""What the engine never imports."""
FACADE = {("redsim", "redsim.envs")}
"""The one allowed edge up: ``import redsim`` registers the Gymnasium ids (redsim.envs' __init__ only registers
string entry points; no env code or checkpoint is loaded)."""


def _modules() -> dict[str, Path]:
    """Module name -> file, for every module of the distribution."""
    out: dict[str, Path] = {}
    for package, folder in FOLDERS.items():
        for path in sorted(folder.rglob("*.py")):
            parts = list(path.relative_to(folder).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts.pop()
            name = ".".join([package, *parts])
            if package == "redsim" and name.startswith(("redsim.envs", "redsim.trainers")):
                continue  # not a folder of redsim/ in this layout; never shadows envs/ or trainers/
            out[name] = path
    return out


def _within(name: str, prefixes: tuple[str, ...]) -> bool:
    return any(name == p or name.startswith(p + ".") for p in prefixes)


def _imports(name: str, path: Path, modules: dict[str, Path]) -> set[str]:
    """The modules of the distribution that module ``name`` (file ``path``) imports."""
    tree = ast.parse(path.read_text(), str(path))
    skipped: set[int] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
            skipped.update(id(child) for stmt in node.body for child in ast.walk(stmt))
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found: set[str] = set()
    for node in ast.walk(tree):
        if id(node) in skipped:
            continue
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")[: len(package.split(".")) - (node.level - 1)]
                base = ".".join([*anchor, *([base] if base else [])])
            for alias in node.names:
                found.add(f"{base}.{alias.name}" if f"{base}.{alias.name}" in modules else base)
    return {m for m in found if m in modules and m != name}


def _graph() -> dict[str, set[str]]:
    modules = _modules()
    return {name: _imports(name, path, modules) for name, path in modules.items()}


def _cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One import circle as a path [a, b, ..., a], or None."""
    state: dict[str, int] = {}  # 1: on the current path, 2: done
    path: list[str] = []

    def visit(node: str) -> list[str] | None:
        state[node] = 1
        path.append(node)
        for nxt in sorted(graph[node]):
            if state.get(nxt) == 1:
                return [*path[path.index(nxt) :], nxt]
            if nxt not in state and (found := visit(nxt)) is not None:
                return found
        path.pop()
        state[node] = 2
        return None

    for node in sorted(graph):
        if node not in state and (found := visit(node)) is not None:
            return found
    return None


def test_the_graph_sees_the_known_edges() -> None:
    graph = _graph()
    assert {"redsim.subspace", "redsim.metrics", "redsim.integrators", "redsim.trainers.fit"} <= set(graph)
    assert "redsim.subspace" in graph["redsim.trainers.fit"]
    assert "redsim.integrators.reference" in graph["redsim.metrics.energy"]


def test_the_import_graph_has_no_circle() -> None:
    cycle = _cycle(_graph())
    assert cycle is None, "import circle: " + " -> ".join(cycle or [])


def test_the_cycle_finder_finds_a_circle() -> None:
    assert _cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert _cycle({"a": {"b"}, "b": set()}) is None


def test_imports_run_one_way() -> None:
    bad = []
    for name, targets in _graph().items():
        if _within(name, UPPER):
            forbidden = TOP if not _within(name, TOP) else ()
        else:
            forbidden = UPPER
        bad += [f"{name} -> {t}" for t in sorted(targets) if _within(t, forbidden) and (name, t) not in FACADE]
    assert not bad, "imports against the layers (engine < envs, trainers < cli, bench): " + ", ".join(bad)


def test_subspace_maps_need_no_solver_stack() -> None:
    """Fitting imports the maps; the maps import neither the solvers, integrators, baselines nor metrics."""
    graph = _graph()
    seen, todo = set(), ["redsim.subspace"]
    while todo:
        node = todo.pop()
        if node not in seen:
            seen.add(node)
            todo += sorted(graph[node])
    heavy = ("redsim.solvers", "redsim.integrators", "redsim.baselines", "redsim.metrics", "redsim.hessian")
    assert not [m for m in seen if _within(m, heavy)]
