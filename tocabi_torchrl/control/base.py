"""The controller interface: ``τ_cmd = F_con(π_θ)`` for one group of joints (TocabiLab's report §3.3).

A :class:`Controller` maps its slice of the policy's action, the robot state and the reference walk to the joint
commands of its group, once per policy step. Two kinds of command exist, and ``servo`` says which one a controller
writes:

- ``servo = False``: joint torques [N·m], held for the policy step (one write into the simulator's controls). They
  pass through the group's actuator layer (:mod:`tocabi_torchrl.control.actuators`) on their way to the joints.
- ``servo = True``: joint position targets [rad], tracked by MuJoCo position servos inside every physics substep
  (the robot's servos run at 2 kHz); :meth:`Controller.servo_gains` gives their gains, or ``None`` for the servos the
  model file already defines (the upper body's).

Everything a controller does per step is batched tensor work on the env's device, with no host reads and no Python
state that changes between steps, so a captured CUDA graph of the env step replays it. Per-world buffers are
allocated in :meth:`Controller.setup` and only ever updated in place.

>>> import torch
>>> from tocabi_torchrl.control import DirectTorque
>>> from tocabi_torchrl.control.base import ControlContext, ControlInput
>>> ctx = ControlContext(num_envs=2, device=torch.device("cpu"), joint_ids=(0, 1),
...                      torque_limits=torch.tensor([10.0, 20.0]), joint_range=torch.tensor([[-1.0, 1.0]] * 2))
>>> law = DirectTorque()
>>> law.setup(ctx)
>>> law.compute(ControlInput(action=torch.tensor([[0.5, -1.0], [0.0, 1.0]]))).tolist()
[[5.0, -20.0], [0.0, 20.0]]
"""

from __future__ import annotations

import abc
import dataclasses
from typing import Any

import torch

from .. import robot

__all__ = ["ControlContext", "ControlInput", "Controller"]


@dataclasses.dataclass(frozen=True)
class ControlContext:
    """What a controller is built for: set once, when the env is built.

    Attributes:
        num_envs: number of worlds N.
        device: the env's device; every tensor a controller keeps lives there.
        joint_ids: the group's joints, indices into ``robot.JOINT_NAMES`` (J of them).
        torque_limits: (J,) float32 [N·m], the joints' torque limits.
        joint_range: (J, 2) float32 [rad], the joints' position limits (low, high) in the model.
        dt: the policy step [s].
        sim: the physics backend (``SimBackend``), for laws that read more than joint positions and velocities
            (``mass_matrix``, ``qfrc_bias``).
        motion: the reference motion (``ReferenceMotion``) on ``device``.
        extras: anything else a law needs from its builder.
        model_file: the robot model file ``joint_range`` comes from, for messages ("" when not known).
    """

    num_envs: int
    device: torch.device
    joint_ids: tuple[int, ...]
    torque_limits: torch.Tensor
    joint_range: torch.Tensor
    dt: float = 0.004
    sim: Any = None
    motion: Any = None
    extras: dict = dataclasses.field(default_factory=dict)
    model_file: str = ""


@dataclasses.dataclass
class ControlInput:
    """One policy step's input to a controller; every tensor is on the env's device, N = num_envs, J = the group's
    joints. Fields a law does not need may be left ``None`` (as in the examples).

    Attributes:
        action: (N, A) the policy's action slice for the group, clipped to [-1, 1] (A = ``Controller.action_dim``).
        q: (N, J) joint positions [rad] before the step.
        qd: (N, J) joint velocities [rad/s] before the step.
        q_ref: (N, J) the reference walk's joint targets at the pre-step phase clock [rad].
        time: (N,) the pre-step phase clock [s]; init_row: (N,) int64 the episodes' start rows of the motion.
        rate: (N,) this step's phase rate (1 + phase_rate_gain · a[12]).
    """

    action: torch.Tensor
    q: torch.Tensor | None = None
    qd: torch.Tensor | None = None
    q_ref: torch.Tensor | None = None
    time: torch.Tensor | None = None
    init_row: torch.Tensor | None = None
    rate: torch.Tensor | None = None


class Controller(abc.ABC):
    """A control law for one group of joints. Subclass it, set ``servo`` and ``action_dim``, and implement
    :meth:`compute`; allocate per-world state in :meth:`setup` and clear it in :meth:`reset`."""

    #: True: :meth:`compute` returns position targets [rad] for servos that run inside every physics substep;
    #: False: joint torques [N·m] held for the policy step.
    servo: bool = False
    #: Width of the action slice the law reads (0 for a group the policy does not command).
    action_dim: int = 0

    def setup(self, ctx: ControlContext) -> None:
        """Allocate buffers for ``ctx.num_envs`` worlds on ``ctx.device``; the base keeps ``ctx`` as ``self.ctx``."""
        self.ctx = ctx

    @abc.abstractmethod
    def compute(self, inp: ControlInput) -> torch.Tensor:
        """(N, J) this step's command: torques [N·m] or, for a servo law, position targets [rad]."""

    def applied_action(self, inp: ControlInput, command: torch.Tensor) -> torch.Tensor:
        """(N, A) what the ``applied_action`` signal (observation history, torque rewards) reports for this group:
        the action itself by default."""
        return inp.action

    def reset_command(self) -> torch.Tensor:
        """(J,) the command a reset world starts with: no torque [N·m], or for a servo law (``servo`` True) targets
        [rad]: here the start pose's joint positions (``robot.INIT_JOINT_POS``), which a law with another rest
        overrides (``JointPD``: its nominal pose). Zeros once drove a servo law's joints to 0 rad at every reset."""
        if self.servo:
            start = robot.INIT_JOINT_POS[list(self.ctx.joint_ids)]
            return torch.as_tensor(start, dtype=torch.float32, device=self.ctx.device)
        return torch.zeros(len(self.ctx.joint_ids), dtype=torch.float32, device=self.ctx.device)

    def servo_gains(self) -> tuple | None:
        """``(kp, kv)``, J numbers >= 0 each [N·m/rad, N·m·s/rad], of the position servos this law's targets need, or
        None to keep the actuators of the model file (motors for the legs, servos for the upper body). Read when
        the model is built, before :meth:`setup`."""
        return None

    def reset(self, mask: torch.Tensor) -> None:
        """Clear the per-world state of the worlds flagged in ``mask`` (N,) bool, in place."""

    def signals(self) -> dict[str, torch.Tensor]:
        """Extra env signals this law computes (name -> (N, J) tensor it updates in place), e.g. ``leg_assist``."""
        return {}
