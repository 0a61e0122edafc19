"""PPO training configuration: one typed dataclass, named presets, and command-line overrides generated from it."""

from __future__ import annotations

import argparse
import dataclasses
from dataclasses import dataclass
from typing import Any

__all__ = ["PPOConfig", "PRESETS", "preset_config", "parse_args", "LR_SCHEDULES", "STD_MODES", "ENV_GRAPH_MODES",
           "ENV_GRAPH_AUTO_MAX_ENVS", "uses_env_graph"]

LR_SCHEDULES = ("fixed", "linear", "adaptive")
ENV_GRAPH_MODES = ("auto", "on", "off")
_GRAPH_ALIASES = {"true": "on", "yes": "on", "1": "on", "false": "off", "no": "off", "0": "off"}
#: Largest env count for which ``cuda_graph="auto"`` captures the env step (see ``PPOConfig.cuda_graph``): the
#: graph won at 96 envs and lost at 256 on an H100 (128 only in short memory-sweep runs, see env_graph.md).
ENV_GRAPH_AUTO_MAX_ENVS = 128
STD_MODES = ("scheduled", "learned")
LOGGERS = ("csv", "tensorboard", "wandb")


@dataclass
class PPOConfig:
    """Everything a PPO run needs. Units: steps are policy steps (4 ms each); times are wall-clock seconds.

    The ``default`` preset is tuned for thousands of envs on one GPU: residual imitation (``pd_reference``: leg
    servos with the robot's gains track the reference walk plus the policy's correction), the velocity-tracking
    reward tripled (0.3 -> 0.9, so that following a 0.5 m/s command pays more than replaying the 0.13 m/s walk),
    48-step rollouts with gamma 0.995 (a 0.8 s horizon at 250 Hz), large mini-batches, a KL-adaptive learning rate
    and a scheduled std from 0.2 to 0.05. Chosen from three 7.5-minute H100 runs (docs/training/README.md);
    ``reference`` reproduces the reference training
    (spec §10: 8 envs × 2048 steps, mini-batch 128, 3 epochs, 256-256 ReLU, LR 1e-5 → 2e-7 linear, value head at
    5e-4, std 0.1 → 0.05, 120 M steps).
    """

    preset: str = "default"
    name: str = "ppo_walk"
    run_dir: str = "runs"
    seed: int = 0
    device: str = "auto"
    # environment
    num_envs: int = 4096
    control_mode: str = "pd_reference"
    command_preset: str = "tocabilab"
    transform_preset: str = "reference"
    max_episode_steps: int = 8000
    #: PD gains of the "pd"/"pd_reference" leg servos: "tocabilab" (robot Kp/9, Kv/3) or "robot" (full Kp, Kv).
    pd_gains: str = "robot"
    #: Residual range [rad] of the PD modes: target = center + pd_action_scale × action.
    pd_action_scale: float = 0.5
    #: Torque mode training aid (0 = off): the leg actions morph from position residuals tracked by a PD
    #: (``pd_gains``, ``pd_action_scale``) at β = 1 to torques at β = 0 (``TocabiWalkConfig.torque_assist``). β starts
    #: at this value, holds until ``assist_fade_start`` env steps and falls to 0 at ``assist_fade_end`` (geometrically
    #: in the action gain, with the adaptive learning rate held, see rl/assist.AssistSchedule);
    #: during the fade a loss term (weight ``assist_absorb``) moves each step of the morph into the actor
    #: (rl/assist.py), so the run ends as a pure torque policy. Evaluations never use the assist.
    torque_assist: float = 0.0
    assist_fade_start: int = 0
    assist_fade_end: int = 0
    assist_absorb: float = 1.0
    #: What the absorbing loss copies (rl/assist.py): "teacher", the torque of a frozen copy of the actor taken as
    #: the fade starts, in the fading policy's own states (DAgger); or "rollout", the torque the rollout's own mean
    #: applied (only the fade's step). With "teacher" the pull holds to ``assist_fade_end`` and then falls linearly
    #: to 0 over ``assist_anchor_decay`` env steps.
    assist_target: str = "teacher"
    assist_anchor_decay: int = 0
    #: Reward re-weighting, "term=weight" entries (e.g. body_vel=0.9); empty = the reference weights.
    reward_weights: tuple[str, ...] = ("body_vel=0.9",)
    #: On a GPU, capture the training env's whole step (physics, signals, transforms, masked reset) as one CUDA
    #: graph: "on", "off", or "auto" = on up to ENV_GRAPH_AUTO_MAX_ENVS envs. Small counts are launch-bound, and the
    #: graph trained 1.5-1.8x faster at 8-96 envs on an H100 (short runs); from 256 envs up it was 3-6 % slower
    #: (docs/benchmarks/env_graph.md). Both compute the same step (tests compare them).
    cuda_graph: str = "auto"
    #: Keep every env signal (joint_pos, base_pos, ...) in the training rollout; off: only what PPO and the logs
    #: read (observation, reward, done flags, reward terms, episode counters), ~40 % less rollout memory.
    store_env_signals: bool = False
    # rollout and budget
    steps_per_env: int = 48
    total_env_steps: int = 300_000_000
    max_minutes: float = 0.0  # 0 = no wall-clock limit
    # PPO update
    epochs: int = 5
    minibatch_size: int = 49152
    gamma: float = 0.995
    gae_lambda: float = 0.95
    clip_epsilon: float = 0.2
    entropy_coef: float = 0.0
    value_coef: float = 1.0
    value_loss: str = "l2"
    max_grad_norm: float = 1.0
    #: On a GPU, capture each PPO mini-batch step (loss, backward, clipping, fused Adam) as one CUDA graph after 3
    #: eager steps: the same kernels in one launch instead of ~300 launched from Python (falls back to eager, with a
    #: warning, if the capture fails, e.g. with entropy_coef > 0, whose TorchRL entropy check reads the host).
    update_graph: bool = True
    # learning rate
    lr: float = 1e-3
    lr_end: float = 1e-5
    lr_schedule: str = "adaptive"
    desired_kl: float = 0.01
    value_head_lr: float = 0.0  # > 0: the value head gets its own constant LR (the reference's second optimizer)
    adam_eps: float = 1e-8
    # networks and exploration
    actor_hidden: tuple[int, ...] = (400, 200, 100)
    critic_hidden: tuple[int, ...] = (400, 200, 100)
    activation: str = "elu"
    value_out_gain: float = 1.0
    std_mode: str = "scheduled"
    std_start: float = 0.2
    std_end: float = 0.05
    std_hold: float = 0.5
    # logging, checkpoints, evaluation
    log_every: int = 1
    checkpoint_every: int = 100
    #: Checkpoint retention: keep the newest ``checkpoint_keep_last`` iteration files (0 = keep all) and every file
    #: whose iteration is a multiple of ``checkpoint_keep_every`` (0 = none more); ``latest.pt`` is always kept.
    checkpoint_keep_last: int = 3
    checkpoint_keep_every: int = 50
    #: Also save ``checkpoints/wall_XXXXXs.pt`` whenever the training wall-clock (summed over resumed segments)
    #: passes a multiple of this many minutes (0 = off); ``benchmarks/time_to_walk.py`` evaluates these.
    checkpoint_minutes: float = 0.0
    loggers: tuple[str, ...] = ("csv",)
    resume: str = ""
    eval_at_end: bool = True
    eval_envs: int = 256
    eval_seconds: float = 8.0
    progress_bar: bool = True

    def __post_init__(self) -> None:
        # Configs and checkpoints written before "auto" existed hold a bool here, and the command line used to take
        # true/false/yes/no/1/0: all of them still read as on/off; any case is accepted.
        value = self.cuda_graph
        if isinstance(value, (bool, int, str)):
            text = str(value).strip().lower()
            self.cuda_graph = _GRAPH_ALIASES.get(text, text)

    def validate(self) -> None:
        """Raise ``ValueError`` naming the first bad field and the accepted values."""
        positive = ("num_envs", "steps_per_env", "total_env_steps", "epochs", "minibatch_size", "max_episode_steps",
                    "log_every", "checkpoint_every", "eval_envs")
        for name in positive:
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"PPOConfig.{name} must be a positive int, got {value!r}")
        for name, low, high in (("gamma", 0.0, 1.0), ("gae_lambda", 0.0, 1.0), ("clip_epsilon", 0.0, 1.0)):
            value = getattr(self, name)
            if not low < value <= high:
                raise ValueError(f"PPOConfig.{name} must be in ({low}, {high}], got {value!r}")
        for name in ("lr", "std_start", "std_end", "desired_kl", "max_grad_norm", "adam_eps"):
            if not getattr(self, name) > 0:
                raise ValueError(f"PPOConfig.{name} must be > 0, got {getattr(self, name)!r}")
        if not self.eval_seconds > 0:
            raise ValueError(f"PPOConfig.eval_seconds must be > 0, got {self.eval_seconds!r}")
        self.reward_weight_map()  # raises on a malformed entry
        if not self.pd_action_scale > 0:
            raise ValueError(f"PPOConfig.pd_action_scale must be > 0, got {self.pd_action_scale!r}")
        for name in ("checkpoint_keep_last", "checkpoint_keep_every", "assist_anchor_decay"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 0:
                raise ValueError(f"PPOConfig.{name} must be an int >= 0, got {value!r}")
        if not 0 <= self.torque_assist <= 1 or self.assist_absorb < 0:
            raise ValueError(f"PPOConfig.torque_assist must be in [0, 1] and assist_absorb >= 0, got "
                             f"{self.torque_assist!r}, {self.assist_absorb!r}")
        if self.torque_assist > 0:
            if self.control_mode != "torque":
                raise ValueError(f"PPOConfig.torque_assist > 0 needs control_mode='torque', got "
                                 f"{self.control_mode!r} (set torque_assist=0 for the PD modes)")
            if not 0 <= self.assist_fade_start < self.assist_fade_end:
                raise ValueError(f"PPOConfig.torque_assist > 0 needs 0 <= assist_fade_start < assist_fade_end (env "
                                 f"steps), got {self.assist_fade_start}, {self.assist_fade_end}")
        for name in ("entropy_coef", "value_coef", "value_head_lr", "lr_end", "max_minutes", "checkpoint_minutes"):
            if not getattr(self, name) >= 0:
                raise ValueError(f"PPOConfig.{name} must be >= 0, got {getattr(self, name)!r}")
        for name, allowed in field_choices().items():
            if getattr(self, name) not in allowed:
                raise ValueError(f"PPOConfig.{name} must be one of {allowed}, got {getattr(self, name)!r}")
        bad = set(self.loggers) - set(LOGGERS)
        if bad:
            raise ValueError(f"unknown logger(s) {sorted(bad)}; choose from {', '.join(LOGGERS)}")
        if self.minibatch_size > self.num_envs * self.steps_per_env:
            raise ValueError(
                f"minibatch_size {self.minibatch_size} exceeds the rollout ({self.num_envs} envs × "
                f"{self.steps_per_env} steps = {self.num_envs * self.steps_per_env}); lower it or collect more"
            )

    def reward_weight_map(self) -> dict[str, float]:
        """``reward_weights`` as ``{term: weight}``; raises ``ValueError`` naming a malformed or unknown entry."""
        from ..transforms.reward_terms import REFERENCE_TERMS

        weights = {}
        for entry in self.reward_weights:
            name, sep, value = entry.partition("=")
            try:
                weight = float(value)
            except ValueError:
                weight = None
            if not sep or weight is None:
                raise ValueError(f"PPOConfig.reward_weights entry {entry!r} must look like 'body_vel=0.9'")
            if name not in REFERENCE_TERMS:
                raise ValueError(f"PPOConfig.reward_weights: unknown term {name!r}; known: {list(REFERENCE_TERMS)}")
            weights[name] = weight
        return weights

    @property
    def frames_per_batch(self) -> int:
        return self.num_envs * self.steps_per_env

    @property
    def iterations(self) -> int:
        return max(1, -(-self.total_env_steps // self.frames_per_batch))

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


PRESETS: dict[str, dict[str, Any]] = {
    "default": {},
    "reference": dict(
        control_mode="torque", reward_weights=(), gamma=0.99,
        num_envs=8, steps_per_env=2048, minibatch_size=128, epochs=3, total_env_steps=120_000_000,
        command_preset="reference", lr=1e-5, lr_end=2e-7, lr_schedule="linear", value_head_lr=5e-4,
        adam_eps=1e-5, actor_hidden=(256, 256), critic_hidden=(256, 256), activation="relu", value_out_gain=0.01,
        value_coef=0.5, value_loss="l2", max_grad_norm=0.5, std_start=0.1, std_end=0.05, std_hold=0.5,
    ),
    # The reference's action space (12 normalised leg torques + phase rate) learned from scratch on one GPU: the
    # default's PPO on an assisted torque env whose leg actions start as the residual-PD preset's position residuals
    # (β = 1 for 50 M steps) and morph into torques by 110 M (geometric in the action gain, learning rate held), a
    # loss moving each step of the morph into the actor (rl/assist.py); the rest trains the pure torque policy.
    # Without the assist, PPO at thousands of envs learned to stand (issue 19); docs/training/torque.md has the runs.
    # The pull copies a frozen β = 1 teacher (DAgger) and fades out over 30 M steps after the fade. Run 5 of
    # docs/training/torque.md: walks at 24.0 min of training on an H100 (178.7 M steps). A teacher taken at 75 M
    # (run 6) went faster (3.3-3.4 m in the 8 s test) but drifted 0.30-0.34 m, just past the limit, to its end.
    "torque": dict(control_mode="torque", torque_assist=1.0, assist_fade_start=50_000_000,
                   assist_fade_end=110_000_000, assist_target="teacher", assist_anchor_decay=30_000_000,
                   total_env_steps=200_000_000),
    # What a CPU-only machine can run in a minute or two: proves the whole pipeline, learns nothing useful.
    "cpu_smoke": dict(num_envs=8, steps_per_env=16, minibatch_size=64, epochs=2, total_env_steps=8 * 16 * 3,
                      checkpoint_every=1, eval_envs=2, eval_seconds=1.0, actor_hidden=(64, 64),
                      critic_hidden=(64, 64)),
}


def field_choices() -> dict[str, tuple[str, ...]]:
    """The allowed values of each PPOConfig field that takes one of a few names (checked by ``validate``, listed
    by ``--help``)."""
    from ..envs.config import CONTROL_MODES
    from ..transforms.presets import PRESETS as TRANSFORM_PRESETS
    from .assist import ASSIST_TARGETS

    return {"lr_schedule": LR_SCHEDULES, "std_mode": STD_MODES, "control_mode": CONTROL_MODES,
            "value_loss": ("l2", "smooth_l1", "l1"), "command_preset": ("tocabilab", "reference"),
            "transform_preset": tuple(TRANSFORM_PRESETS), "activation": ("relu", "elu", "tanh", "silu"),
            "pd_gains": ("tocabilab", "robot"), "cuda_graph": ENV_GRAPH_MODES,
            "assist_target": ASSIST_TARGETS}


def uses_env_graph(cfg: PPOConfig, device: Any, num_envs: int | None = None) -> bool:
    """Whether the trainer captures the env step of ``num_envs`` envs (default ``cfg.num_envs``) on ``device`` (a
    ``torch.device``) as a CUDA graph: ``cfg.cuda_graph`` "on", or "auto" with at most ``ENV_GRAPH_AUTO_MAX_ENVS``
    envs; never off the GPU."""
    if device.type != "cuda" or cfg.cuda_graph == "off":
        return False
    return cfg.cuda_graph == "on" or (num_envs or cfg.num_envs) <= ENV_GRAPH_AUTO_MAX_ENVS


def preset_config(name: str, /, **overrides) -> PPOConfig:
    """The named preset with ``overrides`` applied (a ``preset`` key in ``overrides`` is ignored)."""
    overrides.pop("preset", None)
    if name not in PRESETS:
        raise ValueError(f"unknown preset {name!r}; choose one of {sorted(PRESETS)}")
    unknown = set(overrides) - {f.name for f in dataclasses.fields(PPOConfig)}
    if unknown:
        raise ValueError(f"unknown PPOConfig field(s) {sorted(unknown)}")
    cfg = PPOConfig(**{**PRESETS[name], **overrides, "preset": name})
    cfg.validate()
    return cfg


def _parse_value(kind: Any, text: str):
    if kind is bool or kind == "bool":
        if text.lower() in ("1", "true", "yes", "on"):
            return True
        if text.lower() in ("0", "false", "no", "off"):
            return False
        raise argparse.ArgumentTypeError(f"expected true/false, got {text!r}")
    return text


def build_parser(description: str = "") -> argparse.ArgumentParser:
    """The command line of :func:`parse_args`: ``--preset`` plus one option per PPOConfig field, each with its
    one-line description (``rl.options.FIELD_HELP``), allowed values and default. Every default is None in the
    namespace, so the options given explicitly are the ones that are not None."""
    from .options import field_help

    parser = argparse.ArgumentParser(
        description=description,
        epilog="Defaults are the 'default' preset's; another --preset changes some of them. With --resume the saved "
               "run's options apply and only budget, logging, checkpoint, eval and device options may change.")
    defaults = PPOConfig()
    choices = field_choices()
    for f in dataclasses.fields(PPOConfig):
        default = getattr(defaults, f.name)
        kind = type(default)
        text = field_help(f.name)
        if f.name == "preset":
            parser.add_argument("--preset", default=None, choices=sorted(PRESETS),
                                help=f"{text}; one of: {', '.join(sorted(PRESETS))} (default: {default})")
        elif kind is tuple:
            elem = type(default[0]) if default else str
            allowed = f"any of {', '.join(LOGGERS)}, " if f.name == "loggers" else ""
            shown = ",".join(map(str, default)) or "none"
            parser.add_argument(f"--{f.name}", type=lambda s, e=elem: tuple(e(x) for x in s.split(",") if x),
                                default=None, metavar="A,B,...",
                                help=f"{text}; {allowed}comma-separated (default: {shown})")
        elif kind is bool:
            parser.add_argument(f"--{f.name}", type=lambda s: _parse_value(bool, s), default=None, metavar="BOOL",
                                help=f"{text}; true/false (default: {str(default).lower()})")
        elif f.name in choices:
            parser.add_argument(f"--{f.name}", type=kind, default=None, metavar="NAME",
                                help=f"{text}; one of: {', '.join(choices[f.name])} (default: {default})")
        else:
            shown = "none" if default == "" else default
            parser.add_argument(f"--{f.name}", type=kind, default=None, metavar=kind.__name__.upper(),
                                help=f"{text} (default: {shown})")
    return parser


def parse_args(argv: list[str] | None = None, description: str = "") -> tuple[PPOConfig, argparse.Namespace]:
    """Build a :class:`PPOConfig` from ``--preset`` plus ``--field value`` overrides (every field is an option).

    With ``--resume`` the config starts from the one saved in that run's checkpoint instead, and the explicit
    options may only change the fields ``rl.options.RESUME_SAFE`` lists (``rl.resume.resume_config`` raises
    ``ValueError`` naming any other). In the namespace, options not given are None. ``recipes/ppo_walk.py`` uses
    ``rl.launch.launch_config``, which also decides what runs on a machine without CUDA.
    """
    args = build_parser(description).parse_args(argv)
    overrides = {k: v for k, v in vars(args).items() if v is not None}
    if args.resume:
        from .resume import resume_config

        return resume_config(args.resume, overrides), args
    return preset_config(args.preset or "default", **overrides), args
