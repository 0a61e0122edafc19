"""Reward terms: one small class per reference reward component (spec §8).

A term is called as ``term(td, next_td) -> (num_envs, 1)`` float32 and returns ``weight · kernel``: ``td`` holds the
signals at time t (the root tensordict: after the previous step, or the reset state) and ``next_td`` those at t+1,
so differences over one policy step (force jump, action change, joint-velocity change) need no hidden state.
Each reference term's ``weight`` defaults to the reference maximum (e.g. 0.3 for ``0.3·exp(-13.2·|θ|)``) and each
kernel is in [0, 1] (the penalties' kernels are 0/1 indicators with negative weights), so re-weighting is a config
change. Norms follow the reference exactly (spec §13.10-11): the torque and contact-force terms use plain
(not squared) L2 norms, qpos/qvel/qacc/body_vel use squared norms, qacc is the velocity change per policy step.

Write your own term by subclassing :class:`RewardTerm` (set ``name``, ``weight``, implement :meth:`kernel`) or by
wrapping a function ``fn(td, next_td) -> (num_envs, 1)`` with :class:`CallableTerm`.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass, field
from types import MappingProxyType

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey

from tocabi_torchrl import robot
from tocabi_torchrl.rotations import quat_rotation_angle
from tocabi_torchrl.signals import SIGNALS
from tocabi_torchrl.transforms._checks import check_finite, check_positive

__all__ = [
    "RewardTerm",
    "CallableTerm",
    "NeckOrientation",
    "JointPosTracking",
    "JointVelRegulation",
    "BodyVelTracking",
    "ContactForce",
    "TorqueRegulation",
    "TorqueDiffRegulation",
    "JointAccRegulation",
    "FootContactPattern",
    "ContactForceDiff",
    "ForceReference",
    "ForceThresholdPenalty",
    "ForceDiffThresholdPenalty",
    "HeadingHold",
    "CycleVelTracking",
    "FootGap",
    "feet_apart_across_heading",
    "check_term",
    "REFERENCE_TERMS",
    "SIGNAL_SHAPES",
    "reference_terms",
]

#: Body weight m·g [N] of the nominal robot, the scale of the force penalties.
_BODY_WEIGHT = robot.NOMINAL_MASS * robot.GRAVITY
#: The reference scales every leg action by the first joint's limit (333 N·m), not by its own limit (spec §13.10).
_REFERENCE_TORQUE_SCALE = float(robot.LEG_TORQUE_LIMITS[0])

class RewardTerm:
    """Base class: ``term(td, next_td) = weight · kernel(td, next_td)``, shape (num_envs, 1) float32.

    Subclasses define ``name`` (the ``("reward_terms", name)`` key), ``weight`` and :meth:`kernel`, and list the keys
    they read in ``root_keys`` (time t, from ``td``) and ``next_keys`` (time t+1) so a missing signal is reported
    when the env is built rather than mid-rollout.
    """

    name: str
    weight: float
    root_keys: tuple[NestedKey, ...] = ()
    next_keys: tuple[NestedKey, ...] = ()

    def kernel(self, td: TensorDictBase, next_td: TensorDictBase) -> torch.Tensor:
        """The unweighted term, (num_envs, 1) float32, from ``td`` (the state an action was applied to, time t) and
        ``next_td`` (the step's output, time t+1); override it in a subclass. Keep it branch-free tensor code on the
        env's device: on CUDA it runs inside the captured step graph."""
        raise NotImplementedError

    def __call__(self, td: TensorDictBase, next_td: TensorDictBase) -> torch.Tensor:
        return self.weight * self.kernel(td, next_td)

    def __post_init__(self):
        # Shared by every dataclass term: validate the name and weight, and the positive scales a term declares.
        self._check()
        if hasattr(self, "scale"):
            self.scale = _scale(self.scale, f"{self.name} scale")
        if hasattr(self, "torque_scale"):
            self.torque_scale = _torque_scale(self.torque_scale, self.name)

    def _check(self) -> None:
        self.weight = check_term(self)


def check_term(term: RewardTerm) -> float:
    """``term``'s weight as a float, after checking its name, weight, kernel and keys; raises naming the fix.

    A dataclass term runs it when made; :class:`~.reward.TaskReward` runs it on every term it gets, since a plain
    subclass (class attributes, no ``__post_init__``) gets no other check: a NaN weight made every reward NaN without a
    word, and a missing name or kernel surfaced at the first step as a bare ``AttributeError`` or
    ``NotImplementedError``."""
    kind = type(term).__name__
    name = getattr(term, "name", None)
    if not isinstance(name, str) or not name:
        raise ValueError(f"{kind}: name must be a non-empty string (the ('reward_terms', name) key), got {name!r}")
    if "/" in name or "\\" in name or name.startswith("."):
        # The name is also a file name: metrics/scalars/reward_terms/<name>.csv ("a/b" wrote into a subfolder).
        raise ValueError(f"{kind}: name {name!r} names the term's metrics file too: use no '/', '\\' or leading '.'")
    weight = check_finite(getattr(term, "weight", None), f"reward term {name!r} weight")
    if type(term).kernel is RewardTerm.kernel:
        # TaskReward calls kernel and applies the weights itself (one multiply for all terms): __call__ is not used.
        raise TypeError(f"reward term {name!r} ({kind}) does not implement kernel(td, next_td); override kernel, "
                        "which returns the unweighted (num_envs, 1) value")
    for attr in ("root_keys", "next_keys"):
        keys = getattr(term, attr, ())
        if isinstance(keys, str) or not isinstance(keys, (tuple, list)):  # a str would be read as its letters
            raise TypeError(f"reward term {name!r} {attr} must be a tuple of keys, e.g. ('base_pos',), got {keys!r}")
    return weight


def _scale(value: float, what: str) -> float:
    return check_positive(value, what)


@dataclass
class CallableTerm(RewardTerm):
    """Wrap ``fn(td, next_td) -> (num_envs, 1)`` as a term: ``weight · fn(td, next_td)``.

    Example: ``CallableTerm("alive", lambda td, nxt: torch.ones_like(nxt["reward"]), weight=0.1)``.
    """

    name: str
    fn: Callable[[TensorDictBase, TensorDictBase], torch.Tensor]
    weight: float = 1.0
    root_keys: tuple = ()
    next_keys: tuple = ()

    def __post_init__(self):
        if not callable(self.fn):
            raise TypeError(f"CallableTerm {self.name!r}: fn must be callable, got {self.fn!r}")
        self._check()

    def kernel(self, td, next_td):
        return self.fn(td, next_td)


@dataclass
class NeckOrientation(RewardTerm):
    """Reference ``mimic_body_orientation_reward``: ``weight · exp(-scale · |θ_neck|)``.

    θ_neck (rad) is the rotation angle of the Neck_Link world quaternion ``next["neck_quat"]`` (num_envs, 4) from
    identity, yaw included (pyquaternion's angle).
    """

    name: str = "orientation"
    weight: float = 0.3
    scale: float = 13.2
    next_keys: tuple = field(default=("neck_quat",), init=False, repr=False)

    def kernel(self, td, next_td):
        return torch.exp(-self.scale * quat_rotation_angle(next_td.get("neck_quat")))


@dataclass
class JointPosTracking(RewardTerm):
    """Reference ``qpos_regulation``: ``weight · exp(-scale · ‖q_ref - q‖²)`` over all 33 joints.

    ``q = next["joint_pos"]`` (post-step), ``q_ref = next["ref_joint_pos"]`` (the targets of the pre-step time), rad.
    """

    name: str = "qpos"
    weight: float = 0.35
    scale: float = 4.0
    next_keys: tuple = field(default=("joint_pos", "ref_joint_pos"), init=False, repr=False)

    def kernel(self, td, next_td):
        err = next_td.get("ref_joint_pos") - next_td.get("joint_pos")
        return torch.exp(-self.scale * err.square().sum(-1, keepdim=True))


@dataclass
class JointVelRegulation(RewardTerm):
    """Reference ``qvel_regulation``: ``weight · exp(-scale · ‖q̇‖²)`` over all 33 joints, q̇ in rad/s."""

    name: str = "qvel"
    weight: float = 0.05
    scale: float = 0.01
    next_keys: tuple = field(default=("joint_vel",), init=False, repr=False)

    def kernel(self, td, next_td):
        return torch.exp(-self.scale * next_td.get("joint_vel").square().sum(-1, keepdim=True))


@dataclass
class BodyVelTracking(RewardTerm):
    """Reference ``body_vel_reward``: ``weight · exp(-scale · ‖v_xy - cmd‖²)``.

    ``v_xy = next["base_lin_vel"][..., :2]`` (pelvis-frame linear velocity, m/s), ``cmd = next["command"]`` (m/s).
    """

    name: str = "body_vel"
    weight: float = 0.3
    scale: float = 3.0
    next_keys: tuple = field(default=("base_lin_vel", "command"), init=False, repr=False)

    def kernel(self, td, next_td):
        err = next_td.get("base_lin_vel")[..., :2] - next_td.get("command")
        return torch.exp(-self.scale * err.square().sum(-1, keepdim=True))


@dataclass
class HeadingHold(RewardTerm):
    """Not a reference term: ``weight · exp(-scale · ψ²)``, ψ = ``next["base_rpy"][..., 2]`` the pelvis yaw [rad].

    Every episode starts facing the world's +x (ψ = 0) and the command is meant in the heading frame, so ψ is how far
    the robot has turned from the way it was sent. ``body_vel`` tracks the command in the pelvis frame and is blind to
    a slow turn; a policy that turns 0.3 rad in 8 s while walking at 0.5 m/s ends ~0.6 m to the side, which the gait
    tests measure as drift. The weight defaults to 0 (off); ``transforms.heading_weight`` and
    ``transforms.heading_scale`` set it in the run config.
    """

    name: str = "heading"
    weight: float = 0.0
    scale: float = 20.0
    next_keys: tuple = field(default=("base_rpy",), init=False, repr=False)

    def kernel(self, td, next_td):
        return torch.exp(-self.scale * next_td.get("base_rpy")[..., 2:3].square())


@dataclass
class CycleVelTracking(RewardTerm):
    """Not a reference term: ``weight · exp(-scale · ‖ē‖²)``, ē = ``next["cycle_vel_error"]`` (num_envs, 2) [m/s],
    the heading-frame pelvis velocity minus the command averaged over the world's last gait cycle (the env's
    ``env.task.cycle_velocity``; envs/cycle_velocity.py).

    ``body_vel`` reads the instantaneous velocity, whose error is mostly the gait's own sway and surge; a sideways
    walk of 0.02 m/s, 0.16 m of drift in the gait tests' 8 s, changes it by a fraction of a percent. Averaged over a
    cycle the rhythm cancels, and this term pays for the average itself, the quantity the robust gait test's
    tracking error reads. The weight defaults to 0 (off); ``transforms.cycle_vel_weight`` and
    ``transforms.cycle_vel_scale`` set it in the run config.

    >>> import torch
    >>> from tensordict import TensorDict
    >>> nxt = TensorDict({"cycle_vel_error": torch.tensor([[0.0, 0.0], [0.0, 0.1], [0.06, -0.08]])}, [3])
    >>> [round(k, 4) for k in CycleVelTracking(weight=1.0).kernel(None, nxt).squeeze(-1).tolist()]
    [1.0, 0.3679, 0.3679]
    """

    name: str = "cycle_vel"
    weight: float = 0.0
    scale: float = 100.0
    next_keys: tuple = field(default=("cycle_vel_error",), init=False, repr=False)

    def kernel(self, td, next_td):
        return torch.exp(-self.scale * next_td.get("cycle_vel_error").square().sum(-1, keepdim=True))


@dataclass
class FootGap(RewardTerm):
    """Not a reference term: ``weight · exp(-(max(min_gap − d, 0) / width)²)``, d the left foot's sideways offset
    from the right [m] in the pelvis heading frame (the world's horizontal plane turned by the pelvis yaw ψ):
    ``d = (p_L − p_R)·(−sin ψ, cos ψ)``, p = ``next["foot_pos"]`` (num_envs, 2, 3) the ``Foot_Link`` origins.

    The task ends an episode when the feet touch (a self-collision, spec §9.1). The reference walk keeps the origins
    0.25 m apart; the soles are 0.17 m wide and sit 0.145 m below the origins, so tilted feet touch well before the
    origins are 0.17 m apart, and crossed feet have d < 0. The termination alone pays for touching only through the
    lost future; this term pays at every step for a margin, fully from ``min_gap`` on (the robots start standing
    0.205 m apart, where the default pays 0.61 of it: a first step outwards earns the rest). The weight defaults to 0
    (off); ``transforms.foot_gap_weight`` and ``transforms.foot_gap_min`` set it in the run config.

    >>> import torch
    >>> from tensordict import TensorDict
    >>> feet = torch.tensor([[[0.0, 0.125, 0.1], [0.0, -0.125, 0.1]], [[0.0, 0.075, 0.1], [0.0, -0.075, 0.1]]])
    >>> nxt = TensorDict({"foot_pos": feet, "base_rpy": torch.zeros(2, 3)}, [2])
    >>> [round(k, 4) for k in FootGap(weight=1.0).kernel(None, nxt).squeeze(-1).tolist()]  # 0.25 m; 0.15 m: e^-3.24
    [1.0, 0.0392]
    """

    name: str = "foot_gap"
    weight: float = 0.0
    min_gap: float = 0.24
    width: float = 0.05
    next_keys: tuple = field(default=("foot_pos", "base_rpy"), init=False, repr=False)

    def __post_init__(self):
        super().__post_init__()
        self.min_gap = check_positive(self.min_gap, f"{self.name} min_gap [m]")
        self.width = check_positive(self.width, f"{self.name} width [m]")

    def kernel(self, td, next_td):
        d = feet_apart_across_heading(next_td.get("foot_pos"), next_td.get("base_rpy")[..., 2:3])
        short = (self.min_gap - d).clamp_min(0.0) / self.width
        return torch.exp(-short.square())


def feet_apart_across_heading(foot_pos: torch.Tensor, yaw: torch.Tensor) -> torch.Tensor:
    """(…, 1) [m] the left foot's offset from the right across the heading, ``(p_L − p_R)·(−sin ψ, cos ψ)``, from
    ``foot_pos`` (…, 2, 3) [m] (world frame, [left, right]) and the pelvis yaw ``yaw`` (…, 1) [rad]; negative when
    the feet are crossed (:class:`FootGap`)."""
    apart = foot_pos[..., 0, :2] - foot_pos[..., 1, :2]  # left minus right, world horizontal plane
    return apart[..., 1:2] * torch.cos(yaw) - apart[..., 0:1] * torch.sin(yaw)


@dataclass
class ContactForce(RewardTerm):
    """Reference ``contact_force_penalty`` (a positive term): ``weight · exp(-scale · (‖F_L‖ + ‖F_R‖))``.

    F = ``next["foot_force"]`` (num_envs, 2, 3) in N; 3-D norms, not squared.
    """

    name: str = "contact_force"
    weight: float = 0.1
    scale: float = 0.0005
    next_keys: tuple = field(default=("foot_force",), init=False, repr=False)

    def kernel(self, td, next_td):
        norms = torch.linalg.vector_norm(next_td.get("foot_force"), dim=-1)  # (N, 2)
        return torch.exp(-self.scale * norms.sum(-1, keepdim=True))


@dataclass
class TorqueRegulation(RewardTerm):
    """Reference ``torque_regulation``: ``weight · exp(-scale · ‖torque_scale · a[0:12]‖)``.

    a = ``next["applied_action"]`` (raw clipped action); every leg action is scaled by 333 N·m (the reference's
    quirk, spec §13.10); plain L2 norm, not squared. ``torque_scale`` may also be a 12-sequence of per-joint limits.
    """

    name: str = "torque"
    weight: float = 0.05
    scale: float = 0.01
    torque_scale: float | tuple = _REFERENCE_TORQUE_SCALE
    next_keys: tuple = field(default=("applied_action",), init=False, repr=False)

    def kernel(self, td, next_td):
        tau = _apply_torque_scale(next_td.get("applied_action")[..., robot.LEGS], self.torque_scale)
        return torch.exp(-self.scale * torch.linalg.vector_norm(tau, dim=-1, keepdim=True))


@dataclass
class TorqueDiffRegulation(RewardTerm):
    """Reference ``torque_diff_regulation``: ``weight · exp(-scale · ‖torque_scale · (a - a⁻)[0:12]‖)``.

    a = ``next["applied_action"]``, a⁻ = ``td["applied_action"]`` (previous step's action; zeros after a reset).
    """

    name: str = "torque_diff"
    weight: float = 0.6
    scale: float = 0.01
    torque_scale: float | tuple = _REFERENCE_TORQUE_SCALE
    root_keys: tuple = field(default=("applied_action",), init=False, repr=False)
    next_keys: tuple = field(default=("applied_action",), init=False, repr=False)

    def kernel(self, td, next_td):
        da = next_td.get("applied_action")[..., robot.LEGS] - td.get("applied_action")[..., robot.LEGS]
        tau = _apply_torque_scale(da, self.torque_scale)
        return torch.exp(-self.scale * torch.linalg.vector_norm(tau, dim=-1, keepdim=True))


@dataclass
class JointAccRegulation(RewardTerm):
    """Reference ``qacc_regulation``: ``weight · exp(-scale · ‖q̇ - q̇⁻‖²)`` over all 33 joints.

    The velocity change over one policy step (rad/s), not divided by dt: q̇ = ``next["joint_vel"]``,
    q̇⁻ = ``td["joint_vel"]``.
    """

    name: str = "qacc"
    weight: float = 0.05
    scale: float = 20.0
    root_keys: tuple = field(default=("joint_vel",), init=False, repr=False)
    next_keys: tuple = field(default=("joint_vel",), init=False, repr=False)

    def kernel(self, td, next_td):
        dv = next_td.get("joint_vel") - td.get("joint_vel")
        return torch.exp(-self.scale * dv.square().sum(-1, keepdim=True))


@dataclass
class FootContactPattern(RewardTerm):
    """Reference ``foot_contact_reward``: ``weight`` if the feet touching the ground match the expected pattern.

    ``next["stance"]`` (num_envs, 1) int: 0 double support: both feet; 1 right stance: right and not left;
    2 left stance: left and not right. ``next["foot_contact"]`` (num_envs, 2) bool, [left, right].
    """

    name: str = "foot_contact"
    weight: float = 0.2
    next_keys: tuple = field(default=("stance", "foot_contact"), init=False, repr=False)

    def kernel(self, td, next_td):
        contact = next_td.get("foot_contact").to(torch.bool)
        left, right = contact[..., 0:1], contact[..., 1:2]
        stance = next_td.get("stance")
        match = torch.where(
            stance == 0, left & right, torch.where(stance == 1, right & ~left, left & ~right)
        )
        return match.to(torch.float32)


@dataclass
class ContactForceDiff(RewardTerm):
    """Reference ``contact_force_diff_regulation``: ``weight · exp(-scale · (‖F_L - F_L⁻‖ + ‖F_R - F_R⁻‖))``.

    F = ``next["foot_force"]``, F⁻ = ``td["foot_force"]`` (num_envs, 2, 3), N; 3-D norms, not squared.
    """

    name: str = "contact_force_diff"
    weight: float = 0.2
    scale: float = 0.01
    root_keys: tuple = field(default=("foot_force",), init=False, repr=False)
    next_keys: tuple = field(default=("foot_force",), init=False, repr=False)

    def kernel(self, td, next_td):
        df = next_td.get("foot_force") - td.get("foot_force")
        return torch.exp(-self.scale * torch.linalg.vector_norm(df, dim=-1).sum(-1, keepdim=True))


@dataclass
class ForceReference(RewardTerm):
    """Reference ``force_ref_reward`` (2 × 0.1): ``weight · mean over feet of exp(-scale · |F_z - w · F_ref|)``.

    The reference writes ``0.1·exp(..L) + 0.1·exp(..R)``; with ``weight = 0.2`` and the mean this is identical and
    keeps the weight equal to the term's maximum. F_z = ``next["foot_force"][..., 2]``, F_ref =
    ``next["ref_foot_force"]`` (num_envs, 2) in N (negative when loaded); w = ``weight_scale`` (mass ratio, 1).
    """

    name: str = "force_ref"
    weight: float = 0.2
    scale: float = 0.001
    weight_scale: float = 1.0
    next_keys: tuple = field(default=("foot_force", "ref_foot_force"), init=False, repr=False)

    def __post_init__(self):
        super().__post_init__()
        self.weight_scale = check_finite(self.weight_scale, f"{self.name} weight_scale")

    def kernel(self, td, next_td):
        err = (next_td.get("foot_force")[..., 2] - self.weight_scale * next_td.get("ref_foot_force")).abs()
        return torch.exp(-self.scale * err).mean(-1, keepdim=True)


@dataclass
class _FootForceThreshold(RewardTerm):
    """The force penalties' shared kernel: 1 if either foot's vertical-force quantity (:meth:`vertical_force`,
    (num_envs, 2) N) exceeds ``factor · body_weight`` in absolute value (strict inequality), else 0."""

    name: str = ""
    weight: float = 0.0
    factor: float = 1.0
    body_weight: float = _BODY_WEIGHT

    def __post_init__(self):
        super().__post_init__()
        self.factor = _scale(self.factor, f"{self.name} factor")
        self.body_weight = _scale(self.body_weight, f"{self.name} body_weight")

    @property
    def threshold(self) -> float:
        """The force threshold [N]: ``factor · body_weight``."""
        return self.factor * self.body_weight

    def vertical_force(self, td: TensorDictBase, next_td: TensorDictBase) -> torch.Tensor:
        raise NotImplementedError

    def kernel(self, td, next_td):
        over = self.vertical_force(td, next_td).abs() > self.threshold
        return over.any(-1, keepdim=True).to(torch.float32)


@dataclass
class ForceThresholdPenalty(_FootForceThreshold):
    """Reference ``force_thres_penalty``: ``weight`` (−0.08) if ``|F_z,L|`` or ``|F_z,R|`` > factor · m · g.

    factor 1.4, m = ``robot.NOMINAL_MASS``, g = ``robot.GRAVITY`` (threshold ≈ 1435.0 N), strict inequality.
    F_z = ``next["foot_force"][..., 2]``.
    """

    name: str = "force_threshold"
    weight: float = -0.08
    factor: float = 1.4
    next_keys: tuple = field(default=("foot_force",), init=False, repr=False)

    def vertical_force(self, td, next_td):
        return next_td.get("foot_force")[..., 2]


@dataclass
class ForceDiffThresholdPenalty(_FootForceThreshold):
    """Reference ``force_diff_thres_penalty``: ``weight`` (−0.05) if ``|ΔF_z|`` of either foot > factor · m · g.

    factor 0.2 (threshold ≈ 205.0 N), ΔF_z = ``next["foot_force"][..., 2] - td["foot_force"][..., 2]``, strict.
    """

    name: str = "force_diff_threshold"
    weight: float = -0.05
    factor: float = 0.2
    root_keys: tuple = field(default=("foot_force",), init=False, repr=False)
    next_keys: tuple = field(default=("foot_force",), init=False, repr=False)

    def vertical_force(self, td, next_td):
        return next_td.get("foot_force")[..., 2] - td.get("foot_force")[..., 2]


def _torque_scale(value, name: str) -> float | tuple[float, ...]:
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        return _scale(value, f"{name} torque_scale")
    values = tuple(value)
    if len(values) != robot.NUM_LEG_JOINTS:
        raise ValueError(
            f"{name} torque_scale must be one number or {robot.NUM_LEG_JOINTS} per-joint numbers, got {len(values)}"
        )
    return tuple(_scale(v, f"{name} torque_scale") for v in values)


def _apply_torque_scale(a: torch.Tensor, torque_scale: float | tuple[float, ...]) -> torch.Tensor:
    if isinstance(torque_scale, float):
        return a * torque_scale
    return a * _per_joint_tensor(torque_scale, a.dtype, a.device)


@functools.lru_cache(maxsize=16)
def _per_joint_tensor(values: tuple[float, ...], dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    # Cached so the per-joint scales are copied to the device once, not every step.
    return torch.tensor(values, dtype=dtype, device=device)


#: The reference's 11 terms and 2 penalties (spec §8), by name, with their reference constants.
REFERENCE_TERMS: MappingProxyType[str, type[RewardTerm]] = MappingProxyType(
    {
        cls.name: cls
        for cls in (
            NeckOrientation,
            JointPosTracking,
            JointVelRegulation,
            BodyVelTracking,
            ContactForce,
            TorqueRegulation,
            TorqueDiffRegulation,
            JointAccRegulation,
            FootContactPattern,
            ContactForceDiff,
            ForceReference,
            ForceThresholdPenalty,
            ForceDiffThresholdPenalty,
        )
    }
)


#: Per-env shapes of the signals the reference terms read, from the signal table (tocabi_torchrl.signals), checked
#: when the env is built.
SIGNAL_SHAPES: MappingProxyType[str, tuple[int, ...]] = MappingProxyType(
    {
        key: SIGNALS[key].shape
        for term in REFERENCE_TERMS.values()
        for key in (*term.root_keys, *term.next_keys)
    }
)


def reference_terms(names: tuple[str, ...] | None = None) -> list[RewardTerm]:
    """Fresh instances of the named reference terms (default: all 13, in spec order)."""
    names = tuple(REFERENCE_TERMS) if names is None else tuple(names)
    unknown = [n for n in names if n not in REFERENCE_TERMS]
    if unknown:
        raise KeyError(f"unknown reward term(s) {unknown}; known terms: {list(REFERENCE_TERMS)}")
    return [REFERENCE_TERMS[n]() for n in names]
