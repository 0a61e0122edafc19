"""The run config tree: one nested dataclass from which a training run, its env and its command line are built.

::

    RunConfig                      name, run_dir, seed, device, resume, budget, logging, checkpoints, evaluation
    ├── env: TocabiWalkConfig      num_envs
    │   ├── sim: EnvSimConfig      backend, substeps, contact buffers, threads
    │   ├── task: TaskConfig       episode length (the one truncation clock), motion, terminations
    │   ├── command: CommandConfig velocity-command schedule
    │   ├── control: ControlConfig control mode, PD gains and residual range, actuator layer
    │   ├── scene: SceneConfig     obstacles
    │   ├── pushes: PushConfig     kicks during the episode
    │   └── dynamics: DynamicsRandomization   per-world masses, damping, armature, friction
    ├── transforms: TransformSettings   history layout, reward weights, normalisation, sensor noise
    ├── ppo: PPOConfig             rollout, PPO update, learning rate, networks, action std, torque assist, graphs
    └── viewer: ViewerConfig       the live viewer of a training run

Every value has one home (its dotted path, e.g. ``ppo.lr``, ``env.control.mode``) and one default; the defaults
are the ``default`` preset, which is also what ``TocabiWalk()`` and ``make_env()`` build. Named presets
(:data:`PRESETS`) change a few paths. The tree is saved with every checkpoint (:func:`to_dict`) and read back by
:func:`config_from_dict`. The command line of ``recipes/ppo_walk.py`` is generated from the tree by tyro
(:mod:`tocabi_torchrl.rl.config`): each field's docstring is its ``--help`` line.
"""

from __future__ import annotations

import difflib
import math
import numbers
import warnings
from collections.abc import Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any

from .cli import GAIT_TESTS, listed_spelling
from .envs.command_config import CommandConfig
from .envs.config import CONTROL_MODES, MB_RESIDUAL_GAIN_PD, UPPER_BODY_LAWS, TocabiWalkConfig
from .envs.push_config import PushConfig
from .randomize import tocabi_lab_paths
from .sim.config import RESET_PASSES
from .transforms.settings import TransformSettings
from .tree import OWN_NUMBER_CHECK, ConfigError, check_field_types, leaf_paths, replace_paths
from .tree import from_dict as _tree_from_dict
from .tree import to_dict as _tree_to_dict
from .value_rules import MAX_SEED, POSITIVE, check_seed
from .viewer.config import ViewerConfig

__all__ = ["RunConfig", "PPOConfig", "PRESETS", "RENAMED_PRESETS", "preset_now", "preset_tree", "preset_config",
           "config_from_dict", "to_dict", "ConfigError", "UnusedOptionError", "LR_SCHEDULES", "STD_MODES",
           "ENV_GRAPH_MODES", "LOGGERS", "SYMMETRY_MODES", "field_choices", "canonical_choices", "wall_tag",
           "check_snapshot_minutes", "LEGACY_VALUES", "MAX_SEED", "KL_ADAPT_MODES", "schedule_past_budget",
           "schedule_warning"]

LR_SCHEDULES = ("fixed", "linear", "adaptive")
ENV_GRAPH_MODES = ("auto", "on", "off")
#: How a data-parallel run averages the ranks' gradients (``ppo.grad_sync``).
GRAD_SYNCS = ("allreduce", "ddp")
#: torch's float32 matrix-product precisions a run may train with (``ppo.matmul_precision``).
MATMUL_PRECISIONS = ("highest", "high")
#: The dtypes the PPO update's hidden layers may compute in (``ppo.update_dtype``).
UPDATE_DTYPES = ("float32", "bfloat16")
_GRAPH_ALIASES = {"true": "on", "yes": "on", "1": "on", "false": "off", "no": "off", "0": "off"}
STD_MODES = ("scheduled", "learned")
#: What the torque assist's absorbing loss copies into the actor (``ppo.assist_target``; rl/assist.py).
ASSIST_TARGETS = ("rollout", "teacher")
#: How long the adaptive learning rate is held around the torque assist's fade (``ppo.assist_lr_hold``).
ASSIST_LR_HOLDS = ("fade", "pull")
#: When the adaptive learning-rate rule acts (``ppo.kl_adapt_every``): once per iteration, or before every mini-batch
#: step.
KL_ADAPT_MODES = ("iteration", "minibatch")
LOGGERS = ("csv", "tensorboard", "wandb")
#: Left-right symmetry in PPO (``ppo.symmetry``; rl/symmetry.py): none, each mini-batch doubled with its mirror, or a
#: mean action symmetric by construction.
SYMMETRY_MODES = ("none", "augment", "equivariant")


def wall_tag(seconds: float) -> str:
    """Name (without ``.pt``) of the wall-clock snapshot at ``seconds`` of training, the trainer's and the library
    recipes' alike: rounded, not truncated, so that a 1 s period that floating point makes a hair shorter still
    names its marks 1, 2, 3 s and not 0, 1, 2 s."""
    return f"wall_{round(seconds):05d}s"


def wall_seconds(tag: str) -> int:
    """The training second a :func:`wall_tag` name marks (``"wall_00540s"`` -> 540).

    >>> wall_seconds(wall_tag(750.2))
    750
    """
    return int(tag[len("wall_"):-1])


def check_snapshot_minutes(minutes: float, name: str = "checkpoint_minutes") -> None:
    """``ValueError`` unless ``minutes`` is 0 (no snapshots) or at least 1/60 (1 s): :func:`wall_tag` names are
    whole seconds, so marks less than a second apart could get one name and one snapshot would replace the other."""
    if not minutes >= 0:
        raise ValueError(f"{name} must be >= 0, got {minutes!r}")
    if 0 < minutes and 60.0 * minutes < 1.0 - 1e-9:
        raise ValueError(f"{name} {minutes:g} is a snapshot period of {60.0 * minutes:.3g} s; snapshots are named by "
                         f"whole seconds (wall_XXXXXs.pt), so give 0 (none) or at least {1 / 60:.6g} (1 s)")


#: The learning rates [min, max] between which the ``adaptive`` schedule moves the rate (rl/update_step.adapt_lr).
ADAPTIVE_LR_RANGE = (1e-5, 1e-2)


@dataclass
class PPOConfig:
    """The PPO section of :class:`RunConfig` (``ppo``): rollout, update, learning rate, networks, action noise, the
    torque assist's schedule and how the training computation runs. Steps are policy steps (4 ms each).

    The defaults (the ``default`` preset) are tuned for thousands of envs on one GPU: 48-step rollouts with gamma
    0.995 (a 0.8 s horizon at 250 Hz), large mini-batches, a KL-adaptive learning rate and a scheduled std from 0.2
    to 0.05 (docs/training.md).
    """

    # rollout
    steps_per_env: int = 48
    """rollout length per env and iteration [policy steps]"""
    # PPO update
    epochs: int = 5
    """passes over each rollout per update"""
    minibatch_size: int = 49152
    """frames per mini-batch; each epoch takes floor(rollout / size) mini-batches of a fresh shuffle, so a size
    that does not divide the rollout (env.num_envs × ppo.steps_per_env) leaves another remainder out of each epoch"""
    gamma: float = 0.995
    """discount factor per policy step"""
    gae_lambda: float = 0.95
    """GAE lambda"""
    clip_epsilon: float = 0.2
    """PPO ratio clip"""
    entropy_coef: float = 0.0
    """entropy bonus weight; 0 = none"""
    value_coef: float = 1.0
    """value loss weight (> 0)"""
    value_loss: str = "l2"
    """value loss function: l2, smooth_l1 or l1"""
    #: Gradient-norm clip; inf = no clipping (the one number of the tree allowed to be infinite).
    max_grad_norm: float = field(default=1.0, metadata=OWN_NUMBER_CHECK)
    """gradient norm clip"""
    # learning rate
    lr: float = 1e-3
    """learning rate (start value of the schedule)"""
    lr_end: float = 1e-5
    """final learning rate of the linear schedule (at most ppo.lr)"""
    lr_schedule: str = "adaptive"
    """learning-rate schedule: adaptive (from the KL to desired_kl), linear (lr to lr_end) or fixed"""
    desired_kl: float = 0.01
    """KL target of the adaptive schedule"""
    #: "iteration" applies the rule once per update, from its mean KL: a run of too-large mini-batch steps goes on at
    #: the same rate to the update's end. "minibatch" applies it before every mini-batch step, from that mini-batch's
    #: KL to the rollout's policy (rsl_rl's schedule, on the loss's KL estimate; with overlap_update, to the policy the
    #: update starts from), so the rate falls within the update that overshoots; it runs on the device inside the
    #: (captured) step, and one rank's KL would set one rank's rate, so it trains on one GPU only.
    #: (The torque preset at 16,384 envs broke in one update of KL 4.3e4, docs/training/torque/h100_16k_run1.)
    kl_adapt_every: str = "iteration"
    """when the adaptive rule sets the learning rate: once per iteration from the update's mean KL, or before every
    mini-batch step from that mini-batch's KL (minibatch, rsl_rl's schedule; one GPU only)"""
    #: The adaptive rule's floor. At a small action σ one step of the mean is a large KL, and the rule can sit at
    #: its floor for the rest of a run (the robust preset's sixth run: 1e-5 for its last seven minutes,
    #: docs/training/robust/h200_run6); a higher floor keeps it learning, PPO's ratio clip bounding each update.
    lr_min: float = ADAPTIVE_LR_RANGE[0]
    """lowest learning rate of the adaptive schedule (at least 1e-5, at most ppo.lr)"""
    value_head_lr: float = 0.0  # > 0: the value head gets its own constant LR (the reference's second optimizer)
    """constant learning rate of the value head; 0 = share the policy's"""
    adam_eps: float = 1e-8
    """Adam epsilon"""
    #: Left-right mirror symmetry (rl/symmetry.py): "augment" doubles every mini-batch with its mirror image
    #: (observations and actions mirrored; advantages, value targets and old log-probabilities kept), so that the
    #: policy and the critic learn from both sides of every state. Twice the frames per update step. "equivariant"
    #: makes the policy's mean action symmetric by construction, ½·(f(o) + A·f(M·o)) (EquivariantMean): the actor's
    #: network runs twice per input, the critic and the batch are unchanged.
    symmetry: str = "none"
    """left-right symmetry: none, augment (each mini-batch doubled with its mirror image: mirrored observations
    and actions, same advantages, value targets and old log-probabilities), or equivariant (the mean action is
    ½·(f(o) + A·f(M·o)), symmetric by construction)"""
    #: The augmentation acts through PPO's ratio, whose mirrored half is clipped away once the policy is a little
    #: asymmetric at a small action σ (docs/training.md, "Left-right symmetry"). A mirror loss on the mean action acts
    #: at any σ (rsl_rl's symmetry module offers both).
    symmetry_loss: float = 0.0
    """weight of the mirror loss (with symmetry augment): mean over mini-batch frames and actions of (μ(M·o) −
    A·μ(o))², μ the policy's mean action, M and A the input and action mirrors; 0: off"""
    #: The trained network made symmetric after training, as the policy its checkpoints give: made symmetric, run
    #: 12's 16-minute mark passed the robust test where the mark itself drifted too far
    #: (docs/training/robust/symmetrized), and an actor trained equivariant from the start fell (run 18). Training
    #: never sees it, so a run trains as without it.
    symmetric_policy: bool = False
    """the policy of a checkpoint (every gait test, play, viewer and export) is the trained actor's mean made
    left-right symmetric, ½·(f(o) + A·f(M·o)); training acts with f itself, so the run trains as without it"""
    #: Asymmetric actor-critic (transforms/privileged.py): the critic also reads ``privileged``, 12 values of true
    #: state (pelvis velocities and height, foot loads, orientation), beyond what the policy sees (with
    #: transforms.observation base_vel the policy observes the velocities too); the policy and its export are
    #: unchanged. The env gets a PrivilegedState transform.
    critic_privileged: bool = False
    """the critic also reads true pelvis velocity, height, orientation and foot loads (asymmetric actor-critic; the
    policy's input is unchanged)"""
    # networks and exploration
    actor_hidden: tuple[int, ...] = (400, 200, 100)
    """hidden layer sizes of the policy network"""
    critic_hidden: tuple[int, ...] = (400, 200, 100)
    """hidden layer sizes of the value network"""
    activation: str = "elu"
    """hidden-layer activation: elu, relu, tanh or silu"""
    value_out_gain: float = 1.0
    """init gain of the value output layer"""
    std_mode: str = "scheduled"
    """action noise: scheduled (std_start -> std_end) or learned"""
    std_start: float = 0.2
    """action std at the start"""
    std_end: float = 0.05
    """action std at the end of the schedule (at most ppo.std_start)"""
    std_hold: float = 0.5
    """fraction of training still left when the scheduled std reaches std_end (held there after)"""
    #: Torque mode training aid (0 = off): the training env gets ``env.control.torque_assist`` and its leg actions
    #: morph from position residuals tracked by a PD (``env.control.pd_kp``/``pd_kv``/``pd_action_scale``) at β = 1
    #: to torques at β = 0. β starts at this value, holds until ``assist_fade_start`` env steps and falls to 0 at
    #: ``assist_fade_end`` (geometrically in the action gain, with the adaptive learning rate held, see
    #: rl/assist.AssistSchedule); during the fade a loss term (weight ``assist_absorb``) moves each step of the morph
    #: into the actor (rl/assist.py), so the run ends as a pure torque policy. Evaluations never use the assist.
    torque_assist: float = 0.0
    """torque mode training aid: start scale β in [0, 1] of the morph from PD residuals (β = 1) to torques (β =
    0); 0 = off"""
    assist_fade_start: int = 0
    """env steps at which the torque assist starts to fade"""
    assist_fade_end: int = 0
    """env steps at which the torque assist reaches 0 (pure torque from there on)"""
    assist_absorb: float = 1.0
    """weight of the loss that moves each step of the morph into the actor"""
    #: What the absorbing loss copies (rl/assist.py): "teacher", the torque of a frozen copy of the actor taken as
    #: the fade starts, in the fading policy's own states (DAgger); or "rollout", the torque the rollout's own mean
    #: applied (only the fade's step). With "teacher" the pull holds to ``assist_fade_end`` and then falls linearly
    #: to 0 over ``assist_anchor_decay`` env steps.
    assist_target: str = "teacher"
    """what that loss copies: 'teacher' (the torque of a frozen copy of the actor taken as the fade starts,
    DAgger) or 'rollout' (the torque the rollout's own mean applied)"""
    assist_anchor_decay: int = 0
    """env steps after assist_fade_end over which the teacher's pull falls to 0"""
    #: The adaptive learning rate reads the KL of each update, and while the loss pulls the actor to the next β's
    #: actions or to the teacher that KL measures the intended pull as well: "fade" holds the rate while β falls
    #: (the rule alone starved the fade, docs/training.md), "pull" holds it on until the teacher's pull has decayed
    #: too. (With "fade" the robust preset's fourth run read KLs of 0.1-2.3 after the fade and its rate sat at the
    #: 1e-5 floor for the next 27 M env steps, docs/training/robust/h200_run4.)
    assist_lr_hold: str = "fade"
    """hold the adaptive learning rate while β fades ('fade') or until the teacher's pull has decayed too
    ('pull')"""
    #: The hold keeps the rate the adaptive rule happened to reach by the fade's start: 7.5e-5 to 3.0e-4 in the
    #: robust preset's fourth to twelfth runs, and the twelfth, holding 3.0e-4, read KLs 3-5 times the ninth's (7.5e-5)
    #: while its teacher pulled (docs/training/robust/h200_run12). A bound makes the held rate a setting, not a draw;
    #: bounded at 7.5e-5, the capped thirteenth run still failed (docs/training/robust/h200_run13), so it stays 0.
    assist_lr_max: float = 0.0
    """highest learning rate while assist_lr_hold holds the adaptive rate (0: no bound; the rate the rule had
    reached when the hold began); with the adaptive schedule and a torque assist only"""
    #: The assist's PD on the true joint positions is feedback a policy with biased encoders cannot copy when the
    #: PD fades (transforms.sensor_noise: the TOCABI lab's ±π/100 rad is 0.2-0.7 of a leg's torque limit through the
    #: PD's stiffness). On: the PD reads each world's sensed positions, the SensorNoise transform's bias included
    #: (TocabiWalk.sense_assist_joints); no effect without encoder biases. The robust preset's fifth run, with it
    #: off, lost its kick recoveries as the PD faded (docs/training/robust/h200_run5).
    assist_pd_sensed: bool = False
    """the torque assist's PD reads the joint positions the policy senses (with transforms.sensor_noise's encoder
    biases) instead of the true ones, so the fade copies feedback the policy can reproduce"""
    #: The pushes' curriculum (env.pushes): every kick is scaled by 0 before ``push_ramp[0]`` env steps, rising
    #: linearly to full strength at ``push_ramp[1]`` ((0, 0): full from the start). A schedule on env steps, like the
    #: assist's, so a resumed run takes it up where it was.
    push_ramp: tuple[int, int] = (0, 0)
    """(start, full) env steps of the pushes' curriculum: no kicks before start, full strength from full; (0, 0):
    full from the start"""
    #: On a GPU, capture the training env's whole step (physics, signals, transforms, masked reset) as one CUDA
    #: graph: "on", "off", or "auto" = on up to ``cuda_graphs.ENV_GRAPH_AUTO_MAX_ENVS`` envs. Small counts are
    #: launch-bound, and the graph trained 1.5-1.8x faster at 8-96 envs on an H100 (short runs); from 256 envs up it
    #: was 3-6 % slower (docs/benchmarks/env_graph.md). Both compute the same step (tests compare them).
    cuda_graph: str = "auto"
    """capture the env step as one CUDA graph: on, off, or auto (on up to 128 envs)"""
    #: On a GPU, capture each PPO mini-batch step (loss, backward, clipping, fused Adam) as one CUDA graph after 3
    #: eager steps (falls back to eager, with a warning, if the capture fails, e.g. with entropy_coef > 0).
    update_graph: bool = True
    """on a GPU, capture each mini-batch step as a CUDA graph"""
    #: Run each PPO update on a side CUDA stream while the next rollout is collected, instead of between rollouts.
    #: mujoco-warp's kernels at a few thousand worlds leave most of a GPU idle, and the update (~6-14 % of a training
    #: step at 4,096 envs) can fill it. The price: each rollout is collected with the policy of one update before.
    #: So the update is decoupled PPO (rl/rollout_guard.GuardedClipPPOLoss.use_proximal): its ratio, clip and KL are
    #: taken against the policy it starts from, the surrogate weighted by that policy over the one that acted.
    #: (Against the policy that acted, a pd-preset run's KL held the previous update's move too and its adaptive
    #: rate sat at the floor: docs/training/pd/h100_overlap_seed0.) One rank only; on a CPU the order is the same,
    #: without the concurrency (rl/overlap.py).
    overlap_update: bool = False
    """update on a side stream while the next rollout is collected (the rollout's policy lags one update)"""
    #: Data-parallel runs (torchrun, several ranks): how the ranks' gradients are averaged before clipping.
    #: "allreduce": one all-reduce of one flat buffer after backward, captured with the update step; "ddp": torch's
    #: DistributedDataParallel around the loss (bucketed all-reduces that overlap backward), which cannot be captured,
    #: so it needs ``update_graph`` false. Both give every rank the same mean gradient (tests/test_distributed.py).
    #: On one rank nothing is exchanged either way (the update_graph rule still applies, so a config means the
    #: same on any rank count).
    grad_sync: str = "allreduce"
    """several ranks: average gradients with one captured all-reduce (allreduce), or ddp (needs update_graph
    false)"""
    #: float32 matrix products while training (torch.set_float32_matmul_precision, set for the run and restored
    #: after it): "highest" (full float32) or "high" (TF32 tensor cores where the GPU has them, a 10-bit mantissa;
    #: the update's and GAE's network passes are matmul-bound, ~115 GFLOP per default mini-batch step). It applies
    #: to every torch product in the process, the env's transforms included; C MuJoCo and mujoco-warp are untouched.
    matmul_precision: str = "highest"
    """float32 matrix products while training: highest (float32) or high (TF32 on GPUs)"""
    #: The dtype the PPO update's hidden layers compute in: "float32", or "bfloat16" (torch.autocast around the
    #: update's network passes, the decoupled update's proximal log-probabilities included). The output layers
    #: (action mean, value), the distribution, the losses, the gradients and the optimiser stay float32
    #: (rl/networks.OutputLinear). Half the bytes per activation: beside the rollout (``overlap_update``), the
    #: update's memory traffic slows the physics. The rollout's own policy pass stays float32, so a bfloat16 update
    #: is decoupled PPO as ``overlap_update``'s is, overlapped or not (rl/trainer.decoupled_update): the rounding alone
    #: starts the shipped torque policy's ratio past the clip on 30-59 % of its frames
    #: (docs/training/bf16_rounding.json).
    update_dtype: str = "float32"
    """the PPO update's hidden layers in float32 or bfloat16 (output layers, loss and optimiser stay float32)"""
    #: Compile the PPO loss with torch.compile (static shapes; the first mini-batch steps compile it, a few tens of
    #: seconds once per run): its element-wise kernels fused, 29 % off the update's GPU time at 16,384 envs on an
    #: H100 (docs/benchmarks/train_over_ceiling_overlap). Needs a C++ compiler on a CPU and Triton on a GPU.
    compile_loss: bool = False
    """compile the PPO loss with torch.compile (fused kernels; compiles during the first mini-batch steps)"""
    #: Keep every env signal (joint_pos, base_pos, ...) in the training rollout; off: only what PPO and the logs
    #: read (observation, reward, done flags, reward terms, episode counters), ~40 % less rollout memory.
    store_env_signals: bool = False
    """keep every env signal in the rollout (more memory; off keeps what PPO reads)"""

    def __post_init__(self) -> None:
        # Configs and checkpoints written before "auto" existed hold a bool here, and the command line used to take
        # true/false/yes/no/1/0: all of them still read as on/off; any case is accepted.
        value = self.cuda_graph
        if isinstance(value, (bool, int, str)):
            text = str(value).strip().lower()
            self.cuda_graph = _GRAPH_ALIASES.get(text, text)

    def validate(self, allow_unused: bool = False) -> None:
        """Raise ``ValueError`` naming the first bad option (``ppo.NAME``) and the accepted values; an option set
        where it changes nothing raises :class:`UnusedOptionError`, a warning with ``allow_unused`` (as
        :meth:`RunConfig.validate`)."""
        for name in ("steps_per_env", "epochs", "minibatch_size"):
            _check_int(self, name, 1, "ppo.")
        for name, low, high in (("gamma", 0.0, 1.0), ("gae_lambda", 0.0, 1.0), ("clip_epsilon", 0.0, 1.0)):
            value = getattr(self, name)
            if not low < value <= high:
                raise ValueError(f"ppo.{name} must be in ({low}, {high}], got {value!r}")
        if isinstance(self.max_grad_norm, bool) or not isinstance(self.max_grad_norm, numbers.Real):
            raise ValueError(  # noqa: TRY004 - a config error, a ValueError like every other of the tree
                f"ppo.max_grad_norm must be a number > 0 (inf: no clipping), got {self.max_grad_norm!r}")
        for name in ("lr", "std_start", "std_end", "desired_kl", "max_grad_norm", "adam_eps"):
            if not getattr(self, name) > 0:
                raise ValueError(f"ppo.{name} must be > 0, got {getattr(self, name)!r}")
        _check_int(self, "assist_anchor_decay", 0, "ppo.")
        if not 0 <= self.push_ramp[0] <= self.push_ramp[1]:
            raise ValueError(f"ppo.push_ramp must be (start, full) env steps with 0 <= start <= full, got "
                             f"{self.push_ramp!r}")
        if not 0 <= self.torque_assist <= 1 or self.assist_absorb < 0:
            raise ValueError(f"ppo.torque_assist must be in [0, 1] and ppo.assist_absorb >= 0, got "
                             f"{self.torque_assist!r}, {self.assist_absorb!r}")
        if self.symmetric_policy is True and self.symmetry == "equivariant":
            raise ValueError("ppo.symmetric_policy makes a trained actor symmetric; with ppo.symmetry='equivariant' "
                             "it is symmetric already: leave ppo.symmetric_policy false")
        if self.symmetry_loss > 0 and self.symmetry != "augment":
            _unused(f"ppo.symmetry_loss > 0 works with ppo.symmetry='augment' (whose mirrors it uses), got "
                    f"ppo.symmetry={self.symmetry!r}: set both, or leave ppo.symmetry_loss at 0", allow_unused)
        if self.assist_target == "rollout" and (self.assist_anchor_decay > 0 or self.assist_lr_hold == "pull"):
            # Both act on the frozen teacher the "teacher" target copies from; "rollout" has none, so they trained
            # exactly as without them, without a word.
            given = "ppo.assist_anchor_decay > 0" if self.assist_anchor_decay > 0 else "ppo.assist_lr_hold='pull'"
            _unused(f"{given} is about the teacher's pull, and ppo.assist_target='rollout' has no teacher: use "
                    "ppo.assist_target='teacher', or leave assist_anchor_decay at 0 and assist_lr_hold at 'fade'",
                    allow_unused)
        if self.assist_pd_sensed and not self.torque_assist > 0:
            _unused("ppo.assist_pd_sensed is about the torque assist's PD and needs ppo.torque_assist > 0; leave it "
                    "false without the assist", allow_unused)
        if self.torque_assist > 0 and not 0 <= self.assist_fade_start < self.assist_fade_end:
            raise ValueError(f"ppo.torque_assist > 0 needs 0 <= assist_fade_start < assist_fade_end (env "
                             f"steps), got {self.assist_fade_start}, {self.assist_fade_end}")
        if self.grad_sync == "ddp" and self.update_graph:
            raise ValueError("ppo.grad_sync=ddp runs the update step eagerly (DDP's gradient hooks cannot be captured "
                             "in a CUDA graph): set ppo.update_graph=false as well")
        for name in ("entropy_coef", "value_head_lr", "lr_end", "value_out_gain", "symmetry_loss"):
            if not getattr(self, name) >= 0:
                raise ValueError(f"ppo.{name} must be >= 0, got {getattr(self, name)!r}")
        if not self.value_coef > 0:
            # TorchRL's ClipPPOLoss drops its critic term at 0: the critic GAE reads would never learn, and the first
            # update failed on the missing loss_critic, after the run folder was written.
            raise ValueError(f"ppo.value_coef must be > 0 (the value loss's weight: the critic whose values GAE's "
                             f"advantages read learns from that loss alone), got {self.value_coef!r}; give e.g. 0.5 "
                             f"or the default 1.0")
        if self.std_mode == "scheduled" and not 0 <= self.std_hold < 1:
            raise ValueError(f"ppo.std_hold is the fraction of training still left when the scheduled std reaches "
                             f"std_end, in [0, 1), got {self.std_hold!r}")
        if self.std_mode == "scheduled" and self.std_end > self.std_start:
            # Exploration noise that grows as the policy improves undoes what it learned; no preset schedules that,
            # so a rising pair is taken for swapped values.
            raise ValueError(f"ppo.std_end {self.std_end!r} is above ppo.std_start {self.std_start!r}: the scheduled "
                             f"std falls from std_start to std_end; give std_end <= std_start (equal: a constant std)")
        if self.lr_schedule == "linear" and self.lr_end > self.lr:
            raise ValueError(f"ppo.lr_end {self.lr_end!r} is above ppo.lr {self.lr!r}: the linear schedule falls from "
                             f"lr to lr_end; give lr_end <= lr (equal: a constant rate, or ppo.lr_schedule fixed)")
        for name in ("actor_hidden", "critic_hidden"):
            sizes = getattr(self, name)
            if not sizes or any(isinstance(h, bool) or not isinstance(h, numbers.Integral) or h < 1 for h in sizes):
                raise ValueError(f"ppo.{name} must be one or more positive layer sizes (e.g. 400,200,100), got "
                                 f"{sizes!r}")
        low, high = ADAPTIVE_LR_RANGE
        if isinstance(self.lr_min, bool) or not isinstance(self.lr_min, numbers.Real) or not (
                low <= self.lr_min <= max(self.lr, low)):
            raise ValueError(f"ppo.lr_min must be a number in [{low:g}, ppo.lr = {self.lr:g}] (the adaptive "
                             f"schedule's floor), got {self.lr_min!r}")
        # The adaptive rule may have raised the rate above ppo.lr by the time the hold begins, so the ceiling may
        # lie anywhere in the rule's range.
        if isinstance(self.assist_lr_max, bool) or not isinstance(self.assist_lr_max, numbers.Real) or not (
                self.assist_lr_max == 0 or self.lr_min <= self.assist_lr_max <= high):
            raise ValueError(f"ppo.assist_lr_max must be 0 (no bound) or a number in [ppo.lr_min = {self.lr_min:g}, "
                             f"{high:g}] (the held adaptive rate's ceiling), got {self.assist_lr_max!r}")
        if self.lr_schedule == "adaptive" and not low <= self.lr <= high:
            # The rule keeps the rate inside this range: from outside it, its first clamp would move the rate the
            # wrong way (up when the KL says down).
            raise ValueError(f"ppo.lr {self.lr!r} is outside the adaptive schedule's range [{low:g}, {high:g}]; give "
                             f"a learning rate inside it, or ppo.lr_schedule linear or fixed")


@dataclass
class RunConfig:
    """One training run: where it writes, its budget, logging, checkpoints and evaluation, and the ``env``,
    ``transforms`` and ``ppo`` sections (see the module doc). Times are wall-clock; steps are env steps summed over
    the envs unless a name says otherwise."""

    preset: str = "default"
    """the training preset the other options change (PRESETS: cpu_smoke, default, model_based, model_based_ideal, pd,
    reference, robust, torque, torque_ideal); on the command line it is read first, whatever its place"""
    name: str = "ppo_walk"
    """run folder name under run_dir; an existing run is never overwritten (--resume it or pick a new name)"""
    run_dir: str = "runs"
    """parent folder of the run folders"""
    # validate() checks it with check_seed, the rule and message of every place a seed enters.
    seed: int = field(default=0, metadata=OWN_NUMBER_CHECK)
    """seed of torch and of the env's random draws, in [0, 2**63 - 1]"""
    device: str = "auto"
    """auto (CUDA if present, else the small CPU smoke run), cpu, cuda or cuda:N"""
    resume: str = ""
    """run folder or checkpoint to continue; its saved options apply, and only these may be given other values:
    checkpoint_every, checkpoint_keep_every, checkpoint_keep_last, checkpoint_minutes, device,
    env.sim.reset_pass, env.sim.threads, eval_at_end, eval_envs, eval_seconds, eval_test, log_every, loggers,
    max_minutes, name, ppo.cuda_graph, ppo.grad_sync, ppo.store_env_signals, ppo.symmetric_policy,
    ppo.update_graph, progress_bar, run_dir, total_env_steps, viewer.enabled, viewer.every, viewer.host,
    viewer.port, viewer.worlds"""
    # budget
    total_env_steps: int = 300_000_000
    """training budget in env steps (all envs together)"""
    max_minutes: float = 0.0  # 0 = no wall-clock limit
    """wall-clock budget [min]; 0 = none"""
    # logging and checkpoints
    log_every: int = 1
    """iterations between log rows"""
    loggers: tuple[str, ...] = ("csv",)
    """where metrics go besides the progress bar: csv, tensorboard, wandb; csv (runs/<name>/metrics/) is always
    written"""
    progress_bar: bool = True
    """show a progress bar (else one line per log row)"""
    checkpoint_every: int = 100
    """iterations between checkpoints"""
    #: Checkpoint retention: keep the newest ``checkpoint_keep_last`` iteration files (0 = keep all) and every file
    #: whose iteration is a multiple of ``checkpoint_keep_every`` (0 = none more); ``latest.pt`` is always kept.
    checkpoint_keep_last: int = 3
    """newest iteration checkpoints (iter_*.pt) kept; 0 = keep all"""
    checkpoint_keep_every: int = 50
    """also keep checkpoints of iterations that are multiples of this; 0 = none"""
    #: Also save ``checkpoints/wall_XXXXXs.pt`` whenever the training wall-clock (summed over resumed segments)
    #: passes a multiple of this many minutes (0 = off; else at least 1/60: :func:`wall_tag` names whole seconds).
    checkpoint_minutes: float = 0.0
    """also save checkpoints/wall_XXXXXs.pt every this many minutes of training (all kept: the pruning of
    checkpoint_keep_last/keep_every leaves them); 0 = none, else at least 1/60 (the names are whole seconds)"""
    # evaluation at the end
    eval_at_end: bool = True
    """run the gait test (eval/) when training ends (recipes/ppo_walk.py does; trainer.train() itself does not)"""
    eval_envs: int = 256
    """robots in the gait test (per case in the robust test)"""
    eval_seconds: float = 8.0
    """duration of the gait test [s]"""
    #: The gait test run at the end: "standard" (one command, 256 robots) or "robust" (evaluation/robust.py: diverse
    #: starts, four cases of ``eval_envs`` robots each; docs/evaluation.md).
    eval_test: str = "standard"
    """which gait test runs when training ends: standard (one command) or robust (diverse starts, four cases of
    eval_envs robots each; docs/evaluation.md)"""
    # The sections: each has a docstring, the title of its group in --help (a comment above them would be taken
    # for all three titles).
    env: TocabiWalkConfig = field(default_factory=TocabiWalkConfig)
    """the walking task's env: worlds, simulation, task, commands, control, scene, pushes, dynamics"""
    transforms: TransformSettings = field(default_factory=TransformSettings)
    """the env's transforms: observation history, normalisation, clipping and noise; reward terms and weights"""
    ppo: PPOConfig = field(default_factory=PPOConfig)
    """PPO: rollout, update, learning rate, networks, action noise, torque assist and how the training runs"""
    #: The live web viewer of the training worlds (``--viewer``; the ``viewer`` extra; docs/viewer.md).
    viewer: ViewerConfig = field(default_factory=ViewerConfig)

    @property
    def frames_per_batch(self) -> int:
        """Env steps per rollout: ``env.num_envs × ppo.steps_per_env``."""
        return self.env.num_envs * self.ppo.steps_per_env

    def minibatch_note(self) -> str | None:
        """What a mini-batch size that does not divide the rollout leaves out of each epoch, with the dividing size
        nearest to it; ``None`` when it divides (or exceeds the rollout, which :meth:`validate` refuses)."""
        frames, size = self.frames_per_batch, self.ppo.minibatch_size
        left = frames % size
        if left == 0 or size > frames:
            return None
        divisors = {d for k in range(1, math.isqrt(frames) + 1) if frames % k == 0 for d in (k, frames // k)}
        nearest = min(divisors, key=lambda d: (abs(d - size), -d))
        return (f"ppo.minibatch_size {size:,} leaves {left:,} of the rollout's {frames:,} frames out of each epoch "
                f"({100 * left / frames:.0f} %; each epoch reshuffles, so a different share); {nearest:,} divides it")

    @property
    def iterations(self) -> int:
        """Rollout + update iterations that ``total_env_steps`` asks for (at least 1)."""
        return max(1, -(-self.total_env_steps // self.frames_per_batch))

    def to_dict(self) -> dict[str, Any]:
        """The tree as nested dicts of plain values (what checkpoints and ``config.json`` hold)."""
        return _tree_to_dict(self)

    def validated(self) -> RunConfig:
        """``self`` after :meth:`validate` (for chaining)."""
        self.validate()
        return self

    def validate(self, allow_unused: bool = False) -> None:
        """Raise ``ValueError`` naming the first bad option by its path (``ppo.lr``, ``env.control.mode``) and the
        accepted values.

        An option set where it changes nothing (a kick's speed without kicks, ``ppo.lr_end`` under the adaptive
        schedule) raises :class:`UnusedOptionError`; with ``allow_unused`` it is a warning. That is for a saved run
        (resumed, evaluated, exported): it trained exactly as without the option, and versions before the rule
        saved such options."""
        check_field_types(self)  # the whole tree: every switch a bool, every number finite, named by its path
        canonical_choices(self)  # before the sections' own checks, which compare the names
        if isinstance(self.eval_envs, bool) or not isinstance(self.eval_envs, int) or self.eval_envs < 1:
            # The fix either way: a refusal that gave none left a user of --eval_at_end false --eval_envs 0 stuck.
            hint = ("; for no test at the end, set eval_at_end=false instead" if self.eval_at_end else
                    "; eval_at_end is false, so no test runs at the end and eval_envs is not needed: leave it at the "
                    "preset's value (leave --eval_envs out)")
            raise ValueError(f"eval_envs must be a positive int (robots in the gait test at the end), got "
                             f"{self.eval_envs!r}{hint}")
        for name in ("log_every", "checkpoint_every", "total_env_steps"):
            _check_int(self, name, 1)
        self.seed = check_seed(self.seed)
        for name in ("checkpoint_keep_last", "checkpoint_keep_every"):
            _check_int(self, name, 0)
        if not self.eval_seconds > 0:
            raise ValueError(f"eval_seconds must be > 0, got {self.eval_seconds!r}")
        if not self.max_minutes >= 0:
            raise ValueError(f"max_minutes must be >= 0, got {self.max_minutes!r}")
        check_snapshot_minutes(self.checkpoint_minutes)
        if isinstance(self.loggers, str):  # iterated, one name would be read as its letters
            raise ValueError(f"loggers must be a tuple of names, e.g. ({self.loggers!r},), got the string "
                             f"{self.loggers!r}")
        if not isinstance(self.loggers, (tuple, list)):  # None (a saved null) failed as "not iterable"
            raise ValueError(f"loggers must be a tuple of names from {LOGGERS} (csv is always written; () for no "
                             f"others), got {self.loggers!r}")
        bad = set(self.loggers) - set(LOGGERS)
        if bad:
            raise ValueError(f"unknown logger(s) {sorted(bad)}; choose from {', '.join(LOGGERS)}")
        self.env.validate()
        self.transforms.validate()
        self.ppo.validate(allow_unused)
        self.viewer.validate()
        for path, allowed in field_choices().items():
            value = _get(self, path)
            if value not in allowed:
                raise ValueError(f"{path} must be one of {allowed}, got {value!r}")
        # Stricter than the env's rule (>= 0): at 0 the PD modes' leg actions move nothing, so nothing is learned.
        POSITIVE.check(self.env.control.pd_action_scale, "env.control.pd_action_scale")
        if self.ppo.torque_assist > 0 and self.env.control.mode != "torque":
            raise ValueError(f"ppo.torque_assist > 0 needs control_mode='torque' (env.control.mode), got "
                             f"{self.env.control.mode!r} (set ppo.torque_assist=0 for the PD modes)")
        if self.transforms.cycle_vel_weight > 0 and not self.env.task.cycle_velocity:
            raise ValueError("transforms.cycle_vel_weight > 0 reads the env's cycle_vel_error signal, which "
                             "env.task.cycle_velocity turns on: set env.task.cycle_velocity=true as well")
        if self.transforms.kick_relax.enabled and self.env.pushes.count == 0:
            # Not an error in the env (a gait test builds the trained env without its kicks), but a run that sets it
            # would train exactly as without it.
            _unused("transforms.kick_relax relaxes reward terms after a kick, and env.pushes.count is 0 (no kicks): "
                    "set env.pushes.count > 0, or transforms.kick_relax.seconds=0", allow_unused)
        # Likewise options that only shape the kicks or schedule the assist: a run that sets them without either
        # would train exactly as without them.
        if self.env.pushes.count == 0 and (unused := ", ".join(self._changed_options(KICK_OPTIONS))):
            _unused(f"env.pushes.count is 0 (no kicks), so the kicks' {unused} would change nothing: set "
                    f"env.pushes.count > 0, or leave {unused} at the preset's values", allow_unused)
        if not self.ppo.torque_assist > 0 and (unused := ", ".join(self._changed_options(ASSIST_OPTIONS))):
            _unused(f"ppo.torque_assist is 0 (no assist), so the assist's schedule {unused} would change nothing: "
                    f"set ppo.torque_assist > 0, or leave {unused} at the preset's values", allow_unused)
        # The bound on the held rate where no hold keeps an adaptive rate; like the options above, a preset's own
        # bound stays valid under another schedule (the robust preset's, with --ppo.lr_schedule fixed).
        ppo = self.ppo
        if ppo.assist_lr_max and (ppo.lr_schedule != "adaptive" or not ppo.torque_assist) and \
                self._changed_options(("ppo.assist_lr_max",)):
            _unused(f"ppo.assist_lr_max {ppo.assist_lr_max:g} bounds the adaptive rate the torque assist's hold "
                    f"keeps, and this run has no such hold (ppo.lr_schedule {ppo.lr_schedule!r}, ppo.torque_assist "
                    f"{ppo.torque_assist:g}); set it to 0, or train with the adaptive schedule and an assist",
                    allow_unused)
        # And the options of a learning-rate schedule or an action-std mode the run does not use: --ppo.lr_end 1e-6
        # under the default's adaptive schedule trained exactly as without it.
        for switch, mode, paths in MODE_OPTIONS:
            if _get(self, switch) != mode and (unused := ", ".join(self._changed_options(paths))):
                _unused(f"{switch} is {_get(self, switch)!r}, so {unused} (read by {switch} {mode!r} only) would "
                        f"change nothing: set {switch}={mode}, or leave {unused} at the preset's values", allow_unused)
        if self.ppo.minibatch_size > self.frames_per_batch:
            quarter = max(1, self.frames_per_batch // 4)
            raise ValueError(
                f"ppo.minibatch_size {self.ppo.minibatch_size} exceeds the rollout ({self.env.num_envs} envs × "
                f"{self.ppo.steps_per_env} steps = {self.frames_per_batch}); lower it (e.g. ppo.minibatch_size="
                f"{quarter}: four mini-batches per epoch) or collect more (env.num_envs, ppo.steps_per_env)")

    def _changed_options(self, paths: tuple[str, ...]) -> list[str]:
        """The options of ``paths`` whose value is neither the field's default nor its preset's (``self.preset``):
        the ones a caller set. A preset's own values are not (``--preset robust --env.pushes.count 0`` keeps the
        robust preset's kick speeds, and sets none)."""
        default = RunConfig()
        changed = [path for path in paths if _get(self, path) != _get(default, path)]
        if changed and self.preset in PRESETS:  # the preset's tree only when needed: building it takes ~10 ms
            preset = preset_tree(self.preset)
            changed = [path for path in changed if _get(self, path) != _get(preset, path)]
        return changed


def schedule_past_budget(cfg: RunConfig) -> list[str]:
    """The env-step schedules of ``cfg`` that end past its budget (``total_env_steps``), one line each: the field,
    its value, the budget and what the run ends at; ``[]`` when every schedule ends within it (or acts not at all:
    no assist, no kicks).

    Not an error: a run may be trained in segments, each resumed with a larger ``total_env_steps``, and a schedule
    on env steps takes up where it was. The trainer warns with these lines at the run's start. The teacher's pull
    (``ppo.assist_anchor_decay`` after the fade) is not listed: a pull still decaying at the end is a choice (the
    robust preset's is at 0.33 of its weight at its budget), where an unfinished fade leaves a policy that never
    acted alone."""
    budget, ppo, found = cfg.total_env_steps, cfg.ppo, []
    if ppo.torque_assist > 0:
        fade = ppo.assist_fade_end - ppo.assist_fade_start  # > 0: validate() refuses an empty fade with an assist
        done = min(max((budget - ppo.assist_fade_start) / fade, 0.0), 1.0)
        ends = f"the run ends {100 * done:.0f} % through the fade, still assisted"
        for name, what, end in (("assist_fade_start", "the torque assist starts to fade", "the assist never fades"),
                                ("assist_fade_end", "the torque assist reaches 0, a pure torque policy", ends)):
            if (value := getattr(ppo, name)) > budget:
                found.append(f"ppo.{name} {value:,} (where {what}) is past total_env_steps {budget:,}: {end}")
    if cfg.env.pushes.count > 0:
        start, full = ppo.push_ramp
        # push_scale's rule (rl/trainer.py), read at the budget: full from ``full`` on, a step where start == full.
        if budget >= full:
            strength = 1.0
        else:
            strength = max(0.0, (budget - start) / (full - start)) if full > start else 0.0
        for index, what, end in ((0, "the kicks start", "the run ends without kicks"),
                                 (1, "the kicks reach full strength",
                                  f"the run ends with kicks at {100 * strength:.0f} % of their strength")):
            if (value := ppo.push_ramp[index]) > budget:
                found.append(f"ppo.push_ramp[{index}] {value:,} (where {what}) is past total_env_steps {budget:,}: "
                             f"{end}")
    return found


def schedule_warning(cfg: RunConfig) -> str | None:
    """The warning a run starts with when :func:`schedule_past_budget` finds schedules past its budget, with how to
    fix them; ``None`` when it finds none."""
    found = schedule_past_budget(cfg)
    if not found:
        return None
    return (f"the run's schedules end past its budget: {'; '.join(found)}. Lower them to at most total_env_steps "
            f"{cfg.total_env_steps:,}, or raise total_env_steps; ignore this if the run is to be resumed with a larger "
            "total_env_steps, where the schedules go on where they were")


#: Options that act only with kicks (``env.pushes.count`` > 0) and only with the torque assist
#: (``ppo.torque_assist`` > 0): :meth:`RunConfig.validate` refuses them set without.
KICK_OPTIONS = ("env.pushes.window", "env.pushes.speed", "env.pushes.duration", "env.pushes.kind",
                "env.pushes.calm_fraction", "ppo.push_ramp")
ASSIST_OPTIONS = ("ppo.assist_fade_start", "ppo.assist_fade_end", "ppo.assist_anchor_decay")
#: Options read under one learning-rate schedule or action-std mode only, as ``(switch, mode, paths)``:
#: :meth:`RunConfig.validate` refuses them set under another mode.
MODE_OPTIONS = (("ppo.lr_schedule", "linear", ("ppo.lr_end",)),
                ("ppo.lr_schedule", "adaptive", ("ppo.lr_min", "ppo.desired_kl", "ppo.assist_lr_hold",
                                                   "ppo.kl_adapt_every")),
                ("ppo.std_mode", "scheduled", ("ppo.std_end", "ppo.std_hold")))


class UnusedOptionError(ConfigError):
    """An option set where it changes nothing (:meth:`RunConfig.validate`): refused on a new run's command line, a
    warning for a saved run (``validate(allow_unused=True)``), which trained exactly as without it."""


def _unused(message: str, allow: bool) -> None:
    """Raise :class:`UnusedOptionError` with ``message``, or warn with it when ``allow``."""
    if not allow:
        raise UnusedOptionError(message)
    # One location for every reader of a saved config (checkpoint, resume, trainer): Python's default filter then says
    # it once per process, not once per reader.
    warnings.warn(f"the saved config sets an option that changes nothing; it is kept as saved (the run trains as "
                  f"without it, and a resume cannot change it): {message}", UserWarning, stacklevel=1)


def _get(tree: Any, path: str) -> Any:
    for name in path.split("."):
        tree = getattr(tree, name)
    return tree


def _check_int(obj: Any, name: str, low: int, prefix: str = "") -> None:
    value = getattr(obj, name)
    if isinstance(value, bool) or not isinstance(value, int) or value < low:
        kind = "a positive int" if low == 1 else f"an int >= {low}"
        raise ValueError(f"{prefix}{name} must be {kind}, got {value!r}")


#: The gait tests the end-of-training evaluation can run (``eval_test``; docs/evaluation.md).
EVAL_TESTS = GAIT_TESTS


def field_choices() -> dict[str, tuple[str, ...]]:
    """The allowed values of each option that takes one of a few names (checked by ``validate``, listed by
    ``--help``), by path."""
    from .transforms.layouts import OBS_LAYOUTS
    from .transforms.settings import HISTORIES, NORMALIZATIONS
    from .value_rules import PUSH_KINDS

    return {"env.pushes.kind": PUSH_KINDS, "transforms.normalization": NORMALIZATIONS,
            "ppo.lr_schedule": LR_SCHEDULES, "ppo.std_mode": STD_MODES, "env.control.mode": CONTROL_MODES,
            "env.control.upper_body": UPPER_BODY_LAWS,
            "ppo.value_loss": ("l2", "smooth_l1", "l1"), "transforms.history": tuple(HISTORIES),
            "transforms.observation": tuple(OBS_LAYOUTS),
            "ppo.activation": ("relu", "elu", "tanh", "silu"), "ppo.cuda_graph": ENV_GRAPH_MODES,
            "ppo.assist_target": ASSIST_TARGETS, "ppo.assist_lr_hold": ASSIST_LR_HOLDS,
            "ppo.kl_adapt_every": KL_ADAPT_MODES,
            "env.sim.backend": ("warp", "mujoco", "auto"),
            "env.sim.reset_pass": RESET_PASSES, "ppo.grad_sync": GRAD_SYNCS,
            "ppo.matmul_precision": MATMUL_PRECISIONS, "ppo.update_dtype": UPDATE_DTYPES, "eval_test": EVAL_TESTS,
            "ppo.symmetry": SYMMETRY_MODES}


def canonical_choices(cfg: RunConfig) -> RunConfig:
    """``cfg`` with each :func:`field_choices` value given in another case set to its listed spelling, in place
    (``Linear`` -> ``linear``), as ``ppo.cuda_graph`` always took any case: ``--ppo.lr_schedule Linear`` was refused
    while ``--ppo.cuda_graph OFF`` was taken. A value listed in no case is left for ``validate`` to refuse. The run
    config's (command line, :func:`preset_config`, saved configs) only: the env's own config (``TocabiWalkConfig``,
    ``TocabiWalk(control_mode=...)``) takes the listed spelling and refuses another, naming the choices."""
    for path, allowed in field_choices().items():
        *parents, name = path.split(".")
        owner = _get(cfg, ".".join(parents)) if parents else cfg
        value = getattr(owner, name)
        if isinstance(value, str) and value not in allowed and (listed := listed_spelling(value, allowed)):
            setattr(owner, name, listed)
    return cfg


# ---------------------------------------------------------------------------------------------------------- presets
#: Named presets: the paths each one changes from the defaults (the ``default`` preset). :func:`preset_tree` builds
#: the tree.
_TORQUE = {
    "env.control.mode": "torque", "ppo.torque_assist": 1.0, "ppo.assist_fade_start": 50_000_000,
    "ppo.assist_fade_end": 110_000_000, "ppo.assist_target": "teacher", "ppo.assist_anchor_decay": 30_000_000,
    "total_env_steps": 200_000_000,
}

# The robust recipe: torque control trained for the real robot, under the TOCABI lab's uncertainty model
# (randomize.tocabi_lab: motor constant, 2-10 ms torque delay, link masses, joint damping, armature, sensor biases and
# encoder noise, drawn per world at every reset), diverse starts (the robust gait test's start velocities) and pushes:
# sixteen velocity kicks per 32 s episode, each of 0.4-1.4 m/s within one 4 ms step, the test's kind of kick (every
# body's velocity changes alike; 40 % of them at 1.0 m/s or more): twice the fourth run's eight, so twice the recoveries
# to learn from per training minute, 1.9 s apart on average (the test's three: 1.7 s). (The third and fourth runs kicked
# the pelvis alone, 0.3-1.2 m/s over 4-200 ms and 0.3-1.3 m/s over 4-40 ms: the same momentum, but the limbs lag and the
# joints are kicked too; docs/training/robust/h200_run4.) The kicks ramp in from 10 M to 35 M env steps, while the legs
# are still PD residuals (β = 1), so that the frozen teacher the fade copies from (taken at its start, 60 M) already
# recovers from them; the assist then fades into pure torques from 60 M to 120 M. (The first run ramped four kicks in
# from 60 M to 120 M, during the fade and after the teacher was taken: its pure-torque policy fell every ~1,700 steps
# and did not walk in 24 minutes, docs/training/robust/h200_run1.) The adaptive learning rate is held until the
# teacher's pull has decayed (ppo.assist_lr_hold "pull"): the fourth run's fell to its 1e-5 floor as the fade ended and
# stayed there from 122 M to 149 M env steps. The assist's PD reads the joint positions the policy senses
# (ppo.assist_pd_sensed): in the fifth run the assisted policy survived 0.75-0.80 of the test's 1.0 m/s kicks at β
# 0.93-0.39 and the pure-torque one 0.52-0.53, the fade's copy loss (0.9 at β 0.44, 148 at β 0: the torques 0.25 of the
# limits apart, RMS) the size of what the encoder biases make of the PD on true positions. The kicks reach full strength
# at 35 M env steps (the fifth run: 55 M), so the policy the fade copies from has trained on them for 25 M steps, not 5
# M. Left-right symmetry augmentation, for a gait without a sideways bias. An asymmetric critic
# (transforms/privileged.py): the policy's sensors are biased and noisy, the critic reads the true pelvis velocity,
# height, orientation and foot loads, so that a kicked or heavier robot's state is valued as such. For the test's drift,
# a heading-hold term (0.3·exp(-20·ψ²), ψ the pelvis yaw): the second run's pure-torque policy turned 0.29 rad on
# average in the test's 8 s, every robot to the same side, and drifted 0.74 m (p95), unseen by the pelvis-frame velocity
# term. For the test's changing commands, a command every 2 s (the test's rate; the default draws one per 8 s) and a
# sharper and heavier velocity-tracking term (1.5·exp(-8·‖v − cmd‖²); the reference's 0.3·exp(-3·‖v − cmd‖²) barely pays
# for the last 0.1 m/s: the shipped policies walk at 0.36-0.42 m/s when asked for 0.5, and the second run at 0.37 with
# 0.9·exp(-8·‖v − cmd‖²)). Verdict: the robust gait test (evaluation/robust.py).
_ROBUST = {
    **_TORQUE,
    **tocabi_lab_paths(),
    "env.command.resample_every": 500, "transforms.body_vel_scale": 8.0,
    "transforms.reward_weights.body_vel": 1.5, "transforms.heading_weight": 0.3,
    "env.pushes": PushConfig(count=16, window=(1.0, 31.0), speed=(0.4, 1.4), duration=(0.004, 0.004),
                             kind="velocity"),
    "ppo.assist_lr_hold": "pull", "ppo.assist_pd_sensed": True,
    "ppo.push_ramp": (10_000_000, 35_000_000),
    "ppo.assist_fade_start": 60_000_000, "ppo.assist_fade_end": 120_000_000,
    "ppo.symmetry": "augment", "ppo.critic_privileged": True,
    "env.task.start_joint_vel_std": 0.5, "env.task.start_base_vel_std": 0.1,
    # Each world's start velocities and dynamics from 16 drawn at build, so that resets keep the reduced pass
    # (env.sim.start_pool; the full pass took 1.15 ms a step more at 4,096 envs on an H100, docs/benchmarks.md;
    # the fourth run, with the pool, trained at 117,215 env steps/s, the third, without, at 110,263, both on one
    # H200); a run meets 65,536 robots.
    "env.sim.start_pool": 16,
    # The sixth run (these settings without the two below) passed nominal, commands and robust_0.5 and kept 0.693
    # under 1.0 m/s kicks (docs/training/robust/h200_run6): its robots survived a lone 1.0 m/s kick and fell on
    # a fifth of the kicks that came within 2 s of the previous one, a second after the kick on average, and its
    # learning rate sat at the 1e-5 floor for the last seven minutes. The seventh run relaxed the clocked and
    # smoothness terms for 1.5 s after a kick (transforms.kick_relax) and fell 1.7-1.8x as often in training, 0.44
    # under the test's 1.0 m/s kicks at 18 minutes against the sixth's 0.84 (docs/training/robust/h200_run7):
    # the relaxation takes reward from the recovering robot, so surviving a kick is worth less. So no relaxation;
    # instead a longer horizon: at gamma 0.995 (0.8 s) a fall 1 s after a kick weighs 0.29 of its cost and the
    # next kick, 1-2 s on, is nearly out of sight; at 0.997 (1.3 s) 0.47. The adaptive rate keeps at least 5e-5
    # (ppo.lr_min).
    "ppo.gamma": 0.997, "ppo.lr_min": 5e-5,
    # The eighth run (these settings without the two below) was best at 18 minutes, while the teacher still pulled
    # (0.827 under the test's 1.0 m/s kicks at 1,024 robots, commands and robust_0.5 passing), and worse from 20
    # minutes on, once its pull (30 M env steps after the fade) had gone: PPO alone let the velocity-tracking
    # term fall from 0.74-0.76 to 0.61-0.65 per step, and the robots walked too fast, drifted and fell more
    # (docs/training/robust/h200_run8). So the pull decays over 90 M env steps: 0.78 at 140 M, 0.11 at the
    # budget's 200 M. Half of that run's falls under the 1.0 m/s kicks were the feet touching (a
    # self-collision), so a foot-gap term (transforms.foot_gap_weight, reward_terms.FootGap) pays for keeping
    # the feet at least 0.24 m apart across the heading, where the reference walk keeps 0.25 m.
    "ppo.assist_anchor_decay": 90_000_000, "transforms.foot_gap_weight": 0.3,
    # Its verdict at the end of training: the robust gait test at its own size (1,024 robots per case).
    "eval_test": "robust", "eval_envs": 1024,
    # 16,384 robots, so that the randomisation costs under 5 % of the training rate: at 4,096 the torque delay
    # (a world's delayed torque jumps in some substep, and every world iterates until the slowest converges)
    # cost 7.3 % (0.927x); at 16,384, with the delay on a 1 ms grid (env.control.actuators.delay_stride 2:
    # 2-10 ms in 1 ms steps), 1.9 % (0.981x, docs/benchmarks/randomization/envs_16k). 12 steps per env keep
    # the 4,096-robot run's PPO iterations per env step (196,608 samples per update). Two runs at 16,384 with the
    # rate rules of 4,096 fell 4-20x as often per env step as run 9 (docs/training/robust/h100_run21,
    # h200_run22): their KL-adaptive rate sat 2-4x below run 9's. A KL target of 0.02 keeps it up, and the held
    # rate is bounded at run 9's 7.5e-5 while the teacher pulls; the twenty-third run passed the robust gait test
    # from its 13-minute mark (docs/training/robust/h100_run23).
    "env.num_envs": 16_384, "env.control.actuators.delay_stride": 2, "ppo.steps_per_env": 12,
    "ppo.desired_kl": 0.02, "ppo.assist_lr_max": 7.5e-5,
}

#: The robust recipe without the torque assist: every assist option at its default (off), for control laws that
#: carry their own prior (model_based's feed-forward law).
_ROBUST_NO_ASSIST = {path: value for path, value in _ROBUST.items()
                     if path != "ppo.torque_assist" and not path.startswith("ppo.assist_")}

#: The robust recipe on the computed-torque law.
_MODEL_BASED = {
    **_ROBUST_NO_ASSIST, "env.control.mode": "model_based", "env.control.mb_residual_gain": MB_RESIDUAL_GAIN_PD,
    "ppo.matmul_precision": "high", "transforms.observation": "base_vel",
}

#: The robust recipe on held leg PD (the robot's PD law on its encoder-biased joints, its torque held for the step).
_PD = {
    **_ROBUST_NO_ASSIST, "env.control.mode": "pd_held", "ppo.matmul_precision": "high",
    "transforms.observation": "base_vel", "ppo.kl_adapt_every": "minibatch",
}

PRESETS: Mapping[str, Mapping[str, Any]] = MappingProxyType({
    # Residual imitation (pd_reference: leg servos with the robot's gains track the reference walk plus the policy's
    # correction), the velocity-tracking reward tripled (0.3 -> 0.9, so that following a 0.5 m/s command pays more
    # than replaying the 0.13 m/s walk): the defaults. Chosen from three 7.5-minute H100 runs (docs/training/).
    "default": MappingProxyType({}),
    # The reference training (spec §10: 8 envs × 2048 steps, mini-batch 128, 3 epochs, 256-256 ReLU, LR 1e-5 -> 2e-7
    # linear, value head at 5e-4, std 0.1 -> 0.05, 120 M steps), on the reference's task.
    "reference": MappingProxyType({
        "env.control.mode": "torque", "env.command": CommandConfig.reference(), "env.num_envs": 8,
        "transforms.reward_weights.body_vel": None, "total_env_steps": 120_000_000,
        "ppo.gamma": 0.99, "ppo.steps_per_env": 2048, "ppo.minibatch_size": 128, "ppo.epochs": 3,
        "ppo.lr": 1e-5, "ppo.lr_end": 2e-7, "ppo.lr_schedule": "linear", "ppo.value_head_lr": 5e-4,
        "ppo.adam_eps": 1e-5, "ppo.actor_hidden": (256, 256), "ppo.critic_hidden": (256, 256),
        "ppo.activation": "relu", "ppo.value_out_gain": 0.01, "ppo.value_coef": 0.5, "ppo.value_loss": "l2",
        "ppo.max_grad_norm": 0.5, "ppo.std_start": 0.1, "ppo.std_end": 0.05, "ppo.std_hold": 0.5,
    }),
    # The torque policy for the real robot: the robust recipe (above) with float32 matrix products in TF32 while it
    # trains (ppo.matmul_precision "high": the update's above all, and the rollout's networks; the simulator is
    # untouched), and the pelvis's linear and angular velocity in the policy's observation (transforms.observation
    # "base_vel"). Without the velocity its first from-scratch run (seed 0) stood and tracked its commands but walked
    # sideways after the diverse starts, drift p95 0.46-0.63 m at 12-15 minutes against the test's 0.30 m
    # (docs/training/torque/h100_seed0); with it, the same seed passed from its 11-minute mark, drift p95 0.08-0.11 m
    # (docs/training/torque/h100_base_vel_seed0), and seed 1 from its 11.5-minute mark (h100_base_vel_seed1).
    # Verdict: the robust gait test's diverse-start nominal and commands cases (evaluation/robust.py;
    # docs/training.md).
    "torque": MappingProxyType({**_ROBUST, "ppo.matmul_precision": "high", "transforms.observation": "base_vel"}),
    # The robust recipe in full float32, as the runs of docs/training/robust/ trained: the twenty-third passed the
    # robust gait test's nominal and commands cases at its 12-minute mark (the first it tested) and every case from
    # its 13-minute mark (docs/training/robust/h100_run23).
    "robust": MappingProxyType(_ROBUST),
    # The torque preset of before the uncertainty model, on a perfect robot (no randomisation, noise, delay or kicks).
    # The reference's action space (12 normalised leg torques + phase rate) learned from scratch on one GPU: the
    # default's PPO on an assisted torque env whose leg actions start as the residual-PD preset's position residuals
    # (β = 1 for 50 M steps) and morph into torques by 110 M (geometric in the action gain, learning rate held), a
    # loss moving each step of the morph into the actor (rl/assist.py); the rest trains the pure torque policy.
    # Without the assist, PPO at thousands of envs learned to stand (issue 19); docs/training.md has the runs.
    # The pull copies a frozen β = 1 teacher (DAgger) and fades out over 30 M steps after the fade. Run 5 of
    # docs/training.md: walks at 24.0 min of training on an H100 (178.7 M steps). A teacher taken at 75 M
    # (run 6) went faster (3.3-3.4 m in the 8 s test) but drifted 0.30-0.34 m, just past the limit, to its end.
    "torque_ideal": MappingProxyType(_TORQUE),
    # The model-based policy for the real robot: the robust recipe (randomisation, sensor noise, kicks ramped in from
    # 10 M to 35 M env steps, mirror augmentation, the privileged critic, the heading and foot-gap terms, 16,384 envs)
    # on the computed-torque law with the PD-authority residual gain (model_based_ideal, below), without the torque
    # assist (the feed-forward law is the prior), with TF32 and the pelvis velocity observed as in the torque preset.
    # Its first from-scratch run (seed 0, H100) passed the robust gait test's diverse-start nominal and commands cases
    # at its 7- to 10.5-minute marks, the ones it kept (docs/training/model_based/h100_robust_seed0).
    "model_based": MappingProxyType(_MODEL_BASED),
    # The PD policy for the real robot: the robust recipe (as the model_based preset, above) in the default preset's
    # action space, the reference walk plus 0.5 rad x the action as the legs' PD targets, with the PD run as on the
    # robot (env.control.mode "pd_held", control/torque.py): once per 4 ms step, from the true joint positions plus
    # each world's encoder bias (no encoder noise) and the true joint velocities, its torque held for the step and
    # passed through the actuator model (2-10 ms delay, motor constant 0.8-1.2), where the default preset's servos act
    # inside every physics substep on the true joints (env.control.mode "pd", a servo about the nominal pose, is
    # another law). No torque assist: the reference walk is the prior. The KL-adaptive learning rate acts before every
    # mini-batch (ppo.kl_adapt_every "minibatch", rsl_rl's rule): with the rule once per iteration the first run in
    # this mode broke in one update at 7 M env steps (KL 6,933 at a rate of 3.4e-3,
    # docs/training/default/h100_robust_pd_held_run3). Its first from-scratch run with the rule (seed 0, H100) passed
    # the robust gait test's diverse-start nominal and commands cases at each of its 4- to 6-minute marks
    # (docs/training/pd/h100_seed0). The per-mini-batch rule trains on one GPU (each rank's rate would follow its own
    # KL): for several, set ppo.kl_adapt_every "iteration".
    "pd": MappingProxyType(_PD),
    # The model_based preset of before the uncertainty model, on a perfect robot (no randomisation, noise, delay or
    # kicks). Residual torque on a computed-torque law (env.control.mode "model_based", envs/model_based.py): the 12
    # leg actions add g·a to τ_ff = M_LL·(q̈_ref + ω²·(q_ref − q) + 2ζω·(q̇_ref − q̇)) + c_L from the simulator's own
    # inertia and bias forces. The default's PPO, unchanged; no torque assist: the feed-forward law is itself the
    # prior, and never fades. The budget is torque_ideal's. The residual gain g is the PD-residual modes' authority
    # (0.5 rad × the robot's Kp, 3-11× the torque limits), the action space the default preset and torque_ideal's
    # β = 1 phase learn to walk in: with g = the limits, H100 run 1 (std 0.2 -> 0.05) did not walk in its 24 minutes
    # and run 2 (std 0.1 -> 0.05, less exploration still) fell within 8 s at every checkpoint (docs/training.md).
    "model_based_ideal": MappingProxyType({
        "env.control.mode": "model_based", "env.control.mb_residual_gain": MB_RESIDUAL_GAIN_PD,
        "total_env_steps": 200_000_000,
    }),
    # What a CPU-only machine can run in a minute or two: proves the whole pipeline, learns nothing useful.
    "cpu_smoke": MappingProxyType({
        "env.num_envs": 8, "ppo.steps_per_env": 16, "ppo.minibatch_size": 64, "ppo.epochs": 2,
        "total_env_steps": 8 * 16 * 3, "checkpoint_every": 1, "eval_envs": 2, "eval_seconds": 1.0,
        "ppo.actor_hidden": (64, 64), "ppo.critic_hidden": (64, 64),
    }),
})


#: Presets renamed since runs of theirs were recorded: the name then -> (the first date, ISO, on which it named
#: another recipe, its name now). For reading records written before (benchmark pages, the library table). A run of
#: this package's trainer saves its whole config tree, so resuming or playing one never reads its preset's name; the
#: other libraries' recipes (recipes/train_*.py) save the name alone. A date is a day: a run recorded on the rename's
#: day counts as one of after it.
RENAMED_PRESETS: Mapping[str, tuple[str, str]] = MappingProxyType({
    "torque": ("2026-12-06", "torque_ideal"), "model_based": ("2026-12-06", "model_based_ideal"),
})


def preset_now(name: str, date: str) -> str:
    """The name now of the preset a run recorded as ``name`` on ``date`` (ISO, ``YYYY-MM-DD``) trained.

    >>> preset_now("torque", "2026-11-27"), preset_now("torque", "2026-12-07"), preset_now("default", "2026-11-27")
    ('torque_ideal', 'torque', 'default')
    """
    since, now = RENAMED_PRESETS.get(name, ("", name))
    return now if date < since else name


def preset_tree(name: str) -> RunConfig:
    """The named preset as a tree (not validated: see :func:`preset_config`)."""
    if name not in PRESETS:
        raise ValueError(f"unknown preset {name!r}; choose one of {sorted(PRESETS)}")
    return replace_paths(RunConfig(preset=name), dict(PRESETS[name]))


def preset_config(name: str, /, **overrides) -> RunConfig:
    """The named preset with ``overrides`` applied and validated. Keys are dotted paths (``**{"ppo.lr": 3e-4}``;
    top-level options also as keywords, ``seed=1``); a ``preset`` key is ignored. Raises :class:`ConfigError` naming
    an unknown key (with the nearest paths), ``ValueError`` for a bad value."""
    overrides.pop("preset", None)
    return replace_paths(preset_tree(name), _known_paths(overrides)).validated()


def _known_paths(values: Mapping[str, Any]) -> dict[str, Any]:
    """``values`` as given, after checking every key names a leaf or a section of the tree; raises
    :class:`ConfigError` naming an unknown key and the nearest paths."""
    paths = set(leaf_paths(RunConfig()))
    for key in values:
        if key in paths or key.split(".")[0] in ("env", "transforms", "ppo", "viewer"):
            continue  # a path, or a whole section; replace_paths names an unknown one
        # The nearest paths, by the whole path or by its last name (num_envs -> env.num_envs, gama -> ppo.gamma).
        names = set(difflib.get_close_matches(key, sorted({p.rsplit(".", 1)[-1] for p in paths}), n=3, cutoff=0.75))
        near = sorted({p for p in paths if p.rsplit(".", 1)[-1] in names}
                      | set(difflib.get_close_matches(key, sorted(paths), n=3, cutoff=0.75)))
        raise ConfigError(f"unknown config option {key!r}"
                          + (f"; did you mean {near}?" if near else "; options are dotted paths such as 'ppo.lr', "
                             "'env.num_envs', 'env.control.mode' (see recipes/ppo_walk.py --help)"), unknown=[key])
    return dict(values)


def to_dict(cfg: RunConfig) -> dict[str, Any]:
    """``cfg`` as nested dicts of plain values."""
    return _tree_to_dict(cfg)


def _renamed(data: Mapping[str, Any]) -> dict[str, Any]:
    """A saved tree with the two options renamed since it was written, in their new form: ``transforms.preset``
    (the observation-history layout) is ``transforms.history``, and ``transforms.reward_weights``, once
    ``"term=weight"`` entries, is one weight per term. This is the loader's one rename step; the shipped policies
    are saved in the current form. Raises :class:`ConfigError` for the flat ``PPOConfig`` dict of before the tree."""
    if not isinstance(data.get("ppo"), Mapping):
        raise ConfigError("the saved config is the flat PPOConfig of before the run config tree (it has no 'ppo' "
                          "section, checkpoint schema 0 or 1), which this version no longer reads: convert it with a "
                          "version of tocabi-torchrl from before 2026-12-02, whose config_from_dict migrates it "
                          "(save its RunConfig.to_dict() as the checkpoint's config), or retrain", unknown=[])
    transforms = data.get("transforms")
    if not isinstance(transforms, Mapping) or not ("preset" in transforms or isinstance(
            transforms.get("reward_weights"), (list, tuple))):
        return dict(data)
    transforms = dict(transforms)
    if "preset" in transforms:
        if "history" in transforms:
            raise ConfigError("the saved config has both transforms.preset and transforms.history (the first is the "
                              "old name of the second); keep one", unknown=["transforms.preset"])
        transforms["history"] = transforms.pop("preset")
    if isinstance(transforms.get("reward_weights"), (list, tuple)):
        weights = {}
        for entry in transforms["reward_weights"]:
            name, sep, value = str(entry).partition("=")
            try:
                weights[name] = float(value) if sep else None
            except ValueError:
                weights[name] = None
            if weights[name] is None:
                raise ConfigError(f"transforms.reward_weights entry {entry!r} of the saved config must look like "
                                  f"'body_vel=0.9'")
        # An empty list meant the reference weights: every term None, body_vel's default of 0.9 included.
        transforms["reward_weights"] = {"body_vel": None, **weights}
    return {**data, "transforms": transforms}


#: Fields whose default changed after files were saved without them: such a file gets the value it ran with, not
#: today's default (the reduced reset pass became the env's default on 2026-11-28; every file without the field ran
#: the full pass).
LEGACY_VALUES: Mapping[str, Any] = MappingProxyType({"env.sim.reset_pass": "full"})


def config_from_dict(data: Mapping[str, Any]) -> RunConfig:
    """The :class:`RunConfig` a checkpoint or ``config.json`` saved (fields it lacks take their defaults, except
    :data:`LEGACY_VALUES`; options renamed since, by :func:`_renamed`). Not validated; raises :class:`ConfigError`
    naming an unknown key."""
    data = _renamed({k: v for k, v in data.items() if k != "schema_version"})  # config.json carries it beside them
    cfg, saved = _tree_from_dict(RunConfig, data), {path for path in LEGACY_VALUES if _has_path(data, path)}
    missing = {path: value for path, value in LEGACY_VALUES.items() if path not in saved}
    return replace_paths(cfg, missing) if missing else cfg


def _has_path(tree: Mapping[str, Any], path: str) -> bool:
    """Whether the nested dict ``tree`` holds the dotted ``path``."""
    for key in path.split("."):
        if not isinstance(tree, Mapping) or key not in tree:
            return False
        tree = tree[key]
    return True
