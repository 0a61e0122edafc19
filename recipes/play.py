"""Evaluate a trained walking policy: deterministic policy, command (0.5, 0) m/s for 8 s (TocabiLab's gait test).

    python recipes/play.py --checkpoint runs/ppo_walk                 # a run folder (uses checkpoints/latest.pt)
    python recipes/play.py --checkpoint runs/ppo_walk/checkpoints/iter_000500.pt --num_envs 64 --vx 0.3

Writes <run>/eval/summary.json (survival, forward distance, lateral drift, speed tracking error, knee RMS against the
reference motion), knees.png (left/right knee over 6 s against the reference) and walk.mp4 (a few robots, rendered
offscreen; set MUJOCO_GL=egl on a headless GPU machine, osmesa on a headless CPU one).
"""

from __future__ import annotations

import argparse
import json
import ctypes.util
import os
import sys

if "MUJOCO_GL" not in os.environ and not os.environ.get("DISPLAY") and ctypes.util.find_library("EGL"):
    os.environ["MUJOCO_GL"] = "egl"  # headless: must be chosen before mujoco is imported

from tocabi_torchrl.rl.evaluate import evaluate_run  # noqa: E402


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    parser.add_argument("--checkpoint", required=True, help="run folder or checkpoint .pt file")
    parser.add_argument("--num_envs", type=int, default=256)
    parser.add_argument("--device", default="auto")
    parser.add_argument("--seconds", type=float, default=8.0)
    parser.add_argument("--vx", type=float, default=0.5, help="commanded forward speed [m/s]")
    parser.add_argument("--vy", type=float, default=0.0, help="commanded lateral speed [m/s]")
    parser.add_argument("--out", default=None, help="output folder (default: eval/ beside the checkpoint)")
    parser.add_argument("--video_envs", type=int, default=4, help="robots shown side by side in the video")
    args = parser.parse_args(argv)
    if args.num_envs < 1 or args.seconds <= 0:
        parser.error("--num_envs must be >= 1 and --seconds > 0")
    summary = evaluate_run(args.checkpoint, num_envs=args.num_envs, device=args.device, seconds=args.seconds,
                           command=(args.vx, args.vy), video_envs=min(args.video_envs, args.num_envs), out_dir=args.out)
    print(json.dumps(summary, indent=2))


if __name__ == "__main__":
    main(sys.argv[1:])
