"""Train the walking task with rsl_rl's ``OnPolicyRunner`` and PPO (rsl-rl-lib 5.x), then run the 8 s gait test.

    pip install -e ".[rsl_rl]"
    python recipes/train_rsl_rl.py --out runs/rsl_rl                  # 4,096 envs on a GPU, 1,500 iterations
    python recipes/train_rsl_rl.py --out /tmp/r --device cpu --num_envs 4 --iterations 2 --steps_per_env 8 --hidden 32

The hyper-parameters mirror the TorchRL ``default`` preset (48 steps per env, 5 epochs, 4 mini-batches of 49,152 at
4,096 envs, gamma 0.995, lambda 0.95, 400-200-100 ELU networks, initialised as the preset's: orthogonal, action-mean
gain 0.01, plain L2 value loss), and so do the learning rate and the std by default. The rate starts at 1e-3 and
follows the preset's KL rule (``--lr_schedule per_iteration``: towards a KL of 0.01, on the update's mean KL, once per
iteration); rsl_rl's own rule (``adaptive``: the same target, checked before every mini-batch step) held it near 1e-4,
the critic lagged and three rows of up to 22 minutes on one H200 did not walk, while this rule walked at 10
(docs/other-libraries.md). The std by default (``--std scheduled``): the preset's schedule (from 0.2 down to 0.05 over
the first half of the preset's env-step budget, then 0.05), set after each update from the env steps trained, not
learned. ``--std learned`` is rsl_rl's own way (a learned std starting at 0.2); on one H200 it fell to 0.03 and the
policy had not walked after 22 minutes (docs/other-libraries.md). Writes rsl_rl's own logs and model_*.pt under
<out>/rsl_rl, the policy as <out>/policy.pt (tensors only, tocabi_torchrl.adapters.policy_file) and the gait test
under <out>/eval/ (``--eval_test robust``: the robust gait test, robust.json and robust.png, docs/evaluation.md).

A run can be split over several calls: ``--resume`` continues the run in ``--out`` from the state its previous call
saved (see ``tocabi_torchrl.adapters.recipe``), with ``--max_minutes`` the cap on the total training time:

    python recipes/train_rsl_rl.py --out runs/r --max_minutes 9 --eval_envs 0
    python recipes/train_rsl_rl.py --out runs/r --max_minutes 18 --eval_envs 0 --resume    # 9 more minutes
"""

from __future__ import annotations

import argparse
import functools
import io
import json
import sys
from importlib import metadata

from tocabi_torchrl.cli import base_parser, hidden_sizes
from tocabi_torchrl.config import PRESETS  # torch-free: --help answers before torch loads


def build_parser() -> argparse.ArgumentParser:
    """The command line: the options every library recipe takes and rsl_rl's own."""
    parser = base_parser(__doc__.split("\n\n")[0], num_envs=4096, iterations=1500, presets=PRESETS)
    parser.add_argument("--steps_per_env", type=int, default=48, help="rollout length per env (default: 48)")
    parser.add_argument("--learning_rate", type=float, default=1e-3,
                        help="Adam's learning rate: the start of the adaptive schedules, or the fixed rate "
                             "(default: 1e-3)")
    parser.add_argument("--lr_schedule", choices=("per_iteration", "adaptive", "fixed"), default="per_iteration",
                        help="per_iteration: the preset's rule (towards a KL of 0.01, on the update's mean KL, once "
                             "per iteration; default: walked at 10 training minutes on one H200); adaptive: rsl_rl's "
                             "own rule (the same target, checked before every mini-batch step: it held the rate near "
                             "1e-4 and three rows did not walk); fixed. docs/other-libraries.md has the rows")
    parser.add_argument("--std", choices=("scheduled", "learned"), default="scheduled",
                        help="action std: the preset's schedule, set after each update (default), or learned by "
                             "rsl_rl from the schedule's start")
    parser.add_argument("--hidden", type=hidden_sizes, default=(400, 200, 100),
                        help="hidden layer sizes of actor and critic, comma-separated (default: 400,200,100)")
    return parser


if __name__ == "__main__":  # --help or a misspelt option answers before torch and rsl_rl load
    build_parser().parse_args(sys.argv[1:])

import torch  # noqa: E402

from tocabi_torchrl.adapters.evaluate import evaluate_policy_file  # noqa: E402
from tocabi_torchrl.adapters.policy_file import load_network, load_policy, require_meta, save_policy  # noqa: E402
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
from tocabi_torchrl.rl.networks import ACTION_OUT_GAIN, INIT_SETTING, init_orthogonal  # noqa: E402
from tocabi_torchrl.rl.std_schedule import StdSchedule  # noqa: E402
from tocabi_torchrl.rl.update_step import adapt_lr  # noqa: E402

#: What a resumed call does not carry over (also in the per-library table's notes).
RESUME_NOTES = ("resumes actor (with the scheduled std as the last update set it), critic, Adam state, learning "
                "rate and iteration count (rsl_rl's OnPolicyRunner.load); not the env state (every call starts from a "
                "reset), the random-number state (reseeded with seed + call index) or rsl_rl's logger buffers; the "
                "rollout in progress when a call's time is up is discarded")


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
                      "learning_rate": args.learning_rate, "max_grad_norm": 1.0,
                      # per_iteration runs rsl_rl's adaptive code for its KL values only (PerIterationLR)
                      "schedule": "fixed" if args.lr_schedule == "fixed" else "adaptive",
                      "desired_kl": 0.01,
                      # The preset's critic loss is plain L2 (ClipPPOLoss without clip_value). Clipped, each value
                      # could move only +-0.2 from its rollout value per update, on returns of O(100), and at the
                      # ~1e-4 learning rate rsl_rl's per-mini-batch KL rule settles at here the critic lagged behind
                      # (docs/other-libraries.md, "Second GPU row").
                      "use_clipped_value_loss": False},
        "actor": {"class_name": "MLPModel", "hidden_dims": hidden, "activation": "elu",
                  "distribution_cfg": {"class_name": "GaussianDistribution", "init_std": std_schedule(args)(1.0),
                                       "learn_std": args.std == "learned"}},
        "critic": {"class_name": "MLPModel", "hidden_dims": hidden, "activation": "elu"},
    }


def std_schedule(args) -> StdSchedule:
    """The preset's action-std schedule (``ppo.std_start``/``std_end``/``std_hold``), by progress through its
    ``total_env_steps``; with ``--std learned`` only its start (the learned std's initial value) is used."""
    ppo = preset_config(args.preset).ppo
    return StdSchedule(ppo.std_start, ppo.std_end, ppo.std_hold)


def scheduled_std_setter(runner, args):
    """``set(env_steps)``: the actor's (fixed) std for the next rollout, from the env steps trained so far."""
    schedule, total = std_schedule(args), preset_config(args.preset).total_env_steps
    # All GPUs' steps, as the preset's trainer counts them (rsl_rl runs multi-GPU under torchrun by itself).
    scale = runner.alg.gpu_world_size / total
    std_param = runner.alg.actor.distribution.std_param

    def set_std(env_steps: int) -> None:
        std_param.data.fill_(schedule(1.0 - env_steps * scale))

    return set_std


class PerIterationLR:
    """The ``default`` preset's learning-rate rule on rsl_rl's PPO (``--lr_schedule per_iteration``): once per
    iteration, :func:`~tocabi_torchrl.rl.update_step.adapt_lr` (the trainer's rule) on the mean over the update's
    mini-batches of the KL to the rollout policy, each measured before its mini-batch's step, as rsl_rl measures it.
    rsl_rl's own per-mini-batch rule is kept from acting by handing it a zero KL, which it leaves alone. Under
    torchrun the mean is averaged over the GPUs (as rsl_rl averages its KL), so every GPU sets the same rate."""

    def __init__(self, alg):
        self.alg, self.kls = alg, []
        measure = alg.actor.get_kl_divergence

        def recorded(old, new):
            kl = measure(old, new)
            self.kls.append(kl.mean())  # a device tensor: read once per iteration, in step()
            return torch.zeros_like(kl)

        alg.actor.get_kl_divergence = recorded

    def step(self) -> None:
        kl = torch.stack(self.kls).mean() if self.kls else torch.zeros((), device=self.alg.device)
        self.kls.clear()
        if self.alg.is_multi_gpu:  # every rank calls step() after the same update: the collective lines up
            torch.distributed.all_reduce(kl, op=torch.distributed.ReduceOp.SUM)
            kl = kl / self.alg.gpu_world_size
        lr = self.alg.learning_rate = adapt_lr(self.alg.learning_rate, float(kl), self.alg.desired_kl)
        for group in self.alg.optimizer.param_groups:
            group["lr"] = lr


def make_actor(obs_dim: int, num_actions: int, cfg: dict):
    """rsl_rl's actor network (as its runner builds it) for the adapter's observation groups."""
    from rsl_rl.models import MLPModel
    from tensordict import TensorDict

    groups = TensorDict({"policy": torch.zeros(1, obs_dim), "critic": torch.zeros(1, obs_dim)}, batch_size=[1])
    actor_cfg = {k: v for k, v in cfg["actor"].items() if k != "class_name"}
    return MLPModel(groups, cfg["obs_groups"], "actor", num_actions, **actor_cfg)


def main(argv=None) -> dict:
    parser = build_parser()
    args = parser.parse_args(argv)
    check_args(parser, args, at_least={"steps_per_env": 1}, positive=("learning_rate",))
    if args.steps_per_env * args.num_envs < 2:  # one sample: the advantages' std is NaN, and so is every weight after
        parser.error(f"--steps_per_env {args.steps_per_env} x --num_envs {args.num_envs} must be at least 2 (rsl_rl's "
                     "PPO normalises the rollout's advantages)")
    # The adapter checks the installed rsl-rl-lib version before any of rsl_rl's own modules is imported.
    TocabiRslRlEnv = adapter("TocabiRslRlEnv")
    from rsl_rl.runners import OnPolicyRunner

    out = check_out_dir(args.out, args.resume)  # created once the env is built: a failed call leaves no folder
    prior = read_resume(out, torch_state=True) if args.resume else {}
    seed = call_seed(args.seed, int(prior.get("calls", 0)))
    torch.manual_seed(seed)  # a resumed call draws other exploration noise
    env = TocabiRslRlEnv(args.num_envs, args.device, preset=args.preset, seed=seed)
    open_out_dir(out, args.resume)
    cfg = train_cfg(args)
    settings = json.loads(json.dumps({"train_cfg": cfg, "lr_rule": args.lr_schedule, "num_envs": args.num_envs,
                                      "preset": args.preset, "init": INIT_SETTING}))
    if prior and prior["settings"] != settings:
        raise SystemExit(f"error: --resume of {out} with other settings than it started with: saved "
                         f"{prior['settings']}, given {settings}")
    calls = int(prior.get("calls", 0))
    # Each call logs to its own folder: rsl_rl's model_<it>.pt and event files of earlier calls stay as they were.
    log_dir = out / "rsl_rl" if calls == 0 else fresh_dir(out / f"rsl_rl_call{calls + 1}")
    runner = OnPolicyRunner(env, cfg, log_dir=str(log_dir), device=str(env.device))
    # The preset's own networks start so (spec §10.3), rsl_rl's would not: PyTorch's default init gives first action
    # means far from 0, and the first rollouts fall instead of replaying the reference (a resumed call loads weights).
    init_orthogonal(runner.alg.actor.mlp, ACTION_OUT_GAIN)
    init_orthogonal(runner.alg.critic.mlp, preset_config(args.preset).ppo.value_out_gain)
    done_before = int(prior.get("iterations", 0))
    if prior:
        # rsl_rl's own load: actor, critic, optimizer (with the adaptive learning rate in its param groups) and the
        # iteration counter, which we set to the number of completed updates so the next one gets a new index.
        # The bytes read_resume checked (tensors only), not the file again: rsl_rl's load unpickles what it reads.
        runner.load(io.BytesIO(prior["state_bytes"]), map_location=str(env.device))
        runner.current_learning_iteration = done_before
    updates = [0]
    update = runner.alg.update

    per_iteration = PerIterationLR(runner.alg) if args.lr_schedule == "per_iteration" else None
    set_std = scheduled_std_setter(runner, args) if args.std == "scheduled" else None

    def counted_update(*a, **k):
        result = update(*a, **k)
        updates[0] += 1
        if per_iteration is not None:
            per_iteration.step()
        if set_std is not None:  # the next rollout's noise, from the progress made (as the preset's trainer)
            set_std(env_steps())
        return result

    runner.alg.update = counted_update
    meta = {"preset": args.preset, "task": {"seed": args.seed}, "train_cfg": cfg, "num_envs": args.num_envs,
            "obs_dim": env.stepper.obs_dim, "num_actions": env.num_actions,
            "library_version": metadata.version("rsl-rl-lib")}
    env_steps_before = int(prior.get("env_steps", 0))

    def env_steps():
        return env_steps_before + env.stepper.env_steps

    def save(path):
        save_policy(path, "rsl_rl", runner.alg.get_policy().state_dict(),
                    {**meta, "env_steps": env_steps(), "train_seconds": clock.elapsed})

    clock = TrainingClock(out, save, args.max_minutes, args.checkpoint_minutes,
                          offset=float(prior.get("train_seconds", 0.0)), snapshots=prior.get("snapshots"))
    env.stepper.step_hooks.append(clock)
    left = args.iterations - done_before
    _, interrupted = run_call("rsl_rl", clock, out, lambda: runner.learn(left), left, f"{done_before} iterations")
    env.stepper.step_hooks.clear()
    seconds = clock.freeze()
    iterations = done_before + updates[0]
    meta.update(env_steps=env_steps(), train_seconds=seconds, env_steps_per_s=env_steps() / max(seconds, 1e-9),
                snapshots=clock.snapshots, iterations=iterations, calls=calls + 1,
                resume_notes=RESUME_NOTES,
                iterations_budget=args.iterations)  # the table tells a used budget by this, not the clock
    runner.current_learning_iteration = iterations
    saved = runner.alg.save()
    saved.update(iter=iterations, infos=None)
    buffer = io.BytesIO()
    torch.save(saved, buffer)  # rsl_rl's checkpoint format (what OnPolicyRunner.save writes), written atomically
    result = finish_call(out, args, meta, settings, buffer.getvalue(), save, evaluate, interrupted)
    env.close()
    print(f"rsl_rl: {meta['iterations']} PPO iterations in {seconds:.1f} s of training; gait test: "
          f"{eval_text(result)}")
    return result


#: The metadata fields :func:`load_actor` rebuilds the actor from: {name: (kind, what it holds)} (see
#: :func:`tocabi_torchrl.adapters.policy_file.require_meta`).
POLICY_FIELDS = {"obs_dim": ("count", "the observation size, e.g. 237"),
                 "num_actions": ("count", "the action size, e.g. 13"),
                 "train_cfg": ("object", "the rsl_rl runner configuration the policy trained with")}
#: The keys of ``train_cfg`` that :func:`make_actor` reads.
TRAIN_CFG_FIELDS = {"actor": ("object", "the actor's settings, e.g. {'hidden_dims': [400, 200, 100], ...}"),
                    "obs_groups": ("object", "the observation groups, e.g. {'actor': ['policy'], ...}")}


def load_actor(policy: str):
    """``(meta, act)`` for a ``policy.pt`` this recipe wrote: rsl_rl's actor rebuilt from the metadata, and ``act``
    its deterministic output (the Gaussian mean) for (num_envs, 237) observations on any device."""
    from tensordict import TensorDict

    from tocabi_torchrl.adapters._versions import require

    require("rsl_rl")
    meta, state = load_policy(policy, "rsl_rl")
    require_meta(meta, POLICY_FIELDS, policy, "load_actor needs to rebuild the network")
    require_meta(meta["train_cfg"], TRAIN_CFG_FIELDS, policy, "make_actor needs to rebuild the network",
                 within="train_cfg")
    actor = load_network(policy, meta, tuple(POLICY_FIELDS),
                         lambda: make_actor(meta["obs_dim"], meta["num_actions"], meta["train_cfg"]), state)
    actor.eval()

    def act(obs):  # the env clips the mean to the action bounds
        groups = TensorDict({"policy": obs, "critic": obs}, batch_size=obs.shape[:1])
        return actor.to(obs.device)(groups)

    return meta, act


#: ``evaluate(policy, out_dir, **options)``: the gait test (``test="standard"`` or ``"robust"``) of a ``policy.pt``
#: this recipe wrote.
evaluate = functools.partial(evaluate_policy_file, load_actor)


if __name__ == "__main__":
    sys.exit(exit_status(main(sys.argv[1:])))
