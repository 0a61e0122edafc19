"""Torch ops per training env step that each piece of the robust preset's randomisation adds (a CPU count).

On a GPU every torch op of the env step that does work (besides the physics, which mujoco-warp launches itself) is a
kernel, a few microseconds each at 4,096 envs whatever its size: step timelines on an H200 put the randomisation's
steady non-physics cost at about 2.5 us per such op (docs/benchmarks/randomization/delay_average_cost). Counting the
ops of the step as training runs it (``build_env(..., for_training=True, sync_free_resets=True)``, the sync-free
masked reset every step) therefore shows where the randomisation's per-step overhead comes from, on any machine.
Two counts of top-level ``aten::`` ops under ``torch.profiler``, per ``step_and_maybe_reset``, averaged over 10 steps
of 32 envs on C MuJoCo: every op (views included), and the kernels: the ops outside the simulator's own calls (on
a GPU those are warp graphs, on the CPU C MuJoCo's bookkeeping) that do work, i.e. neither views (:data:`VIEWS`)
nor casts to the dtype a tensor already has. Each row switches one piece of the ``robust`` preset on over the
preset with all of them off, the last row is the preset itself.

Wrote docs/benchmarks/randomization/step_ops.json (about a minute on 2 cores; ``--before`` adds an earlier report's
counts as a column, here the one this script wrote at 3862f44, copied to /tmp first)::

    PYTHONPATH=. python lab/analysis/step_ops.py --overwrite --out docs/benchmarks/randomization/step_ops.json \
        --before /tmp/an/step_ops_3862f44.json --before_note "before the one-pass sensor noise"
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

from lab.new_files import write_new_files

#: Ops that launch no kernel: views and shape bookkeeping.
VIEWS = frozenset({
    "alias", "as_strided", "chunk", "detach", "empty", "empty_like", "empty_strided", "expand", "expand_as",
    "flatten", "lift_fresh", "narrow", "permute", "reshape", "_reshape_alias", "resolve_conj", "resolve_neg",
    "result_type", "select", "slice", "split", "split_with_sizes", "squeeze", "t", "transpose", "unbind",
    "unflatten", "unsqueeze", "_unsafe_view", "view", "view_as"})
#: The simulator's methods whose ops the kernel count leaves out (the physics, not the step's torch ops).
SIM_CALLS = ("step", "reset", "reset_to_start", "forward")
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


def ops_per_step(cfg, num_envs: int, steps: int) -> tuple[float, float, dict[str, float]]:
    """Top-level aten ops per ``step_and_maybe_reset`` of ``cfg``'s training env, its kernels (see the module doc)
    and the ten most frequent ops."""
    from torch.profiler import ProfilerActivity, profile, record_function

    from tocabi_torchrl.rl.trainer import build_env

    env = build_env(cfg, torch.device("cpu"), num_envs=num_envs, for_training=True, sync_free_resets=True)
    sim = env.base_env.sim
    for name in SIM_CALLS:
        if hasattr(sim, name):
            def marked(*args, _fn=getattr(sim, name), **kwargs):
                with record_function("step_ops:sim"):
                    return _fn(*args, **kwargs)
            setattr(sim, name, marked)
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
    top = [e for e in prof.events() if e.name.startswith("aten::")
           and not (e.cpu_parent is not None and e.cpu_parent.name.startswith("aten::"))]
    count = collections.Counter(e.name for e in top)
    kernels = sum(1 for e in top if _is_kernel(e))
    return sum(count.values()) / steps, kernels / steps, {k: v / steps for k, v in count.most_common(10)}


def _is_kernel(event) -> bool:
    """A top-level op that does work outside the simulator: not a view, not a cast to the same dtype."""
    name = event.name.removeprefix("aten::")
    if name in VIEWS or (name == "to" and not any(c.name == "aten::_to_copy" for c in event.cpu_children)):
        return False
    parent = event.cpu_parent
    while parent is not None:
        if parent.name == "step_ops:sim":
            return False
        parent = parent.cpu_parent
    return True


def read_before(parser: argparse.ArgumentParser, path: Path) -> dict:
    """The earlier report ``--before`` names, checked before the count (a minute of work it would otherwise lose
    at the end): ``parser.error`` naming the file when it is missing or not a report of this script."""
    try:
        before = json.loads(path.read_text())
        before["meta"]["code"]  # noqa: B018 - what main reads of it: the commit and each row's "what"
        if not all("what" in row for row in before["results"]):
            raise KeyError("what")
    except (OSError, ValueError, KeyError, TypeError) as err:
        parser.error(f"--before {path}: not a report of lab/analysis/step_ops.py ({type(err).__name__}: {err}); "
                     "give a JSON this script wrote with --out")
    return before


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--num_envs", type=int, default=32, help="envs (the count does not depend on it)")
    p.add_argument("--steps", type=int, default=10, help="steps counted per row")
    p.add_argument("--out", type=Path, default=None, help="JSON to write (default: print only)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing --out file")
    p.add_argument("--before", type=Path, default=None,
                   help="an earlier report of this script, whose counts become a column beside these")
    p.add_argument("--before_note", default="", help="what the earlier report's code lacked (shown with its column)")
    args = p.parse_args(argv)
    if args.out is not None and args.out.exists() and not args.overwrite:
        p.error(f"{args.out} exists; pass --overwrite to replace it, or --out another path")
    before = read_before(p, args.before) if args.before is not None else None
    torch.set_num_threads(1)
    robust = preset_tree("robust")
    off = replace_paths(robust, OFF)
    rows = [("nothing", off)] + [(name, replace_paths(off, paths)) for name, paths in pieces(robust).items()]
    rows.append(("everything (the robust preset)", robust))
    results, base, base_k = [], None, None
    for name, cfg in rows:
        ops, kernels, top = ops_per_step(cfg, args.num_envs, args.steps)
        base, base_k = (ops, kernels) if base is None else (base, base_k)
        results.append({"what": name, "ops_per_step": ops, "over_nothing": ops - base, "kernels_per_step": kernels,
                        "kernels_over_nothing": kernels - base_k, "most_frequent": top})
        print(f"{name:40s} {ops:7.0f} ops per step ({ops - base:+.0f}), {kernels:5.0f} kernels "
              f"({kernels - base_k:+.0f})", flush=True)
    if args.out is not None:
        commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], check=False, capture_output=True,
                                text=True).stdout.strip()
        meta = {"command": shlex.join(["python", "lab/analysis/step_ops.py", *(argv or sys.argv[1:])]),
                "date": time.strftime("%Y-%m-%d"), "code": commit, "torch": torch.__version__,
                "hardware": "CPU (C MuJoCo)", "num_envs": args.num_envs, "steps": args.steps}
        if before is not None:
            earlier = {r["what"]: r for r in before["results"]}
            meta["before"] = {"code": before["meta"]["code"], "what": args.before_note or "an earlier count"}
            for r in results:
                r["ops_per_step_before"] = earlier.get(r["what"], {}).get("ops_per_step")
                r["kernels_per_step_before"] = earlier.get(r["what"], {}).get("kernels_per_step")
        text = json.dumps({"meta": meta, "results": results}, indent=1) + "\n"
        if args.overwrite:
            atomic_write_text(args.out, text)
        else:  # nor over a file that appeared there while counting: the results then go beside it
            write_new_files({args.out: text})
    return 0


if __name__ == "__main__":
    sys.exit(main())
