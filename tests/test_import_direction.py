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
    "gateway/cli.py": "the `simulate`, `record` and `demo` commands start the simulated plant",
    "gateway/demo.py": "the demo runs the gateway loop against the simulated plant",
    "gateway/demo_effect.py": "the demo's monitor phase runs the simulated plant's physics",
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
    assert any(path == "gateway/cli.py" and name.startswith("simulator.") for path, name in edges)


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
        ("gateway/app.py", "from simulator.serve import SimulatedPlant\n", 1, "only gateway/"),
        ("simulator/x.py", "import importlib\nimportlib.import_module('gateway.cli')\n", 2, "may"),
        ("simulator/servers/x.py", "from ..link import MachineLink\n", 1, None),
        ("gateway/demo.py", "from simulator.closed_loop import ClosedLoop\n", 1, None),
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
