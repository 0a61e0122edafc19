"""Torch ops per training env step that each piece of the robust preset's randomisation adds (a CPU count).

On a GPU the env step is one captured CUDA graph; every torch op in it (besides the physics, which mujoco-warp
launches itself) is at least one kernel, a few microseconds each at 4,096 envs whatever its size. Counting the ops
of the step as training runs it (``build_env(..., for_training=True, sync_free_resets=True)``, the sync-free
masked reset every step) therefore shows where the randomisation's per-step overhead comes from, on any machine.
The count is of top-level ``aten::`` ops (views included) under ``torch.profiler``, per ``step_and_maybe_reset``,
averaged over 10 steps of 32 envs on C MuJoCo; each row switches one piece of the ``robust`` preset on over the
preset with all of them off, the last row is the preset itself.

Wrote docs/benchmarks/randomization/step_ops.json (about a minute on 2 cores; ``--before`` adds an earlier report's
counts as a column, here the one this script wrote at 2000356, copied to /tmp first)::

    PYTHONPATH=. python lab/analysis/step_ops.py --out docs/benchmarks/randomization/step_ops.json \
        --before /tmp/an/step_ops_2000356.json --before_note "before velocity kicks and the sensed assist PD"
"""

from __future__ import annotations

import argparse
import collections
import json
import shlex
import subprocess
import sys
import time
from pathlib import Path

import torch

from tocabi_torchrl.atomic import atomic_write_text
from tocabi_torchrl.config import preset_tree
from tocabi_torchrl.control.config import ActuatorConfig
from tocabi_torchrl.envs.push_config import PushConfig
from tocabi_torchrl.randomize import TOCABI_LAB_ACTUATORS, TOCABI_LAB_DYNAMICS
from tocabi_torchrl.sim.dynamics_config import DynamicsRandomization
from tocabi_torchrl.transforms.sensor_noise_config import SensorNoiseConfig
from tocabi_torchrl.tree import replace_paths

#: The robust preset with every randomisation piece off.
OFF = {"env.control.actuators": ActuatorConfig(), "env.dynamics": DynamicsRandomization(),
       "transforms.sensor_noise": SensorNoiseConfig(), "env.pushes": PushConfig(),
       "env.task.start_joint_vel_std": 0.0, "env.task.start_base_vel_std": 0.0}


def pieces(robust) -> dict[str, dict]:
    """Each piece's paths, as the robust preset sets them."""
    return {"actuators (delay, motor constant)": {"env.control.actuators": TOCABI_LAB_ACTUATORS},
            "dynamics (mass, damping, armature)": {"env.dynamics": TOCABI_LAB_DYNAMICS},
            "sensor biases and noise": {"transforms.sensor_noise": SensorNoiseConfig.tocabi_lab()},
            "pushes": {"env.pushes": robust.env.pushes},
            "diverse starts": {"env.task.start_joint_vel_std": robust.env.task.start_joint_vel_std,
                               "env.task.start_base_vel_std": robust.env.task.start_base_vel_std}}


def ops_per_step(cfg, num_envs: int, steps: int) -> tuple[float, dict[str, float]]:
    """Top-level aten ops per ``step_and_maybe_reset`` of ``cfg``'s training env, and the ten most frequent."""
    from torch.profiler import ProfilerActivity, profile

    from tocabi_torchrl.rl.trainer import build_env

    env = build_env(cfg, torch.device("cpu"), num_envs=num_envs, for_training=True, sync_free_resets=True)
    td = env.reset()
    td["action"] = env.action_spec.zero()

    def run(n, td):
        for _ in range(n):
            td, nxt = env.step_and_maybe_reset(td)
            nxt["action"] = td["action"]
            td = nxt
        return td

    td = run(3, td)  # first-call set-up (index tensors, buffers) out of the count
    with profile(activities=[ProfilerActivity.CPU]) as prof:
        run(steps, td)
    count = collections.Counter(e.name for e in prof.events() if e.name.startswith("aten::")
                                and not (e.cpu_parent is not None and e.cpu_parent.name.startswith("aten::")))
    return sum(count.values()) / steps, {k: v / steps for k, v in count.most_common(10)}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--num_envs", type=int, default=32, help="envs (the count does not depend on it)")
    p.add_argument("--steps", type=int, default=10, help="steps counted per row")
    p.add_argument("--out", type=Path, default=None, help="JSON to write (default: print only)")
    p.add_argument("--before", type=Path, default=None,
                   help="an earlier report of this script, whose counts become a column beside these")
    p.add_argument("--before_note", default="", help="what the earlier report's code lacked (shown with its column)")
    args = p.parse_args(argv)
    before = json.loads(args.before.read_text()) if args.before is not None else None
    torch.set_num_threads(1)
    robust = preset_tree("robust")
    off = replace_paths(robust, OFF)
    rows = [("nothing", off)] + [(name, replace_paths(off, paths)) for name, paths in pieces(robust).items()]
    rows.append(("everything (the robust preset)", robust))
    results, base = [], None
    for name, cfg in rows:
        ops, top = ops_per_step(cfg, args.num_envs, args.steps)
        base = ops if base is None else base
        results.append({"what": name, "ops_per_step": ops, "over_nothing": ops - base, "most_frequent": top})
        print(f"{name:40s} {ops:7.0f} ops per step ({ops - base:+.0f})", flush=True)
    if args.out is not None:
        commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], check=False, capture_output=True,
                                text=True).stdout.strip()
        meta = {"command": shlex.join(["python", "lab/analysis/step_ops.py", *(argv or sys.argv[1:])]),
                "date": time.strftime("%Y-%m-%d"), "code": commit, "torch": torch.__version__,
                "hardware": "CPU (C MuJoCo)", "num_envs": args.num_envs, "steps": args.steps}
        if before is not None:
            earlier = {r["what"]: r["ops_per_step"] for r in before["results"]}
            meta["before"] = {"code": before["meta"]["code"], "what": args.before_note or "an earlier count"}
            for r in results:
                r["ops_per_step_before"] = earlier.get(r["what"])
        atomic_write_text(args.out, json.dumps({"meta": meta, "results": results}, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
