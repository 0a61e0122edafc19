"""Early-termination conditions of the walking task (spec §9.1), as one batched, branch-free function."""

from __future__ import annotations

import torch

from ..rotations import quat_rotation_angle

__all__ = ["termination_flags"]


def termination_flags(
    *,
    pelvis_height: torch.Tensor,
    neck_height: torch.Tensor,
    neck_quat: torch.Tensor,
    forbidden_ground_contact: torch.Tensor,
    self_collision: torch.Tensor,
    healthy: torch.Tensor,
    min_pelvis_height: float,
    min_neck_height: float,
    max_neck_angle: float,
    use_forbidden_contact: bool = True,
    use_self_collision: bool = True,
) -> dict[str, torch.Tensor]:
    """Each condition as a (num_envs,) bool tensor, plus ``"any"``.

    Args:
        pelvis_height, neck_height: (num_envs,) m, world z of the pelvis and Neck_Link origins.
        neck_quat: (num_envs, 4) Neck_Link world orientation (w, x, y, z); its angle from identity includes yaw.
        forbidden_ground_contact, self_collision, healthy: (num_envs,) bool from the simulator.
    """
    flags = {
        "pelvis_low": pelvis_height < min_pelvis_height,
        "neck_low": neck_height < min_neck_height,
        "neck_tilt": quat_rotation_angle(neck_quat).squeeze(-1) > max_neck_angle,
        "forbidden_contact": forbidden_ground_contact & use_forbidden_contact,
        "self_collision": self_collision & use_self_collision,
        "unhealthy": ~healthy,
    }
    # NaN heights or orientations compare False above; the health flag catches them.
    any_flag = torch.zeros_like(healthy)
    for value in flags.values():
        any_flag = any_flag | value
    flags["any"] = any_flag
    return flags
