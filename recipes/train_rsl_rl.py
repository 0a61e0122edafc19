"""Train the walking task with rsl_rl's ``OnPolicyRunner`` and PPO (rsl-rl-lib 5.x), then run the 8 s gait test.

    pip install -e ".[rsl_rl]"
    python recipes/train_rsl_rl.py --out runs/rsl_rl                  # 4,096 envs on a GPU, 1,500 iterations
    python recipes/train_rsl_rl.py --out /tmp/r --device cpu --num_envs 4 --iterations 2 --steps_per_env 8 --hidden 32

The hyper-parameters mirror the TorchRL ``default`` preset (48 steps per env, 5 epochs, 4 mini-batches of 49,152 at
4,096 envs, gamma 0.995, lambda 0.95, adaptive LR from 1e-3 at KL 0.01, 400-200-100 ELU networks) except the std:
rsl_rl learns it (starting at 0.2) where the preset schedules it. Writes rsl_rl's own logs and model_*.pt under
<out>/rsl_rl, the policy as <out>/policy.pt (tensors only, tocabi_torchrl.adapters.policy_file) and the gait test
under <out>/eval/.
"""

from __future__ import annotations

import functools
import sys
from importlib import metadata

import torch

from tocabi_torchrl.adapters.evaluate import evaluate_policy_file
from tocabi_torchrl.adapters.policy_file import load_policy, save_policy
from tocabi_torchrl.adapters.recipe import TimeUp, TrainingClock, base_parser, open_out_dir, write_json


def train_cfg(args) -> dict:
    """rsl_rl 5's runner configuration (a plain dict, its documented format)."""
    hidden = list(args.hidden)
    frames = args.num_envs * args.steps_per_env
    return {
        "num_steps_per_env": args.steps_per_env,
        "save_interval": 100,
        "seed": args.seed,
        "obs_groups": {"actor": ["policy"], "critic": ["critic"]},
        "logger": "tensorboard",
        "algorithm": {"class_name": "PPO", "num_learning_epochs": 5, "num_mini_batches": max(1, frames // 49152),
                      "clip_param": 0.2, "gamma": 0.995, "lam": 0.95, "value_loss_coef": 1.0, "entropy_coef": 0.0,
                      "learning_rate": 1e-3, "max_grad_norm": 1.0, "schedule": "adaptive", "desired_kl": 0.01,
                      "use_clipped_value_loss": True},
        "actor": {"class_name": "MLPModel", "hidden_dims": hidden, "activation": "elu",
                  "distribution_cfg": {"class_name": "GaussianDistribution", "init_std": 0.2}},
        "critic": {"class_name": "MLPModel", "hidden_dims": hidden, "activation": "elu"},
    }


def make_actor(obs_dim: int, num_actions: int, cfg: dict):
    """rsl_rl's actor network (as its runner builds it) for the adapter's observation groups."""
    from rsl_rl.models import MLPModel
    from tensordict import TensorDict

    groups = TensorDict({"policy": torch.zeros(1, obs_dim), "critic": torch.zeros(1, obs_dim)}, batch_size=[1])
    actor_cfg = {k: v for k, v in cfg["actor"].items() if k != "class_name"}
    return MLPModel(groups, cfg["obs_groups"], "actor", num_actions, **actor_cfg)


def main(argv=None) -> dict:
    parser = base_parser(__doc__.split("\n\n")[0], num_envs=4096, iterations=1500)
    parser.add_argument("--steps_per_env", type=int, default=48, help="rollout length per env (default: 48)")
    parser.add_argument("--hidden", type=lambda s: tuple(int(x) for x in s.split(",")), default=(400, 200, 100),
                        help="hidden layer sizes of actor and critic, comma-separated (default: 400,200,100)")
    args = parser.parse_args(argv)
    # The adapter checks the installed rsl-rl-lib version before any of rsl_rl's own modules is imported.
    from tocabi_torchrl.adapters import TocabiRslRlEnv  # isort: skip
    from rsl_rl.runners import OnPolicyRunner

    out = open_out_dir(args.out)
    torch.manual_seed(args.seed)
    env = TocabiRslRlEnv(args.num_envs, args.device, preset=args.preset, seed=args.seed)
    cfg = train_cfg(args)
    runner = OnPolicyRunner(env, cfg, log_dir=str(out / "rsl_rl"), device=str(env.device))
    meta = {"preset": args.preset, "task": {"seed": args.seed}, "train_cfg": cfg, "num_envs": args.num_envs,
            "obs_dim": env.stepper.obs_dim, "num_actions": env.num_actions,
            "library_version": metadata.version("rsl-rl-lib")}

    def save(path):
        save_policy(path, "rsl_rl", runner.alg.get_policy().state_dict(),
                    {**meta, "env_steps": env.stepper.env_steps, "train_seconds": clock.elapsed})

    clock = TrainingClock(out, save, args.max_minutes, args.checkpoint_minutes)
    env.stepper.step_hooks.append(clock)
    try:
        runner.learn(args.iterations)
    except TimeUp as stop:
        print(f"rsl_rl: {stop}")
    meta.update(env_steps=env.stepper.env_steps, train_seconds=clock.elapsed,
                env_steps_per_s=env.stepper.env_steps / clock.elapsed, snapshots=clock.snapshots)
    env.stepper.step_hooks.clear()
    save(out / "policy.pt")
    seconds = meta["train_seconds"]
    done = meta["env_steps"] // (args.num_envs * args.steps_per_env)
    result = {"train": meta}
    if args.eval_envs > 0:
        result["eval"] = evaluate(out / "policy.pt", out / "eval", num_envs=args.eval_envs, device=args.device,
                                  seconds=args.eval_seconds)
    write_json(out / "result.json", result)
    env.close()
    print(f"rsl_rl: {done} full rollouts in {seconds:.1f} s; gait test: {result.get('eval', 'skipped')}")
    return result


def load_actor(policy: str):
    """``(meta, act)`` for a ``policy.pt`` this recipe wrote: rsl_rl's actor rebuilt from the metadata, and ``act``
    its deterministic output (the Gaussian mean) for (num_envs, 237) observations on any device."""
    from tensordict import TensorDict

    from tocabi_torchrl.adapters._versions import require

    require("rsl_rl")
    meta, state = load_policy(policy, "rsl_rl")
    actor = make_actor(meta["obs_dim"], meta["num_actions"], meta["train_cfg"])
    actor.load_state_dict(state)
    actor.eval()

    def act(obs):  # the env clips the mean to the action bounds
        groups = TensorDict({"policy": obs, "critic": obs}, batch_size=obs.shape[:1])
        return actor.to(obs.device)(groups)

    return meta, act


#: ``evaluate(policy, out_dir, **options)``: the 8 s gait test of a ``policy.pt`` this recipe wrote.
evaluate = functools.partial(evaluate_policy_file, load_actor)


if __name__ == "__main__":
    main(sys.argv[1:])
