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


def test_the_live_page_of_64_robots_on_the_gpu_runs_in_real_time_at_30_fps():
    pytest.importorskip("viser", reason="the viewer extra (viser) is not installed")
    import socket
    import threading
    from pathlib import Path

    from tocabi_torchrl.viewer.play import serve_policy

    policy = Path(__file__).resolve().parents[1] / "assets" / "policies" / "tocabi_walk_ppo.pt"
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    started, stop = [], threading.Event()
    thread = threading.Thread(target=serve_policy, daemon=True, kwargs=dict(
        path=policy, num_envs=64, device="cuda", port=port, backend="warp", stop=stop, ready=started.append))
    thread.start()
    try:
        end = time.monotonic() + 600  # the first build may compile mujoco-warp's kernels
        while not started and time.monotonic() < end:
            time.sleep(0.5)
        assert started, "the page did not come up"
        session = started[0]
        time.sleep(3.0)  # past the first steps (CUDA graph capture)
        steps0, frames0, t0 = session.total_steps, session.frames, time.monotonic()
        time.sleep(10.0)
        elapsed = time.monotonic() - t0
        steps_per_s = (session.total_steps - steps0) / elapsed
        fps = (session.frames - frames0) / elapsed
    finally:
        stop.set()
        thread.join(timeout=30)
    print(f"64 robots on the GPU: {steps_per_s:.0f} policy steps/s (real time: {1 / session.dt:.0f}), {fps:.1f} fps")
    assert fps >= 27, f"{fps:.1f} frames/s sent, wanted 30"
    assert steps_per_s >= 0.9 / session.dt, f"{steps_per_s:.0f} policy steps/s, below real time ({1 / session.dt:.0f})"
