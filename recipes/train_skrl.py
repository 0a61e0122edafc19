"""Train the walking task with skrl's PPO (skrl 2.x, torch) and its ``SequentialTrainer``, then run the 8 s gait
test.

    pip install -e ".[skrl]"
    python recipes/train_skrl.py --out runs/skrl                      # 4,096 envs on a GPU
    python recipes/train_skrl.py --out /tmp/k --device cpu --num_envs 4 --iterations 2 --rollouts 8 --hidden 32

skrl is this project's fourth library rather than rl_games: it is pure PyTorch on gymnasium spaces and takes the
env's device tensors as they are, where rl_games builds on the unmaintained ``gym`` package and its own env
registry. Hyper-parameters mirror the TorchRL ``default`` preset (48-step rollouts, 5 epochs, mini-batches of
49,152 at 4,096 envs, gamma 0.995, lambda 0.95, KL-adaptive LR from 1e-3 at KL 0.01, 400-200-100 ELU networks
initialised as the preset's, time-limit bootstrapping from the ended episode's last observation); the std is learned
from 0.2. Writes skrl's own logs and checkpoints under <out>/skrl, the policy as <out>/policy.pt (tensors only) and
the gait test under <out>/eval/ (``--eval_test robust``: the robust gait test, robust.json and robust.png,
docs/evaluation.md).

``--resume`` continues the run in ``--out`` from skrl's agent checkpoint of its previous call (``--max_minutes``
caps the total training time over all calls):

    python recipes/train_skrl.py --out runs/k --max_minutes 9 --eval_envs 0
    python recipes/train_skrl.py --out runs/k --max_minutes 18 --eval_envs 0 --resume    # 9 more minutes
"""

from __future__ import annotations

import argparse
import functools
import io
import math
import sys
from importlib import metadata

from tocabi_torchrl.cli import base_parser, hidden_sizes
from tocabi_torchrl.config import PRESETS  # torch-free: --help answers before torch loads


def build_parser() -> argparse.ArgumentParser:
    """The command line: the options every library recipe takes and skrl's own."""
    parser = base_parser(__doc__.split("\n\n")[0], num_envs=4096, iterations=1500, presets=PRESETS)
    parser.add_argument("--rollouts", type=int, default=48, help="rollout length per env (default: 48)")
    parser.add_argument("--hidden", type=hidden_sizes, default=(400, 200, 100),
                        help="hidden layer sizes of actor and critic, comma-separated (default: 400,200,100)")
    return parser


if __name__ == "__main__":  # --help or a misspelt option answers before torch and skrl load
    build_parser().parse_args(sys.argv[1:])

import torch  # noqa: E402
from torch import nn  # noqa: E402

from tocabi_torchrl.adapters.evaluate import evaluate_policy_file  # noqa: E402
from tocabi_torchrl.adapters.policy_file import (  # noqa: E402
    action_bounds,
    load_network,
    load_policy,
    require_meta,
    save_policy,
)
from tocabi_torchrl.adapters.recipe import (  # noqa: E402
    TrainingClock,
    adapter,
    call_seed,
    check_args,
    check_out_dir,
    eval_text,
    exit_status,
    finish_call,
    fresh_dir,
    open_out_dir,
    read_resume,
    run_call,
)
from tocabi_torchrl.config import preset_config  # noqa: E402
from tocabi_torchrl.rl.networks import ACTION_OUT_GAIN, INIT_SETTING, make_mlp  # noqa: E402

#: What a resumed call does not carry over (also in the per-library table's notes).
RESUME_NOTES = ("resumes skrl's agent checkpoint (agent.save/agent.load): policy with its learned std, value and Adam "
                "state, whose param groups hold the KL-adaptive learning rate; skrl's trainer timestep restarts at 0 "
                "each call (it only names skrl's logs and checkpoints, kept per call); not the env state (every call "
                "starts from a reset), the random-number state (reseeded with seed + call index) or the rollout in "
                "progress when a call's time is up (discarded; its steps and seconds count)")


def make_models(observation_space, action_space, device, hidden: tuple[int, ...], init_std: float = 0.2,
                value_out_gain: float = 1.0) -> dict:
    """skrl models: a Gaussian policy with a state-independent learned std and a value network, initialised as the
    preset's networks (orthogonal, action-mean gain :data:`ACTION_OUT_GAIN`, value head ``value_out_gain``)."""
    from skrl.models.torch import DeterministicMixin, GaussianMixin, Model

    obs_dim, act_dim = observation_space.shape[0], action_space.shape[0]

    class Policy(GaussianMixin, Model):
        def __init__(self):
            Model.__init__(self, observation_space=observation_space, action_space=action_space, device=device)
            GaussianMixin.__init__(self, clip_actions=False, clip_log_std=True, min_log_std=-20.0, max_log_std=2.0)
            self.net = make_mlp(obs_dim, hidden, act_dim, "elu", ACTION_OUT_GAIN)
            self.log_std_parameter = nn.Parameter(torch.full((act_dim,), math.log(init_std)))

        def compute(self, inputs, role=""):
            return self.net(inputs["observations"]), {"log_std": self.log_std_parameter}

    class Value(DeterministicMixin, Model):
        def __init__(self):
            Model.__init__(self, observation_space=observation_space, action_space=action_space, device=device)
            DeterministicMixin.__init__(self, clip_actions=False)
            self.net = make_mlp(obs_dim, hidden, 1, "elu", value_out_gain)

        def compute(self, inputs, role=""):
            return self.net(inputs["observations"]), {}

    return {"policy": Policy().to(device), "value": Value().to(device)}


def time_limit_ppo():
    """skrl's PPO, bootstrapping a time-out from the value of the ended episode's last observation.

    With ``time_limit_bootstrap`` skrl adds ``discount · V(next_observations)`` to a truncated step's reward. An
    autoresetting env (this one, as Isaac Lab's) returns the next episode's first observation there, so skrl's own
    PPO bootstrapped from the value of an unrelated start. This one takes that value from ``infos["final_obs"]``
    (num_envs, 237), where the episode ran out of time, and keeps ``next_observations`` as the observation acted on
    next (the rollout's last value is taken from it)."""
    from skrl.agents.torch.ppo import PPO

    class TimeLimitPPO(PPO):
        def record_transition(self, *, next_observations, infos, **kwargs):
            super().record_transition(next_observations=infos["final_obs"], infos=infos, **kwargs)
            if self.training:
                self._current_next_observations = next_observations

    return TimeLimitPPO


def main(argv=None) -> dict:
    parser = build_parser()
    args = parser.parse_args(argv)
    check_args(parser, args, at_least={"rollouts": 1})
    if args.rollouts * args.num_envs < 2:  # one sample: the advantages' std is NaN, and so is every weight after
        parser.error(f"--rollouts {args.rollouts} x --num_envs {args.num_envs} must be at least 2 (skrl's PPO "
                     "normalises the rollout's advantages)")
    # The adapter checks the installed skrl version before any of skrl's own modules is imported.
    TocabiSkrlEnv = adapter("TocabiSkrlEnv")
    from skrl.agents.torch.ppo import PPO_CFG
    from skrl.memories.torch import RandomMemory
    from skrl.resources.schedulers.torch import KLAdaptiveLR
    from skrl.trainers.torch import SequentialTrainer
    from skrl.utils import set_seed

    out = check_out_dir(args.out, args.resume)  # created once the env is built: a failed call leaves no folder
    prior = read_resume(out, torch_state=True) if args.resume else {}
    calls = int(prior.get("calls", 0))
    settings = {"num_envs": args.num_envs, "preset": args.preset, "hidden": list(args.hidden),
                "rollouts": args.rollouts, "seed": args.seed, "init": INIT_SETTING}
    if prior and prior["settings"] != settings:
        raise SystemExit(f"error: --resume of {out} with other settings than it started with: saved "
                         f"{prior['settings']}, given {settings}")
    set_seed(call_seed(args.seed, calls))  # a resumed call draws other exploration noise
    env = TocabiSkrlEnv(args.num_envs, args.device, preset=args.preset, seed=call_seed(args.seed, calls))
    open_out_dir(out, args.resume)
    models = make_models(env.observation_space, env.action_space, env.device, args.hidden,
                         value_out_gain=preset_config(args.preset).ppo.value_out_gain)
    cfg = PPO_CFG(
        rollouts=args.rollouts, learning_epochs=5, mini_batches=max(1, args.num_envs * args.rollouts // 49152),
        discount_factor=0.995, gae_lambda=0.95, learning_rate=1e-3, learning_rate_scheduler=KLAdaptiveLR,
        learning_rate_scheduler_kwargs={"kl_threshold": 0.01}, grad_norm_clip=1.0, ratio_clip=0.2, value_clip=0.2,
        entropy_loss_scale=0.0, value_loss_scale=1.0, time_limit_bootstrap=True,
        # Each call writes skrl's logs and checkpoints to its own experiment folder: skrl names its checkpoints by
        # the call's own timestep, which restarts at 0, so a shared folder would overwrite the earlier call's.
        experiment={"directory": str(out / "skrl"),
                    "experiment_name": "ppo" if calls == 0 else fresh_dir(out / "skrl" / f"ppo_call{calls + 1}").name,
                    "write_interval": args.rollouts, "checkpoint_interval": 100 * args.rollouts})
    memory = RandomMemory(memory_size=args.rollouts, num_envs=env.num_envs, device=env.device)
    agent = time_limit_ppo()(models=models, memory=memory, observation_space=env.observation_space,
                             action_space=env.action_space, device=env.device, cfg=cfg)
    done_before = int(prior.get("iterations", 0))
    if prior:
        # skrl's own load of its own save: policy (with its learned std), value and Adam, whose param groups hold
        # the KL-adaptive learning rate; the scheduler keeps no other state.
        # The bytes read_resume checked (tensors only), not the file again: skrl's load unpickles what it reads.
        agent.load(io.BytesIO(prior["state_bytes"]))
    updates = [0]
    update = agent.update

    def counted_update(*a, **k):
        update(*a, **k)
        updates[0] += 1

    agent.update = counted_update
    left = args.iterations - done_before
    trainer = SequentialTrainer(env=env, agents=agent, cfg={"timesteps": max(left, 0) * args.rollouts,
                                                            "headless": True, "close_environment_at_exit": False})
    meta = {"preset": args.preset, "task": {"seed": args.seed}, "hidden": list(args.hidden),
            "num_envs": args.num_envs, "library_version": metadata.version("skrl"),
            "obs_dim": env.observation_space.shape[0], "action_low": env.action_space.low.tolist(),
            "action_high": env.action_space.high.tolist()}
    env_steps_before = int(prior.get("env_steps", 0))

    def env_steps():
        return env_steps_before + env.stepper.env_steps

    def save(path):
        save_policy(path, "skrl", models["policy"].state_dict(),
                    {**meta, "env_steps": env_steps(), "train_seconds": clock.elapsed})

    clock = TrainingClock(out, save, args.max_minutes, args.checkpoint_minutes,
                          offset=float(prior.get("train_seconds", 0.0)), snapshots=prior.get("snapshots"))
    env.stepper.step_hooks.append(clock)
    _, interrupted = run_call("skrl", clock, out, trainer.train, left, f"{done_before} iterations")
    env.stepper.step_hooks.clear()
    seconds = clock.freeze()
    meta.update(env_steps=env_steps(), train_seconds=seconds, env_steps_per_s=env_steps() / max(seconds, 1e-9),
                snapshots=clock.snapshots, iterations=done_before + updates[0], calls=calls + 1,
                resume_notes=RESUME_NOTES,
                iterations_budget=args.iterations)  # the table tells a used budget by this, not the clock
    buffer = io.BytesIO()
    agent.save(buffer)  # skrl's own checkpoint (its checkpoint_modules), written atomically as a new file
    result = finish_call(out, args, meta, settings, buffer.getvalue(), save, evaluate, interrupted)
    env.close()
    print(f"skrl: {meta['env_steps']} env steps in {meta['train_seconds']:.1f} s; gait test: "
          f"{eval_text(result)}")
    return result


#: The metadata fields :func:`load_actor` rebuilds the network from: {name: (kind, what it holds)} (see
#: :func:`tocabi_torchrl.adapters.policy_file.require_meta`).
POLICY_FIELDS = {"obs_dim": ("count", "the observation size, e.g. 237"),
                 "action_low": ("numbers", "the action space's lower bounds, one per action"),
                 "action_high": ("numbers", "the action space's upper bounds, one per action"),
                 "hidden": ("sizes", "the hidden layer widths, e.g. [256, 256]")}


def load_actor(policy: str):
    """``(meta, act)`` for a ``policy.pt`` this recipe wrote: skrl's policy model rebuilt from the metadata, and
    ``act`` its Gaussian mean (skrl's ``"mean_actions"``) for (num_envs, 237) observations on any device."""
    from gymnasium import spaces

    from tocabi_torchrl.adapters._versions import require

    require("skrl")
    meta, state = load_policy(policy, "skrl")
    require_meta(meta, POLICY_FIELDS, policy, "load_actor needs to rebuild the network")
    obs_space = spaces.Box(-float("inf"), float("inf"), (meta["obs_dim"],))
    act_space = spaces.Box(*(bound.numpy() for bound in action_bounds(meta, policy)))
    net = load_network(policy, meta, tuple(POLICY_FIELDS),
                       lambda: make_models(obs_space, act_space, "cpu", tuple(meta["hidden"]))["policy"], state)
    net.eval()

    def act(obs):  # the env clips the mean to the action bounds
        net.to(obs.device)
        return net.act({"observations": obs}, role="policy")[1]["mean_actions"]

    return meta, act


#: ``evaluate(policy, out_dir, **options)``: the gait test (``test="standard"`` or ``"robust"``) of a ``policy.pt``
#: this recipe wrote.
evaluate = functools.partial(evaluate_policy_file, load_actor)


if __name__ == "__main__":
    sys.exit(exit_status(main(sys.argv[1:])))
