"""The layouts of the policy input, as plain values: which signals form the per-step observation
(:class:`ObsComponent`, :data:`REFERENCE_OBS_LAYOUT`) and which past observations and actions the history keeps
(:class:`HistoryLayout`). Config, not transforms: they live in a module without torch so that the run config tree
(and ``--help``) reads without it; ``observation`` and ``history`` hold the transforms that use them, and name them
too."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from types import MappingProxyType
from typing import TYPE_CHECKING

from tocabi_torchrl import robot
from tocabi_torchrl.transforms._checks import check_positive_int
from tocabi_torchrl.value_rules import plain_number

if TYPE_CHECKING:
    from tensordict.utils import NestedKey

__all__ = ["ObsComponent", "REFERENCE_OBS_LAYOUT", "BASE_VEL_OBS_LAYOUT", "OBS_LAYOUTS", "NON_PHASE_VALUES",
           "layout_name", "HistoryLayout", "REFERENCE_HISTORY", "TOCABILAB_HISTORY"]

_ALL = slice(None)


@dataclass(frozen=True)
class ObsComponent:
    """One block of the observation vector.

    Attributes:
        name: label of the block (for docs and :attr:`ObservationAssembly.slices`).
        key: tensordict key to read, shape (num_envs, *signal_shape).
        index: index into the signal dimensions (not the batch), made of ints and slices only so that no index
            tensor is copied to the device each step; e.g. ``(slice(0, 12),)`` for the leg joints of a (N, 33)
            signal, ``(slice(None), 2)`` for the z components of a (N, 2, 3) signal. The result is flattened.
    """

    name: str
    key: NestedKey
    index: tuple = ()

    def __post_init__(self):
        if not isinstance(self.index, tuple):
            # A lone slice or int failed here as a bare "not iterable" TypeError, and a list passed and failed once
            # an env was attached, concatenated to the batch's index inside ObservationAssembly.
            one = isinstance(self.index, (slice, int)) or self.index is Ellipsis
            fix = f"({self.index!r},)" if one else "a tuple, e.g. (slice(0, 12),)"
            raise TypeError(f"ObsComponent {self.name!r}: index must be a tuple of ints, slices or Ellipsis, got "
                            f"{self.index!r}; pass {fix}")
        for i in self.index:
            if not (isinstance(i, slice) or i is Ellipsis or (isinstance(i, int) and not isinstance(i, bool))):
                raise TypeError(
                    f"ObsComponent {self.name!r}: index entries must be ints, slices or Ellipsis, got {i!r}; "
                    "split a scattered selection into several components"
                )


#: The reference per-step observation (spec §7.1): 3 + 12 + 12 + 1 + 1 + 2 + 2 + 2 + 2 = 37 values.
REFERENCE_OBS_LAYOUT: tuple[ObsComponent, ...] = (
    ObsComponent("base_rpy", "base_rpy"),  # 0-2: roll, pitch, yaw of the pelvis
    ObsComponent("leg_joint_pos", "joint_pos", (robot.LEGS,)),  # 3-14
    ObsComponent("leg_joint_vel", "joint_vel", (robot.LEGS,)),  # 15-26
    ObsComponent("phase_sin", "phase_sin"),  # 27
    ObsComponent("phase_cos", "phase_cos"),  # 28
    ObsComponent("command", "command"),  # 29-30: vx, vy
    ObsComponent("foot_force_z", "foot_force", (_ALL, 2)),  # 31-32: Fz_L, Fz_R
    ObsComponent("foot_torque_x", "foot_torque", (_ALL, 0)),  # 33-34: Mx_L, Mx_R
    ObsComponent("foot_torque_y", "foot_torque", (_ALL, 1)),  # 35-36: My_L, My_R
)

#: The reference observation and the pelvis's velocity, 43 values: what the TOCABI lab's later walking policies sense
#: beyond the reference's. Nothing in the reference observation gives it directly, and its history spans 32 ms: a
#: slow sideways walk goes unseen. The IMU's gyro gives the angular velocity, a state estimator the linear one.
BASE_VEL_OBS_LAYOUT: tuple[ObsComponent, ...] = (
    *REFERENCE_OBS_LAYOUT,
    ObsComponent("base_lin_vel", "base_lin_vel"),  # 37-39: pelvis linear velocity [m/s], pelvis frame
    ObsComponent("base_ang_vel", "base_ang_vel"),  # 40-42: pelvis angular velocity [rad/s], pelvis frame
)

#: The per-step observations a run config names (``transforms.observation``).
OBS_LAYOUTS: Mapping[str, tuple[ObsComponent, ...]] = MappingProxyType(
    {"reference": REFERENCE_OBS_LAYOUT, "base_vel": BASE_VEL_OBS_LAYOUT})
#: Values of each named layout other than the phase's sines and cosines (TOCABI's fixed-size signals): the reference's
#: base rpy 3, leg joint positions and velocities 12 + 12, command 2, foot force z 2, foot torques x and y 2 + 2;
#: ``base_vel`` adds the pelvis's linear and angular velocity, 3 + 3.
NON_PHASE_VALUES: Mapping[str, int] = MappingProxyType({"reference": 35, "base_vel": 41})


def layout_name(layout: tuple[ObsComponent, ...]) -> str | None:
    """The name of ``layout`` in :data:`OBS_LAYOUTS`; None for a layout of one's own."""
    return next((name for name, known in OBS_LAYOUTS.items() if tuple(layout) == known), None)


@dataclass(frozen=True)
class HistoryLayout:
    """Which past observations and actions form the policy input.

    Attributes:
        num_obs: K >= 1 observations, ``stride`` policy steps apart, the newest being the current one.
        stride: s >= 1 policy steps between stored entries.
        num_actions: M >= 0 past actions (default K - 1), slot j holding ``a_{τ+1 - s·(M - j)}``.
    """

    num_obs: int = 5
    stride: int = 2
    num_actions: int | None = None

    def __post_init__(self):
        # Stored as plain ints: a sweep's np.int64 is taken as the config tree takes it, and kept out of the layout.
        object.__setattr__(self, "num_obs", check_positive_int(
            self.num_obs, "HistoryLayout num_obs (K)", "use num_obs=1 for no observation history"))
        object.__setattr__(self, "stride", check_positive_int(
            self.stride, "HistoryLayout stride", "use stride=1 for consecutive steps"))
        if self.num_actions is None:
            object.__setattr__(self, "num_actions", self.num_obs - 1)
        m = plain_number(self.num_actions)
        if isinstance(m, bool) or not isinstance(m, int) or m < 0:
            raise ValueError(f"HistoryLayout num_actions must be an integer >= 0 (or None for num_obs - 1), "
                             f"got {self.num_actions!r}")
        object.__setattr__(self, "num_actions", m)

    @property
    def obs_ages(self) -> tuple[int, ...]:
        """Age in policy steps of each stored observation, oldest first (reference: 8, 6, 4, 2, 0)."""
        return tuple(self.stride * (self.num_obs - 1 - i) for i in range(self.num_obs))

    @property
    def action_ages(self) -> tuple[int, ...]:
        """Age of each stored action, oldest first; age 0 is the action just applied (reference: 7, 5, 3, 1)."""
        return tuple(self.stride * (self.num_actions - j) - 1 for j in range(self.num_actions))

    def size(self, obs_dim: int, action_dim: int) -> int:
        """Length of the policy input: K·obs_dim + M·action_dim."""
        return self.num_obs * obs_dim + self.num_actions * action_dim

    def describe(self) -> list[str]:
        """Human-readable content of each block, e.g. ``['obs[t-8]', …, 'action[t-1]']``."""
        fmt = lambda a: "t" if a == 0 else f"t-{a}"  # noqa: E731
        return [f"obs[{fmt(a)}]" for a in self.obs_ages] + [f"action[{fmt(a)}]" for a in self.action_ages]


#: Reference layout (spec §7.4): 5 observations two steps apart + 4 raw actions, 237 values with 37/13.
REFERENCE_HISTORY = HistoryLayout(num_obs=5, stride=2, num_actions=4)
#: TocabiLab's consecutive layout: the last 5 observations + the last 4 applied actions, 237 values with 37/13.
TOCABILAB_HISTORY = HistoryLayout(num_obs=5, stride=1, num_actions=4)
