"""The obstacle experiment's analysis of a recorded rollout (:class:`~.gait_record.GaitRecord`) with one box on the
robot's path (``lab/experiments/obstacle_test.py``, TocabiLab's experiment 3).

Definitions, per robot (env):

* **on the obstacle**: a foot touches the box: the env's ``obstacle_contact`` signal when it has one; otherwise (or
  for a height-0 "virtual" box, i.e. no box at all) the sole's footprint overlaps the box's footprint while the
  sole's lowest point is within ``contact_margin`` (1 cm) of the box top. The first such step is the **first
  contact**.
* **a step**: one footfall: a foot touching down (ground or box) after at least ``min_air_s`` (0.2 s) in the air,
  i.e. at the end of a swing (a landing foot bounces: gaps of up to ~60 ms in its contact are not steps). **The first
  3 steps on the obstacle** run from the first contact until the third footfall after it (or the end of the robot's
  episode).
* **reached**: a sole's front edge got past the box's near edge (x) while the robot was up; **crossed**: both
  soles' rear edges got past the box's far edge while up.
* **pass**: the robot survived the whole episode (no termination). **failed on the obstacle** (TocabiLab's failure):
  it terminated after its first contact with the box; **failed before**: it terminated without having touched it.
* **lateral deviation after the obstacle**: |pelvis y at its last alive step − pelvis y when the pelvis passed the
  box centre's x|, for robots whose pelvis passed it.
* torque metrics inside the 3-step window (hip pitch, knee and ankle pitch of both legs): the peak |τ| and the mean
  |τ_k − τ_(k−1)| per policy step (:func:`~.gait_record.torque_stats`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from .gait_record import CRITICAL, GaitRecord, torque_stats

__all__ = ["ObstacleOutcome", "analyse_obstacle", "footfalls", "on_box_geometric", "pick_example", "step_window"]


@dataclass
class ObstacleOutcome:
    """Per-robot results of :func:`analyse_obstacle` ((N,) tensors unless noted) and their summary row."""

    on_box: torch.Tensor  #: (T, N, 2) bool, a foot on the box
    first_contact: torch.Tensor  #: int64 step of the first contact, -1 for none
    window: torch.Tensor  #: (T, N) bool, the first 3 steps on the obstacle
    reached: torch.Tensor
    crossed: torch.Tensor
    passed: torch.Tensor  #: survived the whole episode
    failed_on_obstacle: torch.Tensor
    failed_before: torch.Tensor
    lateral_after: torch.Tensor  #: [m], NaN where the pelvis never passed the box centre
    window_peak: torch.Tensor  #: (N, 6) [N·m] max |τ| in the window per critical joint (NaN without a window)
    window_variation: torch.Tensor  #: [N·m/step] mean |Δτ| in the window over the critical joints
    contact_source: str  #: "obstacle_contact signal" or "sole geometry"
    summary: dict  #: the table row's values


def on_box_geometric(record: GaitRecord, centre: torch.Tensor, size, contact_margin: float = 0.01) -> torch.Tensor:
    """(T, N, 2) bool: the sole's footprint overlaps the box's (``centre`` (N, 3) [m], ``size`` (3,) full sizes
    [m]) in x and y while the sole's lowest point (a flat sole's) is at most ``contact_margin`` [m] above the box
    top (the box top is at z = size[2]; a 0-height box is the ground's footprint)."""
    sole = record.sole_pos  # (T, N, 2, 3)
    half = torch.as_tensor(record.sole_half_size, dtype=sole.dtype)
    size = torch.as_tensor(size, dtype=sole.dtype)
    c = centre[None, :, None, :].to(sole.dtype)
    overlap_x = (sole[..., 0] - c[..., 0]).abs() <= half[:, 0] + size[0] / 2
    overlap_y = (sole[..., 1] - c[..., 1]).abs() <= half[:, 1] + size[1] / 2
    low = sole[..., 2] - half[:, 2] <= size[2] + contact_margin
    return overlap_x & overlap_y & low


def footfalls(contact: torch.Tensor, min_air_steps: int = 50) -> torch.Tensor:
    """(T, N) bool: a foot touches down at step k after at least ``min_air_steps`` steps in the air (``contact``:
    (T, N, 2) bool foot contact)."""
    air = (~contact).to(torch.int32)
    t = contact.shape[0]
    # air steps in [k - min_air_steps, k - 1] from a cumulative sum (0 before the rollout: the feet start down)
    csum = torch.cat((torch.zeros_like(air[:1]), air.cumsum(0)), 0)  # csum[k] = air steps before k
    k = torch.arange(t)
    lo = (k - min_air_steps).clamp_min(0)
    in_air = (csum[k] - csum[lo]) >= min_air_steps
    down = contact & in_air & (k >= min_air_steps).view(-1, 1, 1)
    return down.any(-1)


def step_window(first_contact: torch.Tensor, falls: torch.Tensor, alive: torch.Tensor, steps: int = 3) -> torch.Tensor:
    """(T, N) bool: from each robot's ``first_contact`` step (-1: none, empty window) until its ``steps``-th
    footfall after it (exclusive), within its alive steps."""
    t = falls.shape[0]
    k = torch.arange(t).view(-1, 1)
    count = falls.long().cumsum(0)  # footfalls at or before k
    start = first_contact.clamp_min(0)
    at_start = count.gather(0, start.view(1, -1))
    window = (k >= start) & (count - at_start < steps) & (first_contact >= 0)
    return window & alive


def analyse_obstacle(record: GaitRecord, centre: torch.Tensor, size, virtual: bool = False,
                     steps: int = 3, contact_margin: float = 0.01, min_air_s: float = 0.2) -> ObstacleOutcome:
    """Apply the module's definitions to ``record`` (on the CPU) for a box of full ``size`` (3,) [m] centred at
    ``centre`` (N, 3) [m] per robot; ``virtual``: there is no box (height 0), only its footprint."""
    rec = record
    centre = torch.as_tensor(centre, dtype=torch.float32)
    size = tuple(float(v) for v in size)
    if rec.obstacle_contact is not None and not virtual:
        on_box, source = rec.obstacle_contact, "obstacle_contact signal"
    else:
        on_box, source = on_box_geometric(rec, centre, size, contact_margin), "sole geometry"
    alive = rec.alive
    touching = (on_box.any(-1) & alive)
    t, n = touching.shape
    has = touching.any(0)
    first = torch.where(has, touching.float().argmax(0), torch.full((n,), -1))
    contact = rec.foot_contact | on_box
    min_air_steps = max(1, int(round(min_air_s / rec.dt)))
    window = step_window(first, footfalls(contact, min_air_steps), alive, steps)

    half = torch.as_tensor(rec.sole_half_size, dtype=torch.float32)
    near, far = centre[:, 0] - size[0] / 2, centre[:, 0] + size[0] / 2
    front = rec.sole_pos[..., 0] + half[:, 0]  # (T, N, 2)
    rear = rec.sole_pos[..., 0] - half[:, 0]
    reached = ((front.amax(-1) >= near) & alive).any(0)
    crossed = ((rear.amin(-1) > far) & alive).any(0)

    term = rec.termination_step
    terminated = term >= 0
    passed = ~terminated
    failed_on = terminated & has  # a contact needs the robot alive, so it came before the termination
    failed_before = terminated & ~failed_on

    pelvis_x = rec.base_pos[..., 0]
    past = (pelvis_x >= centre[:, 0]) & alive
    crossed_pelvis = past.any(0)
    at_cross = past.float().argmax(0)
    y_cross = rec.base_pos[at_cross, torch.arange(n), 1]
    last = torch.where(terminated, (term - 1).clamp_min(0), torch.full_like(term, t - 1))
    y_end = rec.base_pos[last, torch.arange(n), 1]
    lateral_after = torch.where(crossed_pelvis, (y_end - y_cross).abs(), torch.tensor(float("nan")))

    stats = torque_stats(rec, joints=CRITICAL, window=window)
    peak, variation = stats["peak"], stats["smoothness"]
    nan = float("nan")

    def mean(x, mask=None):
        x = x.float() if mask is None else x[mask].float()
        x = x[~torch.isnan(x)]
        return float(x.mean()) if x.numel() else nan

    summary = {
        "num_envs": n,
        "pass_rate": mean(passed),
        "failed_on_obstacle_rate": mean(failed_on),
        "failed_before_obstacle_rate": mean(failed_before),
        "stepped_on_rate": mean(has),
        "reached_rate": mean(reached),
        "crossed_rate": mean(crossed),
        "lateral_deviation_after_m": mean(lateral_after),
        "lateral_drift_m": float(rec.per_env["lateral_m"].abs().mean()) if rec.per_env else nan,
        "forward_distance_m": float(rec.per_env["forward_m"].mean()) if rec.per_env else nan,
        "peak_torque_on_obstacle_Nm": mean(peak.amax(-1)),
        "torque_variation_on_obstacle_Nm_per_step": mean(variation),
        "peak_torque_on_obstacle_per_joint_Nm": [mean(peak[:, j]) for j in range(peak.shape[1])],
        "contact_source": source,
    }
    return ObstacleOutcome(on_box=on_box, first_contact=first, window=window, reached=reached, crossed=crossed,
                           passed=passed, failed_on_obstacle=failed_on, failed_before=failed_before,
                           lateral_after=lateral_after, window_peak=peak, window_variation=variation,
                           contact_source=source, summary=summary)


def pick_example(outcome: ObstacleOutcome, want_pass: bool) -> int | None:
    """A robot to show: the first that passed (survived), preferring one that crossed the box, then one that reached
    it; or the first that failed on the obstacle, else the first that failed at all. None if there is none."""
    if want_pass:
        pools = (outcome.passed & outcome.crossed, outcome.passed & outcome.reached, outcome.passed)
    else:
        pools = (outcome.failed_on_obstacle, ~outcome.passed)
    for pool in pools:
        idx = np.flatnonzero(pool.numpy())
        if idx.size:
            return int(idx[0])
    return None

