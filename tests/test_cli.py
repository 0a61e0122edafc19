"""The recipes' command lines: ``--help`` answers before the heavy libraries load, and a misspelt option is one short
error naming the nearest option (``tocabi_torchrl.cli``)."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
from recipe_runner import load_recipe

from tocabi_torchrl.cli import RecipeParser, base_parser, listed_spelling, suggest_options

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


def _text(err: str) -> str:
    """tyro's boxed message as one line of words (no frame characters, no line breaks)."""
    return " ".join(err.replace("│", " ").replace("╭", " ").replace("╰", " ").replace("─", " ").split())


def test_ppo_walk_answers_help_and_a_misspelt_option_without_the_heavy_libraries(tmp_path):
    # Its command line is tyro's, generated from the run config tree, whose modules (dataclasses, the config halves
    # of the env, sim and transforms modules) import none of them; the packages' __init__ files load their names on
    # first use.
    proc, modules = imported_modules("ppo_walk", "--help")
    assert proc.returncode == 0 and "--env.num_envs" in proc.stdout and "--ppo.assist_target" in proc.stdout
    assert not modules & set(HEAVY), f"--help imported {sorted(modules & set(HEAVY))}"
    # It shows the default preset's 4,096 envs; without CUDA the same command runs cpu_smoke, which it now says.
    assert "Without CUDA and without --preset or --device, the run uses the small 'cpu_smoke'" in \
        " ".join(proc.stdout.split())
    proc, modules = imported_modules("ppo_walk", "--env.num_env", "8", cwd=tmp_path)
    assert proc.returncode == 2 and "Unrecognized options: --env.num_env" in _text(proc.stderr)
    assert "Perhaps you meant: --env.num_envs INT" in _text(proc.stderr)
    assert not modules & set(HEAVY), f"the error imported {sorted(modules & set(HEAVY))}"


def test_ppo_walk_help_is_the_fields_docstrings_with_the_presets_values(tmp_path):
    from tocabi_torchrl.config import RunConfig
    from tocabi_torchrl.tree import leaf_paths

    env = {**os.environ, "COLUMNS": "100"}  # one column of option boxes
    out = subprocess.run([sys.executable, str(RECIPES / "ppo_walk.py"), "--preset", "torque", "--help"], env=env,
                         capture_output=True, text=True, timeout=300).stdout
    helps, option = {}, None  # option -> its help text, the lines after "--option TYPE" joined
    for line in (line.strip("│ ") for line in out.splitlines()):
        if line.startswith("--"):
            option = line.split()[0][2:]
            helps[option] = ""
        elif option and line and line[0] not in "╭╰─":
            helps[option] = f"{helps[option]} {line}".strip()
        else:
            option = None
    missing = [p for p in leaf_paths(RunConfig()) if not helps.get(p, "(default").strip().partition("(default")[0]]
    assert not missing, f"options without help text: {missing}"
    assert helps["ppo.lr"].startswith("learning rate (start value of the schedule)")
    assert helps["transforms.reward_weights.body_vel"].startswith("pelvis velocity against the command")
    assert "(default: torque)" in helps["env.control.mode"] and "(default: 200000000)" in helps["total_env_steps"]


def test_ppo_walk_help_shows_values_not_sphinx_roles_and_titles_each_section_by_its_own_docstring():
    from tocabi_torchrl.control.config import MAX_DELAY_SUBSTEPS
    from tocabi_torchrl.envs.config import CPU_DEFAULT_BACKEND

    env = {**os.environ, "COLUMNS": "100"}
    out = subprocess.run([sys.executable, str(RECIPES / "ppo_walk.py"), "--help"], env=env, capture_output=True,
                         text=True, timeout=300).stdout
    text = _text(out)
    # ":data:`CPU_DEFAULT_BACKEND`" hid the value it stands for; a role is a link in the docs, noise in a terminal.
    assert not re.search(r":\w+:`", text), re.search(r".{40}:\w+:`.{40}", text)
    assert f'(warp on CUDA, "{CPU_DEFAULT_BACKEND}" on the CPU)' in text
    assert f"high at most {MAX_DELAY_SUBSTEPS}." in text
    # A "# sections" comment above env, transforms and ppo was each group's title.
    lines = [line.strip("│ ") for line in out.splitlines()]
    titles = {line.split()[1]: lines[i + 1] for i, line in enumerate(lines) if line.startswith("╭─ ")}
    assert titles["env"].startswith("the walking task's env") and titles["ppo"].startswith("PPO:"), titles
    assert "sections" not in titles.values()


def test_a_misspelt_option_of_ppo_walk_is_an_error_naming_the_nearest_option(capsys):
    with pytest.raises(SystemExit) as info:
        load_recipe("ppo_walk").main(["--ppo.lrr", "8"])
    err = _text(capsys.readouterr().err)
    assert info.value.code == 2
    assert "Unrecognized options: --ppo.lrr, 8" in err and "Perhaps you meant: --ppo.lr FLOAT" in err


@pytest.mark.parametrize("argv, message", [
    (["--ppo.epochs", "three"], "Error parsing --ppo.epochs: expected an int (e.g. 200000000 or 2e8), got 'three'"),
    (["--eval_at_end", "maybe"], "Error parsing --eval_at_end: expected true or false, got 'maybe'"),
    (["--transforms.reward_weights.qpos", "heavy"], "Error parsing --transforms.reward_weights.qpos"),
    (["--env.scene.obstacles", "[{]"], "Error parsing --env.scene.obstacles: expected JSON"),
])
def test_a_bad_value_of_ppo_walk_names_the_option(argv, message, capsys):
    with pytest.raises(SystemExit) as info:
        load_recipe("ppo_walk").main(argv)
    assert info.value.code == 2 and message in _text(capsys.readouterr().err)


def test_a_value_the_config_refuses_is_one_error_line_naming_the_option(capsys):
    for argv, message in ((["--ppo.gamma", "1.5"], "error: ppo.gamma must be in (0.0, 1.0], got 1.5"),
                          (["--transforms.reward_weights.qpos", "nan"],
                           "error: transforms.reward_weights.qpos must be"),
                          (["--preset", "torq"], "error: --preset torq: unknown preset; choose one of")):
        with pytest.raises(SystemExit) as info:
            load_recipe("ppo_walk").main(argv)
        assert str(info.value.code).startswith(message), info.value.code
        assert "\n" not in str(info.value.code)


def test_an_option_given_twice_on_ppo_walk_keeps_the_last_and_says_so(tmp_path, capsys):
    # --ppo.lr 1e-4 --ppo.lr 2e-4 trained with 2e-4 without a word. A warning, not a refusal: a script may append its
    # overrides after its defaults. (--viewer.port without --viewer then stops the run before anything is built.)
    with pytest.raises(SystemExit, match="^error: --viewer.port set the live viewer"):
        load_recipe("ppo_walk").main(["--preset", "cpu_smoke", "--run_dir", str(tmp_path), "--ppo.lr", "1e-4",
                                      "--ppo.actor_hidden", "8", "8", "--ppo.lr=2e-4", "--ppo.actor-hidden", "16",
                                      "--viewer.port", "9000"])
    assert capsys.readouterr().err.splitlines() == [
        "warning: --ppo.lr is given 2 times; the last applies: --ppo.lr 2e-4",
        "warning: --ppo.actor_hidden is given 2 times; the last applies: --ppo.actor_hidden 16"]


def test_ppo_walk_without_matplotlib_is_refused_before_training_unless_the_test_at_the_end_is_off(tmp_path,
                                                                                                 monkeypatch):
    # The gait test after training draws knees.png: without the viz extra the run trained (hours on a GPU preset),
    # then ended in a ModuleNotFoundError traceback. The library recipes already said so up front.
    monkeypatch.setitem(sys.modules, "matplotlib", None)  # what an install without the viz extra imports
    with pytest.raises(SystemExit) as info:
        load_recipe("ppo_walk").main(["--preset", "cpu_smoke", "--run_dir", str(tmp_path)])
    message = str(info.value.code)
    assert message.startswith('error: the gait test draws knees.png with matplotlib, which is not installed: pip '
                              'install -e ".[viz]"') and message.endswith("--eval_at_end false"), message
    assert not any(tmp_path.iterdir())  # refused before the run folder


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


def test_the_recipes_named_values_take_any_case_and_give_the_listed_spelling(capsys):
    # --test Robust and --lr_schedule Adaptive were "invalid choice" errors, while the config's named values
    # (--ppo.lr_schedule Adaptive) take any case.
    play = load_recipe("play").build_parser().parse_args(["--checkpoint", "r", "--test", "Robust", "--backend",
                                                          "MUJOCO"])
    assert (play.test, play.backend) == ("robust", "mujoco")
    rsl = load_recipe("train_rsl_rl").build_parser().parse_args(["--out", "r", "--lr_schedule", "Adaptive",
                                                                 "--std", "LEARNED"])
    assert (rsl.lr_schedule, rsl.std) == ("adaptive", "learned")
    sim = load_recipe("sim2sim").build_parser().parse_args(["--contract", "c.json", "--randomize", "TocaBi_Lab",
                                                            "--push_kind", "Force"])
    assert (sim.randomize, sim.push_kind) == ("tocabi_lab", "force")
    parser = RecipeParser(prog="demo.py")
    parser.add_argument("--mode", choices=("a", "b"))
    with pytest.raises(SystemExit) as info:  # a value listed in no case is still refused, as given
        parser.parse_args(["--mode", "C"])
    assert info.value.code == 2 and "argument --mode: invalid choice: 'C'" in capsys.readouterr().err


def test_every_shared_library_recipe_option_with_a_default_shows_it():
    # --eval_envs, --max_minutes, --checkpoint_minutes and --device used to leave their defaults out of --help.
    from tocabi_torchrl.config import PRESETS

    parser = base_parser("demo", num_envs=8, iterations=2, presets=PRESETS)
    for action in parser._actions:
        if action.dest not in ("help", "out", "resume"):  # --out is required, --resume a switch
            assert "(default:" in action.help, f"--{action.dest} does not say its default"
    # --preset once said only "task preset of tocabi_torchrl.rl.config": a user had to read the code for the names.
    for parser in (parser, *(load_recipe(name).build_parser() for name in ("train_sb3", "train_rsl_rl", "train_skrl"))):
        preset_help = next(a.help for a in parser._actions if a.dest == "preset")
        assert all(name in preset_help for name in PRESETS), preset_help


def test_the_package_command_lines_take_full_option_names_only(tmp_path, capsys):
    # python -m tocabi_torchrl.export took --over for --overwrite and replaced an export without being asked.
    from tocabi_torchrl.export.__main__ import build_parser as export_parser
    from tocabi_torchrl.motion.gait import main as gait_main
    from tocabi_torchrl.rl.curves import main as curves_main
    from tocabi_torchrl.signals_doc import main as signals_main

    with pytest.raises(SystemExit) as info:
        export_parser().parse_args(["--checkpoint", "c.pt", "--out", "o.onnx", "--over"])
    err = capsys.readouterr().err
    assert info.value.code == 2 and "unrecognized arguments: --over; did you mean --overwrite?" in err
    for main, argv in ((curves_main, [str(tmp_path), str(tmp_path / "c.png"), "--over"]),
                       (signals_main, ["--che"]), (gait_main, ["--ou", str(tmp_path / "g.npz")])):
        with pytest.raises(SystemExit) as info:
            main(argv)
        assert info.value.code == 2 and "did you mean" in capsys.readouterr().err
    assert not list(tmp_path.iterdir())


def test_listed_spelling_takes_one_match_in_any_case_and_nothing_else():
    # The one rule the recipes' options and the run config's named values share.
    assert listed_spelling("LINEAR", ("linear", "adaptive")) == "linear"
    assert listed_spelling("cosine", ("linear", "adaptive")) is None
    assert listed_spelling("ab", ("AB", "ab", 3)) is None  # two spellings: the caller's own error names them
    assert listed_spelling("x", ("X", 3)) == "X"  # non-string choices are skipped
