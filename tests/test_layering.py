"""Package layering, read from the source's import statements: the env and the physics never depend on the
transforms or the trainer, so they can be used (and tested) without them."""

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


def imported_modules(path: Path, root: Path = PACKAGE) -> set[str]:
    """Absolute names of the modules ``path`` (a file under the package folder ``root``) imports, relative imports
    resolved against its package, ``from M import x`` counted as both ``M`` and ``M.x``."""
    package = ["tocabi_torchrl", *path.relative_to(root).parent.parts]
    names = set()
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = package[: len(package) - node.level + 1] if node.level else []
            module = ".".join([*base, *(node.module.split(".") if node.module else [])])
            names.add(module)
            names.update(f"{module}.{alias.name}" for alias in node.names)
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
