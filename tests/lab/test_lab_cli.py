"""The lab's command lines (``python -m lab.<tool>`` from the repository root), built on the recipes' parser
(``tocabi_torchrl.cli``): ``--help`` answers before the heavy libraries load, and a misspelt option is one short
error naming the nearest option."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
#: tool -> the module ``python -m`` runs.
TOOLS = {"compare_gaits": "lab.experiments.compare_gaits", "obstacle_test": "lab.experiments.obstacle_test",
         "library_table": "lab.library_table"}
HEAVY = ("torch", "torchrl", "tensordict", "mujoco", "mujoco_warp", "warp", "rsl_rl", "skrl", "stable_baselines3")


def imported_modules(tool: str, *args: str, cwd: Path = ROOT) -> tuple[subprocess.CompletedProcess, set[str]]:
    """Run ``python -m <tool's module> args`` under ``-X importtime`` (the repository root on the path, as when run
    from it); the call and the modules it imported."""
    proc = subprocess.run([sys.executable, "-X", "importtime", "-m", TOOLS[tool], *args], capture_output=True,
                          text=True, cwd=cwd, timeout=300,
                          env={**os.environ, "PYTHONWARNINGS": "ignore",
                               "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])})
    # importtime lines: "import time: self [us] | cumulative | <indent>package.module"
    modules = {line.rsplit("|", 1)[1].strip() for line in proc.stderr.splitlines() if line.startswith("import time:")}
    return proc, modules


@pytest.mark.parametrize("tool", sorted(TOOLS))
def test_help_of_a_lab_tool_loads_no_heavy_library(tool):
    proc, modules = imported_modules(tool, "--help")
    assert proc.returncode == 0 and "usage:" in proc.stdout, proc.stderr[-2000:]
    assert not modules & set(HEAVY), f"--help imported {sorted(modules & set(HEAVY))}"


@pytest.mark.parametrize("tool, argv, nearest", [
    ("library_table", ["--report", "--jsno", "t.json"], "--json"),
    ("compare_gaits", ["--num_env", "8"], "--num_envs"),
])
def test_a_misspelt_option_of_a_lab_tool_exits_before_anything_loads(tool, argv, nearest, tmp_path):
    proc, modules = imported_modules(tool, *argv, cwd=tmp_path)
    assert proc.returncode == 2 and f"did you mean {nearest}?" in proc.stderr, proc.stderr[-2000:]
    errors = [line for line in proc.stderr.splitlines() if not line.startswith("import time:")]
    assert len(errors) == 2 and "usage:" not in proc.stderr and "--help" in errors[1]
    assert not modules & set(HEAVY)
