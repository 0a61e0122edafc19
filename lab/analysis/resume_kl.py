"""The first PPO updates after a resume, on the CPU: their KL, clip fraction and the teacher's copy term.

Resumes a training checkpoint (a run's ``latest.pt``, optimiser state included) for ``--iterations`` iterations with
``--num_envs`` robots on the CPU, once per variant: ``as_saved``; ``no_absorb``, without the torque assist's
absorbing term (``ppo.assist_absorb`` 0: no pull to the teacher); ``still_starts``, the robots starting still
(``env.task.start_joint_vel_std`` and ``start_base_vel_std`` 0). A resume refuses settings other than the saved ones,
so each variant resumes a copy of the checkpoint whose saved config carries the variant and the robot count (a
divisor of the run's; the mini-batch scaled with it, keeping the run's mini-batches per epoch), written to a
temporary folder; the checkpoint given is only read. Every robot starts a new episode at a resume, all at once: the spread of episode times that a
long run has built up is gone.

Wrote docs/training/robust/h200_run12/resume_kl.json (about 30 s per variant of 12 iterations of 64 robots on 2
cores)::

    PYTHONPATH=. python lab/analysis/resume_kl.py --num_envs 64 --iterations 12 \\
        --out docs/training/robust/h200_run12/resume_kl.json \\
        --checkpoint runs/time_to_walk/robust_v12/checkpoints/latest.pt
"""

from __future__ import annotations

import argparse
import copy
import statistics
import tempfile
import time
from pathlib import Path

import torch

from tocabi_torchrl.rl.checkpoint import read_checkpoint
from tocabi_torchrl.rl.metrics_files import read_metrics
from tocabi_torchrl.rl.resume import saved_config
from tocabi_torchrl.rl.trainer import train
from tocabi_torchrl.tree import replace_paths

from lab.analysis.reports import check_paths, write_report

#: Variant name -> {config path: value} the resumed copy is saved with.
VARIANTS = {
    "as_saved": {},
    "no_absorb": {"ppo.assist_absorb": 0.0},
    "still_starts": {"env.task.start_joint_vel_std": 0.0, "env.task.start_base_vel_std": 0.0},
}
#: Logged per iteration.
COLUMNS = ("kl", "clip_fraction", "loss_absorb", "terminated_frac")


def _set(config: dict, path: str, value) -> None:
    """Set the dotted ``path`` of the saved config dict ``config`` to ``value``; a path it lacks raises KeyError."""
    *parents, leaf = path.split(".")
    for part in parents:
        if not isinstance(config.get(part), dict):
            raise KeyError(f"{path}: not in the checkpoint's config")
        config = config[part]
    if leaf not in config:
        raise KeyError(f"{path}: not in the checkpoint's config")
    config[leaf] = value


def resumed_copy(state: dict, num_envs: int, changes: dict, out: Path) -> Path:
    """Save ``state`` to ``out`` with its config set to ``num_envs`` robots (mini-batch scaled alike) and
    ``changes``; returns ``out``."""
    state = copy.deepcopy(state)
    config = state["config"]
    saved_envs, saved_batch = config["env"]["num_envs"], config["ppo"]["minibatch_size"]
    if saved_envs % num_envs or (saved_batch * num_envs) % saved_envs:
        raise ValueError(f"--num_envs {num_envs} is not a divisor of the run's {saved_envs} robots that keeps its "
                         f"mini-batches per epoch (mini-batch {saved_batch}); give one such as 64")
    config["env"]["num_envs"], config["ppo"]["minibatch_size"] = num_envs, saved_batch * num_envs // saved_envs
    for path, value in changes.items():
        _set(config, path, value)
    torch.save(state, out)
    return out


def resume_iterations(checkpoint: Path, state: dict, variant: str, num_envs: int, iterations: int) -> dict:
    """Resume ``checkpoint`` (read as ``state``) as ``variant`` for ``iterations`` iterations on the CPU; the logged
    rows and summary."""
    with tempfile.TemporaryDirectory() as tmp:
        copy_path = resumed_copy(state, num_envs, VARIANTS[variant], Path(tmp) / "resume.pt")
        cfg = saved_config(copy_path)
        # The budget in whole iterations of this robot count, however many env steps the run had done.
        frames = num_envs * cfg.ppo.steps_per_env
        steps = (int(state["env_steps"]) // frames + iterations) * frames
        cfg = replace_paths(cfg, {"device": "cpu", "run_dir": tmp, "name": "run", "log_every": 1,
                                  "total_env_steps": steps, "checkpoint_minutes": 0.0, "checkpoint_every": 10**9,
                                  "eval_at_end": False, "progress_bar": False, "ppo.cuda_graph": "off"})
        train(cfg)
        rows = read_metrics(Path(tmp) / "run")
    table = [{"iteration": int(r["iteration"]), **{c: round(float(r[c]), 5) for c in COLUMNS if c in r}}
             for r in rows]
    kl = [r["kl"] for r in table]
    third = max(1, len(kl) // 3)
    return {"checkpoint": str(checkpoint), "variant": variant, "changes": VARIANTS[variant], "num_envs": num_envs,
            "resumed_at_env_steps": int(state["env_steps"]), "iterations": table,
            "kl_median_first_third": round(statistics.median(kl[:third]), 4),
            "kl_median_last_third": round(statistics.median(kl[-third:]), 4)}


def main(argv=None) -> int:
    """The command line (module docstring); writes ``--out`` when given. Returns the exit status."""
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--checkpoint", required=True, type=Path, help="a run's checkpoint with its optimiser (latest.pt)")
    p.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=tuple(VARIANTS),
                   help="variants to resume, one after another (default: all)")
    p.add_argument("--num_envs", type=int, default=64, help="robots (a divisor of the run's count)")
    p.add_argument("--iterations", type=int, default=12, help="PPO iterations after the resume")
    p.add_argument("--out", type=Path, default=None, help="JSON to write (default: print only)")
    args = p.parse_args(argv)
    check_paths(p, [args.checkpoint], args.out)
    if args.num_envs < 1 or args.iterations < 1:
        p.error("--num_envs and --iterations must be >= 1")
    state = read_checkpoint(args.checkpoint)
    if state.get("optimizer") is None:
        p.error(f"{args.checkpoint} holds no optimiser state (a shipped policy file?): give a run's latest.pt")
    results = []
    for variant in args.variants:
        start = time.perf_counter()
        r = resume_iterations(args.checkpoint, state, variant, args.num_envs, args.iterations)
        print(f"{variant}: KL per iteration {[row['kl'] for row in r['iterations']]} "
              f"({time.perf_counter() - start:.0f} s)", flush=True)
        results.append(r)
    if args.out is not None:
        write_report(args.out, "lab/analysis/resume_kl.py", argv, results)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
