"""Configuration of the TOCABI walking task: every constant of the task, with its unit, in one dataclass."""

from __future__ import annotations

import os
from dataclasses import dataclass, field

import numpy as np

from .. import robot
from .command import CommandConfig

__all__ = ["TocabiWalkConfig", "CONTROL_MODES", "BACKENDS", "CPU_DEFAULT_BACKEND", "resolve_backend"]

CONTROL_MODES = ("torque", "pd", "pd_reference")
#: Physics backends: mujoco-warp (``WarpSim``, GPU or warp's CPU device) or C MuJoCo on CPU threads (``MujocoSim``).
BACKENDS = ("warp", "mujoco", "auto")
#: ``backend="auto"`` on a CPU device. Measured by ``benchmarks/cpu_backends.py`` (docs/benchmarks/cpu_backends_*.md):
#: on a 2-core machine C MuJoCo stepped the bare env at 1800-3200 env-steps/s against mujoco-warp's CPU device's
#: 315-340 (5.7-9.8x) at 8-96 envs, and needs no minute-long kernel compile.
CPU_DEFAULT_BACKEND = "mujoco"


def resolve_backend(backend: str, device) -> str:
    """The backend that runs: ``"auto"`` is mujoco-warp on CUDA and :data:`CPU_DEFAULT_BACKEND` on the CPU."""
    if backend not in BACKENDS:
        raise ValueError(f"unknown backend {backend!r}; choose one of {BACKENDS}")
    on_cuda = str(device).startswith("cuda")
    if backend == "auto":
        return "warp" if on_cuda else CPU_DEFAULT_BACKEND
    if backend == "mujoco" and on_cuda:
        raise ValueError("backend='mujoco' steps C MuJoCo on the CPU; use device='cpu' with it, or backend='warp' "
                         "(or 'auto') on CUDA")
    return backend


@dataclass
class TocabiWalkConfig:
    """Task constants (spec §2-§9). Angles in rad, lengths in m, times in s unless a name says steps.

    Control modes:
      - ``"torque"`` (reference): leg torque = action[:12] × joint torque limit, held for all substeps.
      - ``"pd"`` (TocabiLab's position-based policy): action[:12] in [-1, 1] maps to a target angle
        ``pd_nominal + pd_action_scale × action`` clipped to the joint range, tracked in every physics substep by
        MuJoCo position servos with gains ``pd_kp``/``pd_kv``, force-limited to the torque limits.
      - ``"pd_reference"``: as ``"pd"`` with the target centred on the reference walk instead of ``pd_nominal``.
    The upper body is held at the reference pose by MuJoCo position servos in every mode.
    """

    control_mode: str = "torque"
    #: Physics substeps per policy step (0.5 ms each: 8 -> 250 Hz policy).
    substeps: int = 8
    #: Policy steps before truncation (8000 = 32 s).
    max_episode_steps: int = 8000
    #: Reference motion: None = the shipped generated cycle; a path to a ``.npz`` or the reference ``.txt`` file.
    motion: str | os.PathLike | None = None
    #: Phase clock: t += dt × (1 + phase_rate_gain × action[12]) per step (reference gain 1: 1× to 2× speed).
    phase_rate_gain: float = 1.0
    command: CommandConfig = field(default_factory=CommandConfig)
    # Early termination (spec §9.1).
    min_pelvis_height: float = 0.6
    min_neck_height: float = 0.8
    max_neck_angle: float = 1.0
    terminate_on_forbidden_contact: bool = True
    terminate_on_self_collision: bool = True
    # PD control mode (TocabiLab divides the robot controller's Kp by 9 and Kv by 3).
    pd_kp: tuple[float, ...] = tuple(robot.LEG_KP / 9.0)
    pd_kv: tuple[float, ...] = tuple(robot.LEG_KV / 3.0)
    pd_action_scale: float = 0.5
    pd_nominal: tuple[float, ...] = tuple(robot.INIT_JOINT_POS[:12])
    #: Torque mode only, a training aid that morphs the action space: the leg torque is
    #: ``(1 − β)·a·limit + β·(pd_kp·(q_ref + pd_action_scale·a − q) − pd_kv·q̇)`` (clipped to the limits), so at β = 1
    #: the 12 leg actions are position residuals around the reference walk tracked by a PD at the policy rate (the
    #: ``pd_reference`` mode, which learns to walk), and at β = 0 they are the reference's normalised torques. β is
    #: the env's device scalar ``assist_scale`` (:meth:`TocabiWalk.set_torque_assist`, 0 at build), so a trainer can
    #: fade it without rebuilding or re-capturing. Adds the ``leg_assist`` signal: the action-independent part of the
    #: PD, ``(pd_kp·(q_ref − q) − pd_kv·q̇) / limit`` (num_envs, 12), from the pre-step state. The leg entries of
    #: ``applied_action`` (observation history, torque rewards) are the applied torque over the limits, the same at
    #: every β for the same torques (at β = 0 they equal the action, as in plain torque mode).
    torque_assist: bool = False
    #: Robot model path: None = the shipped assets/tocabi/tocabi.xml.
    model_path: str | os.PathLike | None = None
    #: Contact/constraint buffers per world for mujoco-warp (None = the backend's measured defaults).
    nconmax: int | None = None
    njmax: int | None = None
    #: Physics backend: "warp" (mujoco-warp), "mujoco" (C MuJoCo on CPU threads, CPU only) or "auto" (warp on CUDA,
    #: ``CPU_DEFAULT_BACKEND`` on the CPU).
    backend: str = "auto"
    #: CPU threads of the "mujoco" backend (None = every available core).
    sim_threads: int | None = None

    @classmethod
    def reference(cls, **overrides) -> "TocabiWalkConfig":
        """The reference code's task: its command schedule (U(-0.2, 0.8) with the linear ramp)."""
        overrides.setdefault("command", CommandConfig.reference())
        return cls(**overrides)

    def validate(self) -> None:
        if self.control_mode not in CONTROL_MODES:
            raise ValueError(f"unknown control_mode {self.control_mode!r}; choose one of {CONTROL_MODES}")
        for name in ("substeps", "max_episode_steps"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"TocabiWalkConfig.{name} must be >= 1, got {getattr(self, name)}")
        for name in ("min_pelvis_height", "min_neck_height", "max_neck_angle", "pd_action_scale"):
            value = float(getattr(self, name))
            if not np.isfinite(value) or value < 0:
                raise ValueError(f"TocabiWalkConfig.{name} must be a finite number >= 0, got {value}")
        if not 0 <= self.phase_rate_gain < 100:
            raise ValueError(f"TocabiWalkConfig.phase_rate_gain must be in [0, 100), got {self.phase_rate_gain}")
        for name in ("pd_kp", "pd_kv", "pd_nominal"):
            if len(getattr(self, name)) != robot.NUM_LEG_JOINTS:
                raise ValueError(f"TocabiWalkConfig.{name} needs {robot.NUM_LEG_JOINTS} values (one per leg joint)")
        if self.torque_assist and self.control_mode != "torque":
            raise ValueError(f"TocabiWalkConfig.torque_assist needs control_mode='torque' (the PD modes already track "
                             f"with servos), got control_mode={self.control_mode!r}")
        if min(self.pd_kp) < 0 or min(self.pd_kv) < 0:
            raise ValueError("TocabiWalkConfig.pd_kp and pd_kv must be >= 0")
        if self.backend not in BACKENDS:
            raise ValueError(f"unknown TocabiWalkConfig.backend {self.backend!r}; choose one of {BACKENDS}")
        t = self.sim_threads
        if t is not None and (isinstance(t, bool) or not isinstance(t, int) or t < 1):
            raise ValueError(f"TocabiWalkConfig.sim_threads must be a positive int or None, got {t!r}")
        self.command.validate()
