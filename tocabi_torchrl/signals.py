"""The signal table: every tensor ``TocabiWalk`` returns, with its shape, dtype, unit and meaning, in one place.

The env's observation, done and reward specs (``TocabiWalk._make_specs``), the reward's shape checks of every
signal its terms read (``transforms.reward.TaskReward``), the transforms' test stand-in (``tests/mock_env.py``) and
the table in ``docs/concepts/env-and-signals.md`` (``python -m tocabi_torchrl.signals_doc``) are all made from these
rows. Adding a signal is a row here and the line of ``TocabiWalk._observe`` that computes it; the env refuses to build
when the two disagree.

Shapes are per env: the env's tensors are ``(num_envs, *shape)``. Joint-sized signals follow ``robot.JOINT_NAMES``;
pairs of feet are [left, right].
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass
from types import MappingProxyType

import torch
from torchrl.data import Bounded, Categorical, Composite, TensorSpec, Unbounded

from . import robot

__all__ = ["Signal", "SignalTable", "SIGNALS", "EPISODE_FLAGS", "REWARD"]

_DTYPES = (torch.float32, torch.int64, torch.bool)


@dataclass(frozen=True)
class Signal:
    """One row of the table.

    Attributes:
        name: the tensordict key.
        shape: per-env shape (the env's tensor is ``(num_envs, *shape)``).
        dtype: ``torch.float32``, ``torch.int64`` or ``torch.bool``.
        unit: physical unit (``"rad"``, ``"m/s"``, ``"N"``, ...); ``""`` for unitless values, flags and labels.
        meaning: one line for docs/concepts/env-and-signals.md (no ``|``, no line breaks).
        categories: for discrete signals, the number of values ``0 … categories − 1`` (bool flags: 2).
        bounds: ``(low, high)`` for a continuous signal with a known range (its spec is then ``Bounded``).
        requires: the name of the env option that turns the signal on (``"torque_assist"``, ``"model_based"``,
            ``"obstacles"``, ``"pushes"``; the env passes its options' values as ``flags``, see
            ``TocabiWalk.signal_flags``); ``None``: always on.
    """

    name: str
    shape: tuple[int, ...]
    dtype: torch.dtype
    unit: str
    meaning: str
    categories: int | None = None
    bounds: tuple[float, float] | None = None
    requires: str | None = None

    def __post_init__(self):
        where = f"signal {self.name!r}"
        if not isinstance(self.name, str) or not self.name.isidentifier():
            raise ValueError(f"signal names must be identifiers (they are tensordict keys), got {self.name!r}")
        shape = tuple(self.shape)
        if not all(isinstance(d, int) and not isinstance(d, bool) and d > 0 for d in shape):
            raise ValueError(f"{where}: shape must be a tuple of positive ints (per env), got {self.shape!r}")
        object.__setattr__(self, "shape", shape)
        if self.dtype not in _DTYPES:
            raise ValueError(f"{where}: dtype must be one of {_DTYPES}, got {self.dtype!r}")
        for field_name in ("unit", "meaning"):
            text = getattr(self, field_name)
            if not isinstance(text, str) or "|" in text or "\n" in text:
                raise ValueError(f"{where}: {field_name} must be one line of text without '|' (a markdown cell)")
        if self.dtype == torch.bool and self.categories not in (None, 2):
            raise ValueError(f"{where}: a bool signal has 2 categories, got categories={self.categories}")
        if self.dtype == torch.bool:
            object.__setattr__(self, "categories", 2)
        if self.categories is not None and (self.dtype == torch.float32 or self.categories < 2):
            raise ValueError(f"{where}: categories (>= 2) are for int64 or bool signals, got {self.dtype}")
        if self.bounds is not None and (self.dtype != torch.float32 or not self.bounds[0] < self.bounds[1]):
            raise ValueError(f"{where}: bounds must be (low, high) with low < high on a float32 signal")

    def spec(self, num_envs: int, device: torch.device | str) -> TensorSpec:
        """The TorchRL spec of the env's ``(num_envs, *shape)`` tensor."""
        shape = (num_envs, *self.shape)
        if self.categories is not None:
            return Categorical(self.categories, shape=shape, dtype=self.dtype, device=device)
        if self.bounds is not None:
            return Bounded(self.bounds[0], self.bounds[1], shape=shape, dtype=self.dtype, device=device)
        return Unbounded(shape=shape, dtype=self.dtype, device=device)

    def enabled(self, flags: Mapping[str, bool] | None = None) -> bool:
        """Whether an env whose options are ``flags`` returns this signal (``None``: only unconditional ones)."""
        if self.requires is None:
            return True
        if flags is None:
            return False
        if self.requires not in flags:
            raise KeyError(f"signal {self.name!r} requires the option {self.requires!r}, which is not among the "
                           f"env's signal flags {sorted(flags)}; add it to TocabiWalk.signal_flags")
        return bool(flags[self.requires])

    @property
    def shape_text(self) -> str:
        """The shape as docs/concepts/env-and-signals.md writes it, e.g. ``(N, 2, 3)``."""
        return "(" + ", ".join(("N", *map(str, self.shape))) + ")"


class SignalTable:
    """An ordered, name-unique collection of :class:`Signal` rows (order = spec and docs order)."""

    def __init__(self, rows: Iterable[Signal]):
        self.rows: tuple[Signal, ...] = tuple(rows)
        seen: set[str] = set()
        for row in self.rows:
            if not isinstance(row, Signal):
                raise TypeError(f"a SignalTable holds Signal rows, got {row!r}")
            if row.name in seen:
                raise ValueError(f"signal {row.name!r} appears twice in the table")
            seen.add(row.name)
        self._by_name = MappingProxyType({row.name: row for row in self.rows})

    def with_rows(self, *rows: Signal) -> SignalTable:
        """A new table: these rows appended (a name already in the table is an error)."""
        return SignalTable((*self.rows, *rows))

    def __getitem__(self, name: str) -> Signal:
        try:
            return self._by_name[name]
        except KeyError:
            raise KeyError(f"no signal {name!r} in the table; known: {list(self._by_name)}") from None

    def __contains__(self, name: object) -> bool:
        return name in self._by_name

    def __iter__(self) -> Iterator[Signal]:
        return iter(self.rows)

    def __len__(self) -> int:
        return len(self.rows)

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(self._by_name)

    def enabled(self, flags: Mapping[str, bool] | None = None) -> tuple[Signal, ...]:
        """The rows an env whose options are ``flags`` returns (``None``: the unconditional ones)."""
        return tuple(row for row in self.rows if row.enabled(flags))

    def composite(
        self, num_envs: int, device: torch.device | str, flags: Mapping[str, bool] | None = None
    ) -> Composite:
        """A ``Composite`` of the enabled rows' specs, batch ``(num_envs,)``."""
        specs = {row.name: row.spec(num_envs, device) for row in self.enabled(flags)}
        return Composite(specs, shape=(num_envs,), device=device)

    def __repr__(self) -> str:
        return f"SignalTable({list(self._by_name)})"


_F32, _I64, _BOOL = torch.float32, torch.int64, torch.bool
_J, _LEG = robot.NUM_JOINTS, robot.NUM_LEG_JOINTS

#: What ``TocabiWalk`` observes, in spec order. Each is a fresh tensor (never a view of simulator memory).
SIGNALS = SignalTable((
    Signal("joint_pos", (_J,), _F32, "rad", "joints in `robot.JOINT_NAMES` order (`qpos[7:40]`)"),
    Signal("joint_vel", (_J,), _F32, "rad/s", "joint velocities (`qvel[6:39]`)"),
    Signal("base_pos", (3,), _F32, "m", "pelvis (`base_link`) origin in the world"),
    Signal("base_quat", (4,), _F32, "", "pelvis orientation in the world, (w, x, y, z)"),
    Signal("base_lin_vel", (3,), _F32, "m/s",
           "pelvis origin linear velocity rotated into the pelvis frame (`R_baseᵀ · qvel[0:3]`)"),
    Signal("base_ang_vel", (3,), _F32, "rad/s", "pelvis angular velocity in the pelvis frame (`qvel[3:6]`)"),
    Signal("neck_pos", (3,), _F32, "m", "`Neck_Link` origin in the world"),
    Signal("neck_quat", (4,), _F32, "", "`Neck_Link` orientation in the world, (w, x, y, z)"),
    Signal("foot_pos", (2, 3), _F32, "m", "`Foot_Link` origins in the world, [left, right]"),
    Signal("foot_force", (2, 3), _F32, "N",
           "foot F/T sensor force in its site frame, [left, right]; z < 0 when loaded"),
    Signal("foot_torque", (2, 3), _F32, "N·m", "foot F/T sensor torque about the site, site frame, [left, right]"),
    Signal("foot_contact", (2,), _BOOL, "", "a `Foot_Link` geom touches the ground or an obstacle, [left, right]"),
    Signal("phase", (1,), _F32, "", "observation phase in [0, 1) at the post-step time (spec §3.2)", bounds=(0.0, 1.0)),
    Signal("ref_joint_pos", (_J,), _F32, "rad",
           "reference targets used during the step that produced this state (pre-step time)"),
    Signal("ref_foot_force", (2,), _F32, "N",
           "reference vertical foot forces at the pre-step row, [left, right], in [-1025, 0]"),
    Signal("stance", (1,), _I64, "", "contact pattern the reward expects at the pre-step row: 0 double support, "
           "1 right stance, 2 left stance", categories=3),
    Signal("command", (2,), _F32, "m/s", "commanded (vx, vy) in the pelvis frame, after this step's schedule update"),
    Signal("applied_action", (_LEG + 1,), _F32, "",
           "raw clipped action applied in the step that produced this state (zeros after a reset); with "
           "`torque_assist` or in `model_based` or `pd_held` mode, the 12 leg entries are the applied torque over the "
           "limits (with `torque_assist`, equal to the action at β = 0)"),
    Signal("leg_torque", (_LEG,), _F32, "N·m",
           "leg torques commanded in that step (torque mode: action × limit; with `torque_assist=True`: "
           "(1 − β)·limit·a + β·PD(q_ref + pd_action_scale·a), clipped to the limits; model_based mode: "
           "τ_ff + g·a (g = mb_residual_gain), clipped to the limits; pd_held mode: "
           "pd_kp·(q_ref + pd_action_scale·a − q − b) − pd_kv·q̇, b the sensed encoder bias, clipped to the limits; "
           "PD mode: the PD output)"),
    Signal("episode_step", (1,), _I64, "", "policy steps since the env's last reset"),
    Signal("healthy", (1,), _BOOL, "",
           "the world's physics is numerically sound: finite qpos, qvel, qacc (warp) and sensors, no dropped "
           "contacts or constraints; False terminates the episode"),
    Signal("leg_assist", (_LEG,), _F32, "",
           "only with `torque_assist=True`: the action-independent part of the assist's PD, "
           "`(pd_kp·(q_ref − q) − pd_kv·q̇) / limit`, from the pre-step state, as a fraction of each joint's torque "
           "limit", requires="torque_assist"),
    Signal("leg_feedforward", (_LEG,), _F32, "N·m",
           "only in `model_based` mode: the feed-forward torque τ_ff = M_LL·(q̈_ref + ω²·(q_ref − q) + 2ζω·(q̇_ref − "
           "q̇)) + c_L of that step, from the pre-step state (before the residual and the clip)",
           requires="model_based"),
    Signal("kick_age", (1,), _F32, "s",
           "only with `env.pushes`: seconds since the episode's latest kick began (the episode's time before its "
           "first)", requires="pushes"),
    Signal("kick_speed", (1,), _F32, "m/s",
           "only with `env.pushes`: the velocity change that kick gave, its curriculum and per-world scales included "
           "(0 before the first)", requires="pushes"),
    Signal("cycle_vel_error", (2,), _F32, "m/s",
           "only with `env.task.cycle_velocity`: the heading-frame pelvis velocity minus the command, (vx, vy), "
           "averaged over the world's last 450 policy steps (one gait cycle at the nominal phase rate) or its "
           "episode so far if shorter; 0 after a reset (envs/cycle_velocity.py)", requires="cycle_velocity"),
    Signal("obstacle_contact", (2,), _BOOL, "",
           "only with `env.scene.obstacles`: a `Foot_Link` geom touches an obstacle box, [left, right] (also counted "
           "in `foot_contact`)", requires="obstacles"),
))  # fmt: skip

#: The env's done flags (its ``done_spec``), in spec order.
EPISODE_FLAGS = SignalTable((
    Signal("done", (1,), _BOOL, "", "terminated or truncated"),
    Signal("terminated", (1,), _BOOL, "", "early termination (spec §9.1)"),
    Signal("truncated", (1,), _BOOL, "", "time limit (8000 steps by default)"),
))  # fmt: skip

#: The bare env's reward (its ``reward_spec``).
REWARD = Signal("reward", (1,), _F32, "", "0 from the bare env: the task reward is a transform (`transforms.reward`)")
