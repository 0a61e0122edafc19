"""The model_based law at zero (or small random) residual vs pd_reference: survival and leg tracking, C MuJoCo.

Wrote zero_action.json (docs/training.md's table), ~40 min on 2 cores (an existing file is never replaced):
``PYTHONPATH=. python lab/analysis/mb_zero_action.py docs/training/model_based/zero_action.json``
"""
import argparse
import json
import subprocess
import time
from pathlib import Path

import numpy as np
import torch
from tensordict import TensorDict

from tocabi_torchrl.envs import TocabiWalk
from tocabi_torchrl.envs.config import MB_OMEGA

from lab.new_files import write_new_files


def run(noise, steps, n, **kw):
    env = TocabiWalk(num_envs=n, device="cpu", seed=0, backend="mujoco", max_episode_steps=10**6, sim_threads=1, **kw)
    env.reset(); g = torch.Generator().manual_seed(1)
    alive = torch.ones(n, dtype=torch.bool); life = torch.zeros(n); err = []
    for _ in range(steps):
        a = torch.zeros(n, 13); a[:, :12] = noise * torch.randn(n, 12, generator=g)
        out = env.step(TensorDict({"action": a}, batch_size=[n]))["next"]
        e = (out["joint_pos"][:, :12] - out["ref_joint_pos"][:, :12]).abs().mean(-1)
        if alive.any():
            err.append(e[alive].mean().item())
        alive &= ~out["done"].squeeze(-1); life += alive.float()
        if not alive.any():
            break
    return {"mean_steps_alive": life.mean().item(), "min_steps_alive": life.min().item(),
            "survived_all_steps": alive.float().mean().item(), "mean_abs_leg_error_rad": float(np.mean(err))}


def out_path(doc: str, argv=None) -> Path:
    """The JSON to write, from the command line (``--help`` answers, a missing or existing path is refused) before
    the ``doc`` script's cases run for minutes."""
    parser = argparse.ArgumentParser(description=doc.split("\n\n")[0])
    parser.add_argument("out", type=Path, help="the JSON to write (an existing file is never replaced)")
    out = parser.parse_args(argv).out
    if out.exists():
        parser.error(f"{out} exists; give another path or remove it first (results are never overwritten)")
    return out


def write(out: Path, doc: dict) -> None:
    """``doc`` with the commit it was measured at, written to ``out`` atomically (a run killed meanwhile leaves
    nothing half-written), never over a file: one that appeared at ``out`` after :func:`out_path` checked it is left
    as it is and the results go beside it (:func:`lab.new_files.write_new_files` says where)."""
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True).stdout.strip()
    written = write_new_files({out: json.dumps({**doc, "commit": commit}, indent=1) + "\n"})[0]
    print(f"wrote {written}")


def main(argv=None) -> dict:
    out = out_path(__doc__, argv)
    W = np.array(MB_OMEGA)
    cases = [("pd_reference", dict(control_mode="pd_reference"))]
    cases += [(f"model_based omega x{s:g}, zeta {z:g}", dict(control_mode="model_based", mb_omega=tuple(W * s), mb_zeta=(z,) * 12))
              for s, z in [(0.5, 1.0), (0.7, 0.7), (1, 1.0), (1, 0.7), (1.5, 1.0), (1.5, 0.7)]]
    settings = [{"residual_std": 0.0, "steps": 2500, "num_envs": 16}, {"residual_std": 0.05, "steps": 1500, "num_envs": 32}]
    results = []
    for st in settings:
        for name, kw in cases:
            t0 = time.time()
            r = run(st["residual_std"], st["steps"], st["num_envs"], **kw)
            results.append({"case": name, **st, **r})
            print(results[-1], f"{time.time() - t0:.0f}s", flush=True)
    doc = {"what": "model_based law vs pd_reference with the leg actions at 0 (or N(0, std) per step), phase action 0; "
                   "C MuJoCo on the CPU, TocabiWalk(seed=0), default command schedule, episodes never truncated; "
                   "mean |q_leg - q_ref| over the robots still alive",
           "omega_default_rad_s": list(MB_OMEGA), "results": results}
    write(out, doc)
    return doc


if __name__ == "__main__":
    main()
