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
only your own), the policy as <out>/policy.pt (tensors only) and the gait test under <out>/eval/ (``--eval_test
robust``: the robust gait test, robust.json and robust.png, docs/evaluation.md).

``--resume`` continues the run in ``--out`` from the training state its previous call saved in <out>/resume/:
the policy's weights (the scheduled std included), the Adam state of both parameter groups, ``num_timesteps`` and
``_n_updates``, as tensors and plain values (``torch.save``, read back with ``torch.load(weights_only=True)``, so
loading it runs no code). The model is built anew, as by a first call, and that state loaded into it; SB3's zip is
never read on a resume, and a run folder whose state file is one (written by an earlier version of this recipe) is
refused. ``--max_minutes`` caps the total training time over all calls; ``--iterations`` must stay the same, as it
sets where the LR and std schedules are:

    python recipes/train_sb3.py --out runs/s --max_minutes 9 --eval_envs 0
    python recipes/train_sb3.py --out runs/s --max_minutes 18 --eval_envs 0 --resume     # 9 more minutes
"""

from __future__ import annotations

import argparse
import functools
import io
import math
import sys
import zipfile
from importlib import metadata
from pathlib import Path

from tocabi_torchrl.cli import base_parser, hidden_sizes
from tocabi_torchrl.config import PRESETS  # torch-free: --help answers before torch loads


def build_parser() -> argparse.ArgumentParser:
    """The command line: the options every library recipe takes and Stable-Baselines3's own."""
    parser = base_parser(__doc__.split("\n\n")[0], num_envs=8, iterations=7325, presets=PRESETS)
    parser.add_argument("--n_steps", type=int, default=2048, help="rollout length per env (default: 2048)")
    parser.add_argument("--batch_size", type=int, default=128, help="mini-batch size (default: 128)")
    parser.add_argument("--epochs", type=int, default=3, help="passes over each rollout (default: 3)")
    parser.add_argument("--hidden", type=hidden_sizes, default=(256, 256),
                        help="hidden layer sizes of actor and critic, comma-separated (default: 256,256)")
    return parser


if __name__ == "__main__":  # --help or a misspelt option answers before torch and Stable-Baselines3 load
    build_parser().parse_args(sys.argv[1:])

import torch  # noqa: E402

from tocabi_torchrl.adapters.evaluate import evaluate_policy_file  # noqa: E402
from tocabi_torchrl.atomic import atomic_write_bytes  # noqa: E402
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
    keep_previous,
    open_out_dir,
    read_resume,
    run_call,
)
from tocabi_torchrl.rl.std_schedule import StdSchedule  # noqa: E402

#: Reference learning rates (spec §10.2): the policy's schedule ends and the value head's constant rate.
LR_START, LR_END, VALUE_HEAD_LR = 1e-5, 2e-7, 5e-4
STD = StdSchedule(start=0.1, end=0.05, hold=0.5)
#: What a resumed call does not carry over (also in the per-library table's notes).
RESUME_NOTES = ("resumes the policy (with the scheduled std), Adam state of both parameter groups, num_timesteps and "
                "_n_updates, saved as tensors (never SB3's zip, which unpickles) and loaded into a model built anew, "
                "so the LR and std schedules continue where the last completed update left them; not SB3's episode "
                "statistics (logging only), the env state (every call starts from a reset), the random-number state "
                "(reseeded with seed + call index) or the rollout in progress when a call's time is up (discarded; "
                "its steps and seconds count)")
#: Marks a resume state file as this recipe's (``resume/state_call<k>.pt``), so nothing else is taken for one.
STATE_FORMAT = "tocabi_torchrl.train_sb3.resume/1"


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


def training_state(model) -> bytes:
    """The resume state of ``model`` as ``torch.save`` bytes: what SB3's own load would restore and the schedules need
    (policy weights with the scheduled std, the Adam state of both parameter groups, ``num_timesteps``, from which
    ``learn(reset_num_timesteps=False)`` places the LR and std schedules, and ``_n_updates``), tensors and plain
    values only, so that reading it back needs no unpickling of objects."""
    buffer = io.BytesIO()
    torch.save({"format": STATE_FORMAT, "policy": model.policy.state_dict(),
                "optimizer": model.policy.optimizer.state_dict(), "num_timesteps": int(model.num_timesteps),
                "n_updates": int(model._n_updates)}, buffer)
    return buffer.getvalue()


def _is_sb3_zip(data: bytes) -> bool:
    # Only the archive's names are read: SB3's zip holds its pickled objects in "data", torch's own zip in data.pkl.
    try:
        with zipfile.ZipFile(io.BytesIO(data)) as archive:
            names = set(archive.namelist())
    except (zipfile.BadZipFile, OSError):
        return False
    return "_stable_baselines3_version" in names or {"data", "policy.pth"} <= names


def read_training_state(path: Path, data: bytes) -> dict:
    """The resume state :func:`training_state` wrote to ``path``, given as its bytes ``data`` (those ``read_resume``
    checked, not the file read again), read with ``torch.load(weights_only=True)``: tensors and plain values only,
    so nothing in the file can run code. Anything else ends the call with a one-line ``SystemExit``, before the env
    is built: an SB3 zip (the state file of this recipe's earlier versions, which only SB3's unpickling loader
    reads), a file that does not load as tensors, or one lacking a field."""
    fix = "start a new --out (this run cannot be resumed)"
    if _is_sb3_zip(data):
        raise SystemExit(f"error: {path} is a Stable-Baselines3 zip, the resume state of an older train_sb3.py; "
                         f"--resume reads tensors only and never unpickles SB3's saved objects: {fix}")
    try:
        state = torch.load(io.BytesIO(data), map_location="cpu", weights_only=True)
    except Exception as err:  # any refusal means the file is not what this recipe wrote
        first = (str(err).strip().splitlines() or [""])[0]
        raise SystemExit(f"error: {path} does not load as tensors only ({type(err).__name__}: {first}); a resume "
                         f"never unpickles other objects: {fix}") from None
    if not isinstance(state, dict) or state.get("format") != STATE_FORMAT:
        raise SystemExit(f"error: {path} is not a resume state of train_sb3.py (no format {STATE_FORMAT!r}): {fix}")
    for name, kind in (("policy", dict), ("optimizer", dict), ("num_timesteps", int), ("n_updates", int)):
        value = state.get(name)
        if not isinstance(value, kind) or isinstance(value, bool) or (kind is int and value < 0):
            raise SystemExit(f"error: {path} has {name}={type(value).__name__}, which must be "
                             f"{'a state dict' if kind is dict else 'an int >= 0'}: {fix}")
    return state


def load_training_state(model, state: dict, path: Path) -> None:
    """Load ``state`` (:func:`read_training_state`) into ``model``, built as by a first call: the later
    ``learn(total_timesteps=left, reset_num_timesteps=False)`` sets ``_total_timesteps = left + num_timesteps``, the
    first call's total, so the schedules' progress continues where the saved update left it."""
    try:
        model.policy.load_state_dict(state["policy"])
        model.policy.optimizer.load_state_dict(state["optimizer"])
    except (RuntimeError, ValueError, KeyError) as err:
        first = (str(err).strip().splitlines() or [""])[0]
        raise SystemExit(f"error: {path} does not fit the model these settings build ({type(err).__name__}: "
                         f"{first}); start a new --out") from None
    model.num_timesteps, model._n_updates = state["num_timesteps"], state["n_updates"]


def policy_kwargs(hidden: tuple[int, ...]) -> dict:
    return {"net_arch": {"pi": list(hidden), "vf": list(hidden)}, "activation_fn": torch.nn.ReLU,
            "log_std_init": math.log(STD(1.0)), "ortho_init": True}


def main(argv=None) -> dict:
    parser = build_parser()
    args = parser.parse_args(argv)
    # SB3's PPO normalises the advantages of each mini-batch and of the rollout: both need at least 2 samples.
    check_args(parser, args, at_least={"n_steps": 1, "batch_size": 2, "epochs": 1})
    if args.n_steps * args.num_envs < 2:
        parser.error(f"--n_steps {args.n_steps} x --num_envs {args.num_envs} must be at least 2 (SB3's PPO "
                     "normalises the rollout's advantages)")
    TocabiSB3VecEnv = adapter("TocabiSB3VecEnv")  # checks the stable-baselines3 version

    out = check_out_dir(args.out, args.resume)  # created once the env is built: a failed call leaves no folder
    prior = read_resume(out, keep_bytes=True) if args.resume else {}
    # The bytes read_resume checked (intact zip), not the file again: one replaced in between is never loaded.
    state = read_training_state(out / prior["state"], prior["state_bytes"]) if prior else None
    calls = int(prior.get("calls", 0))
    settings = {"num_envs": args.num_envs, "preset": args.preset, "hidden": list(args.hidden), "n_steps": args.n_steps,
                "batch_size": args.batch_size, "epochs": args.epochs, "iterations": args.iterations, "seed": args.seed}
    if prior and prior["settings"] != settings:
        raise SystemExit(f"error: --resume of {out} with other settings than it started with: saved "
                         f"{prior['settings']}, given {settings} (--iterations too: it sets the LR and std schedules)")
    env = TocabiSB3VecEnv(args.num_envs, args.device, preset=args.preset, seed=call_seed(args.seed, calls))
    open_out_dir(out, args.resume)
    total = args.iterations * args.n_steps * args.num_envs
    # The same model as a first call's, seeded for this call (a resumed call draws other noise); a resume then
    # loads its saved tensors into it, never SB3's zip, whose load unpickles.
    model = reference_ppo_class()(
        "MlpPolicy", env, learning_rate=LinearLR(LR_START, LR_END), n_steps=args.n_steps,
        batch_size=args.batch_size, n_epochs=args.epochs, gamma=0.99, gae_lambda=0.95, clip_range=0.2,
        ent_coef=0.0, vf_coef=0.5, max_grad_norm=0.5, policy_kwargs=policy_kwargs(args.hidden),
        seed=call_seed(args.seed, calls), device=str(env.device), verbose=1)
    if state is not None:
        load_training_state(model, state, out / prior["state"])
    meta = {"preset": args.preset, "task": {"seed": args.seed}, "hidden": list(args.hidden),
            "num_envs": args.num_envs, "library_version": metadata.version("stable-baselines3"),
            "obs_dim": env.observation_space.shape[0], "action_low": env.action_space.low.tolist(),
            "action_high": env.action_space.high.tolist(),
            "host_copies_per_step": "observation (num_envs, 237), reward, done flags to the host; actions back"}
    env_steps_before = int(prior.get("env_steps", 0))

    def env_steps():
        return env_steps_before + env.stepper.env_steps

    def save(path):
        save_policy(path, "sb3", model.policy.state_dict(),
                    {**meta, "env_steps": env_steps(), "train_seconds": clock.elapsed})

    clock = TrainingClock(out, save, args.max_minutes, args.checkpoint_minutes,
                          offset=float(prior.get("train_seconds", 0.0)), snapshots=prior.get("snapshots"))
    env.stepper.step_hooks.append(clock)
    left = total - int(model.num_timesteps)
    stopped, interrupted = run_call("sb3", clock, out,
                                    lambda: model.learn(total_timesteps=left, reset_num_timesteps=not prior), left,
                                    f"{model.num_timesteps} timesteps")
    if stopped:
        # The rollout in progress is discarded: SB3 counted its steps in num_timesteps, which sets the schedules'
        # position; take them back so that the next call's schedules continue from the last update.
        model.num_timesteps = int(model._n_updates // args.epochs) * args.n_steps * args.num_envs
    env.stepper.step_hooks.clear()
    seconds = clock.freeze()
    meta.update(env_steps=env_steps(), train_seconds=seconds, env_steps_per_s=env_steps() / max(seconds, 1e-9),
                snapshots=clock.snapshots, iterations=int(model._n_updates // args.epochs), calls=calls + 1,
                sb3_num_timesteps=int(model.num_timesteps), resume_notes=RESUME_NOTES,
                iterations_budget=args.iterations)  # the table tells a used budget by this, not the clock

    def save_sb3_zip(tag: str) -> None:  # SB3's own zip, for SB3's tools only: a resume never reads it
        buffer = io.BytesIO()
        model.save(buffer)
        # Atomic, as the call's other files: a call killed (or a disk full) mid-write leaves no zip cut short.
        atomic_write_bytes(keep_previous(out / "sb3_model.zip", tag), buffer.getvalue())

    result = finish_call(out, args, meta, settings, training_state(model), save, evaluate, interrupted,
                         also_save=save_sb3_zip)
    env.close()
    print(f"sb3: {meta['env_steps']} env steps in {meta['train_seconds']:.1f} s; gait test: "
          f"{eval_text(result)}")
    return result


#: The metadata fields :func:`load_actor` rebuilds the network from: {name: (kind, what it holds)} (see
#: :func:`tocabi_torchrl.adapters.policy_file.require_meta`).
POLICY_FIELDS = {"obs_dim": ("count", "the observation size, e.g. 237"),
                 "action_low": ("numbers", "the action space's lower bounds, one per action"),
                 "action_high": ("numbers", "the action space's upper bounds, one per action"),
                 "hidden": ("sizes", "the hidden layer widths, e.g. [256, 256]")}


def load_actor(policy: str):
    """``(meta, act)`` for a ``policy.pt`` this recipe wrote: SB3's policy network rebuilt from the metadata, and
    ``act`` its Gaussian mean (SB3's deterministic action) for (num_envs, 237) observations on any device."""
    from gymnasium import spaces

    from tocabi_torchrl.adapters._versions import require

    require("stable_baselines3")
    from stable_baselines3.common.policies import ActorCriticPolicy

    meta, state = load_policy(policy, "sb3")
    require_meta(meta, POLICY_FIELDS, policy, "load_actor needs to rebuild the network")
    obs_space = spaces.Box(-float("inf"), float("inf"), (meta["obs_dim"],))
    act_space = spaces.Box(*(bound.numpy() for bound in action_bounds(meta, policy)))
    net = load_network(policy, meta, tuple(POLICY_FIELDS), lambda: ActorCriticPolicy(
        obs_space, act_space, lr_schedule=LinearLR(0.0, 0.0), **policy_kwargs(tuple(meta["hidden"]))), state)
    net.eval()

    def act(obs):  # the env clips the mean to the action bounds, as SB3's predict() would
        return net.to(obs.device)._predict(obs, deterministic=True)

    return meta, act


#: ``evaluate(policy, out_dir, **options)``: the gait test (``test="standard"`` or ``"robust"``) of a ``policy.pt``
#: this recipe wrote.
evaluate = functools.partial(evaluate_policy_file, load_actor)


if __name__ == "__main__":
    sys.exit(exit_status(main(sys.argv[1:])))
