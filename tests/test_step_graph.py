"""StepGraph bookkeeping (static inputs, fresh outputs, aliasing), on CPU through an emulated capture.

The CUDA capture itself is covered by the GPU tests in test_make_env.py.
"""

from __future__ import annotations

import pytest
import torch
from graph_emulation import EmulatedCapture
from tensordict import TensorDict

from tocabi_torchrl.envs.step_graph import StepGraph


def _step(td):
    """Stateless stand-in for step_and_maybe_reset: next = x + action, carry reuses next's tensor for "x"."""
    x = td["x"] + td["action"]
    done = (x.sum(-1, keepdim=True) > 0)
    nxt = TensorDict({"x": x, "done": done, ("terms", "r"): x[:, :1] * 2}, batch_size=td.batch_size)
    td.set("next", nxt)
    carry = TensorDict({"x": x, "reset_obs": torch.where(done, torch.zeros_like(x), x), "done": done.clone()},
                       batch_size=td.batch_size)
    return td, carry


def _input(seed):
    g = torch.Generator().manual_seed(seed)
    return TensorDict({"x": torch.randn(4, 3, generator=g), "action": torch.randn(4, 3, generator=g)},
                      batch_size=[4])


def test_replay_matches_the_eager_step_and_returns_fresh_tensors():
    graph = StepGraph(_step, _input(0), capturer=EmulatedCapture())
    outputs = []
    for seed in range(5):  # the first call takes the capture's input, as SyncFreeResetEnv's first replay does
        td = _input(seed)
        want_td, want_carry = _step(td.clone())
        got_td, got_carry = graph(td)
        assert got_td is td  # the caller's input gets "next", as in eager mode
        for key in want_td["next"].keys(True, True):
            torch.testing.assert_close(got_td["next", key], want_td["next", key], rtol=0, atol=0)
        for key in want_carry.keys(True, True):
            torch.testing.assert_close(got_carry[key], want_carry[key], rtol=0, atol=0)
        # Aliasing as in eager mode: the carry's "x" is next's "x"; nothing aliases the static buffers.
        assert got_carry["x"] is got_td["next", "x"]
        assert got_carry["x"].data_ptr() != graph._next.get("x").data_ptr()
        outputs.append((got_td["next", "x"], got_td["next", "x"].clone()))
    for returned, copy in outputs:  # later replays did not overwrite earlier outputs
        assert torch.equal(returned, copy)


def test_accepts_only_the_captured_keys():
    graph = StepGraph(_step, _input(0), capturer=EmulatedCapture())
    assert graph.accepts(_input(1))
    assert not graph.accepts(_input(1).set("extra", torch.zeros(4)))
    assert not graph.accepts(_input(1).exclude("action"))


def test_capture_needs_cuda():
    with pytest.raises(ValueError, match="CUDA"):
        StepGraph(_step, _input(0))
