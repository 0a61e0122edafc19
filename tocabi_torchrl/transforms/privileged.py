"""The critic's privileged input: true robot state, unperturbed by the sensor noise (``ppo.critic_privileged``).

An asymmetric actor-critic: the policy acts on what the robot's sensors give, biased and noisy under randomisation,
while the value function, used only in training, may read the simulator's state. Knowing the pelvis's true velocity,
height and the true foot loads makes the value of a state after a kick or on a heavier robot easier to tell apart.

``privileged`` (num_envs, 12) float32, from the env's signals of the same step (never from the sensor-noise
transform's output):

===== ================= ====== ============================================ ===========================
index name              unit   meaning                                      mirror (y -> -y)
===== ================= ====== ============================================ ===========================
0-2   base_lin_vel      m/s    pelvis linear velocity, pelvis frame         x, -y, z
3-5   base_ang_vel      rad/s  pelvis angular velocity, pelvis frame        -x, y, -z (axial vector)
6     base_height       m      pelvis height above the world's origin       stays
7-8   foot_load         1      -Fz of [left, right] foot over body weight   feet swap
9-11  base_rpy          rad    true pelvis roll, pitch, yaw                 -roll, pitch, -yaw
===== ================= ====== ============================================ ===========================
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from torchrl.data import Composite, Unbounded

from tocabi_torchrl import robot
from tocabi_torchrl.transforms._base import CallOnReset

__all__ = ["PrivilegedState", "PRIVILEGED_DIM", "PRIVILEGED_MIRROR"]

#: Values of the ``privileged`` vector.
PRIVILEGED_DIM = 12
#: (perm, sign) of the left-right mirror: the mirrored vector is ``sign * x[perm]`` (see the module's table).
PRIVILEGED_MIRROR: tuple[tuple[int, ...], tuple[float, ...]] = (
    (0, 1, 2, 3, 4, 5, 6, 8, 7, 9, 10, 11),
    (1.0, -1.0, 1.0, -1.0, 1.0, -1.0, 1.0, 1.0, 1.0, -1.0, 1.0, -1.0),
)
_BODY_WEIGHT = robot.NOMINAL_MASS * robot.GRAVITY


class PrivilegedState(CallOnReset):
    """Writes ``out_key`` (num_envs, 12) float32, the critic's privileged input (module table), on every step and
    reset, from ``base_lin_vel``, ``base_ang_vel``, ``base_pos``, ``foot_force`` and ``base_rpy`` (the latter from
    :class:`~tocabi_torchrl.transforms.BaseEulerAngles`, so append this transform after the default ones).

    >>> import torch
    >>> from tensordict import TensorDict
    >>> td = TensorDict({"base_lin_vel": torch.tensor([[0.5, 0.0, 0.0]]), "base_ang_vel": torch.zeros(1, 3),
    ...                  "base_pos": torch.tensor([[0.0, 0.0, 0.93]]), "foot_force": torch.zeros(1, 2, 3),
    ...                  "base_rpy": torch.zeros(1, 3)}, [1])
    >>> PrivilegedState()._call(td)["privileged"].shape
    torch.Size([1, 12])
    """

    _IN = ("base_lin_vel", "base_ang_vel", "base_pos", "foot_force", "base_rpy")

    def __init__(self, out_key: str = "privileged"):
        super().__init__(in_keys=list(self._IN), out_keys=[out_key])

    def _call(self, td: TensorDictBase) -> TensorDictBase:
        force = td.get("foot_force")
        parts = (td.get("base_lin_vel"), td.get("base_ang_vel"), td.get("base_pos")[..., 2:3],
                 force[..., 2].neg() / _BODY_WEIGHT, td.get("base_rpy"))
        td.set(self.out_keys[0], torch.cat([p.to(torch.float32) for p in parts], dim=-1))
        return td

    def transform_observation_spec(self, observation_spec: Composite) -> Composite:
        missing = [k for k in self._IN if k not in observation_spec.keys(True, True)]
        if missing:
            raise KeyError(f"PrivilegedState reads {missing}, which the env does not output; append it after the "
                           "default transforms (BaseEulerAngles writes base_rpy)")
        shape = observation_spec["base_pos"].shape[:-1]
        observation_spec[self.out_keys[0]] = Unbounded(shape=(*shape, PRIVILEGED_DIM), dtype=torch.float32,
                                                       device=observation_spec.device)
        return observation_spec
