"""Checkpoint files: no code runs on load, bad files give CheckpointError naming the file, atomic writes, retention."""

from __future__ import annotations

import os
from pathlib import Path

import pytest
import torch

from tocabi_torchrl.rl import preset_config
from tocabi_torchrl.rl.checkpoint import (SCHEMA_VERSION, CheckpointError, config_from_checkpoint, load_checkpoint,
                                          prune_checkpoints, read_checkpoint, save_checkpoint)
from tocabi_torchrl.rl.trainer import build_agent, make_optimizer

CPU = torch.device("cpu")
SHIPPED_POLICY = Path(__file__).resolve().parents[1] / "assets" / "policies" / "tocabi_walk_ppo.pt"


def _config(**overrides):
    return preset_config("cpu_smoke", device="cpu", **{"env.num_envs": 4, "ppo.minibatch_size": 16}, **overrides)


def _saved_run(tmp_path: Path, iterations=(1,), **overrides) -> tuple[Path, object]:
    cfg = _config(**overrides)
    agent = build_agent(cfg, 237, 13, CPU)
    optimizer = make_optimizer(cfg, agent, CPU)
    for it in iterations:
        save_checkpoint(tmp_path / "run", it, 64 * it, agent, optimizer, None, cfg)
    return tmp_path / "run", agent


class _RunsCode:
    """Unpickling this object calls ``open(marker, "w")``: a stand-in for a shell command in a crafted file."""

    def __init__(self, marker: Path):
        self.marker = str(marker)

    def __reduce__(self):
        return open, (self.marker, "w")


def test_a_crafted_checkpoint_runs_no_code(tmp_path):
    from tocabi_torchrl.evaluation.gait_test import evaluate_run

    marker = tmp_path / "code_ran"
    run, agent = _saved_run(tmp_path)
    state = torch.load(run / "checkpoints" / "latest.pt", weights_only=True)
    state["iteration"] = _RunsCode(marker)
    crafted = tmp_path / "crafted.pt"
    torch.save(state, crafted)
    with pytest.raises(CheckpointError, match=r"refusing to load .*crafted\.pt.*could run code"):
        load_checkpoint(crafted, agent)
    with pytest.raises(CheckpointError, match="crafted.pt"):
        evaluate_run(crafted, num_envs=1, device="cpu")
    assert not marker.exists(), "loading the checkpoint executed code from it"


@pytest.mark.parametrize("kind", ["random", "truncated", "empty", "not_a_dict", "no_agent"])
def test_unreadable_files_raise_checkpoint_error_naming_the_file(tmp_path, kind):
    run, agent = _saved_run(tmp_path)
    good = (run / "checkpoints" / "latest.pt").read_bytes()
    bad = tmp_path / f"{kind}.pt"
    if kind == "random":
        bad.write_bytes(torch.randint(0, 256, (4096,), dtype=torch.uint8, generator=torch.Generator().manual_seed(0))
                        .numpy().tobytes())
    elif kind == "truncated":
        bad.write_bytes(good[: len(good) // 2])
    elif kind == "empty":
        bad.write_bytes(b"")
    elif kind == "not_a_dict":
        torch.save([torch.zeros(3)], bad)
    else:
        state = torch.load(run / "checkpoints" / "latest.pt", weights_only=True)
        del state["agent"]
        torch.save(state, bad)
    with pytest.raises(CheckpointError, match=f"{kind}.pt"):
        load_checkpoint(bad, agent)


def test_a_device_it_cannot_load_onto_is_said_not_read_as_a_damaged_file(tmp_path):
    # torch.load's own failure for the device was reported as a truncated or corrupt checkpoint (and a resume then
    # offered another checkpoint of the run in its place).
    run, _ = _saved_run(tmp_path)
    with pytest.raises(ValueError, match=r"unknown device 'cude': use 'cuda', 'cuda:K' or 'cpu'"):
        read_checkpoint(run, device="cude")
    if not torch.cuda.is_available():
        with pytest.raises(RuntimeError, match=r"torch sees no CUDA GPU; pass device='cpu'") as raised:
            read_checkpoint(run, device="cuda")
        assert not isinstance(raised.value, CheckpointError)
    assert read_checkpoint(run, device=torch.device("cpu"))["iteration"] == 1

def test_saved_checkpoints_are_versioned_and_load_with_weights_only(tmp_path):
    run, agent = _saved_run(tmp_path)
    state = torch.load(run / "checkpoints" / "latest.pt", weights_only=True)
    assert state["schema_version"] == SCHEMA_VERSION
    assert config_from_checkpoint(read_checkpoint(run)).env.num_envs == 4
    state["schema_version"] = SCHEMA_VERSION + 1
    torch.save(state, tmp_path / "future.pt")
    with pytest.raises(CheckpointError, match="newer than this tocabi-torchrl reads"):
        read_checkpoint(tmp_path / "future.pt")
    state["schema_version"] = SCHEMA_VERSION
    state["config"]["warp_speed"] = 9
    torch.save(state, tmp_path / "alien.pt")
    with pytest.raises(CheckpointError, match=r"alien\.pt: config has unknown field\(s\) \['warp_speed'\]"):
        config_from_checkpoint(read_checkpoint(tmp_path / "alien.pt"), tmp_path / "alien.pt")


@pytest.mark.skipif(not SHIPPED_POLICY.is_file(), reason="shipped policy not present")
def test_the_shipped_policy_holds_the_current_schema_and_loads():
    # Trained before the schema was versioned, re-saved with its config in the current tree (no train_seconds: the
    # run did not count them).
    state = read_checkpoint(SHIPPED_POLICY)
    assert state["schema_version"] == SCHEMA_VERSION and "train_seconds" not in state
    cfg = config_from_checkpoint(state, SHIPPED_POLICY)
    assert cfg.ppo.actor_hidden == (400, 200, 100) and cfg.ppo.store_env_signals is False  # a field it predates
    load_checkpoint(SHIPPED_POLICY, build_agent(cfg, 237, 13, CPU))


def test_a_network_size_mismatch_names_the_tensors_not_a_state_dict(tmp_path):
    run, _ = _saved_run(tmp_path)
    other = build_agent(_config(**{"ppo.actor_hidden": (32, 32)}), 237, 13, CPU)
    with pytest.raises(CheckpointError, match=r"does not fit this agent's actor .*mean_net.0.weight: file "
                                              r"\(64, 237\) vs \(32, 237\)") as info:
        load_checkpoint(run, other)
    assert len(str(info.value)) < 800


def test_checkpoint_writes_are_atomic(tmp_path, monkeypatch):
    # A crash while latest.pt is being replaced must leave the previous latest.pt readable.
    import tocabi_torchrl.atomic as atomic

    run, agent = _saved_run(tmp_path, iterations=(1,))
    cfg = _config()
    real_replace = atomic.os.replace

    def crash_on_latest(src, dst):
        if Path(dst).name == "latest.pt":
            raise KeyboardInterrupt("killed mid-write")
        return real_replace(src, dst)

    monkeypatch.setattr(atomic.os, "replace", crash_on_latest)
    with pytest.raises(KeyboardInterrupt):
        save_checkpoint(run, 2, 128, agent, None, None, cfg)
    monkeypatch.setattr(atomic.os, "replace", real_replace)
    assert read_checkpoint(run)["iteration"] == 1
    assert not list((run / "checkpoints").glob(".*.tmp")), "the failed write left its temporary file behind"


@pytest.mark.skipif(os.name != "posix", reason="POSIX permission bits")
def test_atomic_writes_get_the_permissions_of_a_plain_write(tmp_path):
    # mkstemp creates files 0o600; a checkpoint, export or config must be readable as open(path, "w") would leave it
    # (0o666 less the umask), and a rewritten file keeps the mode its owner gave it.
    from tocabi_torchrl.atomic import atomic_write_text

    old = os.umask(0o022)
    try:
        new = atomic_write_text(tmp_path / "new.json", "{}")
        assert new.stat().st_mode & 0o777 == 0o644
        os.umask(0o077)
        assert atomic_write_text(tmp_path / "private.json", "{}").stat().st_mode & 0o777 == 0o600
    finally:
        os.umask(old)
    new.chmod(0o640)
    assert atomic_write_text(new, '{"a": 1}').stat().st_mode & 0o777 == 0o640
    assert new.read_text() == '{"a": 1}'


def test_an_atomic_write_that_must_not_replace_leaves_a_file_that_appeared_meanwhile(tmp_path, monkeypatch):
    # A writer checks at its start that its output is free, then writes it: os.replace overwrote a file created in
    # between. With replace=False the write refuses it instead, and leaves no temporary file.
    import errno

    import tocabi_torchrl.atomic as atomic

    target = tmp_path / "metrics.json"
    real_create = atomic._create_temp

    def someone_else_writes_first(path):
        made = real_create(path)
        path.write_text("theirs")
        return made

    monkeypatch.setattr(atomic, "_create_temp", someone_else_writes_first)
    with pytest.raises(FileExistsError, match="appeared while this one was being written") as info:
        atomic.atomic_write_text(target, "ours", replace=False)
    assert info.value.filename == str(target) and target.read_text() == "theirs"
    assert not list(tmp_path.glob(".*.tmp")), "the refused write left its temporary file behind"
    assert atomic.atomic_write_text(target, "ours").read_text() == "ours"  # replace=True (the default) replaces
    monkeypatch.setattr(atomic, "_create_temp", real_create)
    # A file system without hard links: checked just before the rename instead.
    monkeypatch.setattr(atomic.os, "link", lambda src, dst: (_ for _ in ()).throw(OSError(errno.EPERM, "no links")))
    with pytest.raises(FileExistsError, match="appeared while this one was being written"):
        atomic.atomic_write_text(target, "again", replace=False)
    assert atomic.atomic_write_text(tmp_path / "new.json", "{}", replace=False).read_text() == "{}"
    assert target.read_text() == "ours" and not list(tmp_path.glob(".*.tmp"))


def test_retention_keeps_the_last_k_and_every_mth(tmp_path):
    run, _ = _saved_run(tmp_path, iterations=range(1, 13), checkpoint_keep_last=3, checkpoint_keep_every=5)
    names = sorted(p.name for p in (run / "checkpoints").iterdir())
    assert names == ["iter_000005.pt", "iter_000010.pt", "iter_000011.pt", "iter_000012.pt", "latest.pt"]
    assert prune_checkpoints(run / "checkpoints", keep_last=0, keep_every=0) == []  # 0: keep everything
    assert _config().checkpoint_keep_last == 3 and _config().checkpoint_keep_every == 50


def test_policy_file_keeps_the_policy_and_drops_training_state(tmp_path):
    from tocabi_torchrl.rl.checkpoint import write_policy_file

    # A torque-preset run: its checkpoints also hold the assist's teacher.
    run, agent = _saved_run(tmp_path, **{"env.control.mode": "torque", "ppo.torque_assist": 1.0,
                                         "ppo.assist_fade_start": 0, "ppo.assist_fade_end": 10,
                                         "ppo.assist_target": "teacher"})
    full = read_checkpoint(run)
    assert "teacher" in full["agent"] and full["optimizer"] is not None
    out = write_policy_file(run, tmp_path / "ship" / "policy.pt")
    small = read_checkpoint(out)
    assert small["optimizer"] is None and set(small["agent"]) == {"actor", "critic"}
    assert small["config"] == full["config"] and small["env_steps"] == full["env_steps"]
    for part in ("actor", "critic"):
        for k, v in full["agent"][part].items():
            assert torch.equal(small["agent"][part][k], v)
    assert out.stat().st_size < (run / "checkpoints" / "latest.pt").stat().st_size
    fresh = build_agent(config_from_checkpoint(small), 237, 13, CPU)
    fresh.load_state_dict(small["agent"])  # loads without a teacher
    with pytest.raises(FileExistsError, match="overwrite=True"):
        write_policy_file(run, out)
    write_policy_file(run, out, overwrite=True)
    # A run saved before an option existed: the shipped file names it, with the value the run trained with.
    older = read_checkpoint(run)
    del older["config"]["ppo"]["overlap_update"]
    torch.save(older, tmp_path / "older.pt")
    shipped = read_checkpoint(write_policy_file(tmp_path / "older.pt", tmp_path / "older_policy.pt"))
    assert shipped["config"] == full["config"] and shipped["config"]["ppo"]["overlap_update"] is False


def test_a_policy_file_that_appears_while_one_is_written_is_not_replaced(tmp_path, monkeypatch):
    # write_policy_file checked that `out` was free, then renamed its file over whatever was there by then.
    import tocabi_torchrl.rl.checkpoint as checkpoint

    run, _ = _saved_run(tmp_path)
    out = tmp_path / "policy.pt"
    real = checkpoint.config_from_checkpoint

    def another_export_writes_first(*args, **kwargs):  # runs after the existence check, before the write
        out.write_bytes(b"theirs")
        return real(*args, **kwargs)

    monkeypatch.setattr(checkpoint, "config_from_checkpoint", another_export_writes_first)
    with pytest.raises(FileExistsError, match="appeared while this one was being written"):
        checkpoint.write_policy_file(run, out)
    assert out.read_bytes() == b"theirs" and not list(tmp_path.glob(".*.tmp"))
    assert read_checkpoint(checkpoint.write_policy_file(run, out, overwrite=True))["iteration"] == 1

@pytest.mark.parametrize("part, key, value", [
    ("actor", None, float("nan")), ("critic", None, float("inf")),
    ("transforms", "transforms.3.var", float("nan")), ("transforms", "transforms.3.loc", float("-inf")),
])
def test_a_diverged_checkpoint_is_refused_for_evaluation_and_resume(tmp_path, part, key, value):
    from tocabi_torchrl.rl.run_dir import open_run

    run, _ = _saved_run(tmp_path)
    file = run / "checkpoints" / "latest.pt"
    state = torch.load(file, weights_only=True)
    if part == "transforms":
        state["transforms"] = {"transforms.0._angular_freq": torch.ones(1), key: torch.ones(37)}
        state["transforms"][key][5] = value
    else:
        key = next(iter(state["agent"][part]))
        state["agent"][part][key].view(-1)[0] = value
    torch.save(state, file)
    name = f"agent.{part}" if part != "transforms" else "transforms"
    message = rf"latest\.pt: {name} '{key}' holds (NaN|inf) values: the training run that wrote it diverged\. Pick an " \
              r"earlier checkpoint"
    with pytest.raises(CheckpointError, match=message):
        read_checkpoint(run)
    with pytest.raises(CheckpointError, match=message):
        open_run(_config(run_dir=str(tmp_path / "runs"), name="again", resume=str(run)))


def test_transform_state_that_may_be_infinite_still_loads(tmp_path):
    # A clip bound or a mask of another transform can be inf by design; only normaliser statistics are checked.
    run, _ = _saved_run(tmp_path)
    file = run / "checkpoints" / "latest.pt"
    state = torch.load(file, weights_only=True)
    state["transforms"] = {"transforms.2.low": torch.full((3,), float("-inf")), "transforms.3.mean": torch.zeros(3)}
    torch.save(state, file)
    assert read_checkpoint(run)["transforms"]["transforms.2.low"].isinf().all()


@pytest.mark.skipif(not SHIPPED_POLICY.with_name("tocabi_walk_torque.pt").is_file(), reason="shipped policy absent")
def test_a_policy_of_another_control_mode_is_refused_by_the_env():
    # Only tensor sizes were compared, the same in every mode: the torque policy loaded into a PD env, its actions
    # then meaning PD target offsets.
    from tocabi_torchrl.rl.checkpoint import apply_checkpoint, read_checkpoint
    from tocabi_torchrl.rl.trainer import build_env

    cfg = preset_config("default", device="cpu")
    env = build_env(cfg, torch.device("cpu"), num_envs=2)
    agent = build_agent(cfg, env.observation_spec["observation"].shape[-1], env.action_spec.shape[-1],
                        torch.device("cpu"))
    torque = SHIPPED_POLICY.with_name("tocabi_walk_torque.pt")
    with pytest.raises(CheckpointError, match="env.control.mode 'torque', but the env runs 'pd_reference'"):
        apply_checkpoint(read_checkpoint(torque), agent, env=env, path=torque)
    apply_checkpoint(read_checkpoint(SHIPPED_POLICY), agent, env=env, path=SHIPPED_POLICY)  # its own mode loads


@pytest.mark.skipif(not SHIPPED_POLICY.is_file(), reason="shipped policy not present")
def test_a_policy_is_refused_by_an_env_normalising_otherwise():
    # The weights fit an env without a normaliser (the same width): the fixed-normalisation policy acted on raw
    # observations without a word, the saved loc and scale unused.
    import copy
    import dataclasses

    from tocabi_torchrl.rl.checkpoint import read_checkpoint
    from tocabi_torchrl.rl.trainer import build_env, checkpoint_agent

    state = read_checkpoint(SHIPPED_POLICY)
    cfg = config_from_checkpoint(state, SHIPPED_POLICY)
    assert cfg.transforms.normalization == "fixed"
    raw = build_env(dataclasses.replace(cfg, transforms=dataclasses.replace(cfg.transforms, normalization="none")),
                    CPU, num_envs=2)
    with pytest.raises(CheckpointError, match="normalization 'fixed', but the env does not normalise"):
        checkpoint_agent(state, cfg, raw, SHIPPED_POLICY)
    unnormalised = copy.deepcopy(state)
    unnormalised["config"]["transforms"]["normalization"] = "none"
    with pytest.raises(CheckpointError, match="normalization 'none', but the env normalises"):
        checkpoint_agent(unnormalised, cfg, build_env(cfg, CPU, num_envs=2), SHIPPED_POLICY)
    checkpoint_agent(state, cfg, build_env(cfg, CPU, num_envs=2), SHIPPED_POLICY)  # its own kind loads
