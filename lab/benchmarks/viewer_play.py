"""The live page of a policy (``play.py --viewer``): frames sent and policy steps per second for N robots.

    python -m lab.benchmarks.viewer_play --num_envs 64 --seconds 10

Serves the shipped PPO policy's page (no browser connected: viser sends each frame to whoever is connected, so
the server's work per frame is the same), waits past the first steps, then counts frames and steps for
``--seconds``. The page draws at most 30 frames/s and steps in real time (250 policy steps/s); the issue asks for
64 robots at 30 fps.
"""

from __future__ import annotations

import argparse
import socket
import threading
import time
from pathlib import Path

from . import common

NAME = "viewer_play"
POLICY = Path(__file__).resolve().parents[2] / "assets" / "policies" / "tocabi_walk_ppo.pt"


def measure(n: int, seconds: float, device: str, backend: str | None) -> dict:
    from tocabi_torchrl.viewer.play import serve_policy

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    started, stop = [], threading.Event()
    thread = threading.Thread(target=serve_policy, daemon=True, kwargs=dict(
        path=POLICY, num_envs=n, device=device, port=port, backend=backend, stop=stop, ready=started.append))
    thread.start()
    try:
        end = time.monotonic() + 900  # the first build may compile mujoco-warp's kernels
        while not started and time.monotonic() < end:
            time.sleep(0.5)
        if not started:
            raise RuntimeError("the page did not come up")
        live = started[0]
        time.sleep(3.0)  # past the first steps (CUDA graph capture)
        steps0, frames0, t0 = live.total_steps, live.frames, time.monotonic()
        time.sleep(seconds)
        elapsed = time.monotonic() - t0
        steps, frames = live.total_steps - steps0, live.frames - frames0
    finally:
        stop.set()
        thread.join(timeout=30)
    real_time = 1.0 / live.dt
    return {"num_envs": n, "backend": backend or "auto", "seconds": elapsed, "frames_per_s": frames / elapsed,
            "policy_steps_per_s": steps / elapsed, "real_time_steps_per_s": real_time,
            "real_time_fraction": steps / elapsed / real_time}


def render(data: dict, out) -> str:
    rows = [[r["num_envs"], r["backend"], common.fmt(r["frames_per_s"], ".1f"),
             common.fmt(r["policy_steps_per_s"], ".0f"), common.fmt(r["real_time_fraction"], ".2f")]
            for r in data["results"]]
    return common.page("Live page of a policy: frames and steps per second", data,
                       "The page draws at most 30 frames/s and steps in real time (250 policy steps/s).\n\n"
                       + common.table(["robots", "backend", "frames/s", "policy steps/s", "x real time"], rows))


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(prog="python -m lab.benchmarks.viewer_play", description=__doc__.split("\n")[0])
    parser.add_argument("--num_envs", type=int, nargs="+", default=[64], help="robots on the page")
    parser.add_argument("--seconds", type=float, default=10.0, help="how long to count [s]")
    parser.add_argument("--device", default="cuda", help="device of the robots and the policy: cuda or cpu "
                        "(default: cuda)")
    parser.add_argument("--backend", default=None, help="warp or mujoco (default: the device's)")
    parser.add_argument("--out", default=str(common.DOCS / "viewer_overhead"), help="folder of the report")
    args = parser.parse_args(argv)
    results = [measure(n, args.seconds, args.device, args.backend) for n in args.num_envs]
    for r in results:
        print(f"{r['num_envs']} robots: {r['frames_per_s']:.1f} frames/s, {r['policy_steps_per_s']:.0f} policy "
              f"steps/s ({r['real_time_fraction']:.2f}x real time)", flush=True)
    data = {"meta": common.meta(NAME, argv, on=args.device), "results": results}
    print(common.publish(args.out, NAME, data, render, measured_on=args.device))


if __name__ == "__main__":
    main()
