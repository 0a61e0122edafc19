"""Package layering, read from the source's import statements: the env and the physics never depend on the
transforms or the trainer, so they can be used (and tested) without them; and no module imports itself through
others (no import cycle in the package or the benchmarks)."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "tocabi_torchrl"

#: subpackage or module -> the subpackages it must not import.
FORBIDDEN = {
    "envs": ("transforms", "rl"),
    "sim": ("envs", "transforms", "rl"),
    "rotations": ("envs", "transforms", "rl", "sim"),
    "signals": ("envs", "transforms", "rl", "sim"),
}


def _imports(tree: ast.AST):
    """Every import statement of ``tree``, in functions too, except those under ``if TYPE_CHECKING:`` (never run)."""
    for node in ast.iter_child_nodes(tree):
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
            yield from (n for branch in node.orelse for n in [branch, *_imports(branch)]
                        if isinstance(n, (ast.Import, ast.ImportFrom)))
            continue
        if isinstance(node, (ast.Import, ast.ImportFrom)):
            yield node
        yield from _imports(node)


def _statement_modules(node: ast.Import | ast.ImportFrom, package: list[str]) -> tuple[str, list[str]]:
    """``(module, [module.name, ...])`` of one import statement, relative imports resolved against ``package``."""
    if isinstance(node, ast.Import):
        return "", [alias.name for alias in node.names]
    base = package[: len(package) - node.level + 1] if node.level else []
    module = ".".join([*base, *(node.module.split(".") if node.module else [])])
    return module, [f"{module}.{alias.name}" for alias in node.names]


def imported_modules(path: Path, root: Path = PACKAGE, name: str = "tocabi_torchrl") -> set[str]:
    """Absolute names of the modules ``path`` (a file under the package folder ``root``, named ``name``) imports,
    relative imports resolved against its package, ``from M import x`` counted as both ``M`` and ``M.x``."""
    package = [name, *path.relative_to(root).parent.parts]
    names = set()
    for node in _imports(ast.parse(path.read_text(), filename=str(path))):
        module, targets = _statement_modules(node, package)
        names.update([module, *targets] if module else targets)
    return names


def _sources(part: str) -> list[Path]:
    target = PACKAGE / part
    return sorted(target.rglob("*.py")) if target.is_dir() else [target.with_suffix(".py")]


def test_resolves_relative_imports(tmp_path):
    # The import that the layering rule exists for (envs/termination.py once read its quaternion math from the
    # transforms), written three ways: each must be seen.
    module = tmp_path / "envs" / "probe.py"
    module.parent.mkdir()
    module.write_text("from ..transforms.orientation import quat_rotation_angle\n"
                      "from .. import transforms\n"
                      "import tocabi_torchrl.transforms.reward as r\n"
                      "from .config import TocabiWalkConfig\n")
    names = imported_modules(module, root=tmp_path)
    assert {"tocabi_torchrl.transforms.orientation", "tocabi_torchrl.transforms", "tocabi_torchrl.transforms.reward",
            "tocabi_torchrl.envs.config"} <= names


@pytest.mark.parametrize("part", sorted(FORBIDDEN))
def test_no_forbidden_imports(part):
    sources = _sources(part)
    assert sources and all(p.exists() for p in sources), f"{part} not found under {PACKAGE}"
    bad = []
    for path in sources:
        for name in imported_modules(path):
            for banned in FORBIDDEN[part]:
                if name == f"tocabi_torchrl.{banned}" or name.startswith(f"tocabi_torchrl.{banned}."):
                    bad.append(f"{path.relative_to(PACKAGE)} imports {name}")
    assert not bad, f"tocabi_torchrl.{part} must not import {FORBIDDEN[part]}:\n" + "\n".join(bad)


def _module_graph() -> dict[str, set[str]]:
    """module -> the repository modules it imports, for the package and the benchmarks, statement by statement:
    ``from P import x`` is an edge to ``P.x`` when that is a module, else to ``P`` (whose ``__init__`` runs)."""
    repo = PACKAGE.parent
    files = {}
    for top in ("tocabi_torchrl", "benchmarks"):
        for path in sorted((repo / top).rglob("*.py")):
            parts = path.relative_to(repo).with_suffix("").parts
            files[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path

    def owner(name: str) -> str:  # the module that defines ``name`` ("" outside the repository)
        while name and name not in files:
            name = name.rpartition(".")[0]
        return name

    graph = {}
    for module, path in files.items():
        top = module.split(".")[0]
        package = [top, *path.relative_to(repo / top).parent.parts]
        targets = set()
        for node in _imports(ast.parse(path.read_text(), filename=str(path))):
            base, names = _statement_modules(node, package)
            for name in names:
                targets.add(name if name in files else owner(base or name))
        graph[module] = targets - {module, ""}
    return graph


def test_no_import_cycles():
    graph = _module_graph()
    assert "tocabi_torchrl.envs.tocabi_walk" in graph and "benchmarks.common" in graph
    cycles, state, stack = [], {}, []

    def visit(module):
        state[module] = "open"
        stack.append(module)
        for target in sorted(graph[module]):
            if state.get(target) == "open":
                cycles.append(" -> ".join(stack[stack.index(target):] + [target]))
            elif target not in state:
                visit(target)
        stack.pop()
        state[module] = "done"

    for module in sorted(graph):
        if module not in state:
            visit(module)
    assert not cycles, "import cycles (imports inside functions count too):\n" + "\n".join(cycles)


def test_config_classes_keep_their_old_import_paths():
    # The config dataclasses moved to modules without torch (for the config tree and --help); the modules that held
    # them, and the packages, still name the same objects.
    import importlib

    moved = {
        "tocabi_torchrl.envs.command_config": ("tocabi_torchrl.envs.command", "tocabi_torchrl.envs", "CommandConfig"),
        "tocabi_torchrl.envs.push_config": ("tocabi_torchrl.envs.pushes", "tocabi_torchrl.envs.pushes", "PushConfig"),
        "tocabi_torchrl.sim.dynamics_config": ("tocabi_torchrl.sim.dynamics", "tocabi_torchrl.sim.dynamics",
                                               "DynamicsRandomization"),
        "tocabi_torchrl.transforms.sensor_noise_config": ("tocabi_torchrl.transforms.sensor_noise",
                                                          "tocabi_torchrl.transforms", "SensorNoiseConfig"),
        "tocabi_torchrl.transforms.settings": ("tocabi_torchrl.transforms.presets", "tocabi_torchrl.transforms",
                                               "TransformSettings"),
        "tocabi_torchrl.transforms.layouts": ("tocabi_torchrl.transforms.history", "tocabi_torchrl.transforms",
                                              "HistoryLayout"),
    }
    for home, (old, package, name) in moved.items():
        value = getattr(importlib.import_module(home), name)
        assert getattr(importlib.import_module(old), name) is value is getattr(importlib.import_module(package), name)
