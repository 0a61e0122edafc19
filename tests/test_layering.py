"""Package layering, read from the source's import statements: the env and the physics never depend on the
transforms or the trainer, so they can be used (and tested) without them; the installed package imports nothing of
the lab, the benchmarks or the recipes, and no private warp module; no module imports itself through others (no
import cycle anywhere in the repository's code); and the wheel holds every subpackage."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PACKAGE = REPO / "tocabi_torchrl"

#: subpackage or module -> the subpackages it must not import.
FORBIDDEN = {
    "envs": ("transforms", "rl"),
    "sim": ("envs", "transforms", "rl"),
    "rotations": ("envs", "transforms", "rl", "sim"),
    "signals": ("envs", "transforms", "rl", "sim"),
}


def _imports(tree: ast.AST, type_checking: bool = False):
    """Every import statement of ``tree``, in functions too; those under ``if TYPE_CHECKING:`` (never run) only with
    ``type_checking`` (a name imported for annotations still ties the two modules together)."""
    for node in ast.iter_child_nodes(tree):
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test) and not type_checking:
            yield from (n for branch in node.orelse for n in [branch, *_imports(branch)]
                        if isinstance(n, (ast.Import, ast.ImportFrom)))
            continue
        if isinstance(node, (ast.Import, ast.ImportFrom)):
            yield node
        yield from _imports(node, type_checking)


def _statement_modules(node: ast.Import | ast.ImportFrom, package: list[str]) -> tuple[str, list[str]]:
    """``(module, [module.name, ...])`` of one import statement, relative imports resolved against ``package``."""
    if isinstance(node, ast.Import):
        return "", [alias.name for alias in node.names]
    base = package[: len(package) - node.level + 1] if node.level else []
    module = ".".join([*base, *(node.module.split(".") if node.module else [])])
    return module, [f"{module}.{alias.name}" for alias in node.names]


def imported_modules(path: Path, root: Path = PACKAGE, name: str = "tocabi_torchrl",
                     type_checking: bool = False) -> set[str]:
    """Absolute names of the modules ``path`` (a file under the package folder ``root``, named ``name``) imports,
    relative imports resolved against its package, ``from M import x`` counted as both ``M`` and ``M.x``."""
    package = [name, *path.relative_to(root).parent.parts]
    names = set()
    for node in _imports(ast.parse(path.read_text(), filename=str(path)), type_checking):
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


def _repository_modules() -> dict[str, Path]:
    """module name -> file, for every Python file of the repository's code: the package, the lab, the recipes (as
    ``recipes.<name>``) and the tests with their helpers (by their bare names: pytest puts their folders on the
    path). Names must be unique."""
    files = {}
    for top in ("tocabi_torchrl", "lab", "recipes"):
        for path in sorted((REPO / top).rglob("*.py")):
            parts = path.relative_to(REPO).with_suffix("").parts
            files[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    tests = sorted((REPO / "tests").rglob("*.py"))
    names = [path.stem for path in tests]
    assert len(set(names)) == len(names), f"two test files share a name (pytest would import one as the other): {names}"
    files.update({path.stem: path for path in tests})
    return files


def _module_graph() -> dict[str, set[str]]:
    """module -> the repository modules it imports (:func:`_repository_modules`), statement by statement: at module
    level, inside functions and under ``if TYPE_CHECKING:`` alike (a function's import runs when it is called, and an
    import for annotations alone is still a dependency the other way round would close into a circle). ``from P
    import x`` is an edge to ``P.x`` when that is a module, else to ``P`` (whose ``__init__`` runs)."""
    files = _repository_modules()

    def owner(name: str) -> str:  # the module that defines ``name`` ("" outside the repository)
        while name and name not in files:
            name = name.rpartition(".")[0]
        return name

    graph = {}
    for module, path in files.items():
        parts = path.relative_to(REPO).parts
        package = [*module.split(".")[:-1]] if path.name != "__init__.py" else module.split(".")
        if parts[0] == "tests":
            package = []
        targets = set()
        for node in _imports(ast.parse(path.read_text(), filename=str(path)), type_checking=True):
            base, names = _statement_modules(node, package)
            for name in names:
                targets.add(name if name in files else owner(base or name))
        graph[module] = targets - {module, ""}
    return graph


def _cycles(graph: dict[str, set[str]]) -> list[str]:
    """Each import cycle of ``graph`` found by a depth-first walk, as ``a -> b -> a``."""
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
    return cycles


def test_no_import_cycles():
    graph = _module_graph()
    assert {"tocabi_torchrl.envs.tocabi_walk", "lab.benchmarks.common", "recipes.ppo_walk", "recipe_runner"} <= set(graph)
    assert "tocabi_torchrl.envs.config" in graph["tocabi_torchrl.envs.obstacles"]  # edges found under TYPE_CHECKING too
    cycles = _cycles(graph)
    assert not cycles, ("import cycles (imports inside functions and under TYPE_CHECKING count too); move the shared "
                        "name to a module both can import:\n" + "\n".join(cycles))


def test_the_cycle_check_sees_a_circle_made_only_for_types():
    # The circle issue 51 found: each module imports a name of the other, one of them only for annotations.
    assert _cycles({"a": {"b"}, "b": {"a"}, "c": {"a"}}) == ["a -> b -> a"]
    tree = ast.parse("from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from .config import Box\n")
    assert [n.module for n in _imports(tree, type_checking=True)] == ["typing", "config"]
    assert [n.module for n in _imports(tree)] == ["typing"]


#: Top-level folders of the repository that the installed package must never import: the lab (benchmarks,
#: experiments, the per-library table, measurements), the benchmarks' former home and the recipes (scripts).
NOT_INSTALLED = ("lab", "benchmarks", "recipes")


def test_the_package_imports_nothing_from_the_lab_or_the_recipes():
    # Every import of every module, inside functions and under TYPE_CHECKING too: a user's installed package has no
    # lab/ or recipes/ to find.
    sources = sorted(PACKAGE.rglob("*.py"))
    assert len(sources) > 50
    bad = [f"{path.relative_to(REPO)} imports {name}" for path in sources
           for name in sorted(imported_modules(path, type_checking=True))
           if name.split(".")[0] in NOT_INSTALLED]
    assert not bad, "tocabi_torchrl must not import lab/, benchmarks/ or recipes/:\n" + "\n".join(bad)




def _private_warp_uses(path: Path) -> list[str]:
    """Where ``path`` reaches into warp's or mujoco-warp's private modules: an import of ``warp._src...`` /
    ``mujoco_warp._x...`` (at any depth, in functions too) or an attribute ``._src`` (``wp._src.context``)."""
    tree = ast.parse(path.read_text(), filename=str(path))
    uses = []
    for node in _imports(tree, type_checking=True):
        names = [a.name for a in node.names] if isinstance(node, ast.Import) else [node.module or ""]
        for name in names:
            parts = name.split(".")
            if parts[0] in ("warp", "mujoco_warp") and any(p.startswith("_") for p in parts[1:]):
                uses.append(f"line {node.lineno}: import of {name}")
    uses += [f"line {n.lineno}: {ast.unparse(n)}" for n in ast.walk(tree)
             if isinstance(n, ast.Attribute) and n.attr == "_src"]
    return uses


def test_the_package_uses_no_private_warp_module():
    found = {str(path.relative_to(REPO)): _private_warp_uses(path) for path in sorted(PACKAGE.rglob("*.py"))}
    found = {path: uses for path, uses in found.items() if uses}
    assert not found, "private warp API (warp._src, ...) in the package; use warp's public API:\n" + "\n".join(
        f"{path}: {uses}" for path, uses in found.items())


def test_the_private_warp_check_sees_every_form(tmp_path):
    probe = tmp_path / "probe.py"
    probe.write_text("import warp as wp\nfrom warp._src.context import runtime\nimport mujoco_warp._src.io\n"
                     "def f():\n    return wp._src.context.runtime\n")
    assert [use.split(":")[0] for use in _private_warp_uses(probe)] == ["line 2", "line 3", "line 5"]


def test_the_wheel_holds_every_subpackage_of_the_package_and_nothing_else():
    # setuptools installs the listed packages only: a subpackage missing from the list is missing for every user,
    # and lab/ must never be in it.
    import tomllib

    listed = set(tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"])
    folders = {".".join(p.parent.relative_to(REPO).parts) for p in PACKAGE.rglob("__init__.py")}
    assert listed - {"tocabi_torchrl._assets"} == folders
    assert not [name for name in listed if name.split(".")[0] != "tocabi_torchrl"]


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
