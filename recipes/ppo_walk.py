"""Train TOCABI to walk with PPO on TorchRL.

    python recipes/ppo_walk.py                      # default preset: 4096 envs on the GPU
    python recipes/ppo_walk.py --preset reference   # the reference's hyper-parameters (8 envs, 120 M steps)
    python recipes/ppo_walk.py --num_envs 8192 --max_minutes 20 --name walk8k
    python recipes/ppo_walk.py --resume runs/ppo_walk   # continue from runs/ppo_walk/checkpoints/latest.pt
    python recipes/ppo_walk.py --help               # every option

Without CUDA it says so and runs the small ``cpu_smoke`` configuration (minutes on a laptop, learns nothing useful).
Writes runs/<name>/: config.json, metrics.csv, checkpoints/, and (with --eval_at_end) eval/ with a summary JSON,
the knee-trajectory plot and a video.
"""

from __future__ import annotations

import ctypes.util
import os
import sys

if "MUJOCO_GL" not in os.environ and not os.environ.get("DISPLAY") and ctypes.util.find_library("EGL"):
    os.environ["MUJOCO_GL"] = "egl"  # headless video of the final evaluation; chosen before mujoco is imported

import torch  # noqa: E402

from tocabi_torchrl.rl.config import parse_args, preset_config  # noqa: E402
from tocabi_torchrl.rl.trainer import train  # noqa: E402


def main(argv: list[str] | None = None) -> None:
    cfg, args = parse_args(argv, description=__doc__.split("\n\n")[0])
    if not torch.cuda.is_available() and cfg.device in ("auto", "cuda"):
        overrides = {k: v for k, v in vars(args).items() if v is not None and k not in ("preset", "device")}
        print("No CUDA GPU found: running the small CPU smoke configuration (preset 'cpu_smoke': 8 envs, "
              "3 iterations) on the CPU (C MuJoCo backend). Pass --device cpu with your own options to override.",
              flush=True)
        cfg = preset_config("cpu_smoke", **{**overrides, "device": "cpu"})
    print(f"training {cfg.name}: preset {cfg.preset}, {cfg.num_envs} envs, {cfg.iterations} iterations of "
          f"{cfg.frames_per_batch:,} steps on {cfg.device}", flush=True)
    result = train(cfg)
    print(f"done: {result.env_steps:,} env steps in {result.wall_seconds:.0f} s "
          f"({result.env_steps_per_second:,.0f} env-steps/s); run folder {result.run_dir}")
    if cfg.eval_at_end:
        from tocabi_torchrl.rl.evaluate import evaluate_run

        summary = evaluate_run(result.run_dir, num_envs=cfg.eval_envs, device=cfg.device, seconds=cfg.eval_seconds)
        print("evaluation:", {k: summary[k] for k in ("survival", "forward_distance_m", "lateral_drift_m",
                                                       "knee_rms_rad") if k in summary})


if __name__ == "__main__":
    main(sys.argv[1:])
