"""Ctrl-C and SIGTERM stop a ppo_walk run at the end of an iteration with a checkpoint of it that --resume continues
(rl/interrupt.py, shared with the library recipes); a folder whose run saved no checkpoint is refused with advice
that can be followed."""

from __future__ import annotations

import contextlib
import io
import os
import signal
import sys
from pathlib import Path

import pytest
import torch
from recipe_runner import load_recipe as recipe

from tocabi_torchrl.rl import interrupt, parse_args, preset_config
from tocabi_torchrl.rl.checkpoint import read_checkpoint
from tocabi_torchrl.rl.curves import read_metrics

#: 8 env steps per iteration, 10 iterations; no checkpoint_every boundary before the end.
TINY = {"device": "cpu", "env.num_envs": 2, "ppo.steps_per_env": 4, "ppo.minibatch_size": 8, "total_env_steps": 80,
        "progress_bar": False, "eval_at_end": False, "checkpoint_every": 100}


def tiny_args(root: Path, name: str = "run", **extra) -> list[str]:
    options = {**TINY, "run_dir": str(root), "name": name, "preset": "cpu_smoke", **extra}
    return [x for k, v in options.items() for x in (f"--{k}", str(v))]


def signal_during_update(monkeypatch, at: int, signals=(signal.SIGINT,)):
    """Send ``signals`` to this process during the ``at``-th update: what Ctrl-C (or a scheduler's SIGTERM) does."""
    from tocabi_torchrl.rl import trainer

    update, calls = trainer._update_stats, []

    def update_then_signal(*args, **kwargs):
        calls.append(1)
        if len(calls) == at:
            for sig in signals:
                os.kill(os.getpid(), sig)
        return update(*args, **kwargs)

    monkeypatch.setattr(trainer, "_update_stats", update_then_signal)


def test_the_first_signal_sets_the_flag_a_second_stops_at_once_and_the_handlers_come_back():
    before = {sig: signal.getsignal(sig) for sig in interrupt.STOP_SIGNALS}
    flag = interrupt.StopFlag()
    with pytest.raises(KeyboardInterrupt), interrupt.stop_on_signals(flag, "stopping"):
        os.kill(os.getpid(), signal.SIGTERM)
        assert flag.stop_signal == "SIGTERM"
        os.kill(os.getpid(), signal.SIGINT)
    assert {sig: signal.getsignal(sig) for sig in interrupt.STOP_SIGNALS} == before
    # A repeat inside the grace period (torchrun forwarding the terminal's Ctrl-C) is the same request.
    flag = interrupt.StopFlag()
    with interrupt.stop_on_signals(flag, "stopping", repeat_grace_s=60.0):
        os.kill(os.getpid(), signal.SIGINT)
        os.kill(os.getpid(), signal.SIGINT)
    assert flag.stop_signal == "SIGINT"
    assert [interrupt.signal_exit_status(s) for s in (None, "SIGINT", "SIGTERM")] == [0, 130, 143]


def test_the_stop_message_gets_a_line_of_its_own_beside_a_progress_bar():
    from tqdm.auto import tqdm

    # A plain print landed on the bar's line: "...sps=362]SIGINT: stopping".
    err = io.StringIO()
    with contextlib.redirect_stderr(err):
        bar = tqdm(total=10, file=sys.stderr)
        bar.set_postfix(sps="362")
        with interrupt.stop_on_signals(interrupt.StopFlag(), "stopping"):
            os.kill(os.getpid(), signal.SIGINT)
        bar.close()
    text = err.getvalue()
    assert text[:text.index("SIGINT: stopping")].endswith("\r"), repr(text)  # the bar cleared first


def test_the_library_recipes_keep_their_names_for_the_shared_helpers():
    from tocabi_torchrl.adapters import recipe as common

    assert common.Interrupted is interrupt.Interrupted and common.exit_status is interrupt.exit_status
    assert common.exit_status({"interrupted": "SIGTERM"}) == 143 and common.exit_status({}) == 0


def test_train_saves_the_interrupted_iteration_and_resume_goes_on_from_it(tmp_path, monkeypatch):
    from tocabi_torchrl.rl.trainer import train

    before = signal.getsignal(signal.SIGINT)
    signal_during_update(monkeypatch, at=3)
    result = train(preset_config("cpu_smoke", **TINY, run_dir=str(tmp_path), name="run"))
    assert result.interrupted == "SIGINT" and result.iterations == 3 and result.env_steps == 24
    assert signal.getsignal(signal.SIGINT) is before  # train() put the handler back
    run = tmp_path / "run"
    assert sorted(p.name for p in (run / "checkpoints").iterdir()) == ["iter_000003.pt", "latest.pt"]
    assert read_checkpoint(run)["iteration"] == 3
    monkeypatch.undo()
    cfg, _ = parse_args(["--resume", str(run), "--total_env_steps", "40"])
    resumed = train(cfg)
    assert resumed.interrupted is None and resumed.iterations == 5
    assert [int(float(r["iteration"])) for r in read_metrics(run)] == [1, 2, 3, 4, 5]


@pytest.mark.parametrize("sig, status", [(signal.SIGINT, 130), (signal.SIGTERM, 143)])
def test_the_recipe_says_how_to_resume_and_exits_with_the_signal_status(tmp_path, monkeypatch, capsys, sig, status):
    signal_during_update(monkeypatch, at=2, signals=(sig,))
    with pytest.raises(SystemExit) as info:
        recipe("ppo_walk").main(tiny_args(tmp_path, eval_at_end=True))
    assert info.value.code == status
    err = capsys.readouterr().err
    run = tmp_path / "run"
    assert f"--resume {run}" in err and "stopped after iteration 2" in err, err
    assert read_checkpoint(run)["iteration"] == 2 and not (run / "eval").exists()


def test_a_second_signal_stops_at_once(tmp_path, monkeypatch, capsys):
    from tocabi_torchrl.rl import trainer

    # The two signals come within the torchrun grace (1 s): one process has none, or it ignored the second.
    update, calls = trainer._update_stats, []

    def signalled_twice(*args, **kwargs):
        calls.append(1)
        if len(calls) == 2:
            os.kill(os.getpid(), signal.SIGINT)
        out = update(*args, **kwargs)
        if len(calls) == 2:
            os.kill(os.getpid(), signal.SIGINT)  # before the iteration's end: no checkpoint of it
        return out

    monkeypatch.setattr(trainer, "_update_stats", signalled_twice)
    with pytest.raises(SystemExit) as info:
        recipe("ppo_walk").main(tiny_args(tmp_path))
    assert info.value.code == 130
    assert "stopped at once" in capsys.readouterr().err
    assert not (tmp_path / "run" / "checkpoints").exists()


def test_only_a_data_parallel_rank_takes_a_quick_repeat_for_the_same_signal():
    from tocabi_torchrl.rl.distributed import DistInfo
    from tocabi_torchrl.rl.trainer import _REPEAT_GRACE_S, _repeat_grace_s

    assert _repeat_grace_s(DistInfo()) == 0.0  # a second Ctrl-C is the user's: it stops at once, as it says
    assert _repeat_grace_s(DistInfo(rank=1, local_rank=1, world_size=2)) == _REPEAT_GRACE_S > 0


def test_a_folder_without_a_checkpoint_is_refused_with_advice_that_can_be_followed(tmp_path):
    run = tmp_path / "run"
    run.mkdir()
    (run / "config.json").write_text("{}")  # what a run SIGKILLed before its first checkpoint leaves
    for argv in (tiny_args(tmp_path), ["--resume", str(run)]):
        with pytest.raises(SystemExit) as info:
            recipe("ppo_walk").main(argv)
        message = str(info.value.code)
        assert message.startswith("error: ") and "saved no checkpoint" in message, message
        assert "--name" in message and f"rm -r {run}" in message and "--resume" not in message
    assert (run / "config.json").is_file()  # never removed for the user


def test_ranks_agree_on_a_stop_that_one_of_them_was_asked_for(tmp_path):
    import torch.multiprocessing as mp

    out = mp.Manager().dict()
    mp.spawn(_agree_worker, args=(str(tmp_path / "init"), out), nprocs=2, join=True)
    assert out[0] == out[1] == (False, "SIGTERM")


def _agree_worker(rank: int, init: str, out) -> None:
    import torch.distributed as dist

    from tocabi_torchrl.rl.distributed import DistInfo
    from tocabi_torchrl.rl.trainer import _stop_requests

    dist.init_process_group("gloo", init_method=f"file://{init}", rank=rank, world_size=2)
    info = DistInfo(rank=rank, local_rank=rank, world_size=2)
    out[rank] = _stop_requests(False, "SIGTERM" if rank == 1 else None, info, torch.device("cpu"))
    dist.destroy_process_group()
