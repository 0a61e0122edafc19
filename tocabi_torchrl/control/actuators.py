"""The actuator layer: what happens to a torque command between the controller and the joint.

TocabiLab's actuator model (report §3.3) is ``τ = τ_cmd − F_resist(τ_cmd, ...)``; here it is a chain of stages, each
acting per world and joint on the command of one joint group:

====================== ============================================================== ================================
stage                  applied torque                                                 per-world parameter, drawn at
                                                                                      reset
====================== ============================================================== ================================
:class:`Delay`         the command of k physics substeps ago (k per world)            k ~ U{low, ..., high} substeps
:class:`AveragedDelay` the same delayed torque averaged over each policy step          k ~ U{low, ..., high} substeps
:class:`MotorConstant` ``c · τ``                                                      c ~ U(low, high) per joint
:class:`Friction`      ``τ − (F_c·sign(q̇) + F_v·q̇)`` (report eq. 3.6: Coulomb and     F_c, F_v ~ U(low, high) per
                       viscous resistance), q̇ the joint velocity before the step     joint
:class:`Saturation`    ``clip(τ, ±limit)``                                            (the joints' limits)
====================== ============================================================== ================================

An ideal actuator is the empty chain (nothing runs). Without a :class:`Delay` a stage maps (N, J) torques to (N, J)
torques, held for the policy step. A :class:`Delay` turns the command into (N, S, J) torques, one per physics substep
(S = substeps per policy step), which the simulator applies substep by substep (``SimConfig.substep_ctrl``); the
stages after it act on each substep's torque. An :class:`AveragedDelay` holds that torque's mean over the step
instead: the same impulse per step, (N, J) like the other stages.

Parameters live in (N, J) device tensors (a delay's k: (N,)) that :meth:`Actuator.reset` redraws in place for the
flagged worlds from uniforms the env supplies (``episode_uniform``: the same draws whichever reset path runs), so a
captured step graph keeps working across resets. Friction reads the joint velocity before the step, so it is held for
the step like the command (the PD modes' servos, which run inside the physics, take no actuator stages).

>>> import torch
>>> from tocabi_torchrl.control import ActuatorChain, MotorConstant, Saturation
>>> from tocabi_torchrl.control.base import ControlContext, ControlInput
>>> ctx = ControlContext(num_envs=2, device=torch.device("cpu"), joint_ids=(0,), torque_limits=torch.tensor([10.0]),
...                      joint_range=torch.tensor([[-1.0, 1.0]]))
>>> chain = ActuatorChain([MotorConstant(1.5, 1.5), Saturation()])
>>> chain.setup(ctx)
>>> chain.reset(torch.ones(2, dtype=torch.bool), torch.zeros(2, chain.draws))
>>> chain(torch.tensor([[4.0], [8.0]]), ControlInput(action=None)).tolist()
[[6.0], [10.0]]
"""

from __future__ import annotations

import abc
import math
import operator

import torch

from .base import ControlContext, ControlInput

__all__ = ["Actuator", "ActuatorChain", "AveragedDelay", "Delay", "Friction", "MotorConstant", "Saturation"]


def _per_joint(tau: torch.Tensor, values: torch.Tensor) -> torch.Tensor:
    """``values`` (N, J) shaped to broadcast against ``tau``, (N, J) or (N, S, J)."""
    return values if tau.dim() == 2 else values.unsqueeze(1)


def _uniform_range(pair, what: str) -> tuple[float, float]:
    """``pair`` as (low, high) floats with 0 <= low <= high, finite, else a ``ValueError`` naming ``what``: every
    stage's parameter is a scale or a resistance (a negative motor constant flipped the torque's sign), as
    ``ActuatorConfig`` requires."""
    try:
        low, high = (float(v) for v in pair)
    except (TypeError, ValueError):
        raise ValueError(f"{what} must be two numbers (low, high), got {pair!r}") from None
    if not (math.isfinite(low) and math.isfinite(high)) or not 0.0 <= low <= high:
        raise ValueError(f"{what} must be (low, high) with 0 <= low <= high, finite, got {pair!r}")
    return low, high


def _described(t) -> str:
    """``t``'s shape and dtype for an error message, or its type when it is not a tensor."""
    return f"{tuple(t.shape)} {t.dtype}" if isinstance(t, torch.Tensor) else type(t).__name__


def _substeps(value, what: str) -> int:
    """``value`` as an int (a numpy or 0-d tensor integer too), else a ``ValueError`` naming ``what``."""
    if isinstance(value, bool):
        raise ValueError(f"Delay {what} takes a whole number of substeps, got {value!r}")
    try:
        return operator.index(value)
    except TypeError:
        raise ValueError(f"Delay {what} takes a whole number of substeps, got {value!r}") from None


class Actuator(abc.ABC):
    """One stage of the actuator layer (see the module docstring)."""

    #: Uniforms in [0, 1) per world that :meth:`reset` reads (set in :meth:`setup`).
    draws: int = 0

    def setup(self, ctx: ControlContext) -> None:
        """Allocate the per-world parameters for ``ctx.num_envs`` worlds and ``len(ctx.joint_ids)`` joints."""
        self.ctx = ctx
        # Resolved once ("cuda" -> "cuda:0"), so that an input's device is checked by one comparison.
        self._device = torch.empty(0, device=ctx.device).device

    @abc.abstractmethod
    def __call__(self, tau: torch.Tensor, inp: ControlInput) -> torch.Tensor:
        """The torque after this stage: (N, J) or (N, S, J) [N·m] in, the same shape out (:class:`Delay`: (N, J)
        in, (N, S, J) out). The built-in stages refuse a torque (or ``ControlInput.qd``) of another shape or on
        another device than ``ctx.device`` with a ``ValueError``."""

    def reset(self, mask: torch.Tensor, u: torch.Tensor) -> None:
        """Redraw the parameters of the worlds flagged in ``mask`` (N,) bool from ``u`` (N, :attr:`draws`) uniforms
        in [0, 1), in place. The built-in stages (and :class:`ActuatorChain`) refuse a mask or u of another shape,
        a mask that is not bool or a u that is not float with a ``ValueError``."""

    def nominal(self, mask: torch.Tensor) -> None:
        """Give the worlds flagged in ``mask`` (N,) bool the ideal actuator's parameters (no scale, friction or
        delay), in place: the env's worlds that are not randomised (``TocabiWalk.set_randomized_worlds``). A
        stage without parameters has nothing to do."""

    # The checks below read shapes, dtypes and devices only (Python attributes: no host sync, nothing captured in
    # a CUDA graph), and run before any tensor work: a torque or draw of the wrong width broadcast silently against
    # the (N, J) parameters, and a missing input failed as a raw TypeError deep inside torch.
    def _check_input(self, what: str, t, substeps: bool = False) -> None:
        """Raise ``ValueError`` unless ``t`` is an (N, J) tensor (or, with ``substeps``, (N, S, J)) on the stage's
        device; ``what`` names it in the message."""
        n, j = self.ctx.num_envs, len(self.ctx.joint_ids)
        if (isinstance(t, torch.Tensor) and t.dim() in ((2, 3) if substeps else (2,)) and t.shape[0] == n
                and t.shape[-1] == j):
            if t.device == self._device:
                return
            raise ValueError(f"{type(self).__name__} got {what} on {t.device}, its parameters are on {self._device}: "
                             "pass it on the env's device (ControlContext.device)")
        want = f"(N, J) = ({n}, {j})" + (" or (N, S, J)" if substeps else "")
        raise ValueError(f"{type(self).__name__} takes {what} of shape {want}, got {_described(t)}")

    def _check_mask(self, method: str, mask) -> None:
        """Raise ``ValueError`` unless ``mask`` is an (N,) bool tensor on the stage's device."""
        n = self.ctx.num_envs
        if not (isinstance(mask, torch.Tensor) and mask.dtype == torch.bool and tuple(mask.shape) == (n,)):
            raise ValueError(f"{type(self).__name__}.{method} takes mask of shape (N,) = ({n},) torch.bool, got "
                             f"{_described(mask)}")
        if mask.device != self._device:
            raise ValueError(f"{type(self).__name__}.{method} got mask on {mask.device}, its parameters are on "
                             f"{self._device}")

    def _check_reset(self, mask, u) -> None:
        """Raise ``ValueError`` unless ``mask`` is (N,) bool and ``u`` (N, :attr:`draws`) float, both on the stage's
        device: a narrower u gave every joint the same draw, a (1, draws) one every world the same."""
        self._check_mask("reset", mask)
        n = self.ctx.num_envs
        if not (isinstance(u, torch.Tensor) and u.is_floating_point() and tuple(u.shape) == (n, self.draws)):
            raise ValueError(f"{type(self).__name__}.reset takes u of shape (N, draws) = ({n}, {self.draws}) "
                             f"float uniforms in [0, 1), got {_described(u)}")
        if u.device != self._device:
            raise ValueError(f"{type(self).__name__}.reset got u on {u.device}, its parameters are on {self._device}")


class _UniformPerJoint(Actuator):
    """A stage with parameters drawn per world and joint from U(low, high)."""

    #: The ideal actuator's value of each range's parameter (:meth:`nominal`).
    identity: tuple[float, ...] = ()

    def __init__(self, **ranges: tuple[float, float]):
        self.ranges = [_uniform_range(pair, f"{type(self).__name__} {name}") for name, pair in ranges.items()]

    def setup(self, ctx: ControlContext) -> None:
        super().setup(ctx)
        j = len(ctx.joint_ids)
        self.draws = j * len(self.ranges)
        #: One (N, J) tensor per range, the current worlds' values.
        self.values = [torch.full((ctx.num_envs, j), lo, dtype=torch.float32, device=ctx.device)
                       for lo, _ in self.ranges]

    def reset(self, mask: torch.Tensor, u: torch.Tensor) -> None:
        self._check_reset(mask, u)
        j = len(self.ctx.joint_ids)
        for i, ((lo, hi), value) in enumerate(zip(self.ranges, self.values)):
            drawn = lo + (hi - lo) * u[:, i * j:(i + 1) * j]
            torch.where(mask.unsqueeze(-1), drawn, value, out=value)

    def nominal(self, mask: torch.Tensor) -> None:
        self._check_mask("nominal", mask)
        for ideal, value in zip(self.identity, self.values):
            value.masked_fill_(mask.unsqueeze(-1), ideal)


class MotorConstant(_UniformPerJoint):
    """``c · τ`` with the motor-constant scale c ~ U(low, high) per world and joint (1 = the nominal motor;
    0 <= low <= high)."""

    identity = (1.0,)

    def __init__(self, low: float = 1.0, high: float = 1.0):
        super().__init__(scale=(low, high))

    @property
    def scale(self) -> torch.Tensor:
        """(N, J) the current scale of each world's joints."""
        return self.values[0]

    def __call__(self, tau: torch.Tensor, inp: ControlInput) -> torch.Tensor:
        self._check_input("tau", tau, substeps=True)
        return tau * _per_joint(tau, self.values[0])


class Friction(_UniformPerJoint):
    """``τ − (F_c·sign(q̇) + F_v·q̇)``: Coulomb F_c [N·m] ~ U(coulomb) and viscous F_v [N·m·s/rad] ~ U(viscous) per
    world and joint, with q̇ the joint velocity before the step (``ControlInput.qd``)."""

    identity = (0.0, 0.0)

    def __init__(self, coulomb: tuple[float, float] = (0.0, 0.0), viscous: tuple[float, float] = (0.0, 0.0)):
        super().__init__(coulomb=coulomb, viscous=viscous)

    def __call__(self, tau: torch.Tensor, inp: ControlInput) -> torch.Tensor:
        self._check_input("tau", tau, substeps=True)
        if inp.qd is None:
            n, j = self.ctx.num_envs, len(self.ctx.joint_ids)
            raise ValueError(f"Friction needs the joint velocity before the step, ControlInput.qd of shape (N, J) = "
                             f"({n}, {j}) [rad/s], and got none: pass ControlInput(action=..., qd=...)")
        self._check_input("ControlInput.qd (the joint velocity before the step)", inp.qd)
        resist = self.values[0] * torch.sign(inp.qd) + self.values[1] * inp.qd
        return tau - _per_joint(tau, resist)


class Saturation(Actuator):
    """``clip(τ, ±limit)`` at the joints' torque limits (``ControlContext.torque_limits``)."""

    def setup(self, ctx: ControlContext) -> None:
        super().setup(ctx)
        j = len(ctx.joint_ids)
        if not isinstance(ctx.torque_limits, torch.Tensor) or tuple(ctx.torque_limits.shape) != (j,):
            raise ValueError(f"Saturation takes ControlContext.torque_limits of shape (J,) = ({j},) [N·m], got "
                             f"{_described(ctx.torque_limits)}")

    def __call__(self, tau: torch.Tensor, inp: ControlInput) -> torch.Tensor:
        self._check_input("tau", tau, substeps=True)
        limits = self.ctx.torque_limits
        return torch.maximum(torch.minimum(tau, limits), -limits)


class Delay(Actuator):
    """The command of k physics substeps ago, k ~ U{low, low + stride, ..., high} per world (0: none).

    The command is constant within a policy step of S substeps, so the torque in substep s of step t is the command
    of step ``t − ceil((k − s) / S)`` (step t's own from substep k on). A device shift register keeps the last
    ``ceil(high / S) + 1`` commands; a reset world's history is cleared to zero torque.

    Args:
        low, high: the delay range in physics substeps (0.5 ms each at 2 kHz).
        substeps: S, physics substeps per policy step (the env passes its ``sim.substeps``).
        stride: the step of the delay's grid [substeps] (``ActuatorConfig.delay_stride``); ``high - low`` a
            multiple of it.

    >>> Delay(4, 20, substeps=8, stride=8).values()
    [4, 12, 20]
    """

    def __init__(self, low: int = 0, high: int = 0, substeps: int = 8, stride: int = 1):
        low, high = _substeps(low, "low"), _substeps(high, "high")
        substeps, stride = _substeps(substeps, "substeps"), _substeps(stride, "stride")
        if not 0 <= low <= high or substeps < 1 or stride < 1 or (high - low) % stride:
            raise ValueError(f"Delay needs 0 <= low <= high substeps, substeps >= 1 and a stride >= 1 that divides "
                             f"high - low, got ({low}, {high}), {substeps}, stride {stride}")
        self.low, self.high, self.substeps, self.stride = low, high, substeps, stride
        self.draws = 1

    def setup(self, ctx: ControlContext) -> None:
        super().setup(ctx)
        n, j, s, dev = ctx.num_envs, len(ctx.joint_ids), self.substeps, ctx.device
        depth = -(-self.high // s) + 1
        #: (N, depth, J) the last commands, newest first [N·m].
        self.history = torch.zeros(n, depth, j, dtype=torch.float32, device=dev)
        #: (N,) int64 each world's delay k [substeps].
        self.delay = torch.full((n,), self.low, dtype=torch.int64, device=dev)
        self._setup_reader()
        self._set_lag()

    def _setup_reader(self) -> None:
        """The buffers that say which history slot each substep reads (:meth:`_set_lag` fills them)."""
        n, j, s, dev = self.ctx.num_envs, self.history.shape[2], self.substeps, self.ctx.device
        self._substep = torch.arange(s, dtype=torch.int64, device=dev)
        self._lag = torch.zeros(n, s, j, dtype=torch.int64, device=dev)  # history index read in each substep

    def _set_lag(self) -> None:
        lag = ((self.delay.unsqueeze(-1) - self._substep).clamp(min=0) + self.substeps - 1) // self.substeps
        self._lag.copy_(lag.unsqueeze(-1).expand_as(self._lag))

    def _push(self, tau: torch.Tensor) -> None:
        """Shift the command register by one step and put ``tau`` (N, J) at its front (in place)."""
        self.history.copy_(torch.roll(self.history, 1, dims=1))
        self.history[:, 0].copy_(tau)

    def __call__(self, tau: torch.Tensor, inp: ControlInput) -> torch.Tensor:
        self._check_input("tau", tau)
        self._push(tau)
        return torch.gather(self.history, 1, self._lag)

    def values(self) -> list[int]:
        """The delays a world can draw [substeps]."""
        return list(range(self.low, self.high + 1, self.stride))

    def reset(self, mask: torch.Tensor, u: torch.Tensor) -> None:
        self._check_reset(mask, u)
        span = (self.high - self.low) // self.stride + 1
        k = self.low + self.stride * (u[:, 0] * span).long().clamp(max=span - 1)
        torch.where(mask, k, self.delay, out=self.delay)
        self._set_lag()
        self.history.masked_fill_(mask.view(-1, 1, 1), 0.0)

    def nominal(self, mask: torch.Tensor) -> None:
        self._check_mask("nominal", mask)
        self.delay.masked_fill_(mask, 0)
        self._set_lag()


class AveragedDelay(Delay):
    """:class:`Delay`'s torque averaged over each policy step: one (N, J) torque per step, not (N, S, J).

    With k = m·S + r (0 <= r < S), the delayed torque of step t is the command of step t − m − 1 in the step's
    first r substeps and that of step t − m in the others; this stage applies ``(r/S)·τ[t−m−1] + (1 − r/S)·τ[t−m]``
    through the whole step. Each step's impulse is the delayed torque's, to the substep, and so is the delay of a
    slow change; only the shape within one 4 ms step differs. What it buys on a GPU: every world's torque changes
    at the step's first substep, as without a delay, so no substep waits on the worlds a torque change made slow to
    solve (mujoco-warp solves a substep's worlds in lockstep; ``ActuatorConfig.delay_average``).

    Args: as :class:`Delay`'s.

    >>> import torch
    >>> from tocabi_torchrl.control.base import ControlContext, ControlInput
    >>> ctx = ControlContext(num_envs=1, device=torch.device("cpu"), joint_ids=(0,),
    ...                      torque_limits=torch.tensor([10.0]), joint_range=torch.tensor([[-1.0, 1.0]]))
    >>> stage = AveragedDelay(6, 6, substeps=8)  # 6 of 8 substeps still carry the previous command
    >>> stage.setup(ctx)
    >>> stage(torch.tensor([[8.0]]), ControlInput(action=None)).tolist()  # the previous command was 0
    [[2.0]]
    """

    def _setup_reader(self) -> None:
        #: (N, depth) the weight of each history slot in the step's torque (two slots per world).
        self._weights = torch.zeros(self.ctx.num_envs, self.history.shape[1], dtype=torch.float32,
                                    device=self.ctx.device)

    def _set_lag(self) -> None:
        s, depth = self.substeps, self.history.shape[1]
        newer = (self.delay // s).unsqueeze(-1)
        older_share = (self.delay % s).unsqueeze(-1).to(torch.float32) / s
        # A delay of exactly ceil(high / S) steps has no older slot in the register; its share is 0 there.
        self._weights.zero_()
        self._weights.scatter_add_(1, newer, 1.0 - older_share)
        self._weights.scatter_add_(1, (newer + 1).clamp(max=depth - 1), older_share)

    def __call__(self, tau: torch.Tensor, inp: ControlInput) -> torch.Tensor:
        self._check_input("tau", tau)
        self._push(tau)
        return torch.bmm(self._weights.unsqueeze(1), self.history).squeeze(1)


class ActuatorChain(Actuator):
    """Stages applied in order; :attr:`per_substep` is True when one is a :class:`Delay` that is not an
    :class:`AveragedDelay` (at most one delay)."""

    def __init__(self, stages: list[Actuator]):
        self.stages = list(stages)
        for stage in self.stages:
            if not isinstance(stage, Actuator):  # a class or a config failed only at setup or the first step
                raise ValueError(f"an actuator chain takes Actuator instances, got {stage!r}")
        delays = [s for s in self.stages if isinstance(s, Delay)]
        if len(delays) > 1:
            raise ValueError("an actuator chain takes at most one Delay")
        #: True: the chain returns one torque per physics substep, (N, S, J).
        self.per_substep = bool(delays) and not isinstance(delays[0], AveragedDelay)
        self.substeps = delays[0].substeps if self.per_substep else 1

    def setup(self, ctx: ControlContext) -> None:
        super().setup(ctx)
        for stage in self.stages:
            stage.setup(ctx)
        self.draws = sum(stage.draws for stage in self.stages)

    def __call__(self, tau: torch.Tensor, inp: ControlInput) -> torch.Tensor:
        self._check_input("tau", tau)
        for stage in self.stages:
            tau = stage(tau, inp)
        return tau

    def reset(self, mask: torch.Tensor, u: torch.Tensor) -> None:
        self._check_reset(mask, u)
        start = 0
        for stage in self.stages:
            stage.reset(mask, u[:, start:start + stage.draws])
            start += stage.draws

    def nominal(self, mask: torch.Tensor) -> None:
        self._check_mask("nominal", mask)
        for stage in self.stages:
            stage.nominal(mask)

    def __len__(self) -> int:
        return len(self.stages)
