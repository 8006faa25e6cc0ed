"""Imports flow one way: gateway → simulator → drivers, gateway → models, nothing back.

Every ``.py`` file of the four packages is parsed with :mod:`ast` (nothing is
imported, so a cycle cannot hide behind import order), and every project-internal
import is collected: module level, inside functions, under ``TYPE_CHECKING``, and
``importlib.import_module("…")`` with a literal name. Any edge outside the rule fails
the test, naming the file, the line and the import.

The rule:

- ``drivers`` (clients, register codecs, clocks) and ``models`` (fitting, the model
  store) import nothing of the project; ``models`` does not import ``drivers`` either.
- ``simulator`` (the twin and its protocol servers) may import ``drivers``.
- ``gateway`` may import ``drivers`` and ``models``, and ``simulator`` only from the
  modules in :data:`GATEWAY_MODULES_USING_SIMULATOR`.
"""

from __future__ import annotations

import ast
from dataclasses import dataclass
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
PACKAGES = ("gateway", "drivers", "models", "simulator")

#: Which other project packages each package may import (its own is always allowed).
ALLOWED: dict[str, frozenset[str]] = {
    "drivers": frozenset(),
    "models": frozenset(),
    "simulator": frozenset({"drivers"}),
    "gateway": frozenset({"drivers", "models", "simulator"}),
}

#: The only gateway modules that may import ``simulator``, and why.
GATEWAY_MODULES_USING_SIMULATOR: dict[str, str] = {
    "gateway/cli/main.py": "the `simulate`, `record` and `demo` commands start the simulated plant",
    "gateway/demo/compensate.py": "the demo runs the gateway loop against the simulated plant",
    "gateway/demo/monitor_phase.py": "the demo's monitor phase runs the simulated plant's physics",
    "gateway/config.py": "check-config validates the config's `simulator:` section with its schema",
}


@dataclass(frozen=True)
class Edge:
    path: str
    line: int
    imported: str

    @property
    def source(self) -> str:
        return self.path.split("/", 1)[0]

    @property
    def target(self) -> str:
        return self.imported.split(".", 1)[0]

    def __str__(self) -> str:
        return f"{self.path}:{self.line}: imports {self.imported}"


def _package_of(path: Path) -> list[str]:
    """Dotted package of a module file, e.g. simulator/servers/x.py → [simulator, servers]."""
    return list(path.relative_to(ROOT).parent.parts)


def _resolve(node: ast.ImportFrom, package: list[str]) -> str:
    """The absolute module of a ``from … import`` (relative imports resolved)."""
    if node.level == 0:
        return node.module or ""
    base = package[: len(package) - (node.level - 1)]
    return ".".join([*base, *([node.module] if node.module else [])])


def imports_of(path: Path) -> list[Edge]:
    """Every project-internal module ``path`` imports, with its line."""
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    relative = path.relative_to(ROOT).as_posix()
    package = _package_of(path)
    found: list[Edge] = []
    for node in ast.walk(tree):
        names: list[str] = []
        if isinstance(node, ast.Import):
            names = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            module = _resolve(node, package)
            # `from simulator import serve` names the module simulator.serve.
            names = [module] if node.module else [f"{module}.{a.name}" for a in node.names]
        elif (
            isinstance(node, ast.Call)
            and isinstance(node.func, ast.Attribute)
            and node.func.attr == "import_module"
            and node.args
            and isinstance(node.args[0], ast.Constant)
            and isinstance(node.args[0].value, str)
        ):
            names = [node.args[0].value]
        for name in names:
            if name.split(".", 1)[0] in PACKAGES:
                found.append(Edge(relative, node.lineno, name))
    return found


def project_files() -> list[Path]:
    return sorted(p for package in PACKAGES for p in (ROOT / package).rglob("*.py"))


def forbidden(edge: Edge) -> str | None:
    """Why ``edge`` breaks the rule, or None when it is allowed."""
    if edge.target == edge.source:
        return None
    if edge.target not in ALLOWED[edge.source]:
        allowed = ", ".join(sorted(ALLOWED[edge.source])) or "nothing of the project"
        return f"{edge} ({edge.source} may import {allowed})"
    if (
        edge.source == "gateway"
        and edge.target == "simulator"
        and edge.path not in GATEWAY_MODULES_USING_SIMULATOR
    ):
        allowed = ", ".join(GATEWAY_MODULES_USING_SIMULATOR)
        return f"{edge} (only {allowed} may import simulator)"
    return None


def test_the_walk_sees_every_package_and_kind_of_import() -> None:
    """The walk itself works: files of all four packages, function-level imports included."""
    files = project_files()
    assert {p.relative_to(ROOT).parts[0] for p in files} == set(PACKAGES)
    edges = {(e.path, e.imported) for p in files for e in imports_of(p)}
    # A module-level import and a function-level one (cli imports commands lazily).
    assert ("simulator/serve.py", "simulator.servers.modbus_cnc") in edges
    assert any(
        path == "gateway/cli/main.py" and name.startswith("simulator.") for path, name in edges
    )


def test_imports_flow_one_way() -> None:
    problems = [why for p in project_files() for e in imports_of(p) if (why := forbidden(e))]
    assert not problems, "imports against the package rule:\n" + "\n".join(problems)


def test_every_allowed_gateway_module_exists() -> None:
    """A stale allow-list entry would silently widen the rule when a file is renamed."""
    missing = [path for path in GATEWAY_MODULES_USING_SIMULATOR if not (ROOT / path).is_file()]
    assert not missing


@pytest.mark.parametrize(
    ("source", "code", "line", "verdict"),
    [
        ("drivers/x.py", "from gateway.config import GatewayConfig\n", 1, "drivers may import"),
        ("models/x.py", "def f():\n    import drivers.clock\n", 2, "models may import"),
        ("simulator/x.py", "from gateway import runtime\n", 1, "simulator may import"),
        ("gateway/wiring.py", "from simulator.serve import SimulatedPlant\n", 1, "only gateway/"),
        ("simulator/x.py", "import importlib\nimportlib.import_module('gateway.cli')\n", 2, "may"),
        ("simulator/servers/x.py", "from ..link import MachineLink\n", 1, None),
        ("gateway/demo/compensate.py", "from simulator.closed_loop import ClosedLoop\n", 1, None),
    ],
)
def test_a_forbidden_edge_is_named_with_file_and_line(
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    source: str,
    code: str,
    line: int,
    verdict: str | None,
) -> None:
    """The checker on small synthetic modules: bad edges are reported, good ones pass."""
    monkeypatch.setattr(f"{__name__}.ROOT", tmp_path)
    path = tmp_path / source
    path.parent.mkdir(parents=True)
    path.write_text(code, encoding="utf-8")
    edges = imports_of(path)
    assert [e.line for e in edges] == [line]
    reasons = [why for e in edges if (why := forbidden(e))]
    if verdict is None:
        assert reasons == []
    else:
        assert len(reasons) == 1 and verdict in reasons[0], reasons
        assert reasons[0].startswith(f"{source}:{line}: imports "), reasons


# --------------------------------------------------------------------------- layers inside

#: Inside ``gateway`` and ``models``, each subpackage (or top-level module) sits on a
#: layer and imports only from layers below it: the data paths read bottom-up. Two
#: units on one layer do not import each other. Modules inside one unit import each
#: other freely, but without a cycle (:func:`test_no_module_imports_itself_through_others`).
LAYERS: dict[str, tuple[tuple[str, ...], ...]] = {
    "gateway": (
        # Sparkplug's topic rules are the spec's, checked by the configuration too.
        (
            "gateway",
            "gateway.__init__",
            "gateway.limits",
            "gateway.process",
            "gateway.sparkplug.topics",
        ),
        ("gateway.config",),
        ("gateway.live",),
        ("gateway.commands", "gateway.outputs"),
        ("gateway.offline", "gateway.scada", "gateway.sparkplug"),
        ("gateway.web",),  # the console signs in with the SCADA server's accounts
        ("gateway.wiring",),
        ("gateway.demo",),
        ("gateway.cli", "gateway.config_schema"),
        ("gateway.__main__",),
    ),
    "models": (
        ("models", "models.__init__", "models.base", "models.catalogue", "models.json_files"),
        ("models.signing", "models.training_range", "models.data"),
        ("models.estimators",),
        ("models.store",),
        ("models.fit",),
        ("models.analysis",),
        ("models.online",),
    ),
}


def module_of(path: Path) -> str:
    """``gateway/live/loop.py`` → ``gateway.live.loop``."""
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    return ".".join(parts)


def unit_of(module: str) -> tuple[str, int] | None:
    """The layered unit a module belongs to (longest prefix named in LAYERS) and its layer."""
    layers = LAYERS.get(module.split(".", 1)[0])
    if layers is None:
        return None
    best: tuple[str, int] | None = None
    for depth, units in enumerate(layers):
        for unit in units:
            if (module == unit or module.startswith(unit + ".")) and (
                best is None or len(unit) > len(best[0])
            ):
                best = (unit, depth)
    return best


def project_modules() -> set[str]:
    names = set()
    for path in project_files():
        name = module_of(path)
        names.add(name.removesuffix(".__init__"))
    return names


def resolve(imported: str, modules: set[str]) -> str | None:
    """The project module an imported name lives in (``a.b.C`` → ``a.b``)."""
    parts = imported.split(".")
    for end in range(len(parts), 0, -1):
        candidate = ".".join(parts[:end])
        if candidate in modules:
            return candidate
    return None


def layer_problem(source: str, target: str) -> str | None:
    """Why ``source`` may not import ``target`` by the layers, or None."""
    if source.split(".", 1)[0] != target.split(".", 1)[0]:
        return None  # between packages, the package rule above applies
    mine, theirs = unit_of(source), unit_of(target)
    if mine is None or theirs is None or mine[0] == theirs[0]:
        return None
    if theirs[1] < mine[1] or theirs[0] in ("gateway", "models"):
        return None
    return f"{mine[0]} (layer {mine[1]}) imports {theirs[0]} (layer {theirs[1]})"


def module_graph() -> dict[str, set[str]]:
    modules = project_modules()
    graph: dict[str, set[str]] = {m: set() for m in modules}
    for path in project_files():
        source = module_of(path).removesuffix(".__init__")
        for edge in imports_of(path):
            target = resolve(edge.imported, modules)
            if target is not None and target != source and target not in PACKAGES:
                graph[source].add(target)
    return graph


def _pop_component(stack: list[str], on_stack: set[str], root: str) -> list[str]:
    """Tarjan's step: the modules on the stack down to ``root`` form one component."""
    component = []
    while True:
        w = stack.pop()
        on_stack.discard(w)
        component.append(w)
        if w == root:
            return component


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = _pop_component(stack, on_stack, v)
            if len(component) > 1:
                found.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


def test_every_gateway_and_models_module_has_a_layer() -> None:
    """A new subpackage must be placed on a layer, or the rule would not see it."""
    unplaced = sorted(
        m for m in project_modules() if m.split(".")[0] in LAYERS and unit_of(m) is None
    )
    assert not unplaced


def test_subpackages_import_only_from_layers_below() -> None:
    modules = project_modules()
    problems = []
    for path in project_files():
        source = module_of(path).removesuffix(".__init__")
        for edge in imports_of(path):
            target = resolve(edge.imported, modules)
            if target is not None and (why := layer_problem(source, target)):
                problems.append(f"{edge}: {why}")
    assert not problems, "imports against the layers:\n" + "\n".join(problems)


def test_no_module_imports_itself_through_others() -> None:
    graph = module_graph()
    edges = sum(len(targets) for targets in graph.values())
    assert len(graph) > 100 and edges > 200  # the walk saw the tree
    assert cycles(graph) == []


def test_the_cycle_finder_finds_a_cycle() -> None:
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}
    assert cycles(graph) == [["a", "b", "c"]]


@pytest.mark.parametrize(
    ("source", "target", "allowed"),
    [
        ("gateway.live.loop", "gateway.config", True),
        ("gateway.config", "gateway.live.quality", False),
        ("gateway.outputs.sinks", "gateway.live.record", True),
        ("gateway.live.loop", "gateway.outputs.sinks", False),
        ("gateway.scada.server", "gateway.web.server", False),
        ("models.data.dataset", "models.analysis.search", False),
        ("models.online.proposals", "models.store", True),
        ("gateway.cli.main", "gateway.cli.options", True),
    ],
)
def test_the_layer_rule_on_examples(source: str, target: str, allowed: bool) -> None:
    assert (layer_problem(source, target) is None) is allowed
