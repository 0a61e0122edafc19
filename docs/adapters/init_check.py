"""How many robots fall within 1 s under rsl_rl's actor, initialised as rsl_rl does (PyTorch's default) or as the
preset does (orthogonal, action-mean gain 0.01), with the first rollouts' exploration noise (std 0.2).

    PYTHONPATH=. python docs/adapters/init_check.py docs/adapters/init_check.json      # C MuJoCo, ~1 minute
"""

import argparse
import importlib.util
import json
import sys

import torch

from tocabi_torchrl.adapters import TocabiRslRlEnv
from tocabi_torchrl.rl.networks import ACTION_OUT_GAIN, init_orthogonal

NUM_ENVS, STEPS, STD = 256, 250, 0.2

spec = importlib.util.spec_from_file_location("train_rsl_rl", "recipes/train_rsl_rl.py")
recipe = importlib.util.module_from_spec(spec)
spec.loader.exec_module(recipe)
results = {}
for label in ("pytorch_default", "preset_orthogonal"):
    torch.manual_seed(0)
    env = TocabiRslRlEnv(NUM_ENVS, "cpu", preset="default", seed=0)
    cfg = recipe.train_cfg(argparse.Namespace(hidden=(400, 200, 100), num_envs=NUM_ENVS, steps_per_env=48, seed=0))
    actor = recipe.make_actor(env.stepper.obs_dim, env.num_actions, cfg)
    if label == "preset_orthogonal":
        init_orthogonal(actor.mlp, ACTION_OUT_GAIN)
    torch.manual_seed(1)  # the same exploration noise for both inits (init_orthogonal draws random numbers too)
    obs, fell, mean_abs = env.get_observations(), torch.zeros(NUM_ENVS, dtype=torch.bool), 0.0
    for _ in range(STEPS):
        with torch.no_grad():
            mean = actor(obs)
        mean_abs += mean.abs().mean().item() / STEPS
        obs, _, dones, extras = env.step(mean + STD * torch.randn_like(mean))
        fell |= dones.bool() & ~extras["time_outs"].bool()
    results[label] = {"mean_abs_action_mean": round(mean_abs, 4), "fell_within_1s": fell.float().mean().item()}
    print(label, results[label], flush=True)
out = {"num_envs": NUM_ENVS, "steps": STEPS, "std": STD, "results": results}
if len(sys.argv) > 1:
    with open(sys.argv[1], "w") as f:
        f.write(json.dumps(out, indent=2) + "\n")
