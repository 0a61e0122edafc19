"""Gait rollouts that keep every step, for the experiments (``lab/experiments/compare_gaits.py``,
``lab/experiments/obstacle_test.py``).

:func:`record_rollout` runs a deterministic policy at a fixed command, like the gait test, and keeps per policy step
and per env: the leg joint angles and their reference, the applied leg torques (:func:`applied_leg_torque`), the
pelvis position, the foot soles' centres and ground contact, and whether the robot is still up. It also keeps the
full joint state of every env at fixed times (``snapshot_every``) and at each env's termination, for rendering.
Fallen robots are not reset: they lie where they fell, and the ``alive`` mask leaves them out of every metric.
Its metrics are the gait test's (:class:`tocabi_torchrl.evaluation.record.GaitMetrics`), so both report the same
numbers for the same rollout. :func:`torque_stats` adds the torque metrics of the gait comparison.

Memory: the record holds about 50 float32 values per env and step (~100 MB for 256 envs over 8 s), on the env's
device until :meth:`GaitRecord.cpu` moves it.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import torch
from torchrl.envs.utils import ExplorationType, set_exploration_type, step_mdp
from tqdm.auto import tqdm

from tocabi_torchrl import robot
from tocabi_torchrl.envs.config import TORQUE_MODES
from tocabi_torchrl.evaluation.record import KNEES, LEG_JOINTS, GaitMetrics, load_policy, policy_steps
from tocabi_torchrl.rotations import quat_rotate_inverse

__all__ = ["GaitRecord", "record_rollout", "applied_leg_torque", "torque_stats", "sole_geometry", "load_policy",
           "CRITICAL_JOINTS", "CRITICAL"]

#: The joints whose torques TocabiLab plots (sagittal chain of both legs).
CRITICAL_JOINTS: tuple[str, ...] = ("L_HipPitch_Joint", "L_Knee_Joint", "L_AnklePitch_Joint",
                                    "R_HipPitch_Joint", "R_Knee_Joint", "R_AnklePitch_Joint")
#: Their indices into the 12 leg joints.
CRITICAL = tuple(LEG_JOINTS.index(name) for name in CRITICAL_JOINTS)


# ------------------------------------------------------------------------------------------------ torque read-out
def applied_leg_torque(env) -> torch.Tensor:
    """(N, 12) leg torques [N·m] the physics applied in the env's last step (a ``TocabiWalk`` or an env wrapping one).

    In the PD modes the legs are MuJoCo position servos: their ``actuator_force`` (``kp·(target − q) − kv·q̇``,
    clipped to the torque limits) in the last physics substep of the step, as the simulator stored it
    (``sim.applied_actuator_force``). In torque mode (torque assist included) the commanded torque, which the
    motors (gear 1) apply unchanged in every substep: ``sim.ctrl``. Non-finite values (a world whose physics failed)
    read as 0. This is the env's ``leg_torque`` signal, read straight from the simulator.
    """
    base = getattr(env, "base_env", env)
    sim = base.sim
    field_ = sim.ctrl if base.cfg.control.mode in TORQUE_MODES else sim.applied_actuator_force
    return torch.nan_to_num(field_[:, robot.LEGS], nan=0.0, posinf=0.0, neginf=0.0).clone()


# ------------------------------------------------------------------------------------------------ the record
def sole_geometry(model) -> tuple[np.ndarray, np.ndarray]:
    """The foot soles: (2, 3) centre in the foot body's frame [m] and (2, 3) half sizes [m], [left, right] (the
    largest collision box of each foot body)."""
    import mujoco

    centres, halves = [], []
    for name in robot.FOOT_BODIES:
        body = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, name)
        boxes = [g for g in range(model.ngeom) if model.geom_bodyid[g] == body
                 and model.geom_type[g] == mujoco.mjtGeom.mjGEOM_BOX and (model.geom_contype[g] or
                                                                         model.geom_conaffinity[g])]
        if not boxes:
            raise ValueError(f"{name} has no collision box (the sole)")
        g = max(boxes, key=lambda i: float(np.prod(model.geom_size[i])))
        centres.append(model.geom_pos[g].copy())
        halves.append(model.geom_size[g].copy())
    return np.stack(centres), np.stack(halves)


@dataclass
class GaitRecord:
    """Every policy step of a recorded rollout (T steps, N envs); tensors on the env's device until :meth:`cpu`.

    Step ``k`` holds the state after the ``k``-th policy step, at time ``(k + 1)·dt``. ``alive[k]`` is False from
    the step on which the env terminated. An env with obstacles (``env.scene.obstacles``) adds their per-world
    positions and the feet's contact with them.
    """

    dt: float
    command: tuple[float, float]
    seconds: float
    control_mode: str
    joint_pos: torch.Tensor  #: (T, N, 12) leg joint angles [rad]
    ref_joint_pos: torch.Tensor  #: (T, N, 12) reference leg joint angles [rad]
    leg_torque: torch.Tensor  #: (T, N, 12) applied leg torques [N·m] (:func:`applied_leg_torque`)
    base_pos: torch.Tensor  #: (T, N, 3) pelvis origin [m]
    sole_pos: torch.Tensor  #: (T, N, 2, 3) sole box centres [m], [left, right]
    foot_contact: torch.Tensor  #: (T, N, 2) bool, a foot touches the ground (every world-body geom)
    alive: torch.Tensor  #: (T, N) bool
    start_pos: torch.Tensor  #: (N, 3) pelvis origin after the reset [m]
    termination_step: torch.Tensor  #: (N,) int64, the step of the first termination, -1 for none
    snapshot_times: list[float]  #: [s] simulated times of the ``snapshots`` (whole policy steps)
    snapshots: torch.Tensor  #: (S, N, nq) joint states (qpos) at ``snapshot_times``
    termination_qpos: torch.Tensor  #: (N, nq) qpos on the terminating step (NaN for survivors)
    sole_half_size: np.ndarray  #: (2, 3) half sizes of the sole boxes [m]
    metrics: dict = field(default_factory=dict)  #: :meth:`GaitMetrics.summary`
    per_env: dict = field(default_factory=dict)  #: :meth:`GaitMetrics.per_env`
    period: float = float("nan")  #: [s] the reference motion's cycle (two steps)
    #: (T, N, 2) bool, a foot touches an obstacle box (the env's ``obstacle_contact`` signal), when the env has one
    obstacle_contact: torch.Tensor | None = None
    #: (N, K, 3) centres of each world's obstacle boxes [m] (the env's ``obstacle_pos``), when the env has them
    obstacle_pos: torch.Tensor | None = None

    @property
    def steps(self) -> int:
        return int(self.joint_pos.shape[0])

    @property
    def num_envs(self) -> int:
        return int(self.joint_pos.shape[1])

    @property
    def times(self) -> np.ndarray:
        """(T,) [s] time of each step's state."""
        return (np.arange(self.steps) + 1) * self.dt

    def cpu(self) -> GaitRecord:
        """A copy with every tensor on the CPU."""
        moved = {f.name: getattr(self, f.name).cpu() for f in dataclasses.fields(self)
                 if isinstance(getattr(self, f.name), torch.Tensor)}
        moved["per_env"] = {k: v.cpu() for k, v in self.per_env.items()}
        return dataclasses.replace(self, **moved)

    def knee_trace(self, env: int = 0, seconds: float = 6.0) -> tuple[np.ndarray, np.ndarray]:
        """(T', 2) knee angles of ``env`` (NaN from its termination on) and (T', 2) reference, over ``seconds``."""
        steps = min(self.steps, int(round(seconds / self.dt)))
        q = self.joint_pos[:steps, env][:, KNEES].cpu().numpy().astype(float)
        q[~self.alive[:steps, env].cpu().numpy()] = np.nan
        return q, self.ref_joint_pos[:steps, env][:, KNEES].cpu().numpy().astype(float)


def record_rollout(actor, env, seconds: float = 8.0, command: tuple[float, float] = (0.5, 0.0),
                   snapshot_every: float | None = 2.0, progress: bool = True, desc: str = "gait record",
                   on_step: Callable | None = None) -> GaitRecord:
    """Roll the deterministic ``actor`` out in ``env`` (built at the fixed ``command``, e.g. by
    :func:`load_policy`) for ``seconds`` from a reset, recording every step (see :class:`GaitRecord`).

    ``snapshot_every`` [s]: keep every env's qpos at t = 0 and after the policy steps nearest to every, 2·every,
    ... (None: only t = 0); ``snapshot_times`` holds the simulated times of the states kept, so an ``every`` that is
    not a whole number of steps is labelled with the times shown, not the times asked. ``ValueError`` for an
    ``every`` shorter than one policy step (several snapshots would fall on one step).
    ``on_step(k, env)``: called after each step, e.g. to record more from the simulator.
    """
    base = env.base_env
    sim, dt = base.sim, float(base.dt)
    steps = policy_steps(seconds, dt)
    n, device = env.num_envs, env.device
    centre_np, half = sole_geometry(sim.mj_model)
    sole_centre = torch.as_tensor(centre_np, dtype=torch.float32, device=device)
    foot_ids = [sim.mj_model.body(name).id for name in robot.FOOT_BODIES]
    conjugate = torch.tensor([1.0, -1.0, -1.0, -1.0], device=device)  # made once: no host copy inside the loop
    snap_steps = set()
    if snapshot_every:
        if not snapshot_every >= dt * (1 - 1e-9):
            raise ValueError(f"snapshot_every={snapshot_every:g} s is shorter than one policy step ({dt * 1000:g} ms); "
                             f"pass at least {dt:g}")
        for j in range(1, int(np.floor(seconds / snapshot_every + 1e-9)) + 1):
            snap_steps.add(int(round(j * snapshot_every / dt)) - 1)

    def empty(*shape, dtype=torch.float32):
        return torch.zeros(steps, n, *shape, dtype=dtype, device=device)

    rec = {"joint_pos": empty(12), "ref_joint_pos": empty(12), "leg_torque": empty(12), "base_pos": empty(3),
           "sole_pos": empty(2, 3), "foot_contact": empty(2, dtype=torch.bool), "alive": empty(dtype=torch.bool)}
    termination_step = torch.full((n,), -1, dtype=torch.int64, device=device)
    termination_qpos = torch.full_like(sim.qpos, float("nan"))
    with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
        td = env.reset()
        if "obstacle_contact" in td.keys():
            rec["obstacle_contact"] = empty(2, dtype=torch.bool)
        metrics = GaitMetrics(td["base_pos"], command, dt)
        snapshots, snapshot_times = [sim.qpos.clone()], [0.0]
        for k in tqdm(range(steps), desc=desc, unit="step", disable=not progress, leave=False):
            was_alive = metrics.alive
            td = env.step(actor(td))
            nxt = td["next"]
            alive = metrics.update(nxt)
            fell = was_alive & ~alive
            termination_step = torch.where(fell, k, termination_step)
            termination_qpos = torch.where(fell.unsqueeze(-1), sim.qpos, termination_qpos)
            rec["joint_pos"][k] = nxt["joint_pos"][:, robot.LEGS]
            rec["ref_joint_pos"][k] = nxt["ref_joint_pos"][:, robot.LEGS]
            rec["leg_torque"][k] = applied_leg_torque(base)
            rec["base_pos"][k] = nxt["base_pos"]
            feet_q = sim.xquat[:, foot_ids]
            # body frame -> world: rotate by the quaternion (the inverse rotation of its conjugate)
            rec["sole_pos"][k] = sim.xpos[:, foot_ids] + quat_rotate_inverse(feet_q * conjugate,
                                                                              sole_centre.expand(n, 2, 3))
            rec["foot_contact"][k] = nxt["foot_contact"]
            if "obstacle_contact" in rec:
                rec["obstacle_contact"][k] = nxt["obstacle_contact"]
            rec["alive"][k] = alive
            if k in snap_steps:
                snapshots.append(sim.qpos.clone())
                snapshot_times.append((k + 1) * dt)  # the state after step k
            if on_step is not None:
                on_step(k, env)
            td = step_mdp(td)
    return GaitRecord(dt=dt, command=(float(command[0]), float(command[1])), seconds=float(seconds),
                      control_mode=base.cfg.control.mode, start_pos=metrics.start, termination_step=termination_step,
                      snapshot_times=snapshot_times, snapshots=torch.stack(snapshots),
                      termination_qpos=termination_qpos, sole_half_size=half, metrics=metrics.summary(seconds),
                      per_env=metrics.per_env(), period=float(base.period),
                      obstacle_pos=getattr(base, "obstacle_pos", None), **rec)


# ------------------------------------------------------------------------------------------------ torque metrics
def torque_stats(record: GaitRecord, joints=None, window: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
    """Per-env torque metrics over the alive steps (and, with ``window`` (T, N) bool, only inside it):

    * ``mean_abs``: mean |τ| [N·m] over steps and ``joints`` (default: the 12 leg joints);
    * ``smoothness``: mean |τ_k − τ_(k−1)| [N·m per policy step, 4 ms] over consecutive step pairs that are both
      alive (and both in the window) and over ``joints``; the first step's change from the reset is left out;
    * ``peak``: (N, J) max |τ| per joint.
    Each is (N,) or (N, J); an env without a counted step gets NaN.
    """
    tau = record.leg_torque if joints is None else record.leg_torque[:, :, list(joints)]
    mask = record.alive if window is None else record.alive & window
    m = mask.unsqueeze(-1).float()
    count = mask.sum(0).float()
    mean_abs = (tau.abs() * m).sum((0, 2)) / (count * tau.shape[-1])
    pairs = (mask[1:] & mask[:-1]).unsqueeze(-1).float()
    npairs = pairs.sum((0, 2))
    smooth = ((tau[1:] - tau[:-1]).abs() * pairs).sum((0, 2)) / (npairs * tau.shape[-1])
    peak = (tau.abs() * m).amax(0)
    nan = torch.tensor(float("nan"), device=tau.device)
    return {"mean_abs": torch.where(count > 0, mean_abs, nan), "smoothness": torch.where(npairs > 0, smooth, nan),
            "peak": torch.where(count.unsqueeze(-1) > 0, peak, nan)}
