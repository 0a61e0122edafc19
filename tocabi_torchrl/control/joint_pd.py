"""Joint PD laws: position targets tracked by servos inside every physics substep, and the upper body's hold."""

from __future__ import annotations

import math

import torch

from .. import robot
from .base import ControlContext, ControlInput, Controller

__all__ = ["JointPD", "PDHold", "per_joint"]


def per_joint(values, n: int, what: str, minimum: float | None = None) -> torch.Tensor:
    """``values`` as an (n,) float32 CPU tensor, one finite number per joint of a group (each >= ``minimum`` where
    given), else a ``ValueError`` naming ``what``. Reads the values on the host: for set-up time, never a step.

    Without it a wrong count failed as a raw reshape or index error, and NaN or a negative gain (a servo that pushes
    away from its target) was taken without a word."""
    try:
        vector = torch.as_tensor(values, dtype=torch.float32).detach().cpu()
    except (TypeError, ValueError, RuntimeError):
        raise ValueError(f"{what} must be {n} numbers, one per joint of the group, got {values!r}") from None
    if vector.shape != (n,):
        raise ValueError(f"{what} must be {n} numbers, one per joint of the group, got shape {tuple(vector.shape)}: "
                         f"{values!r}")
    bad = [(i, v) for i, v in enumerate(vector.tolist())
           if not math.isfinite(v) or (minimum is not None and v < minimum)]
    if bad:
        rule = "a finite number" + (f" >= {minimum:g}" if minimum is not None else "")
        raise ValueError(f"{what}: each joint's value must be {rule}, got "
                         + ", ".join(f"[{i}] = {v!r}" for i, v in bad))
    return vector


def _vector(values, n: int, device: torch.device, what: str, minimum: float | None = None) -> torch.Tensor:
    """:func:`per_joint` on ``device``."""
    return per_joint(values, n, what, minimum).to(device)


def _finite(value, what: str) -> float:
    """``value`` as a finite float, else a ``ValueError`` naming ``what`` (a NaN scale made every command NaN)."""
    try:
        number = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{what} must be a finite number, got {value!r}") from None
    if not math.isfinite(number):
        raise ValueError(f"{what} must be a finite number, got {value!r}")
    return number


class JointPD(Controller):
    """Target ``centre + scale · a`` clipped to the joint range, tracked by position servos with gains ``kp``/``kv``
    inside every physics substep, force-limited to the torque limits.

    Args:
        kp, kv: (J,) servo gains [N·m/rad], [N·m·s/rad], each >= 0.
        scale: target offset per unit action [rad].
        nominal: (J,) the fixed centre [rad] (``centre="nominal"``) and the pose a reset world's servos hold.
        centre: ``"nominal"`` (absolute targets around ``nominal``: TocabiLab's position policy, mode ``pd``) or
            ``"reference"`` (residuals around the reference walk: mode ``pd_reference``).
    """

    servo = True

    def __init__(self, kp, kv, scale: float, nominal, centre: str = "reference", action_dim: int = 12):
        if centre not in ("nominal", "reference"):
            raise ValueError(f"JointPD centre must be 'nominal' or 'reference', got {centre!r}")
        self.kp, self.kv, self.nominal, self.centre = kp, kv, nominal, centre
        self.scale = _finite(scale, "JointPD scale [rad per action unit]")
        self.action_dim = action_dim

    def setup(self, ctx: ControlContext) -> None:
        super().setup(ctx)
        j, dev = len(ctx.joint_ids), ctx.device
        self._kp = _vector(self.kp, j, dev, "JointPD kp [N·m/rad]", minimum=0.0)
        self._kv = _vector(self.kv, j, dev, "JointPD kv [N·m·s/rad]", minimum=0.0)
        self._nominal = _vector(self.nominal, j, dev, "JointPD nominal [rad]")
        self._low, self._high = ctx.joint_range[:, 0], ctx.joint_range[:, 1]
        self._check_nominal_in_range()

    def _check_nominal_in_range(self) -> None:
        """A nominal pose outside a joint's range (one in degrees) was taken: the reset's servos chased it and
        :meth:`compute` clipped the ``pd`` mode's centre to the range's end, so the legs were driven to their
        limits without a word. The range may be the faulty side instead: one that leaves out the robot's initial
        pose (``robot.INIT_JOINT_POS``, the default nominal) too is the model file's, and is named as such."""
        nominal, low, high = (t.cpu().tolist() for t in (self._nominal, self._low, self._high))
        outside = [(robot.JOINT_NAMES[joint], v, lo, hi, lo <= robot.INIT_JOINT_POS[joint] <= hi)
                   for joint, v, lo, hi in zip(self.ctx.joint_ids, nominal, low, high) if not lo <= v <= hi]
        if not outside:
            return
        model = self.ctx.model_file or "the model file"
        shown = ", ".join(f"{name} = {v:.3f} rad (range [{lo:.3f}, {hi:.3f}])" for name, v, lo, hi, _ in outside)
        checks = []
        if any(holds for *_, holds in outside):
            checks.append("give radians (not degrees) within each joint's range, in robot.JOINT_NAMES order")
        narrow = [name for name, *_, holds in outside if not holds]
        if narrow:
            checks.append(f"the range of {', '.join(narrow)} leaves out the robot's initial pose "
                          f"(robot.INIT_JOINT_POS) too: check {'them' if len(narrow) > 1 else 'it'} in {model}")
        raise ValueError(f"JointPD nominal (env.control.pd_nominal) is outside the model's joint range: {shown}, the "
                         f"ranges of {model}; {'; '.join(checks)}")

    def compute(self, inp: ControlInput) -> torch.Tensor:
        centre = self._nominal if self.centre == "nominal" else inp.q_ref
        target = centre + self.scale * inp.action
        return torch.maximum(torch.minimum(target, self._high), self._low)

    def reset_command(self) -> torch.Tensor:
        return self._nominal.clone()

    def servo_gains(self):
        return self.kp, self.kv


class PDHold(Controller):
    """Hold the group at the reference walk's pose with the model file's own position servos (the upper body:
    no action, its targets ``q_ref`` every step)."""

    servo = True
    action_dim = 0

    def compute(self, inp: ControlInput) -> torch.Tensor:
        return inp.q_ref
