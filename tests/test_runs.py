"""Runs a user can trust: no silent overwrite, --resume restores the saved run, explicit requests are honoured or
refused, clear messages for missing loggers, progress shows '-' until an episode ends, --help describes every option."""

from __future__ import annotations

import dataclasses
import importlib.util
import math
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch
from recipe_runner import load_recipe as recipe

from tocabi_torchrl.rl import parse_args, preset_config
from tocabi_torchrl.rl.checkpoint import CheckpointError, read_checkpoint
from tocabi_torchrl.rl.curves import read_metrics
from tocabi_torchrl.config import PRESETS
from tocabi_torchrl.rl.launch import LaunchError, banner, cpu_sized_hint, fallback_said, launch_config
from tocabi_torchrl.rl.resume import ResumeConfigError
from tocabi_torchrl.rl.run_dir import RunDirError, open_run
from tocabi_torchrl.rl.trainer import train

RECIPES = Path(__file__).resolve().parents[1] / "recipes"
TINY = {"device": "cpu", "env.num_envs": 2, "ppo.steps_per_env": 4, "ppo.minibatch_size": 8, "total_env_steps": 16,
        "progress_bar": False, "eval_at_end": False, "checkpoint_every": 1}


def tiny_args(tmp_path: Path, name: str = "run", **extra) -> list[str]:
    options = {"preset": "cpu_smoke", **TINY, "run_dir": str(tmp_path), "name": name, **extra}
    return [x for k, v in options.items() for x in (f"--{k}", *(map(str, v) if isinstance(v, tuple) else [str(v)]))]


def iterations_logged(run: Path) -> list[int]:
    return [int(row["iteration"]) for row in read_metrics(run)]


@pytest.fixture(scope="module")
def finished_run(tmp_path_factory) -> Path:
    """A 2-iteration cpu_smoke run written by the recipe (shared by the tests that only read or refuse it)."""
    root = tmp_path_factory.mktemp("runs")
    recipe("ppo_walk").main(tiny_args(root))
    return root / "run"


# ------------------------------------------------------------------------------------------ finding 3: no overwrite
def test_rerunning_a_name_refuses_and_keeps_the_earlier_run(finished_run, capsys):
    before = {p.name: p.stat().st_mtime_ns for p in (finished_run / "checkpoints").iterdir()}
    config = (finished_run / "config.json").read_text()
    with pytest.raises(SystemExit) as info:
        recipe("ppo_walk").main(tiny_args(finished_run.parent))
    message = str(info.value.code)
    assert "already holds a run" in message and f"--resume {finished_run}" in message and "--name" in message
    assert {p.name: p.stat().st_mtime_ns for p in (finished_run / "checkpoints").iterdir()} == before
    assert (finished_run / "config.json").read_text() == config
    assert iterations_logged(finished_run) == [1, 2]
    cfg = preset_config("cpu_smoke", **TINY, run_dir=str(finished_run.parent), name="run")
    with pytest.raises(RunDirError, match="already holds a run"):
        train(cfg)


# ------------------------------------------------------------------------------------------- finding 6: --resume
def test_resume_restores_the_saved_config(finished_run):
    cfg, _ = parse_args(["--resume", str(finished_run)])
    saved = preset_config("cpu_smoke", **TINY, run_dir=str(finished_run.parent), name="run")
    assert cfg.env.num_envs == 2 and cfg.ppo.steps_per_env == 4 and cfg.ppo.actor_hidden == saved.ppo.actor_hidden
    assert cfg.preset == "cpu_smoke" and cfg.resume == str(finished_run)
    cfg, _ = parse_args(["--resume", str(finished_run), "--total_env_steps", "24", "--max_minutes", "1"])
    assert cfg.total_env_steps == 24 and cfg.max_minutes == 1.0 and cfg.env.num_envs == 2


def test_a_resumed_call_reports_its_own_env_steps_beside_the_runs(finished_run, tmp_path, capsys):
    # It printed the run's total env steps beside this call's seconds and rate.
    import shutil

    run = tmp_path / "run"
    shutil.copytree(finished_run, run)
    recipe("ppo_walk").main(["--resume", str(run), "--total_env_steps", "32"])
    out = capsys.readouterr().out
    assert "done: 16 env steps in " in out and " env-steps/s) (32 in the run); run folder" in out
    assert "moves the schedules" not in out  # the std holds at its end over the last half: nothing moves
    # A larger budget put the scheduled std back toward its start without a word.
    shutil.rmtree(run)
    shutil.copytree(finished_run, run)
    recipe("ppo_walk").main(["--resume", str(run), "--total_env_steps", "64"])
    assert "note: total_env_steps 64 (the run's was 16) moves the schedules, which follow the progress through the " \
           "budget: at the next iteration action std 0.05 -> 0.0875" in capsys.readouterr().out
    # The data-parallel closing line is the same text after "done on K ranks: ".
    from types import SimpleNamespace

    result = SimpleNamespace(env_steps=48, start_env_steps=16, wall_seconds=2.0, env_steps_per_second=16.0,
                             run_dir="r")
    assert recipe("ppo_walk").done_text(result) == "32 env steps in 2 s (16 env-steps/s) (48 in the run); run folder r"
    # It said nothing of the gait test that --eval_at_end asked for and torchrun leaves out.
    from tocabi_torchrl.rl import preset_config

    line = recipe("ppo_walk").ranks_done_text(result, preset_config("robust"), 2)
    assert line == ("done on 2 ranks: 32 env steps in 2 s (16 env-steps/s) (48 in the run); run folder r; the gait "
                    "test is not run under torchrun, run it with: python recipes/play.py --checkpoint r --num_envs "
                    "1024 --seconds 8 --test robust")
    quiet = preset_config("cpu_smoke", eval_at_end=False)
    assert recipe("ppo_walk").ranks_done_text(result, quiet, 2).endswith("; run folder r")


def test_a_damaged_latest_checkpoint_names_the_newest_readable_one(finished_run, tmp_path):
    # It used to say only that latest.pt was unreadable, though the run's iteration files resume fine.
    import shutil

    from tocabi_torchrl.rl.checkpoint import CheckpointError

    run = tmp_path / "run"
    shutil.copytree(finished_run, run)
    latest = run / "checkpoints" / "latest.pt"
    latest.write_bytes(latest.read_bytes()[:1000])
    files = sorted((run / "checkpoints").glob("iter_*.pt"))
    newest = files[-1]
    assert len(files) >= 2
    for age, older in enumerate(files[1:]):  # as after a `cp -r` in another order: the oldest file written last
        os.utime(older, (1e9 + age, 1e9 + age))
    os.utime(files[0], (2e9, 2e9))
    with pytest.raises(CheckpointError, match=rf"latest.pt.*newest readable checkpoint beside it is {newest.name} "
                                              rf"\(iteration \d+\): continue from it with --resume {newest}"):
        parse_args(["--resume", str(run)])
    cfg, _ = parse_args(["--resume", str(newest)])  # and that advice works
    assert cfg.resume == str(newest)
    # A wall-clock save later than the last iteration file is the newest: named, though iteration files sort first.
    state = torch.load(newest, weights_only=True)
    state["iteration"] += 5
    wall = run / "checkpoints" / "wall_03600s.pt"
    torch.save(state, wall)
    os.utime(wall, (1.5e9, 1.5e9))
    with pytest.raises(CheckpointError, match=rf"beside it is wall_03600s.pt \(iteration {state['iteration']}\)"):
        parse_args(["--resume", str(run)])
    wall.unlink()
    # In a folder of other policies (a copy of assets/policies), a readable file there is no run's to continue.
    other = tmp_path / "policies"
    other.mkdir()
    shutil.copy(newest, other / "tocabi_walk_ppo.pt")
    (other / "mine.pt").write_bytes(latest.read_bytes())
    with pytest.raises(CheckpointError) as info:
        parse_args(["--resume", str(other / "mine.pt")])
    assert "newest readable checkpoint" not in str(info.value)


@pytest.mark.parametrize("option, value, saved", [("ppo.lr", ["0.5"], "0.001"),
                                                  ("env.control.mode", ["torque"], "'pd_reference'"),
                                                  ("transforms.history", ["tocabilab"], "'reference'"),
                                                  ("ppo.actor_hidden", ["32", "32"], r"\(64, 64\)"),
                                                  ("transforms.reward_weights.qpos", ["0.5"], "None"),
                                                  ("preset", ["default"], "'cpu_smoke'")])
def test_resume_refuses_changed_settings_naming_them(finished_run, option, value, saved):
    with pytest.raises(ResumeConfigError, match=rf"{option}: saved {saved}, given .*On --resume only these may change"):
        parse_args(["--resume", str(finished_run), f"--{option}", *value])
    # The same option given with its saved value is no change.
    same = {"ppo.lr": ["0.001"], "env.control.mode": ["pd_reference"], "transforms.history": ["reference"],
            "ppo.actor_hidden": ["64", "64"], "transforms.reward_weights.qpos": ["None"], "preset": ["cpu_smoke"]}
    assert parse_args(["--resume", str(finished_run), f"--{option}", *same[option]])[0].resume == str(finished_run)


def test_train_refuses_a_resume_with_other_network_sizes(finished_run):
    cfg = preset_config("cpu_smoke", **{**TINY, "total_env_steps": 32}, run_dir=str(finished_run.parent), name="run",
                        resume=str(finished_run), **{"ppo.actor_hidden": (32, 32)})
    with pytest.raises(ResumeConfigError, match=r"actor_hidden: saved \(64, 64\), given \(32, 32\)"):
        train(cfg)


def test_resuming_a_finished_run_says_so(finished_run, capsys):
    recipe("ppo_walk").main(["--resume", str(finished_run)])
    out = capsys.readouterr().out
    assert "already finished (iteration 2, 16 of 16 env steps)" in out
    assert "env-steps/s" not in out and "done:" not in out
    cfg, _ = parse_args(["--resume", str(finished_run)])
    result = train(cfg)
    assert result.already_finished and result.iterations == 2 and result.env_steps == 16


def test_resume_continues_the_iterations_after_a_kill(tmp_path):
    # Rows logged after the last checkpoint (a run killed between its log row and its checkpoint) are dropped, so
    # the resumed run's rows continue the numbering without repeats.
    recipe("ppo_walk").main(tiny_args(tmp_path, checkpoint_every=2, total_env_steps=24))
    run = tmp_path / "run"
    assert iterations_logged(run) == [1, 2, 3]
    (run / "checkpoints" / "latest.pt").write_bytes((run / "checkpoints" / "iter_000002.pt").read_bytes())
    recipe("ppo_walk").main(["--resume", str(run), "--total_env_steps", "32"])
    assert iterations_logged(run) == [1, 2, 3, 4]


def folder_bytes(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def copy_of(run: Path, root: Path) -> Path:
    """A copy of ``run`` as ``root/run``, for a test that writes to it (``finished_run`` is shared)."""
    shutil.copytree(run, root / "run")
    return root / "run"


@pytest.mark.parametrize("newest", ["iter_000002.pt", "latest.pt"])
def test_resuming_an_older_checkpoint_into_its_own_folder_is_refused_and_changes_nothing(finished_run, tmp_path,
                                                                                          newest):
    # Resumed there, iteration 1 would cut the metrics of iteration 2, overwrite iter_000002.pt (or have its own
    # iteration files pruned at once by newer ones) and set latest.pt back. "latest.pt": the newest checkpoint is
    # only latest.pt (as after a wall-clock tagged save), which is then read to know its iteration.
    run = copy_of(finished_run, tmp_path)
    if newest == "latest.pt":
        (run / "checkpoints" / "iter_000002.pt").unlink()
    before = folder_bytes(run)
    old = run / "checkpoints" / "iter_000001.pt"
    args = ["--resume", str(old), "--run_dir", str(tmp_path), "--name", "run", "--total_env_steps", "32"]
    with pytest.raises(SystemExit) as info:
        recipe("ppo_walk").main(args)
    message = str(info.value.code)
    assert f"{old} holds iteration 1, but its run folder {run} goes on to iteration 2" in message
    assert str(run / "checkpoints" / newest) in message
    assert f"--resume {run}" in message and f"--resume {old} --name NEW" in message
    cfg, _ = parse_args(args)
    with pytest.raises(RunDirError, match="goes on to iteration 2"):
        train(cfg)
    assert folder_bytes(run) == before and iterations_logged(run) == [1, 2]


def test_an_iteration_file_is_resumable_in_its_folder_when_every_newer_one_is_damaged(finished_run, tmp_path):
    # The damaged-latest.pt hint named iter_000001.pt, and resuming it was refused for iter_000002.pt, which was
    # cut short: each message sent the user to the other.
    run = copy_of(finished_run, tmp_path)
    (run / "checkpoints" / "iter_000002.pt").write_bytes(b"")
    (run / "checkpoints" / "latest.pt").write_bytes(b"")
    cfg, _ = parse_args(["--resume", str(run / "checkpoints" / "iter_000001.pt"), "--run_dir", str(tmp_path),
                         "--name", "run"])
    folder = open_run(cfg)
    assert folder.start_iteration == 1
    folder.release()


def test_a_run_folder_without_latest_pt_resumes_from_its_newest_iteration_file(finished_run, tmp_path):
    # A run killed between writing its first iteration file and latest.pt: the folder's resume said "checkpoint not
    # found: .../latest.pt", and a new run of that name said to resume the folder.
    from tocabi_torchrl.rl.checkpoint import checkpoint_file

    run = copy_of(finished_run, tmp_path)
    (run / "checkpoints" / "latest.pt").unlink()
    (run / "checkpoints" / "iter_000010.pt").write_bytes((run / "checkpoints" / "iter_000002.pt").read_bytes())
    (run / "checkpoints" / "iter_000002.pt").touch()  # written last by file time: the name's iteration counts
    assert checkpoint_file(run) == run / "checkpoints" / "iter_000010.pt"
    (run / "checkpoints" / "iter_000010.pt").unlink()
    recipe("ppo_walk").main(["--resume", str(run), "--total_env_steps", "24"])
    assert iterations_logged(run) == [1, 2, 3] and read_checkpoint(run)["iteration"] == 3


def test_resuming_the_newest_iteration_file_into_its_own_folder_goes_on_and_trims(finished_run, tmp_path):
    run = copy_of(finished_run, tmp_path)
    with open(run / "metrics" / "scalars" / "env_steps.csv", "a") as f:
        f.write("3,24\n")  # logged after the last checkpoint by a run killed before its next one
    assert iterations_logged(run) == [1, 2, 3]
    cfg, _ = parse_args(["--resume", str(run / "checkpoints" / "iter_000002.pt"), "--run_dir", str(tmp_path),
                         "--name", "run"])
    assert open_run(cfg).start_iteration == 2 and iterations_logged(run) == [1, 2]


def test_an_older_checkpoint_branches_into_a_new_folder(finished_run, tmp_path):
    run = copy_of(finished_run, tmp_path)
    before = folder_bytes(run)
    old = run / "checkpoints" / "iter_000001.pt"
    recipe("ppo_walk").main(["--resume", str(old), "--run_dir", str(tmp_path), "--name", "branch",
                             "--total_env_steps", "16"])
    assert iterations_logged(tmp_path / "branch") == [2] and read_checkpoint(tmp_path / "branch")["iteration"] == 2
    assert folder_bytes(run) == before


def test_resume_goes_on_in_the_checkpoints_own_folder_wherever_the_run_was_started(finished_run, tmp_path):
    # The saved run_dir is where the run started. From a run folder moved (or a relative run_dir read from another
    # working folder) it named another folder, so --resume refused or silently split the run in two.
    run = copy_of(finished_run, tmp_path)
    before = folder_bytes(finished_run)
    recipe("ppo_walk").main(["--resume", str(run), "--total_env_steps", "24"])
    assert iterations_logged(run) == [1, 2, 3] and read_checkpoint(run)["iteration"] == 3
    assert folder_bytes(finished_run) == before
    # --name alone (the form docs/training.md shows) branches beside the run, not into the saved run_dir.
    recipe("ppo_walk").main(["--resume", str(run), "--total_env_steps", "32", "--name", "branch"])
    assert iterations_logged(tmp_path / "branch") == [4]
    assert folder_bytes(finished_run) == before


def test_max_grad_norm_inf_means_no_clipping_and_nan_is_refused():
    # The one number of the tree that may be infinite (the finiteness check would otherwise refuse it).
    assert preset_config("cpu_smoke", **{"ppo.max_grad_norm": math.inf}).ppo.max_grad_norm == math.inf
    for value in (math.nan, 0.0, "1.0"):
        with pytest.raises(ValueError, match="ppo.max_grad_norm must be"):
            preset_config("cpu_smoke", **{"ppo.max_grad_norm": value})


@pytest.mark.parametrize(("option", "value", "message"), [
    ("ppo.lr", "inf", "ppo.lr must be a finite number"),
    ("ppo.std_start", "inf", "ppo.std_start must be a finite number"),
    ("ppo.value_out_gain", "nan", "ppo.value_out_gain must be a finite number"),
    ("ppo.std_hold", "1.0", "ppo.std_hold is the fraction of training still left when the scheduled std"),
    ("ppo.actor_hidden", "64 0", "ppo.actor_hidden must be one or more positive layer sizes"),
    ("ppo.lr", "1e-6", "ppo.lr 1e-06 is outside the adaptive schedule's range [1e-05, 0.01]"),
    ("eval_seconds", "inf", "eval_seconds must be a finite number"),
    # Named as ppo_walk's option: "seconds=0.001" was play.py's.
    ("eval_seconds", "0.001", "error: --eval_seconds=0.001 is shorter than one policy step (4 ms)"),
    ("env.sim.substeps", "16", "error: --eval_seconds=0.003 is shorter than one policy step (8 ms)"),  # its own step
])
def test_the_recipe_refuses_values_that_would_train_to_nan_or_fail_after_training(tmp_path, option, value, message):
    # Each of these trained to the end before: to a NaN policy logged with zero losses (lr inf, std_start inf,
    # value_out_gain nan), or to a traceback as the network was built (std_hold 1, a 0-wide layer) or after the whole
    # run (eval_seconds); an adaptive lr below the rule's range was raised tenfold at the first high KL.
    with pytest.raises(SystemExit) as info:
        extra = ["--eval_seconds", "0.003"] if option == "env.sim.substeps" else []  # 1 step of 4 ms, 0 of 8
        recipe("ppo_walk").main(tiny_args(tmp_path, eval_at_end=True) + [f"--{option}", *value.split(), *extra])
    assert str(info.value.code).startswith("error: ") and message in str(info.value.code), info.value.code
    assert not (tmp_path / "run").exists()


def test_a_missing_motion_or_model_file_and_a_run_dir_that_is_a_file_are_one_error_line(tmp_path, monkeypatch):
    for option, file in (("--env.task.motion", "none.npz"), ("--env.task.model_path", "none.xml")):
        with pytest.raises(SystemExit) as info:
            recipe("ppo_walk").main(tiny_args(tmp_path, name="m") + [option, str(tmp_path / file)])
        assert str(info.value.code).startswith("error: ") and file in str(info.value.code), info.value.code
    afile = tmp_path / "afile"
    afile.write_text("")
    with pytest.raises(SystemExit) as info:
        recipe("ppo_walk").main(tiny_args(tmp_path, run_dir=afile))
    assert f"error: {afile} is a file, not a folder" in str(info.value.code)
    # A folder the user cannot write was found by the logger's first write, a traceback after the env build. The
    # probe is made to fail here: these tests may run as root, whom permissions do not stop.
    import tempfile

    def refused(*args, dir=None, **kwargs):
        raise PermissionError(13, "Permission denied")

    monkeypatch.setattr(tempfile, "TemporaryFile", refused)
    with pytest.raises(SystemExit) as info:
        recipe("ppo_walk").main(tiny_args(tmp_path, run_dir=tmp_path / "locked" / "runs"))
    assert str(info.value.code) == (f"error: cannot write the run into {tmp_path}/locked/runs/run: "
                                    f"{tmp_path} is not writable (Permission denied); pass --run_dir (and --name) "
                                    "naming a folder you can write")


def test_a_resume_into_a_read_only_checkpoints_folder_is_said_before_it_trains(finished_run, tmp_path, monkeypatch):
    # Only the run folder was probed: one iteration trained and logged, then an OSError traceback at its save.
    import shutil
    import tempfile

    run = tmp_path / "run"
    shutil.copytree(finished_run, run)
    probe = tempfile.TemporaryFile

    def refused_in_checkpoints(*args, dir=None, **kwargs):
        if dir is not None and Path(dir).name == "checkpoints":
            raise PermissionError(13, "Permission denied")
        return probe(*args, dir=dir, **kwargs)

    monkeypatch.setattr(tempfile, "TemporaryFile", refused_in_checkpoints)
    with pytest.raises(SystemExit) as info:
        recipe("ppo_walk").main(["--resume", str(run), "--total_env_steps", "32"])
    assert str(info.value.code).startswith(f"error: cannot write the run into {run}/checkpoints: ")
    assert iterations_logged(run) == [1, 2]


def test_evaluating_and_exporting_a_running_normalization_policy_freeze_its_statistics(tmp_path):
    # The gait test, play.py, compare_gaits and the export normalised with statistics that kept updating from their
    # own rollouts, unlike the contract (the checkpoint's statistics, frozen).
    from tocabi_torchrl.export.onnx_export import load_policy as load_for_export
    from tocabi_torchrl.evaluation.gait_test import evaluate_policy
    from tocabi_torchrl.evaluation.record import load_policy
    from tocabi_torchrl.transforms.normalize import RunningNormalization

    recipe("ppo_walk").main(tiny_args(tmp_path, **{"transforms.normalization": "running"}))
    saved = read_checkpoint(tmp_path / "run")
    for loaded in (load_policy(tmp_path / "run", 2, torch.device("cpu")), load_for_export(tmp_path / "run", 2)):
        norm = [t for t in loaded.env.transform if isinstance(t, RunningNormalization)]
        assert len(norm) == 1 and norm[0].frozen
        count = norm[0].count.clone()
        with torch.no_grad():
            loaded.env.rollout(3, loaded.agent.actor)
        assert torch.equal(norm[0].count, count)
    policy = load_policy(tmp_path / "run", 2, torch.device("cpu"))
    norm = next(t for t in policy.env.transform if isinstance(t, RunningNormalization))
    norm.unfreeze()  # an env handed to evaluate_policy as it is
    mean = norm.mean.clone()
    evaluate_policy(policy.actor, policy.cfg, tmp_path / "eval", num_envs=2, device="cpu", seconds=0.02,
                    video_envs=0, env=policy.env, progress=False)
    assert norm.frozen and torch.equal(norm.mean, mean) and saved["iteration"] == 2


def test_a_new_run_folder_must_be_named_inside_run_dir_but_old_runs_so_named_still_open(finished_run, tmp_path):
    # run_dir/name is the run folder (the benchmarks clear it before timing): a new one never reaches outside run_dir.
    for name in ("/tmp/abs", "../x", "a/b", "a\\b", "..", ""):
        cfg, _ = parse_args(["--run_dir", str(tmp_path), "--name", name])
        with pytest.raises(RunDirError, match=r"name must be one folder name inside run_dir"):
            open_run(cfg)
    with pytest.raises(SystemExit, match=r"name must be one folder name inside run_dir .*got '../x'"):
        recipe("ppo_walk").main(["--run_dir", str(tmp_path), "--name", "../x", "--total_env_steps", "16"])
    assert not (tmp_path.parent / "x").exists()
    # A run made before the rule under a nested name still resumes in its folder.
    nested = tmp_path / "sweeps" / "lr3"
    shutil.copytree(finished_run, nested)
    cfg, _ = parse_args(["--resume", str(nested), "--run_dir", str(tmp_path), "--name", "sweeps/lr3"])
    assert open_run(cfg).start_iteration == 2


def test_a_resume_never_writes_into_an_existing_folder_outside_run_dir(finished_run, tmp_path):
    # Only a run folder is exempt from the name rule: an existing folder that holds no run is a new run folder, and
    # --name ../elsewhere would put the resumed run's files there, outside run_dir.
    (tmp_path / "elsewhere").mkdir()
    (tmp_path / "runs").mkdir()
    cfg, _ = parse_args(["--resume", str(finished_run), "--run_dir", str(tmp_path / "runs"), "--name", "../elsewhere"])
    with pytest.raises(RunDirError, match=r"name must be one folder name inside run_dir .*got '../elsewhere'"):
        open_run(cfg)
    assert not any((tmp_path / "elsewhere").iterdir())


# The recipe run in a child process that pauses, with a line on stdout, where the Ctrl-C is to come: at its first
# import of torch (the seconds of imports), or once the run folder is claimed (the real open_run, then a wait).
_PAUSED_RECIPE = """
import runpy, sys, time

where, recipe = sys.argv[1], sys.argv[2]
if where == "importing":
    class Pause:
        def find_spec(self, name, path=None, target=None):
            if name == "torch":
                sys.meta_path.remove(self)
                print("paused", flush=True)
                time.sleep(60)
            return None

    sys.meta_path.insert(0, Pause())
else:
    import tocabi_torchrl.rl.run_dir as run_dir

    claim = run_dir.open_run

    def open_and_pause(*args, **kwargs):
        run = claim(*args, **kwargs)
        print("paused", flush=True)
        time.sleep(60)
        return run

    run_dir.open_run = open_and_pause
sys.argv = [recipe, *sys.argv[3:]]
runpy.run_path(recipe, run_name="__main__")
"""


@pytest.mark.parametrize("where", ["importing", pytest.param("claimed", marks=pytest.mark.slow),
                                   pytest.param("resumed", marks=pytest.mark.slow)])
def test_ctrl_c_before_training_starts_exits_130_with_one_line(tmp_path, where):
    # Ctrl-C in the recipe's first seconds (imports, checks, the run folder's claim) printed a KeyboardInterrupt
    # traceback; later it stopped cleanly. On a resume it said "no run was written" after open_run had tidied the
    # run folder (its metrics cut back to the checkpoint).
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, (str(RECIPES.parent), os.getenv("PYTHONPATH"))))}
    args = tiny_args(tmp_path)
    if where == "resumed":
        recipe("ppo_walk").main(args)
        args = ["--resume", str(tmp_path / "run"), "--total_env_steps", "24"]
    proc = subprocess.Popen([sys.executable, "-c", _PAUSED_RECIPE, "importing" if where == "importing" else "claimed",
                             str(RECIPES / "ppo_walk.py"), *args], env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    try:
        assert proc.stdout.readline() == "paused\n"
        assert (tmp_path / ".run.claim").exists() == (where != "importing")
        os.kill(proc.pid, signal.SIGINT)
        out, err = proc.communicate(timeout=60)
    finally:
        proc.kill()
    assert proc.returncode == 130, err
    left = "no iteration ran; the same command resumes the run" if where == "resumed" else "no run was written"
    assert "Traceback" not in err and err.strip() == f"stopped (Ctrl-C) before training started; {left}"
    assert not (tmp_path / ".run.claim").exists()  # nothing held
    assert (tmp_path / "run").exists() == (where == "resumed")  # nothing made
    if where == "resumed":
        recipe("ppo_walk").main(args)  # as it said
        assert iterations_logged(tmp_path / "run") == [1, 2, 3]


@pytest.mark.slow  # a training process, then its resume
def test_a_sigkilled_run_leaves_loadable_checkpoints_and_resumes_at_the_next_iteration(tmp_path, capsys):
    # Issue 20 (formerly the soak's kill_resume mode): SIGKILL somewhere in an iteration once two checkpoints exist;
    # every checkpoint left must load and --resume must go on at the next iteration, without repeated rows.
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, (str(RECIPES.parent), os.getenv("PYTHONPATH"))))}
    train = [sys.executable, str(RECIPES / "ppo_walk.py")]
    run, deadline = tmp_path / "run", time.time() + 300
    proc = subprocess.Popen([*train, *tiny_args(tmp_path, total_env_steps=10**9)], env=env, stdout=subprocess.DEVNULL)
    while proc.poll() is None and time.time() < deadline and len(list(run.glob("checkpoints/iter_*.pt"))) < 2:
        time.sleep(0.05)
    time.sleep(0.2)  # somewhere in the next iteration
    assert proc.poll() is None, "the training ended before it could be killed"
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    for path in run.glob("checkpoints/*.pt"):
        read_checkpoint(path)  # raises on a corrupt file
    last = read_checkpoint(run)["iteration"]
    # The resume runs in this process, as the other resume tests here do (a second interpreter cost ~6 s of imports):
    # what the kill left is read by a fresh trainer either way. A refusal or a failure raises here (SystemExit).
    recipe("ppo_walk").main(["--resume", str(run), "--total_env_steps", str((last + 2) * 8)])
    assert f"at iteration {last} " in capsys.readouterr().out and iterations_logged(run) == list(range(1, last + 3))


# ------------------------------------------------------------------------ finding 4: explicit requests are honoured
def test_explicit_cuda_or_gpu_preset_without_cuda_is_refused(finished_run):
    for argv, match in ((["--device", "cuda"], "--device cuda was requested but torch sees no CUDA GPU"),
                        (["--preset", "reference"], "--preset reference is sized for a GPU"),
                        (["--preset", "default", "--env.num_envs", "8"], "--device cpu"),
                        (["--resume", str(finished_run), "--device", "cuda:0"], "no CUDA GPU")):
        with pytest.raises(LaunchError, match=match):
            launch_config(argv, cuda_available=False)
    cfg, _, note = launch_config(["--preset", "reference", "--device", "cpu"], cuda_available=False)
    assert cfg.preset == "reference" and cfg.device == "cpu" and note is None  # asked for explicitly: honoured
    cfg, _, note = launch_config(["--preset", "reference"], cuda_available=True)
    assert cfg.preset == "reference" and note is None


def test_a_gpu_sized_run_asked_for_on_the_cpu_runs_and_says_its_iterations_take_minutes(tmp_path, capsys,
                                                                                       monkeypatch):
    # It ran as asked, with a progress bar that first moved after about 5 minutes (4,096 envs, 2 cores) and nothing
    # saying why: read as a hang. Said after the banner, before the first iteration; small runs say nothing.
    module = recipe("ppo_walk")

    def stop(cfg, run):
        raise KeyboardInterrupt

    monkeypatch.setattr(module, "train", stop)
    for envs, said in ((65, True), (64, False)):
        with pytest.raises(SystemExit):
            module.main(tiny_args(tmp_path, name=f"n{envs}", **{"env.num_envs": envs, "device": "cpu"}))
        out = capsys.readouterr().out
        assert ("note: 65 envs on the CPU: each iteration of" in out) is said, out
        if said:
            assert out.index("training n65") < out.index("note: 65 envs") and "--env.num_envs 8" in out


@pytest.mark.parametrize("preset", sorted(set(PRESETS) - {"cpu_smoke"}))
def test_the_cpu_hint_of_each_gpu_preset_is_a_run_that_ends_and_uses_every_frame(preset):
    # One hint for all: it gave --preset reference a mini-batch of 96, which leaves frames of its 16,384-step rollout
    # out, and a budget under one of its iterations.
    with pytest.raises(LaunchError) as info:
        launch_config(["--preset", preset], cuda_available=False)
    hint = cpu_sized_hint(preset_config(preset))
    assert hint in str(info.value)
    options = hint.removeprefix("pass ").split(" (docs/")[0].split()
    cfg, _, _ = launch_config(["--preset", preset, *options], cuda_available=False)
    assert cfg.device == "cpu" and cfg.env.num_envs <= 8 and cfg.minibatch_note() is None
    assert cfg.frames_per_batch <= cfg.total_env_steps <= 10 * cfg.frames_per_batch


def test_auto_falls_back_to_the_smoke_run_and_the_banner_says_what_runs():
    smoke, given, note = launch_config(["--env.num_envs", "4", "--name", "mine"], cuda_available=False)
    assert smoke.preset == "cpu_smoke" and smoke.device == "cpu" and smoke.env.num_envs == 4 and smoke.name == "mine"
    assert "No CUDA GPU found" in note and "cpu_smoke" in note
    line = banner(smoke, given, torch.device("cpu"))
    assert "preset cpu_smoke, 4 envs" in line and "on cpu" in line and "env.num_envs=4, name=mine" in line
    assert f"{smoke.iterations:,} iterations of {smoke.frames_per_batch:,} env steps" in line
    cfg, _, note = launch_config([], cuda_available=True)
    assert cfg.preset == "default" and cfg.env.num_envs == 4096 and note is None
    # Hyphens, as the command line also takes them, are the same options.
    cfg, given, _ = launch_config(["--env.num-envs", "6", "--ppo.steps-per-env=12", "--name", "mine"],
                                  cuda_available=False)
    assert cfg.env.num_envs == 6 and cfg.ppo.steps_per_env == 12
    line = banner(cfg, given, torch.device("cpu"))
    assert "env.num_envs=6, ppo.steps_per_env=12, name=mine" in line
    # A mini-batch that does not divide the rollout left frames out of every epoch without a word.
    assert line.endswith("\nnote: ppo.minibatch_size 64 leaves 8 of the rollout's 72 frames out of each epoch (11 %; "
                         "each epoch reshuffles, so a different share); 72 divides it")
    assert "note:" not in banner(smoke, given, torch.device("cpu"))  # 4 envs x 16 steps: one mini-batch of 64
    # An empty run_dir writes into the working folder; the banner said "run folder /mine".
    empty, given, _ = launch_config(["--run_dir", "", "--name", "mine"], cuda_available=False)
    assert banner(empty, given, torch.device("cpu")).endswith("; run folder mine")


def test_the_smoke_fallback_note_says_it_will_not_walk_and_how_the_full_run_is_made():
    # The note said what runs and how to shrink the default preset for a CPU, but not that the same command on a
    # GPU machine is the run that learns to walk: a newcomer was left to find it in the docs.
    _, _, note = launch_config([], cuda_available=False)
    assert "it will not walk" in note
    assert "On a machine with a CUDA GPU the same command trains the default preset (4,096 envs" in note, note


def test_a_value_refused_on_the_smoke_fallback_says_the_sizes_are_the_fallbacks():
    # The user asked for the default preset (4,096 envs); the refusal named 8 envs x 16 steps without saying why.
    with pytest.raises(ValueError) as info:
        launch_config(["--ppo.minibatch_size", "4096"], cuda_available=False)
    message = str(info.value)
    assert "exceeds the rollout (8 envs" in message and fallback_said("cpu_smoke") in message, message
    assert message.endswith("pass --device cpu to keep the default preset's sizes)")
    _, _, note = launch_config([], cuda_available=False)
    assert note.startswith(fallback_said("cpu_smoke"))  # the note and the error say it in the same words
    with pytest.raises(ValueError) as info:  # no fallback, nothing to add
        launch_config(["--preset", "cpu_smoke", "--ppo.minibatch_size", "4096"], cuda_available=False)
    assert "CUDA" not in str(info.value)


def test_a_value_wrong_on_every_preset_is_not_blamed_on_the_smoke_fallback():
    # --max_minutes -5 was refused with "(No CUDA GPU found ...; pass --device cpu to keep the default preset's
    # sizes)" appended: that fix changes nothing, the value itself is wrong.
    for argv, start in ((["--max_minutes", "-5"], "max_minutes must be >= 0"),
                        (["--ppo.lr", "-1"], "ppo.lr must be > 0")):
        with pytest.raises(ValueError) as info:
            launch_config(argv, cuda_available=False)
        assert str(info.value).startswith(start) and "CUDA" not in str(info.value), str(info.value)
    with pytest.raises(ValueError, match="pass --device cpu to keep"):  # the fallback's size: still said
        launch_config(["--ppo.minibatch_size", "4096"], cuda_available=False)


def test_a_resumed_gpu_run_without_cuda_says_where_its_device_came_from(finished_run, tmp_path):
    # The run's device comes from its checkpoint, not from the command line: the message must not tell the user to
    # leave --device out (they did) for a smoke run (a resume never falls back to one).
    gpu_run = tmp_path / "gpu_run"
    shutil.copytree(finished_run, gpu_run)
    for path in (gpu_run / "checkpoints").glob("*.pt"):
        ckpt = torch.load(path, weights_only=True)
        ckpt["config"]["device"] = "cuda"
        torch.save(ckpt, path)
    with pytest.raises(LaunchError) as info:
        launch_config(["--resume", str(gpu_run)], cuda_available=False)
    assert "was trained with --device cuda" in str(info.value) and "pass --device cpu" in str(info.value)
    assert "leave --device out" not in str(info.value)
    cfg, _, _ = launch_config(["--resume", str(gpu_run), "--device", "cpu"], cuda_available=False)
    assert cfg.device == "cpu"


def test_a_resume_given_cuda_without_cuda_does_not_offer_the_smoke_run(finished_run):
    # "--resume RUN --device cuda" said "(or leave --device out for the small CPU smoke run)": a resume never falls
    # back to it, and leaving --device out continues on the run's own device.
    with pytest.raises(LaunchError) as info:
        launch_config(["--resume", str(finished_run), "--device", "cuda"], cuda_available=False)
    assert str(info.value).endswith("pass --device cpu to continue the run on the CPU"), str(info.value)
    with pytest.raises(LaunchError, match=r"leave --device out for the small CPU smoke run\)$"):  # a new run does
        launch_config(["--device", "cuda"], cuda_available=False)


def test_torchrun_without_cuda_refuses_the_smoke_fallback():
    # Under torchrun no rank prints the banner that would say the run changed; the request is refused instead.
    with pytest.raises(LaunchError, match="torchrun started several ranks.*--device cpu"):
        launch_config(["--name", "dp"], cuda_available=False, data_parallel=True)
    cfg, _, note = launch_config(["--preset", "cpu_smoke", "--device", "cpu"], cuda_available=False,
                                 data_parallel=True)
    assert cfg.preset == "cpu_smoke" and cfg.device == "cpu" and note is None
    cfg, _, note = launch_config([], cuda_available=True, data_parallel=True)
    assert cfg.preset == "default" and note is None


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks the behaviour without CUDA")
def test_recipe_exits_non_zero_on_an_impossible_device(tmp_path):
    with pytest.raises(SystemExit) as info:
        recipe("ppo_walk").main(["--device", "cuda", "--run_dir", str(tmp_path)])
    assert info.value.code != 0 and "no CUDA GPU" in str(info.value.code)
    assert not (tmp_path / "ppo_walk").exists()


# --------------------------------------------------------------------------------- finding 9: messages and --help
@pytest.mark.skipif(importlib.util.find_spec("wandb") is not None, reason="wandb is installed")
def test_missing_wandb_names_the_install_command(tmp_path):
    with pytest.raises(SystemExit) as info:
        recipe("ppo_walk").main(tiny_args(tmp_path, loggers=("csv", "wandb")))
    assert 'pip install -e ".[wandb]" in the repository' in str(info.value.code)
    assert not (tmp_path / "run").exists()


def test_log_lines_show_a_dash_until_an_episode_ends(tmp_path, capsys):
    from tocabi_torchrl.rl.logging import RunLogger

    logger = RunLogger(tmp_path, preset_config("cpu_smoke", progress_bar=False), total_iterations=3)
    logger.log(1, {"episode_return": math.nan, "episode_length": math.nan, "env_steps_per_s": 10.0})
    logger.log(2, {"episode_return": 12.34, "episode_length": 50.0, "env_steps_per_s": 10.0})
    logger.log(3, {"episode_return": math.nan, "episode_length": math.nan, "env_steps_per_s": 10.0})
    logger.close()
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].startswith("it 1: return - len -") and "nan" not in " ".join(lines)
    assert lines[2].startswith("it 3: return 12.3 len 50")  # the last finished episodes' values


def test_help_names_every_option_once(capsys):
    from tocabi_torchrl.rl.config import RunConfig
    from tocabi_torchrl.tree import leaf_paths

    with pytest.raises(SystemExit) as info:
        parse_args(["--help"])
    assert info.value.code == 0
    options = [word for word in capsys.readouterr().out.split() if word.startswith("--")]
    for path in leaf_paths(RunConfig()):  # --preset and --resume are named in the description too
        assert options.count(f"--{path}") == (2 if path in ("preset", "resume") else 1), path


# ------------------------------------------------------------------------- audit of the command line and run folder
@pytest.mark.parametrize(("option", "value", "message"), [
    ("transforms.obs_clip", "0", "transforms.obs_clip must be a finite number > 0"),
    ("transforms.obs_clip", "-1", "transforms.obs_clip must be a finite number > 0"),
    ("transforms.reward_weights.qpos", "nan", "transforms.reward_weights.qpos must be a finite number"),
    ("seed", str(2 ** 63), "seed must be an int in [0, 2**63 - 1]"),
    ("seed", "-1", "seed must be an int in [0, 2**63 - 1]"),
    ("ppo.lr_end", "0.5", "ppo.lr_end 0.5 is above ppo.lr"),
    ("ppo.std_end", "0.5", "ppo.std_end 0.5 is above ppo.std_start"),
    # A KeyError traceback from the reward transform, after the banner: heading's weight is 0, so it is not in use.
    ("transforms.kick_relax.terms", "heading", "transforms.kick_relax.terms names ['heading'], which no reward term"),
    ("env.task.motion", "", "env.task.motion must be a path to a .npz or reference .txt motion"),  # after the banner
    # Named without its section, and without the way out of a test at the end.
    ("env.num_envs", "0", "env.num_envs must be a positive int, got 0"),
])
def test_values_the_env_or_schedules_would_refuse_are_one_error_line_before_the_banner(tmp_path, capsys, option,
                                                                                        value, message):
    extra = {"ppo.lr_end": ["--ppo.lr_schedule", "linear"],
             "transforms.kick_relax.terms": ["--transforms.kick_relax.seconds", "1"]}.get(option, [])
    with pytest.raises(SystemExit) as info:
        recipe("ppo_walk").main(tiny_args(tmp_path) + [f"--{option}", value, *extra])
    assert str(info.value.code).startswith("error: ") and message in str(info.value.code), info.value.code
    assert "tiny" not in capsys.readouterr().out and not (tmp_path / "run").exists()


def test_no_robots_in_the_test_at_the_end_points_to_eval_at_end():
    from tocabi_torchrl.rl import preset_config

    with pytest.raises(ValueError, match=r"eval_envs must be a positive int \(robots in the gait test at the end\), "
                                         "got 0; for no test at the end, set eval_at_end=false instead"):
        preset_config("cpu_smoke", eval_envs=0)


def test_a_value_refused_while_the_run_is_set_up_is_one_error_line_and_a_bug_in_training_is_not(tmp_path,
                                                                                                monkeypatch):
    from tocabi_torchrl.rl import trainer

    def refusing(*args, **kwargs):
        raise ValueError("clip must be > 0")

    monkeypatch.setattr(trainer, "build_env", refusing)
    with pytest.raises(SystemExit, match=r"^error: clip must be > 0 \(found while the run was being set up"):
        recipe("ppo_walk").main(tiny_args(tmp_path, name="setup"))
    assert not (tmp_path / "setup").exists()
    monkeypatch.undo()
    monkeypatch.setattr(trainer, "_update_stats", refusing)
    with pytest.raises(ValueError, match="clip must be > 0"):  # not turned into an error line: its traceback shows
        recipe("ppo_walk").main(tiny_args(tmp_path, name="training"))


def test_lr_end_is_not_changed_on_resume(finished_run):
    with pytest.raises(ResumeConfigError, match=r"ppo.lr_end: saved 1e-05, given 0.5"):
        parse_args(["--resume", str(finished_run), "--ppo.lr_end", "0.5"])


def test_equal_reward_weights_written_otherwise_resume(tmp_path):
    recipe("ppo_walk").main(tiny_args(tmp_path, **{"transforms.reward_weights.qpos": "0.5"}))
    cfg, _ = parse_args(["--resume", str(tmp_path / "run"), "--transforms.reward_weights.qpos", "0.50",
                         "--transforms.reward_weights.body_vel", "0.90"])
    assert cfg.transforms.reward_weight_map() == {"qpos": 0.5, "body_vel": 0.9}  # the saved weights
    with pytest.raises(ResumeConfigError, match="transforms.reward_weights.qpos: saved 0.5, given 0.6"):
        parse_args(["--resume", str(tmp_path / "run"), "--transforms.reward_weights.qpos", "0.6"])


def saved_with(run: Path, name: str, value) -> Path:
    """``run`` with ``ppo.<name>`` set to ``value`` in every checkpoint's saved config (a run an older version saved)."""
    for file in (run / "checkpoints").glob("*.pt"):
        state = torch.load(file, weights_only=True)
        state["config"]["ppo"][name] = value
        torch.save(state, file)
    return run


def test_a_checkpoint_older_than_a_value_rule_evaluates_with_a_warning_and_resume_explains(finished_run, tmp_path):
    # What /tmp/audit_cli/oldckpt.py did: a run saved before the adaptive schedule's range rule, with ppo.lr 1e-6.
    from tocabi_torchrl.rl.checkpoint import CheckpointError, config_from_checkpoint
    from tocabi_torchrl.evaluation.record import load_policy

    run = saved_with(copy_of(finished_run, tmp_path), "lr", 1e-6)
    state = read_checkpoint(run)
    with pytest.warns(UserWarning, match=r"breaks a rule .*ppo.lr 1e-06 is outside the adaptive schedule's range"):
        assert config_from_checkpoint(state, run).ppo.lr == 1e-6
    with pytest.warns(UserWarning, match="breaks a rule"):
        policy = load_policy(run, 2, torch.device("cpu"))
    assert policy.cfg.ppo.lr == 1e-6
    with pytest.raises(CheckpointError, match=r"breaks a rule .* continue it with the version that wrote it, or "
                                              r"start a new run \(another --name\)"):
        config_from_checkpoint(state, run, strict=True)
    with pytest.raises(SystemExit, match=r"^error: .*breaks a rule.*start a new run"):
        recipe("ppo_walk").main(["--resume", str(run), "--total_env_steps", "24"])
    state["config"]["ppo"]["lr"] = "fast"  # a wrong type is never taken, however lenient
    with pytest.raises(CheckpointError, match="ppo.lr must be a finite number"):
        config_from_checkpoint(state, run)


def test_a_run_saved_with_an_option_that_changes_nothing_resumes_with_a_warning(finished_run, tmp_path):
    # Saved before the rule that refuses it: ppo.lr_end under the adaptive schedule trained as without it, and the
    # resume was refused as if the run could not go on.
    run = saved_with(copy_of(finished_run, tmp_path), "lr_end", 1e-6)
    with pytest.warns(UserWarning, match=r"changes nothing; it is kept as saved .*: ppo.lr_schedule is 'adaptive', "
                                         r"so ppo.lr_end"):
        cfg, _ = parse_args(["--resume", str(run), "--total_env_steps", "24"])
    assert (cfg.ppo.lr_schedule, cfg.ppo.lr_end) == ("adaptive", 1e-6)
    with pytest.warns(UserWarning, match="changes nothing"):
        recipe("ppo_walk").main(["--resume", str(run), "--total_env_steps", "24"])
    assert iterations_logged(run) == [1, 2, 3]
    with pytest.raises(ResumeConfigError, match="ppo.lr_end"):  # changing it is refused as any other option
        parse_args(["--resume", str(run), "--ppo.lr_end", "1e-5"])


def test_help_lists_the_choices_of_every_option_that_takes_one_of_a_few_names(capsys):
    # field_choices says --help lists them; env.control.mode, ppo.value_loss, ppo.activation, ppo.lr_schedule,
    # ppo.grad_sync and --loggers did not.
    from tocabi_torchrl.config import LOGGERS, field_choices

    with pytest.raises(SystemExit):
        parse_args(["--help"])
    text = " ".join(capsys.readouterr().out.replace("│", " ").split())  # tyro wraps lines in boxes
    for path, choices in {**field_choices(), "loggers": LOGGERS}.items():
        start = text.index(f"--{path} ")
        help_text = text[start:text.index(" --", start + 2)]
        assert all(choice in help_text for choice in choices), help_text


def test_help_of_resume_names_every_option_a_resume_may_change(capsys):
    from tocabi_torchrl.rl.resume import RESUME_SAFE

    with pytest.raises(SystemExit):
        parse_args(["--help"])
    text = " ".join(capsys.readouterr().out.replace("│", " ").split())  # tyro wraps lines in boxes
    resume = text[text.index("--resume STR"):text.index("--total_env_steps INT")]
    assert all(path in resume for path in RESUME_SAFE - {"resume"}), resume
    assert "ppo.lr_end" not in RESUME_SAFE


def test_help_of_a_resume_shows_the_saved_runs_values(finished_run, tmp_path, capsys):
    # It showed the preset's (4096 envs, 300 M env steps) for a run of 2 envs and 16 steps.
    from tocabi_torchrl.rl.config import check_command_line

    with pytest.raises(SystemExit):
        check_command_line(["--resume", str(finished_run), "--help"])
    text = " ".join(capsys.readouterr().out.replace("│", " ").split())
    assert re.search(r"--env\.num_envs INT .{0,80}?\(default: 2\)", text), text
    assert re.search(r"--total_env_steps INT .{0,80}?\(default: 16\)", text), text
    with pytest.raises(SystemExit):  # a resume that cannot be read still answers, with the preset's values
        check_command_line(["--resume", str(tmp_path / "none"), "--help"])
    assert "(default: 4096)" in " ".join(capsys.readouterr().out.replace("│", " ").split())


def test_device_cpu_0_trains(tmp_path):
    # It used to be refused at the first env step ("action is on cpu but the env runs on cpu:0"), after the banner.
    recipe("ppo_walk").main(tiny_args(tmp_path, device="cpu:0"))
    assert read_checkpoint(tmp_path / "run")["iteration"] == 2


def test_the_end_of_a_run_is_a_verdict_against_the_gait_criteria_with_the_files_it_wrote(tmp_path, capsys):
    # It ended with a raw dict of 16-digit floats: no pass/fail, no threshold, no path to what it wrote.
    from tocabi_torchrl.evaluation.gait_test import GAIT_CRITERIA

    recipe("ppo_walk").main(tiny_args(tmp_path, eval_at_end=True, eval_envs=2, eval_seconds=0.1))
    out = capsys.readouterr().out
    report = out[out.index("gait test (0.1 s, 2 robots): "):]
    assert "does not walk yet" in report.splitlines()[0] and report.count("FAIL") >= 1
    assert "needs >= 95.0 %" in report and f"needs <= {GAIT_CRITERIA['knee_rms_rad']:.3f} rad" in report
    paths = [Path(word.rstrip(",")) for line in report.splitlines() for word in line.split() if "/" in word]
    summary = tmp_path / "run" / "eval" / "summary.json"
    assert summary in paths and summary.is_file()
    assert f"checkpoint: {tmp_path / 'run' / 'checkpoints' / 'latest.pt'}" in report
    assert f"python recipes/play.py --checkpoint {tmp_path / 'run'}" in report
    assert not re.search(r"\d\.\d{6,}", report), report  # rounded for people; summary.json keeps full precision


def test_ctrl_c_in_the_final_gait_test_says_training_is_saved_and_the_hint_keeps_its_cpu_size(tmp_path, capsys):
    # Ctrl-C during the end-of-run test printed a raw traceback without the checkpoint or the re-test command; with
    # the test off, the hint named play's default size (256 robots for 8 s: minutes on a CPU).
    module = recipe("ppo_walk")

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    module.evaluate_run = interrupted
    with pytest.raises(SystemExit) as info:
        module.main(tiny_args(tmp_path, eval_at_end=True, eval_envs=2, eval_seconds=0.1))
    assert info.value.code == 130  # as every Ctrl-C stop (docs/training.md): a wrapper tells it from a failure
    said = capsys.readouterr().err
    assert "stopped (Ctrl-C) during the gait test; training had finished and is saved." in said
    assert f"checkpoint: {tmp_path / 'run' / 'checkpoints' / 'latest.pt'}" in said
    assert said.rstrip().endswith(f"--checkpoint {tmp_path / 'run'} --num_envs 2 --seconds 0.1")
    assert read_checkpoint(tmp_path / "run")["iteration"] == 2
    assert not (tmp_path / "run" / "eval").exists()  # the empty results folder the test made is gone


@pytest.mark.parametrize("stop,code,said", [
    # SIGTERM there exited 143 without a word; a full disk or a read-only eval folder was a traceback after "done:",
    # without the checkpoint and re-test lines, and a video that failed to write was blamed on OpenGL.
    ("sigterm", 143, "stopped (SIGTERM) during the gait test; training had finished and is saved."),
    ("disk_full", 1, "error: the gait test could not write its results ([Errno 28] No space left on device); "
                     "training had finished and is saved."),
])
def test_a_final_gait_test_stopped_by_sigterm_or_a_full_disk_says_training_is_saved(tmp_path, capsys, stop, code,
                                                                                    said):
    import errno

    module = recipe("ppo_walk")

    def stopped(*args, **kwargs):
        if stop == "sigterm":
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(5)  # the handler raises first
        raise OSError(errno.ENOSPC, "No space left on device")

    module.evaluate_run = stopped
    with pytest.raises(SystemExit) as info:
        module.main(tiny_args(tmp_path, eval_at_end=True, eval_envs=2, eval_seconds=0.1))
    err = capsys.readouterr().err
    assert info.value.code == code and said in err and f"--checkpoint {tmp_path / 'run'} --num_envs 2" in err
    assert not (tmp_path / "run" / "eval").exists()
    assert signal.getsignal(signal.SIGTERM) is signal.SIG_DFL  # put back


def test_a_disk_that_fills_while_training_is_one_error_line_naming_the_resume(tmp_path, monkeypatch):
    # It ended in an OSError traceback from the checkpoint writer, without how to go on.
    import errno

    from tocabi_torchrl.rl import checkpoint

    saved = []

    def full_after_one(path, data):
        if saved:
            raise OSError(errno.ENOSPC, "No space left on device")
        saved.append(path)
        return write(path, data)

    write = checkpoint.atomic_write_bytes
    monkeypatch.setattr(checkpoint, "atomic_write_bytes", full_after_one)
    with pytest.raises(SystemExit) as info:
        recipe("ppo_walk").main(tiny_args(tmp_path))
    assert str(info.value.code) == (f"error: the run could not write its files ([Errno 28] No space left on device); "
                                    f"free space or make {tmp_path / 'run'} writable, then continue from its last "
                                    f"checkpoint with --resume {tmp_path / 'run'}")


def test_the_re_test_hint_keeps_the_cpu_size_without_the_final_test(tmp_path, capsys):
    recipe("ppo_walk").main(tiny_args(tmp_path, eval_at_end=False, eval_envs=2, eval_seconds=0.1))
    assert capsys.readouterr().out.rstrip().endswith(f"--checkpoint {tmp_path / 'run'} --num_envs 2 --seconds 0.1")


def hold_claim(path: Path) -> subprocess.Popen:
    """Another process that claims ``path`` (as its open_run or evaluation would) and keeps it until killed."""
    code = ("import sys, time; from tocabi_torchrl.atomic import claim_path; "
            "print(claim_path(sys.argv[1])[0] is not None, flush=True); time.sleep(120)")
    other = subprocess.Popen([sys.executable, "-c", code, str(path)], stdout=subprocess.PIPE, text=True)
    assert other.stdout.readline().strip() == "True"
    return other


def test_a_second_run_of_the_same_name_started_at_once_is_refused(tmp_path):
    # Both started before either had written config.json, both trained into one folder and both said "done".
    from tocabi_torchrl.rl import preset_config
    from tocabi_torchrl.rl.run_dir import RunDirError, open_run

    cfg = preset_config("cpu_smoke", device="cpu", run_dir=str(tmp_path), name="same")
    other = hold_claim(tmp_path / "same")
    try:
        with pytest.raises(RunDirError, match=rf"another run \(process {other.pid}\) is writing into .*same \(it "
                                              r"holds .*\.same\.claim\); wait"):
            open_run(cfg)
    finally:
        other.kill()
        other.wait()
    run = open_run(cfg)  # killed: the kernel dropped its lock, and the claim is this run's at once
    assert (tmp_path / ".same.claim").read_text() == str(os.getpid())
    # A second open_run of the folder in this process that fails let the first run's claim go with it.
    with pytest.raises(CheckpointError, match="checkpoint not found"):
        open_run(dataclasses.replace(cfg, resume=str(tmp_path / "missing.pt")))
    assert (tmp_path / ".same.claim").is_file()
    run.release()
    assert not (tmp_path / ".same.claim").exists() and not (tmp_path / "same").exists()


@pytest.mark.parametrize("cause", ["another_users_claim", "read_only_folder"])
def test_a_claim_file_that_cannot_be_opened_is_said_with_its_fix(tmp_path, monkeypatch, cause):
    # Another user's claim file in a shared run_dir, or a run_dir this user may not write in, was a raw
    # PermissionError traceback. These tests may run as root, whom permissions do not stop: the open is refused here.
    from tocabi_torchrl.atomic import claim_path
    from tocabi_torchrl.rl import preset_config
    from tocabi_torchrl.rl.run_dir import RunDirError, open_run

    claim = tmp_path / ".shared.claim"
    if cause == "another_users_claim":
        claim.write_text("4242")
    real = os.open

    def refused(path, *args, **kwargs):
        if Path(path) == claim:
            raise PermissionError(13, "Permission denied", str(path))
        return real(path, *args, **kwargs)

    monkeypatch.setattr(os, "open", refused)
    why = (rf"cannot open the claim file {re.escape(str(claim))}: it belongs to another user .*remove the file \(or "
           r"ask its owner to\)"
           if cause == "another_users_claim" else
           rf"cannot create the claim file {re.escape(str(claim))}: this user may not write in "
           rf"{re.escape(str(tmp_path))}")
    with pytest.raises(PermissionError, match=why) as err:
        claim_path(tmp_path / "shared")
    assert err.value.filename == str(claim)
    cfg = preset_config("cpu_smoke", device="cpu", run_dir=str(tmp_path), name="shared")
    with pytest.raises(RunDirError, match=why + r"\. To write this run elsewhere, pass --run_dir \(and --name\)"):
        open_run(cfg)
    assert not (tmp_path / "shared").exists()


def test_a_run_of_its_own_reward_terms_resumed_by_the_recipe_is_told_how_to_go_on(tmp_path):
    # It was a CheckpointError traceback blaming "another observation layout or normalisation?".
    from tocabi_torchrl.rl import preset_config
    from tocabi_torchrl.rl.trainer import build_env
    from tocabi_torchrl.transforms import CallableTerm
    from tocabi_torchrl.transforms.settings import REFERENCE_TERM_NAMES

    cfg = preset_config("cpu_smoke", **TINY, run_dir=str(tmp_path), name="own")
    height = CallableTerm("height", lambda td, nxt: nxt["base_pos"][:, 2:3], weight=0.1)
    train(cfg, env=build_env(cfg, torch.device("cpu"), for_training=True,
                             reward_terms=(*REFERENCE_TERM_NAMES, height)))
    with pytest.raises(SystemExit) as info:
        recipe("ppo_walk").main(["--resume", str(tmp_path / "own"), "--total_env_steps", "32"])
    assert str(info.value.code).startswith("error: checkpoint ") and \
        "it was trained with 14 reward terms, this env has 13: a run trained with terms of its own" in \
        str(info.value.code)


def test_viewer_options_without_the_viewer_are_refused(tmp_path):
    # --viewer.port 18186 without --viewer trained with no page and no word (the banner even listed it).
    with pytest.raises(SystemExit) as info:
        recipe("ppo_walk").main(tiny_args(tmp_path) + ["--viewer.port", "18186"])
    assert str(info.value.code) == ("error: --viewer.port set the live viewer, which is off: add --viewer, or leave "
                                    "them out")
    assert not (tmp_path / "run").exists()
