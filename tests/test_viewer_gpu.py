"""The viewer's training stream on CUDA: its capture step runs without a host synchronisation (sync debug mode
"error") and the host copy holds the poses of the step it was taken after, not of a later one. Skipped without CUDA."""

from __future__ import annotations

import time

import pytest
import torch

pytestmark = [pytest.mark.gpu, pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")]


@pytest.fixture(scope="module")
def sim():
    import warp as wp

    if not wp.is_cuda_available():
        pytest.skip("warp sees no CUDA device")
    from tocabi_torchrl import robot
    from tocabi_torchrl.sim import SimConfig, WarpSim

    sim = WarpSim(SimConfig(num_worlds=128, device="cuda"))
    qpos = torch.as_tensor(robot.INIT_QPOS, dtype=torch.float32, device=sim.device)
    sim.reset(torch.ones(sim.num_worlds, dtype=torch.bool, device=sim.device), qpos,
              torch.zeros(sim.nv, device=sim.device))
    sim.step()
    torch.cuda.synchronize()
    return sim


def _latest(stream, timeout: float = 10.0):
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        frame = stream.latest()
        if frame is not None:
            return frame
        time.sleep(0.001)
    raise AssertionError("no completed copy")


def test_capture_never_synchronises_and_copies_the_captured_step(sim):
    from tocabi_torchrl.viewer.stream import PoseStream

    stream = PoseStream(sim, worlds=64, every=1)
    assert stream.cuda and all(b.is_pinned() for b in stream._host)
    torch.cuda.set_sync_debug_mode("error")
    try:
        for _ in range(20):  # ticks, copies, skips and reads of completed copies: none may wait for the GPU
            sim.step()
            stream.tick()
            stream.latest()
        sim.step()
        expected_pos = sim.xpos[:64].clone()  # device copies: no sync
        expected_quat = sim.xquat[:64].clone()
        while not stream.capture():  # the previous copy still in flight: skipped, never waited for
            pass
        for _ in range(3):  # the next steps overwrite the poses the copy read
            sim.step()
    finally:
        torch.cuda.set_sync_debug_mode(0)
    assert stream.copies >= 2
    torch.cuda.synchronize()
    frame = _latest(stream)
    assert frame.index == stream.copies, "the newest copy"
    torch.testing.assert_close(torch.from_numpy(frame.xpos), expected_pos.cpu(), rtol=0, atol=0)
    torch.testing.assert_close(torch.from_numpy(frame.xquat), expected_quat.cpu(), rtol=0, atol=0)
    assert not torch.equal(sim.xpos[:64].cpu(), expected_pos.cpu()), "the sim moved on after the capture"


def test_the_live_page_of_64_robots_on_the_gpu_steps_and_draws():
    """The page of 64 robots on mujoco-warp comes up, steps its worlds and sends frames (its rates are measured by
    lab.benchmarks.viewer_play, not asserted here)."""
    pytest.importorskip("viser", reason="the viewer extra (viser) is not installed")
    from lab.benchmarks.viewer_play import measure

    result = measure(64, seconds=2.0, device="cuda", backend="warp")
    assert result["policy_steps_per_s"] > 0 and result["frames_per_s"] > 0
