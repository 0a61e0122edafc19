"""The recipes' command lines: ``--help`` answers before the heavy libraries load, and a misspelt option is one short
error naming the nearest option (``tocabi_torchrl.cli``)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
from recipe_runner import load_recipe

from tocabi_torchrl.cli import RecipeParser, suggest_options

RECIPES = Path(__file__).resolve().parents[1] / "recipes"
#: The recipes whose parser is written out in the recipe (ppo_walk's is generated from the run config tree: see
#: test_ppo_walk_answers_help_and_a_misspelt_option_without_the_heavy_libraries).
#: (The lab's command lines, built on the same parser: tests/lab/test_lab_cli.py.)
LIGHT_PARSERS = ("play", "sim2sim", "train_rsl_rl", "train_sb3", "train_skrl")
HEAVY = ("torch", "torchrl", "tensordict", "mujoco", "mujoco_warp", "warp", "rsl_rl", "skrl", "stable_baselines3")


def imported_modules(recipe: str, *args: str,
                     cwd: Path = RECIPES.parent) -> tuple[subprocess.CompletedProcess, set[str]]:
    """Run ``recipes/<recipe>.py args`` under ``-X importtime``; the call and the modules it imported."""
    proc = subprocess.run([sys.executable, "-X", "importtime", str(RECIPES / f"{recipe}.py"), *args],
                          capture_output=True, text=True, cwd=cwd, timeout=300,
                          env={**os.environ, "PYTHONWARNINGS": "ignore"})
    # importtime lines: "import time: self [us] | cumulative | <indent>package.module"
    modules = {line.rsplit("|", 1)[1].strip() for line in proc.stderr.splitlines() if line.startswith("import time:")}
    return proc, modules


@pytest.mark.parametrize("recipe", LIGHT_PARSERS)
def test_help_of_a_recipe_loads_no_heavy_library(recipe):
    proc, modules = imported_modules(recipe, "--help")
    assert proc.returncode == 0 and "usage:" in proc.stdout
    assert not modules & set(HEAVY), f"--help imported {sorted(modules & set(HEAVY))}"


def test_ppo_walk_answers_help_and_a_misspelt_option_without_the_heavy_libraries(tmp_path):
    # Its parser is generated from the run config tree, whose modules (dataclasses, the config halves of the env,
    # sim and transforms modules) import none of them; the packages' __init__ files load their names on first use.
    proc, modules = imported_modules("ppo_walk", "--help")
    assert proc.returncode == 0 and "--env.num_envs" in proc.stdout and "--ppo.assist_target" in proc.stdout
    assert not modules & set(HEAVY), f"--help imported {sorted(modules & set(HEAVY))}"
    proc, modules = imported_modules("ppo_walk", "--num_env", "8", cwd=tmp_path)
    assert proc.returncode == 2 and "did you mean --num_envs or --env.num_envs?" in proc.stderr
    assert not modules & set(HEAVY), f"the error imported {sorted(modules & set(HEAVY))}"


def test_a_misspelt_option_of_ppo_walk_is_a_short_error_naming_the_nearest_option(capsys):
    with pytest.raises(SystemExit) as info:
        load_recipe("ppo_walk").main(["--num_env", "8"])
    err = capsys.readouterr().err
    assert info.value.code == 2
    assert "error: unrecognized arguments: --num_env 8" in err and "did you mean --num_envs" in err
    assert "--help" in err and "usage:" not in err and len(err.splitlines()) < 5


@pytest.mark.parametrize("recipe, argv, nearest", [
    ("train_rsl_rl", ["--out", "o", "--learnig_rate", "1e-3"], "--learning_rate"),
    ("play", ["--checkpoint", "c", "--vxx", "0.3"], "--vx"),
    # A prefix of an option is no abbreviation of it (RecipeParser's allow_abbrev=False): it used to mean --num_envs.
    ("train_sb3", ["--out", "o", "--num_env", "8"], "--num_envs"),
])
def test_a_misspelt_option_of_a_light_recipe_exits_before_anything_loads(recipe, argv, nearest, tmp_path):
    proc, modules = imported_modules(recipe, *argv, cwd=tmp_path)
    assert proc.returncode == 2 and f"did you mean {nearest}?" in proc.stderr
    errors = [line for line in proc.stderr.splitlines() if not line.startswith("import time:")]
    assert len(errors) == 2 and "usage:" not in proc.stderr and "--help" in errors[1]
    assert not modules & set(HEAVY)


def test_suggestions_ignore_an_attached_value_and_stay_quiet_when_nothing_is_close():
    known = ["--num_envs", "--env.num_envs", "--seed", "--device"]
    assert suggest_options("--num_env=8", known)[0] == "--num_envs"
    assert suggest_options("--colour", known) == []


def test_a_bad_value_or_a_missing_option_is_one_error_line(capsys):
    parser = RecipeParser(prog="demo.py")
    parser.add_argument("--steps", type=int, required=True)
    for argv, message in ((["--steps", "x"], "argument --steps: invalid int value: 'x'"),
                          ([], "the following arguments are required: --steps")):
        with pytest.raises(SystemExit) as info:
            parser.parse_args(argv)
        assert info.value.code == 2 and capsys.readouterr().err == f"demo.py: error: {message}\n"
    with pytest.raises(SystemExit) as info:
        parser.parse_args(["--steps", "1", "--stpes", "2"])
    assert info.value.code == 2 and capsys.readouterr().err.splitlines() == [
        "demo.py: error: unrecognized arguments: --stpes 2; did you mean --steps?",
        "demo.py: demo.py --help lists every option"]
