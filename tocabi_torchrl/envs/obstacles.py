"""Box obstacles of the env's scene (``TocabiWalkConfig.scene.obstacles``): how they enter the model and where each
world's boxes stand.

Each :class:`~tocabi_torchrl.envs.config.BoxObstacle` becomes a mocap body ``obstacle_<k>`` (a child of the world body
without degrees of freedom: static for the physics) holding one box geom of the same name, added to the ``MjSpec``
before the backend compiles it. A mocap body, not a geom on the world body, because its position lives in each
world's data (``mocap_pos``) rather than in the shared model: every world can have its own box position with one
compiled model on both backends, and nothing precomputed from the model (bounding volumes, the static geoms'
placement) goes stale. The backends put each world's positions in at build and after every reset
(``WarpSim``/``MujocoSim``'s ``mocap_pos`` argument). MuJoCo generates no contacts between the box and the ground
or another box (neither has degrees of freedom), and the contact sensors count every body outside the robot as
ground (``sim.contacts``), so an obstacle terminates and counts as foot contact exactly like the ground.
"""

from __future__ import annotations

from collections.abc import Sequence

import mujoco
import numpy as np

from ..robot import initial_sole_centre  # re-exported: where it lived before it became a fact of the robot model
from ..robot import initial_sole_extents
from .config import BoxObstacle

__all__ = ["OBSTACLE_PREFIX", "obstacle_names", "add_obstacles", "world_obstacle_centres", "initial_sole_centre",
           "check_clear_of_start"]

#: Body and geom name of obstacle k: ``OBSTACLE_PREFIX + str(k)``.
OBSTACLE_PREFIX = "obstacle_"
#: Stream tag of the per-world jitter draws (mixed with the env seed), so they never coincide with other draws.
_JITTER_STREAM = 0x0B57AC1E
_RGBA = (0.55, 0.45, 0.3, 1.0)
#: [m] how far a box under a sole may reach into it at the start: the contact solver lifts the robot out of a few mm
#: as softly as out of the ground (a 3 mm plate under both feet keeps it standing, tests/test_obstacles.py).
START_PENETRATION_M = 0.005


def obstacle_names(count: int) -> tuple[str, ...]:
    """``("obstacle_0", ..., "obstacle_<count-1>")``: the body (and geom) names of ``count`` obstacles."""
    return tuple(f"{OBSTACLE_PREFIX}{k}" for k in range(count))


def add_obstacles(spec: mujoco.MjSpec, obstacles: Sequence[BoxObstacle]) -> tuple[str, ...]:
    """Add each box to ``spec`` in place at its nominal (unjittered) position as a mocap body holding one box geom
    (collides with the robot like the robot's own collision geoms: contype = conaffinity = 1, the model's default
    friction); returns the body names. No obstacles: ``spec`` is left untouched."""
    names = obstacle_names(len(obstacles))
    for name, box in zip(names, obstacles):
        if spec.body(name) is not None or spec.geom(name) is not None:
            raise ValueError(f"the model already has a body or geom named {name!r}; obstacle names are reserved")
        x, y = box.pos
        hx, hy, hz = box.half_size
        body = spec.worldbody.add_body(name=name, mocap=True, pos=[x, y, hz])
        body.add_geom(name=name, type=mujoco.mjtGeom.mjGEOM_BOX, size=[hx, hy, hz], contype=1, conaffinity=1,
                      rgba=list(_RGBA))
    return names


def check_clear_of_start(obstacles: Sequence[BoxObstacle], model_path: str | None = None) -> None:
    """``ValueError`` naming the first box whose footprint, anywhere its jitter may put it, overlaps a sole in the
    robot's initial pose and which stands more than :data:`START_PENETRATION_M` above the sole's start height: the
    robot would start inside it (each box stands on the ground, where the soles start), and the contact solver's
    first step throws it off. ``model_path``: the robot model (None: the shipped one)."""
    for k, box in enumerate(obstacles):
        reach = np.array(box.half_size[:2]) + np.array(box.jitter)
        for foot, side in enumerate(("left", "right")):
            sole, size = initial_sole_centre(foot, model_path), initial_sole_extents(foot, model_path)
            centre, extent = sole[:2], size[:2]
            gap = np.abs(np.array(box.pos) - centre) - (reach + extent)
            # A plate up to a few mm above the sole's start height (1.3 mm on the shipped robot) lifts the robot
            # the way the soft ground contact does; a taller box throws it off.
            if (gap < 0).all() and box.size[2] > sole[2] - size[2] + START_PENETRATION_M:
                lo, hi = centre - extent, centre + extent
                raise ValueError(
                    f"env.scene.obstacles[{k}] (centre {tuple(box.pos)}, size {tuple(box.size)}, jitter "
                    f"{tuple(box.jitter)}) overlaps the {side} sole where the robot starts (x "
                    f"{lo[0]:.3f}..{hi[0]:.3f}, y {lo[1]:.3f}..{hi[1]:.3f} m): the robot would start inside the box. "
                    f"Move it at least {-gap.max():.3f} m further along x or y (BoxObstacle.ahead_of_left_foot "
                    "places one ahead of the feet)")


def world_obstacle_centres(obstacles: Sequence[BoxObstacle], num_worlds: int, seed: int) -> np.ndarray:
    """(num_worlds, K, 3) float64 box centres [m] of every world: ``(pos + U(-jitter, jitter), height / 2)``.

    One draw of ``(num_worlds, K, 2)`` uniforms from a generator keyed by ``seed`` (any int) and a fixed stream tag,
    so the positions depend only on the seed, the world count and the boxes, never on the device or the backend.
    """
    k = len(obstacles)
    out = np.zeros((num_worlds, k, 3))
    if k == 0:
        return out
    rng = np.random.default_rng([int(seed) % 2**64, _JITTER_STREAM])
    u = rng.uniform(-1.0, 1.0, size=(num_worlds, k, 2))
    pos = np.array([box.pos for box in obstacles], dtype=np.float64)
    jitter = np.array([box.jitter for box in obstacles], dtype=np.float64)
    out[..., :2] = pos + u * jitter
    out[..., 2] = [box.half_size[2] for box in obstacles]
    return out
