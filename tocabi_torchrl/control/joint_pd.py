"""Joint PD laws: position targets tracked by servos inside every physics substep, and the upper body's hold."""

from __future__ import annotations

import torch

from .base import ControlContext, ControlInput, Controller

__all__ = ["JointPD", "PDHold"]


def _vector(values, n: int, device: torch.device) -> torch.Tensor:
    return torch.as_tensor(values, dtype=torch.float32, device=device).reshape(n)


class JointPD(Controller):
    """Target ``centre + scale · a`` clipped to the joint range, tracked by position servos with gains ``kp``/``kv``
    inside every physics substep, force-limited to the torque limits.

    Args:
        kp, kv: (J,) servo gains [N·m/rad], [N·m·s/rad].
        scale: target offset per unit action [rad].
        nominal: (J,) the fixed centre [rad] (``centre="nominal"``) and the pose a reset world's servos hold.
        centre: ``"nominal"`` (absolute targets around ``nominal``: TocabiLab's position policy, mode ``pd``) or
            ``"reference"`` (residuals around the reference walk: mode ``pd_reference``).
    """

    servo = True

    def __init__(self, kp, kv, scale: float, nominal, centre: str = "reference", action_dim: int = 12):
        if centre not in ("nominal", "reference"):
            raise ValueError(f"JointPD centre must be 'nominal' or 'reference', got {centre!r}")
        self.kp, self.kv, self.scale, self.nominal, self.centre = kp, kv, float(scale), nominal, centre
        self.action_dim = action_dim

    def setup(self, ctx: ControlContext) -> None:
        super().setup(ctx)
        j = len(ctx.joint_ids)
        self._kp, self._kv = _vector(self.kp, j, ctx.device), _vector(self.kv, j, ctx.device)
        self._nominal = _vector(self.nominal, j, ctx.device)
        self._low, self._high = ctx.joint_range[:, 0], ctx.joint_range[:, 1]

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
