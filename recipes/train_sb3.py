"""Train the walking task with Stable-Baselines3's PPO and the reference's hyper-parameters, then run the 8 s gait
test.

    pip install -e ".[sb3]"
    python recipes/train_sb3.py --out runs/sb3                        # 8 envs × 2,048 steps, as the reference
    python recipes/train_sb3.py --out /tmp/s --device cpu --num_envs 4 --iterations 2 --n_steps 8 --batch_size 16

Hyper-parameters (spec §10): 8 envs × 2,048 steps per rollout, mini-batch 128, 3 epochs, gamma 0.99, lambda 0.95,
clip 0.2, no entropy bonus, value coefficient 0.5, global grad-norm 0.5, Adam eps 1e-5, 256-256 ReLU actor and
critic (orthogonal init, value head gain 0.01), LR 1e-5 -> 2e-7 linear with the value head at a constant 5e-4, and
the scheduled (not learned) std: 0.1 -> 0.05 over the first half of training, then 0.05, set before each update.
SB3 keeps numpy arrays on the host: each step copies observations and rewards off the env's device (stated in the
per-library table). Writes SB3's own zip (<out>/sb3_model.zip: loading it unpickles SB3's saved objects, so load
only your own), the policy as <out>/policy.pt (tensors only) and the gait test under <out>/eval/.
"""

from __future__ import annotations

import functools
import math
import sys
from importlib import metadata

import torch

from tocabi_torchrl.adapters.evaluate import evaluate_policy_file
from tocabi_torchrl.adapters.policy_file import load_policy, save_policy
from tocabi_torchrl.adapters.recipe import TimeUp, TrainingClock, base_parser, open_out_dir, write_json
from tocabi_torchrl.rl.std_schedule import StdSchedule

#: Reference learning rates (spec §10.2): the policy's schedule ends and the value head's constant rate.
LR_START, LR_END, VALUE_HEAD_LR = 1e-5, 2e-7, 5e-4
STD = StdSchedule(start=0.1, end=0.05, hold=0.5)


class LinearLR:
    """``lr(P) = P·start + (1 − P)·end`` with P = progress remaining (a class, not a lambda, so SB3 can save it)."""

    def __init__(self, start: float, end: float):
        self.start, self.end = start, end

    def __call__(self, progress_remaining: float) -> float:
        return progress_remaining * self.start + (1.0 - progress_remaining) * self.end


def reference_ppo_class():
    """SB3's PPO with the reference's two changes: the scheduled std set before each update, and the value head
    on its own constant learning rate (a second parameter group that SB3's LR schedule leaves alone)."""
    from stable_baselines3 import PPO
    from stable_baselines3.common.utils import update_learning_rate

    class ReferencePPO(PPO):
        def _setup_model(self) -> None:
            super()._setup_model()
            policy = self.policy
            torch.nn.init.orthogonal_(policy.value_net.weight, gain=0.01)
            torch.nn.init.zeros_(policy.value_net.bias)
            policy.log_std.requires_grad_(False)  # scheduled, not learned
            policy.log_std.data.fill_(math.log(STD(1.0)))
            head = set(policy.value_net.parameters())
            rest = [p for p in policy.parameters() if p not in head and p.requires_grad]
            policy.optimizer = torch.optim.Adam([{"params": rest}, {"params": list(head), "lr": VALUE_HEAD_LR}],
                                                lr=LR_START, eps=1e-5)

        def _update_learning_rate(self, optimizers) -> None:
            lr = self.lr_schedule(self._current_progress_remaining)
            self.logger.record("train/learning_rate", lr)
            update_learning_rate(self.policy.optimizer, lr)
            self.policy.optimizer.param_groups[1]["lr"] = VALUE_HEAD_LR

        def train(self) -> None:
            # The reference sets the std after each rollout, before the update, from the progress remaining.
            self.policy.log_std.data.fill_(math.log(STD(self._current_progress_remaining)))
            super().train()

    return ReferencePPO


def policy_kwargs(hidden: tuple[int, ...]) -> dict:
    return {"net_arch": {"pi": list(hidden), "vf": list(hidden)}, "activation_fn": torch.nn.ReLU,
            "log_std_init": math.log(STD(1.0)), "ortho_init": True}


def main(argv=None) -> dict:
    parser = base_parser(__doc__.split("\n\n")[0], num_envs=8, iterations=7325)
    parser.add_argument("--n_steps", type=int, default=2048, help="rollout length per env (default: 2048)")
    parser.add_argument("--batch_size", type=int, default=128, help="mini-batch size (default: 128)")
    parser.add_argument("--epochs", type=int, default=3, help="passes over each rollout (default: 3)")
    parser.add_argument("--hidden", type=lambda s: tuple(int(x) for x in s.split(",")), default=(256, 256),
                        help="hidden layer sizes of actor and critic, comma-separated (default: 256,256)")
    args = parser.parse_args(argv)
    from tocabi_torchrl.adapters import TocabiSB3VecEnv  # checks the stable-baselines3 version

    out = open_out_dir(args.out)
    env = TocabiSB3VecEnv(args.num_envs, args.device, preset=args.preset, seed=args.seed)
    model = reference_ppo_class()(
        "MlpPolicy", env, learning_rate=LinearLR(LR_START, LR_END), n_steps=args.n_steps,
        batch_size=args.batch_size, n_epochs=args.epochs, gamma=0.99, gae_lambda=0.95, clip_range=0.2,
        ent_coef=0.0, vf_coef=0.5, max_grad_norm=0.5, policy_kwargs=policy_kwargs(args.hidden), seed=args.seed,
        device=str(env.device), verbose=1)
    meta = {"preset": args.preset, "task": {"seed": args.seed}, "hidden": list(args.hidden),
            "num_envs": args.num_envs, "library_version": metadata.version("stable-baselines3"),
            "obs_dim": env.observation_space.shape[0], "action_low": env.action_space.low.tolist(),
            "action_high": env.action_space.high.tolist(),
            "host_copies_per_step": "observation (num_envs, 237), reward, done flags to the host; actions back"}

    def save(path):
        save_policy(path, "sb3", model.policy.state_dict(),
                    {**meta, "env_steps": env.stepper.env_steps, "train_seconds": clock.elapsed})

    clock = TrainingClock(out, save, args.max_minutes, args.checkpoint_minutes)
    env.stepper.step_hooks.append(clock)
    try:
        model.learn(total_timesteps=args.iterations * args.n_steps * args.num_envs)
    except TimeUp as stop:
        print(f"sb3: {stop}")
    meta.update(env_steps=env.stepper.env_steps, train_seconds=clock.elapsed,
                env_steps_per_s=env.stepper.env_steps / clock.elapsed, snapshots=clock.snapshots)
    env.stepper.step_hooks.clear()
    save(out / "policy.pt")
    model.save(out / "sb3_model.zip")
    result = {"train": meta}
    if args.eval_envs > 0:
        result["eval"] = evaluate(out / "policy.pt", out / "eval", num_envs=args.eval_envs, device=args.device,
                                  seconds=args.eval_seconds)
    write_json(out / "result.json", result)
    env.close()
    print(f"sb3: {meta['env_steps']} env steps in {meta['train_seconds']:.1f} s; gait test: "
          f"{result.get('eval', 'skipped')}")
    return result


def load_actor(policy: str):
    """``(meta, act)`` for a ``policy.pt`` this recipe wrote: SB3's policy network rebuilt from the metadata, and
    ``act`` its Gaussian mean (SB3's deterministic action) for (num_envs, 237) observations on any device."""
    from gymnasium import spaces

    from tocabi_torchrl.adapters._versions import require

    require("stable_baselines3")
    from stable_baselines3.common.policies import ActorCriticPolicy

    meta, state = load_policy(policy, "sb3")
    obs_space = spaces.Box(-float("inf"), float("inf"), (meta["obs_dim"],))
    act_space = spaces.Box(torch.tensor(meta["action_low"]).numpy(), torch.tensor(meta["action_high"]).numpy())
    net = ActorCriticPolicy(obs_space, act_space, lr_schedule=LinearLR(0.0, 0.0),
                            **policy_kwargs(tuple(meta["hidden"])))
    net.load_state_dict(state)
    net.eval()

    def act(obs):  # the env clips the mean to the action bounds, as SB3's predict() would
        return net.to(obs.device)._predict(obs, deterministic=True)

    return meta, act


#: ``evaluate(policy, out_dir, **options)``: the 8 s gait test of a ``policy.pt`` this recipe wrote.
evaluate = functools.partial(evaluate_policy_file, load_actor)


if __name__ == "__main__":
    main(sys.argv[1:])
