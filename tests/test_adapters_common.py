"""What every adapter shares, without any RL library installed: version ranges, the policy file, the recipes'
output folder rule and option checks."""

from __future__ import annotations

import importlib.metadata
import json

import pytest
import torch

from tocabi_torchrl.adapters import _versions
from tocabi_torchrl.adapters._versions import LibraryVersionError, require, version_in_range
from tocabi_torchrl.adapters.policy_file import PolicyFileError, load_policy, save_policy
from tocabi_torchrl.adapters.recipe import TimeUp, TrainingClock, open_out_dir, read_resume, write_resume

#: The counters every recipe writes into resume.json (besides the state file it names).
COUNTERS = {"settings": {"num_envs": 2}, "calls": 1, "env_steps": 8, "train_seconds": 1.5, "iterations": 1,
            "snapshots": []}


def test_version_ranges():
    assert version_in_range("5.5.1", "5.0", "6.0")
    assert version_in_range("5.0", "5.0", "6.0")
    assert not version_in_range("6.0.0", "5.0", "6.0")
    assert not version_in_range("4.9.9", "5.0", "6.0")
    assert version_in_range("2.1.1rc1", "2.0", "3.0")


@pytest.mark.parametrize("module", ["rsl_rl", "stable_baselines3", "skrl"])
def test_a_version_outside_the_range_fails_naming_the_range(monkeypatch, module):
    dist, low, high, extra = _versions.SUPPORTED[module]
    real = importlib.metadata.version
    monkeypatch.setattr(importlib.metadata, "version", lambda name: "1.0.0" if name == dist else real(name))
    with pytest.raises(LibraryVersionError) as err:
        require(module)
    message = str(err.value)
    assert f"{dist} 1.0.0 is installed" in message and f"{dist}>={low},<{high}" in message
    assert f'pip install -e ".[{extra}]" in the repository' in message


def test_a_missing_library_says_how_to_install_it(monkeypatch):
    def missing(name):
        raise importlib.metadata.PackageNotFoundError(name)

    monkeypatch.setattr(importlib.metadata, "version", missing)
    with pytest.raises(LibraryVersionError, match=r"rsl-rl-lib is not installed.*rsl-rl-lib>=5.0,<6.0"):
        require("rsl_rl")


def test_the_adapter_import_itself_checks_the_version(monkeypatch):
    # Importing a library adapter (what the recipes do) runs the check before the library is used.
    import sys

    real = importlib.metadata.version
    monkeypatch.setattr(importlib.metadata, "version",
                        lambda name: "9.0" if name == "stable-baselines3" else real(name))
    monkeypatch.delitem(sys.modules, "tocabi_torchrl.adapters.sb3_env", raising=False)
    with pytest.raises(LibraryVersionError, match=r"stable-baselines3>=2.3,<3.0"):
        from tocabi_torchrl.adapters import TocabiSB3VecEnv  # noqa: F401


def test_importing_the_adapters_checks_gymnasiums_version(monkeypatch):
    # gymnasium's range in SUPPORTED was never checked: an older gymnasium failed with a bare ImportError
    # (gymnasium.vector has no AutoresetMode before 1.1) naming neither the version nor the fix.
    import sys

    real = importlib.metadata.version
    monkeypatch.setattr(importlib.metadata, "version", lambda name: "0.29.1" if name == "gymnasium" else real(name))
    for name in [m for m in sys.modules if m == "tocabi_torchrl.adapters" or m.startswith("tocabi_torchrl.adapters.")]:
        monkeypatch.delitem(sys.modules, name)  # put back as they were afterwards
    with pytest.raises(ImportError, match=r"gymnasium 0.29.1 is installed, but .* supports gymnasium>=1.1,<2.0 .*"
                                          r"pip install 'gymnasium>=1.1,<2.0'") as err:
        import tocabi_torchrl.adapters  # noqa: F401
    assert type(err.value).__name__ == "LibraryVersionError"


@pytest.mark.parametrize(("recipe_name", "module", "dist"), [("train_sb3", "sb3_env", "stable-baselines3"),
                                                            ("train_rsl_rl", "rsl_rl_env", "rsl-rl-lib"),
                                                            ("train_skrl", "skrl_env", "skrl")])
def test_a_recipe_without_its_library_ends_in_one_error_line(monkeypatch, tmp_path, recipe_name, module, dist):
    # It used to end in a ~15-line traceback with the install command on its last line.
    import sys

    from recipe_runner import load_recipe

    real = importlib.metadata.version

    def missing(name):
        if name == dist:
            raise importlib.metadata.PackageNotFoundError(name)
        return real(name)

    monkeypatch.setattr(importlib.metadata, "version", missing)
    monkeypatch.delitem(sys.modules, f"tocabi_torchrl.adapters.{module}", raising=False)
    with pytest.raises(SystemExit) as exit_info:
        load_recipe(recipe_name).main(["--out", str(tmp_path / "out"), "--device", "cpu", "--num_envs", "8"])
    message = str(exit_info.value.code)
    assert message.startswith(f"error: {dist} is not installed") and "pip install -e" in message
    assert "\n" not in message and not (tmp_path / "out").exists()


def test_a_policy_or_resume_state_that_appears_after_the_check_is_never_replaced(tmp_path, monkeypatch):
    # save_policy and write_resume checked that their file did not exist, then wrote with replace allowed: a file
    # another call wrote in between was overwritten. Here the check misses it, as it would in that moment.
    from pathlib import Path

    policy, state = tmp_path / "policy.pt", tmp_path / "resume" / "state_call1.pt"
    real = Path.exists
    monkeypatch.setattr(Path, "exists", lambda self, *a, **k: self not in (policy, state) and real(self, *a, **k))
    state.parent.mkdir()
    for path in (policy, state):
        path.write_bytes(b"another call's")
    with pytest.raises(FileExistsError, match="appeared while this one was being written"):
        save_policy(policy, "sb3", {"w": torch.zeros(2)}, {"hidden": [4]})
    with pytest.raises(FileExistsError, match="appeared while this one was being written"):
        write_resume(tmp_path, b"state bytes", COUNTERS)
    assert policy.read_bytes() == state.read_bytes() == b"another call's"
    assert not (tmp_path / "resume.json").is_file() and sorted(p.name for p in tmp_path.rglob("*.tmp")) == []


def test_policy_file_round_trip_and_refusals(tmp_path):
    state = {"w": torch.arange(6.0).reshape(2, 3)}
    path = save_policy(tmp_path / "policy.pt", "sb3", state, {"hidden": [4]})
    meta, loaded = load_policy(path, "sb3")
    assert meta == {"hidden": [4]} and torch.equal(loaded["w"], state["w"])
    with pytest.raises(FileExistsError, match="never overwritten"):
        save_policy(path, "sb3", state, {})
    with pytest.raises(PolicyFileError, match="holds a sb3 policy, not a skrl one"):
        load_policy(path, "skrl")
    (tmp_path / "other.pt").write_bytes(b"not a checkpoint")
    with pytest.raises(PolicyFileError, match="not a readable policy file"):
        load_policy(tmp_path / "other.pt", "sb3")


@pytest.mark.parametrize(("drop", "value", "message"), [
    ("library", None, r"its 'library' is None, not a library's name"),
    ("meta", None, r"its 'meta' is not the text of a JSON object"),
    ("meta", "not json", r"its 'meta' is not the text of a JSON object"),
    ("meta", 3, r"its 'meta' is not the text of a JSON object"),
    ("meta", "[1]", r"its 'meta' is not the text of a JSON object"),
    ("state_dict", None, r"its 'state_dict' is not a dict of named tensors"),
    ("state_dict", [1], r"its 'state_dict' is not a dict of named tensors"),
    ("state_dict", {"w": 3}, r"its 'state_dict' is not a dict of named tensors"),
])
def test_a_policy_file_with_a_missing_or_wrong_field_is_refused_naming_it(tmp_path, drop, value, message):
    # A file naming the format with a field missing ended in a KeyError, a JSONDecodeError or a TypeError from inside
    # load_policy, or loaded a list as the metadata or an int as a weight.
    from tocabi_torchrl.adapters.policy_file import FORMAT

    payload = {"format": FORMAT, "library": "sb3", "meta": "{}", "state_dict": {"w": torch.zeros(2)}}
    if value is None:
        del payload[drop]
    else:
        payload[drop] = value
    torch.save(payload, tmp_path / "policy.pt")
    with pytest.raises(PolicyFileError, match=r"names tocabi_torchrl\.adapters\.policy/1 but was not written by "
                                              r"save_policy: " + message):
        load_policy(tmp_path / "policy.pt", "sb3")


class _Payload:
    """Anything that needs code to unpickle."""


def test_pickled_objects_are_refused(tmp_path):
    torch.save({"format": "x", "obj": _Payload()}, tmp_path / "evil.pt")
    with pytest.raises(PolicyFileError, match="not a readable policy file") as err:
        load_policy(tmp_path / "evil.pt", "sb3")
    # What is wrong, not torch's advice to turn weights_only off, nor its colour codes.
    assert str(err.value).endswith("(UnpicklingError: Unsupported global: GLOBAL test_adapters_common._Payload was "
                                   "not an allowed global)"), str(err.value)


def test_recipes_never_reuse_an_output_folder(tmp_path):
    open_out_dir(tmp_path / "run")
    with pytest.raises(SystemExit, match="exists"):
        open_out_dir(tmp_path / "run")


# Bad values of the options every library recipe shares (base_parser), through train_sb3's own parsing: refused by
# check_args before the library is imported or anything built, with the option, the value and the range.
SHARED_BAD_VALUES = [
    ("--num_envs", "0", "--num_envs must be a positive int, got 0"),
    ("--iterations", "0", "--iterations must be a positive int, got 0"),
    ("--iterations", "-3", "--iterations must be a positive int, got -3"),
    ("--max_minutes", "-1", "--max_minutes must be a finite number >= 0, got -1.0"),
    ("--max_minutes", "nan", "--max_minutes must be a finite number >= 0, got nan"),
    ("--max_minutes", "inf", "--max_minutes must be a finite number >= 0, got inf"),
    ("--checkpoint_minutes", "-0.5", "--checkpoint_minutes must be a finite number >= 0, got -0.5"),
    ("--checkpoint_minutes", "nan", "--checkpoint_minutes must be a finite number >= 0, got nan"),
    ("--checkpoint_minutes", "0.001", "--checkpoint_minutes 0.001 is a snapshot period of 0.06 s"),
    ("--eval_envs", "-1", "--eval_envs must be an int >= 0, got -1"),
    ("--eval_seconds", "nan", "--eval_seconds must be a finite number > 0, got nan"),
    ("--eval_seconds", "0", "--eval_seconds must be a finite number > 0, got 0.0"),
    ("--eval_seconds", "0.001", "--eval_seconds: seconds=0.001 is shorter than one policy step"),
    ("--seed", "-1", "--seed must be an int in [0, 2**32 - 1], got -1"),
    ("--preset", "nope", "--preset: unknown preset 'nope'"),
    ("--device", "gpu", "--device: unknown device 'gpu': use 'cuda', 'cuda:K' or 'cpu' (or 'auto')"),
]


def refused(recipe_name: str, argv: list[str], capsys) -> str:
    """The error line of ``recipes/<recipe_name>.py`` refusing ``argv`` (exit status 2, argparse's)."""
    from recipe_runner import load_recipe

    with pytest.raises(SystemExit) as exit_info:
        load_recipe(recipe_name).main(argv)
    assert exit_info.value.code == 2
    return capsys.readouterr().err.strip().splitlines()[-1]


@pytest.mark.parametrize(("flag", "value", "message"), SHARED_BAD_VALUES,
                         ids=[f"{f}={v}" for f, v, _ in SHARED_BAD_VALUES])
def test_recipes_refuse_a_bad_shared_option_before_creating_the_output_folder(tmp_path, capsys, flag, value, message):
    out = tmp_path / "run"
    argv = ["--out", str(out), "--device", "cpu", "--num_envs", "2", flag, value]
    assert message in refused("train_sb3", argv, capsys)
    assert not out.exists()


@pytest.mark.parametrize(("recipe_name", "argv", "message"), [
    ("train_sb3", ["--batch_size", "1"], "--batch_size must be an int >= 2, got 1"),
    ("train_sb3", ["--n_steps", "0"], "--n_steps must be a positive int, got 0"),
    ("train_sb3", ["--n_steps", "1", "--num_envs", "1"], "--n_steps 1 x --num_envs 1 must be at least 2"),
    ("train_sb3", ["--hidden", "0"], "argument --hidden: must be comma-separated layer sizes >= 1"),
    ("train_rsl_rl", ["--learning_rate", "nan"], "--learning_rate must be a finite number > 0, got nan"),
    ("train_rsl_rl", ["--steps_per_env", "0"], "--steps_per_env must be a positive int, got 0"),
    ("train_skrl", ["--rollouts", "-4"], "--rollouts must be a positive int, got -4"),
    # One sample: both trained, saved and gait-tested a policy whose every weight was NaN, and exited 0.
    ("train_rsl_rl", ["--steps_per_env", "1", "--num_envs", "1"],
     "--steps_per_env 1 x --num_envs 1 must be at least 2"),
    ("train_skrl", ["--rollouts", "1", "--num_envs", "1"], "--rollouts 1 x --num_envs 1 must be at least 2"),
    ("train_skrl", ["--hidden", "64,x"], "must be comma-separated layer sizes >= 1 (e.g. 256,256), got '64,x'"),
])
def test_each_recipe_refuses_a_bad_value_of_its_own_options(tmp_path, capsys, recipe_name, argv, message):
    out = tmp_path / "run"
    assert message in refused(recipe_name, ["--out", str(out), "--device", "cpu", *argv], capsys)
    assert not out.exists()


def test_a_refused_device_leaves_no_output_folder_and_a_rerun_gets_past_the_folder_check(tmp_path, capsys, monkeypatch):
    # The audit's case: --device gpu used to leave an empty --out behind, and the rerun was refused for it.
    from tocabi_torchrl import adapters

    out = tmp_path / "lib_b"
    assert "unknown device 'gpu'" in refused("train_sb3", ["--out", str(out), "--device", "gpu"], capsys)
    assert not out.exists()
    # The rerun with a good device passes the folder check and reaches the env; the folder is created only once the
    # env is built, so an env that cannot be built (ValueError) leaves none either.
    built = []

    def env_that_fails(num_envs, device, **kwargs):
        built.append(device)
        raise ValueError("this env cannot be built")

    # Into the module's dict: getattr would run the adapters' lazy import, which needs stable-baselines3 (not in CI).
    monkeypatch.setitem(vars(adapters), "TocabiSB3VecEnv", env_that_fails)
    from recipe_runner import load_recipe

    with pytest.raises(ValueError, match="this env cannot be built"):
        load_recipe("train_sb3").main(["--out", str(out), "--device", "cpu", "--num_envs", "2"])
    assert built == ["cpu"] and not out.exists()
    # A folder that existed before is never touched: refused as before, its contents kept.
    out.mkdir()
    (out / "earlier.txt").write_text("an earlier run")
    assert "unknown device 'gpu'" in refused("train_sb3", ["--out", str(out), "--device", "gpu"], capsys)
    with pytest.raises(SystemExit, match="exists; pass another --out"):
        load_recipe("train_sb3").main(["--out", str(out), "--device", "cpu", "--num_envs", "2"])
    assert built == ["cpu"] and (out / "earlier.txt").read_text() == "an earlier run"


def test_resume_loads_only_a_state_the_recipe_wrote(tmp_path):
    # The libraries' loaders unpickle the state file, so resume.json may only name one inside <out>/resume/.
    out = tmp_path / "run"
    out.mkdir()
    written = write_resume(out, b"state bytes", COUNTERS)
    assert read_resume(out)["state"] == "resume/state_call1.pt" and written.read_bytes() == b"state bytes"
    (tmp_path / "crafted.pt").write_bytes(b"not ours")
    for state in ("../crafted.pt", str(tmp_path / "crafted.pt")):
        (out / "resume.json").write_text(json.dumps({**COUNTERS, "state": state}))
        with pytest.raises(SystemExit, match="a resume loads only a state this recipe wrote"):
            read_resume(out)
    # a torch state must hold tensors only: a pickled object in it is refused before the library's loader sees it
    torch.save({"iter": 1, "weights": torch.zeros(2)}, out / "resume" / "state_call1.pt")
    (out / "resume.json").write_text(json.dumps({**COUNTERS, "state": "resume/state_call1.pt"}))
    assert read_resume(out, torch_state=True)["calls"] == 1
    torch.save({"iter": 1, "object": TimeUp("pickled")}, out / "resume" / "state_call1.pt")
    with pytest.raises(SystemExit, match="does not load as tensors only"):
        read_resume(out, torch_state=True)
    # a state whose tensor bytes changed after it was written is refused by its zip CRCs, for every library
    torch.save({"iter": 1, "weights": torch.arange(512.0)}, out / "resume" / "state_call1.pt")
    data = bytearray((out / "resume" / "state_call1.pt").read_bytes())
    start = bytes(data).index(torch.arange(512.0).numpy().tobytes()[:64])
    for i in range(start, start + 256, 4):
        data[i] ^= 1
    (out / "resume" / "state_call1.pt").write_bytes(bytes(data))
    assert torch.load(out / "resume" / "state_call1.pt", weights_only=True)["iter"] == 1  # torch reads it silently
    for torch_state in (False, True):
        with pytest.raises(SystemExit, match="is damaged: entry .* fails its CRC-32 check"):
            read_resume(out, torch_state=torch_state)


def test_a_missing_resume_state_is_named_as_missing(tmp_path):
    # A state file deleted, or not copied with the run folder, was reported as one from outside resume/.
    out = tmp_path / "run"
    out.mkdir()
    write_resume(out, b"state bytes", COUNTERS)
    (out / "resume" / "state_call1.pt").unlink()
    with pytest.raises(SystemExit, match=r"names 'resume/state_call1\.pt' as its state file, but .*state_call1\.pt "
                                         r"is missing; restore it \(copy the whole run folder\) or start a new --out"):
        read_resume(out)


def test_training_clock_saves_snapshots_and_stops(tmp_path):
    saved = []
    clock = TrainingClock(tmp_path, saved.append, max_minutes=1.0, checkpoint_minutes=0.5)
    clock()
    assert saved == []
    clock.start -= 31.0
    clock()
    assert [p.name for p in saved] == ["wall_00030s.pt"]
    clock.start -= 30.0
    with pytest.raises(TimeUp, match="max_minutes 1"):
        clock()
    assert [p.name for p in saved] == ["wall_00030s.pt", "wall_00060s.pt"]


def test_snapshot_names_are_rounded_seconds_and_never_shared(tmp_path):
    # A 1 s period that floating point makes a hair shorter: truncating named its marks 0, 1, 2 s (wall_00000s
    # first); rounded, they are 1, 2, 3 s
    saved = []
    clock = TrainingClock(tmp_path, saved.append, checkpoint_minutes=(1 - 1e-12) / 60)
    for _ in range(3):
        clock.start -= 1.0
        clock()
    assert [p.name for p in saved] == ["wall_00001s.pt", "wall_00002s.pt", "wall_00003s.pt"]
    # under 1 s, two marks could round to one name: refused before training, naming the smallest period
    with pytest.raises(ValueError, match=r"0.6 s; snapshots are named by whole seconds .* at least 0.0166667"):
        TrainingClock(tmp_path, saved.append, checkpoint_minutes=0.01)
    # and a name already recorded for this run is never reused silently
    clock = TrainingClock(tmp_path, saved.append, checkpoint_minutes=1 / 60, offset=0.2,
                          snapshots=[str(tmp_path / "checkpoints" / "wall_00001s.pt")])
    clock.start -= 1.0
    with pytest.raises(RuntimeError, match="already one of this run's snapshots"):
        clock()


def test_training_clock_resumes_with_cumulative_time(tmp_path):
    from tocabi_torchrl.adapters.recipe import keep_previous, read_resume, write_resume

    saved = []
    clock = TrainingClock(tmp_path, saved.append, max_minutes=2.0, checkpoint_minutes=0.5, offset=70.0,
                          snapshots=["earlier.pt"])
    assert clock.elapsed >= 70.0 and not clock.time_up
    clock.start -= 21.0  # 91 s in total: the next snapshot is the one at 90 s, not at 30 s
    clock()
    assert [p.name for p in saved] == ["wall_00090s.pt"] and clock.snapshots[0] == "earlier.pt"
    frozen = clock.freeze()
    assert clock.elapsed == frozen
    write_resume(tmp_path, b"x", COUNTERS)
    read = read_resume(tmp_path)
    assert read == {**COUNTERS, "state": "resume/state_call1.pt", "written": read["written"]}
    with pytest.raises(FileExistsError, match="never overwritten"):
        write_resume(tmp_path, b"y", {"calls": 1})
    (tmp_path / "policy.pt").write_text("1")
    assert keep_previous(tmp_path / "policy.pt", "call1") == tmp_path / "policy.pt"
    assert (tmp_path / "policy_call1.pt").read_text() == "1" and not (tmp_path / "policy.pt").exists()
    assert open_out_dir(tmp_path, resume=True) == tmp_path
    with pytest.raises(SystemExit, match="resume.json"):
        open_out_dir(tmp_path / "missing", resume=True)


def test_a_snapshot_left_by_a_killed_call_is_kept_aside(tmp_path):
    # A call killed after a snapshot but before its resume state: the next call (same offset) writes that snapshot
    # again; the orphan is renamed, not overwritten, and the save does not fail.
    from tocabi_torchrl.adapters.recipe import fresh_dir

    (tmp_path / "checkpoints").mkdir()
    (tmp_path / "checkpoints" / "wall_00030s.pt").write_text("killed call")
    saved = []
    clock = TrainingClock(tmp_path, saved.append, checkpoint_minutes=0.5)
    clock.start -= 31.0
    clock()
    assert [p.name for p in saved] == ["wall_00030s.pt"]
    assert (tmp_path / "checkpoints" / "wall_00030s_unresumed0.pt").read_text() == "killed call"
    assert fresh_dir(tmp_path / "logs") == tmp_path / "logs"
    (tmp_path / "logs").mkdir()
    assert fresh_dir(tmp_path / "logs") == tmp_path / "logs_2"


@pytest.mark.parametrize(("text", "message"), [
    ("{", r"is not readable JSON \(Expecting property name"),
    ("[1, 2]", "holds list, not the object of counters a call writes"),
    (json.dumps({k: v for k, v in COUNTERS.items() if k != "settings"}), "lacks 'settings', which every call writes"),
    (json.dumps({**COUNTERS, "calls": "1"}), "has calls='1', which must be an int >= 1"),
    (json.dumps({**COUNTERS, "train_seconds": -2.0}), "has train_seconds=-2.0, which must be a finite number >= 0"),
    (json.dumps({**COUNTERS, "snapshots": None}), "has snapshots=None, which must be a list of paths"),
    (json.dumps({**COUNTERS, "state": 3}), "has state=3, which must be a path"),
])
def test_a_corrupt_or_hand_edited_resume_json_is_refused_with_an_error_line(tmp_path, text, message):
    # A traceback (JSONDecodeError, KeyError in the recipe) used to end the call; now one line names the problem.
    write_resume(tmp_path, b"state", COUNTERS)
    (tmp_path / "resume.json").write_text(text)
    with pytest.raises(SystemExit, match=message) as err:
        read_resume(tmp_path)
    assert str(err.value).startswith(f"error: {tmp_path / 'resume.json'} ")
    assert str(err.value).endswith("restore the file this recipe wrote, or start a new --out")
    (tmp_path / "resume.json").write_bytes(b"\xff\xfe")  # not even text
    with pytest.raises(SystemExit, match="is not readable JSON"):
        read_resume(tmp_path)


def test_a_calls_seed_stays_in_numpys_range():
    # The recipes reseed each call with seed + calls; at the top of the accepted --seed range that left NumPy's
    # [0, 2**32 - 1] and the resumed call crashed.
    from tocabi_torchrl.adapters.recipe import call_seed

    assert call_seed(7, 0) == 7 and call_seed(7, 2) == 9
    assert call_seed(2 ** 32 - 1, 0) == 2 ** 32 - 1 and call_seed(2 ** 32 - 1, 1) == 0
    assert call_seed(2 ** 32 - 2, 3) == 1


def test_the_recipes_gait_test_shows_progress(monkeypatch, tmp_path):
    # The recipes call evaluate_policy_file; the 8 s gait test takes minutes on a CPU and used to print nothing.
    from tocabi_torchrl.adapters import evaluate as ev

    seen = []
    monkeypatch.setattr(ev, "evaluate_policy", lambda *a, **k: seen.append((k["progress"], k["source"])) or {})
    monkeypatch.setattr(ev, "gait_passes", lambda summary: False)

    def load_actor(policy):
        return {"preset": "default", "task": {"seed": 0}}, lambda obs: obs[:, :13]

    assert ev.evaluate_policy_file(load_actor, "policy.pt", tmp_path, num_envs=1, device="cpu") == {"passes": False}
    ev.evaluate_policy_file(load_actor, "policy.pt", tmp_path, num_envs=1, device="cpu", progress=False)
    assert seen == [(True, "policy.pt"), (False, "policy.pt")]  # summary.json names the file it tested


@pytest.mark.parametrize(("meta", "problem"), [
    ({"task": {"seed": 0}}, r"its metadata has no 'preset' \(the name of the preset"),
    ({"preset": "default"}, r"its metadata has no 'task' \(the task options"),
    ({"preset": 3, "task": {}}, r"its metadata's 'preset' is 3, not the name of the preset"),
    ({"preset": "default", "task": [1]}, r"its metadata's 'task' is \[1\], not the task options"),
], ids=["no_preset", "no_task", "preset_not_text", "task_not_a_dict"])
def test_a_policy_file_without_its_preset_or_task_is_refused_naming_file_field_and_fix(tmp_path, monkeypatch, meta,
                                                                                       problem):
    # The recipes always write both; a hand-made or older policy.pt without them ended in a bare KeyError('preset').
    from tocabi_torchrl.adapters import evaluate as ev

    def no_rollout(*args, **kwargs):
        raise AssertionError("the gait test ran")

    monkeypatch.setattr(ev, "evaluate_policy", no_rollout)
    path = save_policy(tmp_path / "policy.pt", "sb3", {"w": torch.zeros(2)}, {"hidden": [4], **meta})

    def load_actor(policy):
        return load_policy(policy, "sb3")[0], lambda obs: obs[:, :13]

    with pytest.raises(PolicyFileError, match=problem) as refused:
        ev.evaluate_policy_file(load_actor, str(path), tmp_path / "eval", num_envs=1, device="cpu")
    message = str(refused.value)
    assert message.startswith(f"{path}: ") and "save_policy(" in message and "'preset'" in message
    assert not (tmp_path / "eval").exists()


#: A complete metadata of each recipe's policy.pt (the fields its load_actor reads), and the library it loads.
_ACTOR_META = {
    "train_sb3": ("sb3", "stable_baselines3", {"obs_dim": 237, "action_low": [-1.0] * 13, "action_high": [1.0] * 13,
                                               "hidden": [8, 8]}),
    "train_skrl": ("skrl", "skrl", {"obs_dim": 237, "action_low": [-1.0] * 13, "action_high": [1.0] * 13,
                                    "hidden": [8, 8]}),
    "train_rsl_rl": ("rsl_rl", "rsl_rl", {"obs_dim": 237, "num_actions": 13, "train_cfg": {}}),
}


@pytest.mark.parametrize(("recipe_name", "field", "value", "problem"), [
    ("train_sb3", "obs_dim", None, r"has no 'obs_dim' \(the observation size"),
    ("train_sb3", "hidden", "256,256", r"'hidden' is '256,256', not the hidden layer widths.*list of positive ints"),
    ("train_sb3", "action_low", [True] * 13, r"'action_low' is \[True, .*, not the action space's lower bounds"),
    ("train_skrl", "action_high", None, r"has no 'action_high' \(the action space's upper bounds"),
    ("train_skrl", "obs_dim", 237.0, r"'obs_dim' is 237.0, not the observation size.*a positive int"),
    ("train_rsl_rl", "num_actions", None, r"has no 'num_actions' \(the action size"),
    ("train_rsl_rl", "train_cfg", [], r"'train_cfg' is \[\], not the rsl_rl runner configuration"),
])
def test_a_recipes_load_actor_refuses_a_policy_file_missing_a_field_naming_file_field_and_fix(
        tmp_path, recipe_name, field, value, problem):
    # A hand-made or older policy.pt without a field load_actor reads ended in a bare KeyError('obs_dim') (or a
    # TypeError from inside the library's network), naming neither the file nor what to add.
    library, module, complete = _ACTOR_META[recipe_name]
    pytest.importorskip(module)
    from recipe_runner import load_recipe

    meta = {"preset": "default", "task": {"seed": 0}, **complete}
    if value is None:
        del meta[field]
    else:
        meta[field] = value
    path = save_policy(tmp_path / "policy.pt", library, {"w": torch.zeros(2)}, meta)
    with pytest.raises(PolicyFileError, match=problem) as refused:
        load_recipe(recipe_name).load_actor(str(path))
    message = str(refused.value)
    assert message.startswith(f"{path}: ") and "load_actor needs to rebuild the network" in message
    assert f"save_policy(new_path, library, state_dict, {{**meta, '{field}': " in message


@pytest.mark.parametrize("meta", [["obs_dim"], {"obs_dim": 237, "hidden": [8, 0]}, {"obs_dim": True}],
                         ids=["not_a_dict", "zero_width", "bool_count"])
def test_require_meta_refuses_what_the_recipes_never_write(meta):
    from tocabi_torchrl.adapters.policy_file import require_meta

    fields = {"obs_dim": ("count", "the observation size"), "hidden": ("sizes", "the hidden layer widths")}
    with pytest.raises(PolicyFileError, match=r"^policy\.pt: its metadata"):
        require_meta(meta, fields, "policy.pt", "the loader needs to rebuild the network")
    complete = {"obs_dim": 237, "hidden": [8, 8], "extra": 1}
    assert require_meta(complete, fields, "policy.pt", "the loader needs them") is complete


def _without_matplotlib(monkeypatch):
    # As on an install without the viz extra: None in sys.modules makes every import of it an ImportError.
    import sys

    for name in [m for m in sys.modules if m == "matplotlib" or m.startswith("matplotlib.")] + ["matplotlib"]:
        monkeypatch.setitem(sys.modules, name, None)


@pytest.mark.parametrize(("recipe_name", "env_class"), [("train_sb3", "TocabiSB3VecEnv"),
                                                        ("train_rsl_rl", "TocabiRslRlEnv"),
                                                        ("train_skrl", "TocabiSkrlEnv")])
def test_a_recipe_without_matplotlib_stops_before_training_unless_the_gait_test_is_off(monkeypatch, tmp_path,
                                                                                       recipe_name, env_class):
    # knees.png needs matplotlib, which no library extra installed: the call trained, saved, ran the gait test's
    # rollout and then ended in a ModuleNotFoundError traceback, without result.json.
    from recipe_runner import load_recipe

    from tocabi_torchrl import adapters
    from tocabi_torchrl.adapters import recipe

    def no_training(*args, **kwargs):
        raise AssertionError("the recipe went on to build its env and train")

    # Into the module's dict: getattr would run the adapters' lazy import, which needs the library (not in CI).
    monkeypatch.setitem(vars(adapters), env_class, no_training)
    _without_matplotlib(monkeypatch)
    out = tmp_path / "run"
    with pytest.raises(SystemExit) as exit_info:
        load_recipe(recipe_name).main(["--out", str(out), "--device", "cpu", "--num_envs", "2"])
    message = str(exit_info.value.code)
    assert message.startswith("error: the gait test draws knees.png with matplotlib, which is not installed")
    assert 'pip install -e ".[viz]"' in message and "--eval_envs 0" in message and "\n" not in message
    assert not out.exists()
    # With the gait test off nothing needs matplotlib: the options pass.
    parser = recipe.base_parser("x", num_envs=2, iterations=1)
    recipe.check_args(parser, parser.parse_args(["--out", str(out), "--device", "cpu", "--eval_envs", "0"]))


def test_the_gait_test_without_matplotlib_names_the_install_before_its_rollout(monkeypatch, tmp_path):
    from tocabi_torchrl.adapters import evaluate as ev

    rollouts = []
    monkeypatch.setattr(ev, "evaluate_policy", lambda *a, **k: rollouts.append(1) or {})
    monkeypatch.setattr(ev, "gait_passes", lambda summary: False)
    _without_matplotlib(monkeypatch)
    with pytest.raises(ImportError, match=r'matplotlib, which is not installed: pip install -e "\.\[viz\]"'):
        ev.evaluate_actions(lambda obs: obs[:, :13], tmp_path, num_envs=1, device="cpu")
    assert rollouts == []


def test_a_signal_during_training_stops_at_the_next_step_and_the_handlers_come_back(tmp_path):
    import os
    import signal

    from tocabi_torchrl.adapters.recipe import Interrupted, exit_status, stop_on_signals

    before = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM)}
    clock = TrainingClock(tmp_path, lambda path: None)
    with stop_on_signals(clock):
        clock()  # no signal yet: a step goes on
        os.kill(os.getpid(), signal.SIGTERM)  # would end the process without the handler
        assert clock.stop_signal == "SIGTERM"
        with pytest.raises(Interrupted, match="SIGTERM"):
            clock()  # the next env step stops training, where TimeUp would
        with pytest.raises(KeyboardInterrupt):
            os.kill(os.getpid(), signal.SIGINT)  # a second signal stops at once
    assert {sig: signal.getsignal(sig) for sig in before} == before
    assert exit_status({"train": {}}) == 0
    assert exit_status({"interrupted": "SIGTERM"}) == 143 and exit_status({"interrupted": "SIGINT"}) == 130
    assert exit_status({"interrupted": "KeyboardInterrupt"}) == 130


def test_an_action_that_requires_grad_steps_the_env_and_the_next_step_too():
    # A policy's output carries its graph; the env wrote it in place into its control buffer, which then joined the
    # graph: every later step failed ("Can't call numpy() on Tensor that requires grad"), even after a reset.
    from tensordict import TensorDict

    from tocabi_torchrl.envs import TocabiWalk

    n = 2
    env = TocabiWalk(num_envs=n, device="cpu", seed=0, control_mode="torque")
    try:
        env.reset()
        weight = torch.zeros(n, 13, requires_grad=True)
        action = weight * 0.5
        out = env.step(TensorDict({"action": action}, batch_size=[n]))["next"]
        assert not env.sim.ctrl.requires_grad and not out["applied_action"].requires_grad
        env.step(TensorDict({"action": torch.zeros(n, 13)}, batch_size=[n]))
        env.step(TensorDict({"action": weight * 0.5}, batch_size=[n]))
        action.sum().backward()  # the caller's graph is left as it was
        assert torch.equal(weight.grad, torch.full((n, 13), 0.5))
    finally:
        env.close()


def test_env_options_of_the_env_config_are_the_config_the_adapter_reports():
    # env_options={"max_episode_steps": 3} ran 3-step episodes while the adapter (rsl_rl's max_episode_length, its
    # logged env.cfg, gymnasium's task_config) reported the preset's 8,000; a key the adapter sets itself crashed
    # from deep inside (num_envs: "got multiple values"; track_episode_return False: at the first step).
    from tocabi_torchrl.adapters._build import build_env

    env, cfg = build_env(2, "cpu", env_options={"max_episode_steps": 3, "control_mode": "torque"})
    assert cfg.env.task.max_episode_steps == env.base_env.cfg.task.max_episode_steps == 3
    assert cfg.env.control.mode == env.base_env.cfg.control.mode == "torque"
    for kwargs, message in ((dict(max_episode_steps=5, env_options={"max_episode_steps": 3}), "given twice"),
                            (dict(env_options={"num_envs": 4}), "the adapter sets these from its own arguments"),
                            (dict(env_options={"transforms": None}), "the adapter sets these from its own arguments"),
                            (dict(env_options={"track_episode_return": False}), "leave it out")):
        with pytest.raises(ValueError, match=message):
            build_env(2, "cpu", **kwargs)
    # Sections and transform settings reached the env alone: the reported config held the preset's kicks and
    # normalisation.
    from tocabi_torchrl.envs.push_config import PushConfig
    from tocabi_torchrl.rl.symmetry import find_normalization
    from tocabi_torchrl.transforms.normalize import RunningNormalization

    env, cfg = build_env(2, "cpu", env_options={"pushes": PushConfig(count=2), "normalization": "running",
                                                "reward_weights": {"qpos": 0.5}})
    assert cfg.env.pushes.count == env.base_env.cfg.pushes.count == 2
    assert cfg.transforms.normalization == "running" and isinstance(find_normalization(env), RunningNormalization)
    assert cfg.transforms.reward_weight_map()["qpos"] == 0.5
    with pytest.raises(ValueError, match="given twice"):
        build_env(2, "cpu", **{"transforms.normalization": "fixed"}, env_options={"normalization": "running"})
    # A weight of a term the config holds none for (heading, a term of one's own) reaches the env as before.
    env, cfg = build_env(2, "cpu", preset="robust", env_options={"reward_weights": {"heading": 0.5}})
    reward = next(t for t in env.transform if type(t).__name__ == "TaskReward")
    assert {t.name: t.weight for t in reward.terms}["heading"] == 0.5


def test_a_star_import_needs_no_optional_library_and_a_numpy_action_is_named():
    # __all__ listed the rsl_rl, SB3 and skrl adapters: the star import failed where those libraries are missing.
    namespace: dict = {}
    exec("from tocabi_torchrl.adapters import *", namespace)
    assert "TocabiVectorEnv" in namespace and "TocabiRslRlEnv" not in namespace
    # rsl_rl's and skrl's steppers take tensors; an array ended in "'numpy.ndarray' object has no attribute 'detach'".
    import numpy as np

    from tocabi_torchrl.adapters._build import build_env
    from tocabi_torchrl.adapters._core import TensorStepper

    stepper = TensorStepper(build_env(2, "cpu")[0], name="test")
    stepper.reset()
    with pytest.raises(TypeError, match=r"actions must be a torch.Tensor of shape \(2, 13\), got ndarray"):
        stepper.step(np.zeros((2, 13), np.float32))


def test_device_none_is_auto_and_an_index_or_other_type_is_named(monkeypatch):
    # SB3 and skrl code passes device=None; None and an int ended in torch's own errors.
    from tocabi_torchrl.adapters._build import build_env

    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    env, _ = build_env(1, None)
    assert env.device == torch.device("cpu")
    with pytest.raises(RuntimeError, match="device 'cuda:0' requested but torch sees no CUDA GPU; pass device='cpu'"):
        build_env(1, 0)
    with pytest.raises(TypeError, match="device must be 'cpu', 'cuda', 'cuda:K', 'auto', a torch.device, a GPU index "
                                        r"or None \(auto\), got 1.5"):
        build_env(1, 1.5)


def test_the_gait_test_takes_a_device_as_the_adapters_do(monkeypatch, tmp_path):
    # evaluate_actions passed anything but text to torch.device: None (the adapters' "auto") ended in torch's
    # TypeError, an int became a CUDA device whether or not torch saw one, and 1.5 was torch's error too.
    from tocabi_torchrl.adapters import evaluate as ev

    devices = []
    monkeypatch.setattr(ev, "evaluate_policy", lambda *a, **k: devices.append(k["device"]) or {})
    monkeypatch.setattr(ev, "gait_passes", lambda summary: False)
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    act = lambda obs: obs[:, :13]  # noqa: E731
    ev.evaluate_actions(act, tmp_path, num_envs=1, device=None)
    ev.evaluate_actions(act, tmp_path, num_envs=1, device=torch.device("cpu"))
    assert devices == [torch.device("cpu")] * 2
    with pytest.raises(RuntimeError, match="device 'cuda:0' requested but torch sees no CUDA GPU; pass device='cpu'"):
        ev.evaluate_actions(act, tmp_path, num_envs=1, device=0)
    with pytest.raises(TypeError, match=r"device must be .* a GPU index or None \(auto\), got 1.5"):
        ev.evaluate_actions(act, tmp_path, num_envs=1, device=1.5)
    assert len(devices) == 2


def _saved_policy(tmp_path, recipe_name: str, meta_changes: dict, train_cfg: dict | None = None):
    """A policy.pt whose state_dict is a real network of ``recipe_name`` (built from :data:`_ACTOR_META`'s sizes, or
    from ``train_cfg`` for rsl_rl) and whose metadata is the complete one with ``meta_changes``."""
    library, module, complete = _ACTOR_META[recipe_name]
    pytest.importorskip(module)
    from recipe_runner import load_recipe

    recipe = load_recipe(recipe_name)
    meta = {"preset": "default", "task": {"seed": 0}, **complete}
    if recipe_name == "train_rsl_rl":
        meta["train_cfg"] = train_cfg
        net = recipe.make_actor(237, 13, train_cfg)
    else:
        from gymnasium import spaces

        obs_space, act_space = spaces.Box(-1.0, 1.0, (237,)), spaces.Box(-1.0, 1.0, (13,))
        if recipe_name == "train_sb3":
            from stable_baselines3.common.policies import ActorCriticPolicy

            net = ActorCriticPolicy(obs_space, act_space, lr_schedule=recipe.LinearLR(0.0, 0.0),
                                    **recipe.policy_kwargs((8, 8)))
        else:
            net = recipe.make_models(obs_space, act_space, "cpu", (8, 8))["policy"]
    meta.update(meta_changes)
    return recipe, save_policy(tmp_path / "policy.pt", library, net.state_dict(), meta)


def _rsl_rl_cfg(**actor) -> dict:
    return {"obs_groups": {"actor": ["policy"], "critic": ["critic"]},
            "actor": {"class_name": "MLPModel", "hidden_dims": [8, 8], "activation": "elu",
                      "distribution_cfg": {"class_name": "GaussianDistribution", "init_std": 0.2, "learn_std": False},
                      **actor}}


@pytest.mark.parametrize(("recipe_name", "changes", "problem"), [
    ("train_sb3", {}, None),
    ("train_sb3", {"hidden": [16, 16]}, r"does not fit the network its metadata describes \(obs_dim=237, "
     r"action_low=\[13 numbers\], action_high=\[13 numbers\], hidden=\[16, 16\]\): "
     r"'mlp_extractor\.policy_net\.0\.weight' is \(8, 237\) in the file but \(16, 237\) in the network"),
    ("train_sb3", {"action_low": [-1.0] * 12}, r"'action_low' has 12 bounds but 'action_high' has 13"),
    ("train_sb3", {"action_low": [1.0] * 13, "action_high": [-1.0] * 13},
     r"'action_low' is above 'action_high' \(or NaN\) at 13 action\(s\), first action 0: 1\.0 > -1\.0"),
    ("train_skrl", {}, None),
    ("train_skrl", {"hidden": [8]}, r"hidden=\[8\]\): 'net\.2\.weight' is \(8, 8\) in the file but \(13, 8\) in the "
     r"network.*the file has 2 tensor\(s\) the network lacks \(\['net\.4\.weight', 'net\.4\.bias'\]\)"),
    ("train_skrl", {"obs_dim": 236}, r"'net\.0\.weight' is \(8, 237\) in the file but \(8, 236\) in the network"),
    ("train_skrl", {"action_high": [1.0] * 14}, r"'action_low' has 13 bounds but 'action_high' has 14"),
    ("train_rsl_rl", {}, None),
    ("train_rsl_rl", {"num_actions": 12}, r"num_actions=12.*'distribution\.std_param' is \(13,\) in the file but "
     r"\(12,\) in the network"),
    ("train_rsl_rl", {"train_cfg": {"obs_groups": {"actor": ["policy"]}}},
     r"its metadata's 'train_cfg' has no 'actor' \(the actor's settings.*which make_actor needs to rebuild the "
     r"network.*\{\*\*meta, 'train_cfg': \{\*\*meta\['train_cfg'\], 'actor': <a JSON object>\}\}"),
    ("train_rsl_rl", {"train_cfg": _rsl_rl_cfg(hidden_dimz=[8, 8])},
     r"the network its metadata describes \(obs_dim=237, num_actions=13, train_cfg=.*\) cannot be built: "
     r"TypeError: .*hidden_dimz"),
    ("train_rsl_rl", {"train_cfg": _rsl_rl_cfg(hidden_dims=[4, 8])}, r"'mlp\.0\.weight' is \(8, 237\) in the file "
     r"but \(4, 237\) in the network"),
])
def test_a_recipes_load_actor_refuses_metadata_that_does_not_fit_the_weights_naming_file_fields_and_fix(
        tmp_path, recipe_name, changes, problem):
    # A field of the right kind but a value that does not fit the saved weights (other hidden widths, bounds of
    # another length, a train_cfg without 'actor') ended in torch's size-mismatch RuntimeError, gymnasium's Box error
    # or a KeyError from inside make_actor, none naming the file or the field to fix.
    recipe, path = _saved_policy(tmp_path, recipe_name, changes, _rsl_rl_cfg())
    if problem is None:  # the metadata the weights were saved with loads, and the actor acts
        meta, act = recipe.load_actor(str(path))
        assert act(torch.zeros(2, 237)).shape == (2, 13)
        return
    with pytest.raises(PolicyFileError, match=problem) as refused:
        recipe.load_actor(str(path))
    message = str(refused.value)
    assert message.startswith(f"{path}: ") and "save_policy(new_path, library, state_dict, {**meta, " in message


def test_pyproject_declares_the_supported_ranges():
    # The adapters refuse a version outside SUPPORTED; pyproject declaring a wider range (gymnasium>=1.1 with no cap)
    # let pip install a version that the first import then refuses.
    import pathlib
    import re

    tomllib = pytest.importorskip("tomllib")  # Python 3.11 on

    project = tomllib.loads((pathlib.Path(__file__).parents[1] / "pyproject.toml").read_text())["project"]
    groups = {"": project["dependencies"], **project["optional-dependencies"]}
    for module, (dist, low, high, extra) in _versions.SUPPORTED.items():
        declared = {}  # group -> (lowest, first excluded) of each requirement naming dist
        for group, requirements in groups.items():
            for requirement in requirements:
                match = re.fullmatch(rf"{re.escape(dist)}(?![\w.-])(.*)", requirement)
                if match:
                    bounds = dict((op, v) for op, v in re.findall(r"(>=|<)\s*([\w.]+)", match.group(1)))
                    declared[group] = (bounds.get(">="), bounds.get("<"))
        assert extra in declared, f"{dist} is not declared in pyproject's {extra or 'dependencies'}"
        for group, (lo, hi) in declared.items():
            where = f"{dist} in pyproject's {group or 'dependencies'}"
            assert lo is not None and hi is not None, f"{where} has no upper or lower bound; SUPPORTED: >={low},<{high}"
            assert _same_version(lo, low) and _same_version(hi, high), (
                f"{where}: >={lo},<{hi}; SUPPORTED: >={low},<{high}")


def _same_version(a: str, b: str) -> bool:
    """Equal as release versions: "6" is "6.0"."""
    a, b = _versions._parse(a), _versions._parse(b)
    width = max(len(a), len(b))
    return a + (0,) * (width - len(a)) == b + (0,) * (width - len(b))


def test_the_robust_gait_test_runs_on_any_librarys_policy(tmp_path):
    # The recipes' policies (another library's network) could only get the standard test: play.py refuses their
    # files, so a --preset robust run had no way to the robust test's verdict.
    from tocabi_torchrl.adapters.evaluate import evaluate_actions
    from tocabi_torchrl.evaluation.robust import CASES, robust_passes

    def act(obs):  # (N, 237) -> (N, 13): the zero action, deterministic as a policy's mean
        return torch.zeros(obs.shape[0], 13, device=obs.device)

    report = evaluate_actions(act, tmp_path, num_envs=2, device="cpu", seconds=0.1, progress=False, test="robust",
                              source="policy.pt")
    saved = json.loads((tmp_path / "robust.json").read_text())
    assert (tmp_path / "robust.png").is_file() and not (tmp_path / "summary.json").exists()
    assert report["test"] == saved["test"] == "robust" and saved["checkpoint"] == "policy.pt"
    assert list(saved["cases"]) == list(CASES) and saved["settings"]["num_envs"] == 2
    assert report["passes"] is saved["passes"] is robust_passes(saved)


def test_a_gait_test_the_recipes_do_not_know_or_a_standard_option_for_the_robust_one_is_refused(tmp_path):
    # Each is named with its fix before any policy loads or env is built; a command would have been ignored by the
    # robust test, whose commands are its cases'.
    from tocabi_torchrl.adapters.evaluate import evaluate_actions, evaluate_policy_file

    def load_actor(policy):
        raise AssertionError("the policy loaded before its test's options were checked")

    act = lambda obs: obs[:, :13]  # noqa: E731
    with pytest.raises(ValueError, match=r"test must be 'standard' \(the 8 s test at one command\) or 'robust' .*"
                                         r"got 'Robust'"):
        evaluate_actions(act, tmp_path, num_envs=1, device="cpu", test="Robust")
    with pytest.raises(ValueError, match=r"test must be 'standard' .* or 'robust' .*got 'pushed'"):
        evaluate_policy_file(load_actor, "policy.pt", tmp_path, num_envs=1, device="cpu", test="pushed")
    fix = r"the robust test's commands are its cases' \(leave command out, or pass test='standard'\)"
    with pytest.raises(ValueError, match=r"command=\(0\.3, 0\.0\) sets the standard test's command; " + fix):
        evaluate_actions(act, tmp_path, num_envs=1, device="cpu", command=(0.3, 0.0), test="robust")
    with pytest.raises(ValueError, match=r"command=\(0\.3, 0\.0\) sets the standard test's command; " + fix):
        evaluate_policy_file(load_actor, "policy.pt", tmp_path, num_envs=1, device="cpu", command=(0.3, 0.0),
                             test="robust")
    with pytest.raises(ValueError, match=r"video_envs=2 sets the standard test's video; the robust test records none "
                                         r"\(leave video_envs out, or pass test='standard'\)"):
        evaluate_actions(act, tmp_path, num_envs=1, device="cpu", video_envs=2, test="robust")
    assert list(tmp_path.iterdir()) == []


def test_a_policy_file_saved_before_a_preset_was_renamed_reads_its_recipes_name_now(tmp_path):
    # policy.pt's metadata keeps the preset's name only: a file written before "torque" was renamed "torque_ideal"
    # (no "written" day) trained the recipe now named torque_ideal, and its gait test must rebuild that task.
    state = {"w": torch.zeros(2)}
    path = save_policy(tmp_path / "policy.pt", "sb3", state, {"preset": "torque", "task": {}})
    payload = torch.load(path, weights_only=True)
    assert payload["written"] >= "2026-12-06" and load_policy(path, "sb3")[0]["preset"] == "torque"
    del payload["written"]  # as every recipe wrote it before
    torch.save(payload, tmp_path / "old.pt")
    assert load_policy(tmp_path / "old.pt", "sb3")[0] == {"preset": "torque_ideal", "task": {}}
    payload["meta"] = json.dumps({"preset": "default", "task": {}})  # a name never renamed reads as written
    torch.save(payload, tmp_path / "old_default.pt")
    assert load_policy(tmp_path / "old_default.pt", "sb3")[0]["preset"] == "default"
    for bad in ("6/12/2026", "2026-13-01", 20261206, None):  # not a day as save_policy writes it: refused, named
        torch.save({**payload, "written": bad}, tmp_path / "bad.pt")
        with pytest.raises(PolicyFileError, match=r"its 'written' is .*, not a day \(YYYY-MM-DD\)"):
            load_policy(tmp_path / "bad.pt", "sb3")


def test_a_resume_saved_before_a_preset_was_renamed_reads_its_recipes_name_now(tmp_path):
    # resume.json keeps the preset's name only: one written before "torque" was renamed "torque_ideal" (no "written"
    # day) ran the recipe now named torque_ideal, and a --resume must name that, not the new torque preset.
    import io

    buffer = io.BytesIO()
    torch.save({"w": torch.zeros(2)}, buffer)
    write_resume(tmp_path, buffer.getvalue(), {**COUNTERS, "settings": {"num_envs": 2, "preset": "torque"}})
    saved = json.loads((tmp_path / "resume.json").read_text())
    assert saved["written"] >= "2026-12-06" and read_resume(tmp_path)["settings"]["preset"] == "torque"
    del saved["written"]  # as every call wrote it before
    (tmp_path / "resume.json").write_text(json.dumps(saved))
    assert read_resume(tmp_path)["settings"] == {"num_envs": 2, "preset": "torque_ideal"}
    assert read_resume(tmp_path, torch_state=True)["settings"]["preset"] == "torque_ideal"
    # A day that is not one (a hand edit) is refused by name, not read as "before every rename".
    for bad in ("06.12.2026", "2026-13-01", 20261206, None):
        (tmp_path / "resume.json").write_text(json.dumps({**saved, "written": bad}))
        with pytest.raises(SystemExit, match=r"has written=.*, which must be the UTC day a call wrote it"):
            read_resume(tmp_path)
