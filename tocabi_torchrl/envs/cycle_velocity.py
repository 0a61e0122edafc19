"""The velocity-tracking error averaged over the last gait cycle, per world, rolling with each world's episode.

A walking pelvis sways sideways with each gait cycle and surges forward with each step, so the instantaneous error
``v − command`` is mostly the gait's own rhythm; a slow sideways walk of 0.02 m/s, 0.16 m of drift in the gait
tests' 8 s, is lost in it. Averaged over one cycle the rhythm cancels and such a bias is what remains: the robust
gait test's tracking error reads the same average (:class:`tocabi_torchrl.evaluation.robust.CycleMeanTracking`).
``TocabiWalk`` keeps one :class:`CycleVelocityError` with ``env.task.cycle_velocity`` and reports its mean as the
``cycle_vel_error`` signal, which the ``cycle_vel`` reward term reads.
"""

from __future__ import annotations

import torch

from ..rotations import quat_to_rpy

__all__ = ["CycleVelocityError", "gait_cycle_steps", "heading_velocity"]


def gait_cycle_steps(period: float, dt: float) -> int:
    """Policy steps in one gait cycle: ``round(period / dt)`` (the reference motion's 1.7995 s at 4 ms: 450)."""
    steps = round(float(period) / float(dt))
    if steps < 1:
        raise ValueError(f"a gait cycle of {period:g} s is shorter than one policy step ({dt:g} s)")
    return steps


def heading_velocity(base_quat: torch.Tensor, world_lin_vel: torch.Tensor) -> torch.Tensor:
    """(N, 2) horizontal pelvis velocity [m/s] in the heading frame (the world turned by the pelvis yaw ψ), from
    ``base_quat`` (N, 4) (w, x, y, z) and the pelvis's world-frame linear velocity ``world_lin_vel`` (N, 3) [m/s]
    (``qvel[:, :3]``). The command is meant in this frame.

    >>> quarter_turn = torch.tensor([[0.7071068, 0.0, 0.0, 0.7071068]])  # ψ = 90°: facing the world's +y
    >>> [round(v, 4) + 0.0 for v in heading_velocity(quarter_turn, torch.tensor([[0.0, 0.5, 0.0]]))[0].tolist()]
    [0.5, 0.0]
    """
    yaw = quat_to_rpy(base_quat)[..., 2]  # scale-invariant: a quaternion a little off unit turns the same
    c, s = torch.cos(yaw), torch.sin(yaw)
    vx, vy = world_lin_vel[..., 0], world_lin_vel[..., 1]
    return torch.stack((c * vx + s * vy, -s * vx + c * vy), -1)


class CycleVelocityError:
    """Per world, the mean of ``v − command`` [m/s] (N, 2) over its last ``window`` policy steps, or over the steps
    of its episode so far when fewer. The env's window is one gait cycle at the nominal phase rate (450 steps); a
    policy that speeds its phase clock up (the phase-rate action, up to 2×) walks up to two cycles in it, which still
    cancel the sway, and it is the window the robust test's tracking error reads.

    Each world writes its step k of an episode into ring slot ``(k − 1) mod window`` and keeps a float64 running sum
    (the value leaving the window cancels what it added up to float64 rounding over a 32 s episode). A reset only
    zeroes the world's sum: during its first ``window`` steps the slots still hold the previous episode's values,
    which are overwritten before they would leave the window, so nothing is subtracted until then. Every update
    is in place and branch-free on the device (a captured step replays it), with the step counts as tensors.

    >>> e = CycleVelocityError(num_envs=2, window=2, device="cpu")
    >>> for k, v in enumerate(([0.3, 0.0], [0.5, 0.2], [0.7, 0.0])):
    ...     e.update(torch.tensor([v, v]), torch.tensor([[0.5, 0.0]] * 2), torch.tensor([k + 1, k + 1]))
    >>> e.mean(torch.tensor([3, 3])).double().round(decimals=4).tolist()  # the last two: (0, 0.2), (0.2, 0)
    [[0.1, 0.1], [0.1, 0.1]]
    >>> e.reset(torch.tensor([True, False]))
    >>> e.mean(torch.tensor([0, 3])).double().round(decimals=4).tolist()  # the reset world: no step yet, 0
    [[0.0, 0.0], [0.1, 0.1]]
    """

    def __init__(self, num_envs: int, window: int, device: torch.device | str):
        if isinstance(window, bool) or not isinstance(window, int) or window < 1:
            raise ValueError(f"CycleVelocityError: window must be an int >= 1 policy step, got {window!r}")
        self.window = window
        #: (N, window, 2) float32 the errors of each world's last ``window`` steps [m/s].
        self.ring = torch.zeros(num_envs, window, 2, dtype=torch.float32, device=device)
        #: (N, 2) float64 their sum over the window (or the episode so far).
        self.total = torch.zeros(num_envs, 2, dtype=torch.float64, device=device)
        self._error = torch.zeros(num_envs, 2, dtype=torch.float32, device=device)

    def update(self, velocity: torch.Tensor, command: torch.Tensor, episode_step: torch.Tensor) -> None:
        """Account one policy step: ``velocity`` and ``command`` (N, 2) [m/s] in the heading frame after the step,
        ``episode_step`` (N,) int64 the step's number in each world's episode, >= 1 (1 for the first step after a
        reset); :meth:`mean` then reads the steps so far. A non-finite error is taken as 0, so that one overflowing
        step cannot poison the window for a whole episode."""
        torch.nan_to_num(torch.sub(velocity, command, out=self._error), nan=0.0, posinf=0.0, neginf=0.0,
                         out=self._error)
        slot = torch.remainder(episode_step - 1, self.window).view(-1, 1, 1).expand(-1, 1, 2)
        leaving = self.ring.gather(1, slot).squeeze(1)
        # A slot still holding the previous episode's value (the world's first `window` steps) adds nothing back.
        leaving = torch.where((episode_step > self.window).unsqueeze(-1), leaving, 0.0)
        self.total.sub_(leaving.double()).add_(self._error.double())
        self.ring.scatter_(1, slot, self._error.unsqueeze(1))

    def mean(self, episode_step: torch.Tensor) -> torch.Tensor:
        """(N, 2) float32 the mean error over each world's last ``min(episode_step, window)`` steps [m/s] (0 before
        its first step)."""
        count = episode_step.clamp(1, self.window).unsqueeze(-1)
        return (self.total / count).float()

    def reset(self, mask: torch.Tensor) -> None:
        """Start the worlds of ``mask`` (N,) bool afresh (their running sum to 0)."""
        self.total.masked_fill_(mask.unsqueeze(-1), 0.0)
