"""tocabi_torchrl.cuda_graphs: the one decision of what a run captures, and the warm-up / capture / fallback helper
shared by the env step and the PPO update (its bookkeeping on CPU through an emulated capture; the CUDA capture itself
is covered by the GPU tests in test_make_env.py, test_update_step.py and test_torque_assist.py)."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from graph_emulation import EmulatedCapture, FailingCapture

from tocabi_torchrl import make_env
from tocabi_torchrl.cuda_graphs import ENV_GRAPH_AUTO_MAX_ENVS, WarmCapture, env_graph_blockers, plan_graphs
from tocabi_torchrl.rl import preset_config

CUDA, CPU = torch.device("cuda"), torch.device("cpu")


def test_plan_graphs_is_the_one_decision():
    def cfg(mode="auto", n=8, update=True, compile_reward=False):
        c = preset_config("default", **{"env.num_envs": n, "ppo.minibatch_size": 16, "ppo.cuda_graph": mode,
                          "ppo.update_graph": update})
        c.transforms.compile_reward = compile_reward
        return c

    plan = plan_graphs(cfg(), CUDA)
    assert plan.env_step and plan.update
    assert not plan_graphs(cfg(), CPU).env_step and not plan_graphs(cfg(), CPU).update  # nothing off CUDA
    assert not plan_graphs(cfg(n=ENV_GRAPH_AUTO_MAX_ENVS + 1), CUDA).env_step
    assert not plan_graphs(cfg(), CUDA, sync_free_resets=False).env_step  # "auto" skips what cannot be captured
    assert not plan_graphs(cfg(compile_reward=True), CUDA).env_step
    assert plan_graphs(cfg("on", n=4096, compile_reward=True), CUDA).env_step  # "on": make_env says why it cannot
    assert not plan_graphs(cfg("off"), CUDA).env_step and not plan_graphs(cfg(update=False), CUDA).update


def test_the_training_and_architecture_pages_state_the_env_graph_limit():
    # Above it a training run's env step is eager while its update is captured: the pages say where that starts.
    docs = Path(__file__).resolve().parents[1] / "docs"
    for page in ("training.md", "architecture.md"):
        text = " ".join((docs / page).read_text().split())
        assert f"up to {ENV_GRAPH_AUTO_MAX_ENVS} envs" in text and "ENV_GRAPH_AUTO_MAX_ENVS" in text, page
        assert "runs eagerly while the update is captured" in text or "eagerly, op by op" in text, page


def test_blockers_name_each_reason_and_make_env_raises_them_all():
    assert env_graph_blockers(CUDA) == []
    reasons = env_graph_blockers(CPU, sync_free_resets=False, compile_reward=True)
    assert len(reasons) == 3 and all("cuda_graph" in r for r in reasons)
    with pytest.raises(ValueError, match="needs a CUDA device.*needs sync_free_resets.*do not combine"):
        make_env(num_envs=2, device="cpu", cuda_graph=True, sync_free_resets=False, compile_reward=True)


class _Counter:
    """A stateful function (x += 1, returns x * a), so that a work run twice or skipped shows."""

    def __init__(self):
        self.x = torch.zeros(3)
        self.calls = 0

    def __call__(self, a: torch.Tensor) -> torch.Tensor:
        self.calls += 1
        self.x += 1
        return self.x * a


def _warm(fn, capturer, modes=("joined", "segmented"), warmup=2):
    def build(args, stream, mode):
        static = args[0].clone()
        replay, out = capturer.capture(lambda: fn(static), device=CPU, stream=stream, mode=mode)

        def run(a):
            static.copy_(a)
            replay()
            return out.clone()

        return run

    return WarmCapture("Test", "the work", fn, build, warmup=warmup, modes=modes, capturer=capturer)


def test_warm_capture_warms_up_captures_once_and_replays():
    fn, capturer = _Counter(), EmulatedCapture()
    cap = _warm(fn, capturer)
    outs = [cap.run(CPU, torch.full((3,), float(i))) for i in range(6)]
    assert [cap.captured, cap.mode, capturer.captures] == [True, "joined", ["joined"]]
    assert fn.calls == 6  # each call did the work once: warm-up, capture + first replay, replays
    for i, out in enumerate(outs):
        torch.testing.assert_close(out, torch.full((3,), float((i + 1) * i)))
    cap.reset()
    assert not cap.captured
    cap.run(CPU, torch.ones(3))
    assert not cap.captured  # warming up again


def test_warm_capture_falls_back_mode_by_mode_then_to_eager():
    fn = _Counter()
    cap = _warm(fn, FailingCapture(failing=("joined",)), warmup=1)
    cap.run(CPU, torch.ones(3))
    with pytest.warns(UserWarning, match=r"Test: capturing the work .*joined: RuntimeError.*using the 'segmented'"):
        cap.run(CPU, torch.ones(3))
    assert cap.mode == "segmented"

    fn = _Counter()
    cap = _warm(fn, FailingCapture(failing=("joined", "segmented")), warmup=1)
    cap.run(CPU, torch.ones(3))
    with pytest.warns(UserWarning, match="running eagerly from now on"):
        out = cap.run(CPU, torch.ones(3))
    torch.testing.assert_close(out, torch.full((3,), 2.0))  # the failed call still did its work, eagerly
    assert cap.gave_up and not cap.captured
    cap.reset()
    cap.run(CPU, torch.ones(3))
    cap.run(CPU, torch.ones(3))
    assert fn.calls == 4 and not cap.captured, "a failed capture is not retried on reset"


def test_warmup_must_be_positive():
    with pytest.raises(ValueError, match="warmup must be an int >= 1"):
        WarmCapture("Test", "the work", print, print, warmup=0)
