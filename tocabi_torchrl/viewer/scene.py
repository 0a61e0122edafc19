"""The viser scene: the ground and every shown world's robot (and obstacles), moved from body poses.

Each :class:`~.geometry.BodyMesh` is one batched (instanced) mesh with one instance per world, so a frame is one
property update per body for all worlds together (about 21 for TOCABI), never a Python loop over worlds or geoms.
The simulated worlds all stand at the same origin; the page spreads them over a grid (:func:`world_offsets`).
"""

from __future__ import annotations

import math

import numpy as np

from .geometry import BodyMesh

__all__ = ["RobotScene", "world_offsets", "follow", "HIGHLIGHT_RGB"]

#: Colour of the selected world's robot (the one pushes, the overlays and the camera follow).
HIGHLIGHT_RGB = (250, 190, 40)


def world_offsets(num_worlds: int, spacing: tuple[float, float] = (3.0, 1.0)) -> np.ndarray:
    """(num_worlds, 3) float32 display offsets [m] of the worlds on a grid centred on the origin: rows ``spacing[0]``
    apart along x (the walking direction, room for a few metres of walk), columns ``spacing[1]`` apart along y."""
    cols = max(1, math.ceil(math.sqrt(num_worlds)))
    rows = math.ceil(num_worlds / cols)
    k = np.arange(num_worlds)
    x = (k // cols - (rows - 1) / 2.0) * spacing[0]
    y = (k % cols - (cols - 1) / 2.0) * spacing[1]
    return np.stack([x, y, np.zeros(num_worlds)], axis=1).astype(np.float32)


class RobotScene:
    """The robots of ``num_worlds`` worlds on a viser server.

    Args:
        server: a ``viser.ViserServer``.
        meshes: the model's :func:`~.geometry.body_meshes`.
        num_worlds: W, the worlds shown.
        offsets: (W, 3) display offsets [m]; default :func:`world_offsets`.
    """

    def __init__(self, server, meshes: list[BodyMesh], num_worlds: int, offsets: np.ndarray | None = None):
        self.server, self.meshes, self.num_worlds = server, meshes, num_worlds
        self.offsets = world_offsets(num_worlds) if offsets is None else np.asarray(offsets, np.float32)
        extent = float(np.abs(self.offsets).max(initial=0.0)) * 2 + 12.0
        server.scene.set_up_direction("+z")
        server.scene.add_grid("/ground", width=extent, height=extent, cell_size=0.5, section_size=1.0,
                              position=(0.0, 0.0, 0.0), plane_color=(235, 235, 235), plane_opacity=1.0)
        # The first view: every world in sight, from behind-left of the walking direction and above.
        span = np.ptp(self.offsets, axis=0) if num_worlds > 1 else np.zeros(3)
        server.initial_camera.look_at = (0.0, 0.0, 0.6)
        far = max(span[:2])
        server.initial_camera.position = (-(span[0] / 2 + 2.0 + 0.1 * far), -(span[1] / 2 + 3.0 + 0.15 * far),
                                          1.5 + 0.3 * far)
        identity = np.tile(np.array([1.0, 0.0, 0.0, 0.0], np.float32), (num_worlds, 1))
        self.handles = [
            server.scene.add_batched_meshes_simple(
                f"/robots/{i:02d}_{m.name}", m.vertices, m.faces, batched_wxyzs=identity,
                batched_positions=self.offsets.copy(), batched_colors=self._colors(m, None), lod="off")
            for i, m in enumerate(meshes)
        ]
        self.selected: int | None = None

    def _colors(self, mesh: BodyMesh, selected: int | None) -> np.ndarray:
        colors = np.tile(np.asarray(mesh.rgb, np.uint8), (self.num_worlds, 1))
        if selected is not None:
            colors[selected] = HIGHLIGHT_RGB
        return colors

    def update(self, xpos: np.ndarray, xquat: np.ndarray) -> None:
        """Move every robot: ``xpos`` (W, nbody, 3) [m] and ``xquat`` (W, nbody, 4) (w, x, y, z) body poses of the
        W shown worlds (the simulator's ``xpos``/``xquat`` rows), sent as one message batch."""
        if xpos.shape[0] != self.num_worlds or xquat.shape[:2] != xpos.shape[:2]:
            raise ValueError(f"poses of {xpos.shape[0]} worlds ({xpos.shape}, {xquat.shape}) for a scene of "
                             f"{self.num_worlds}: pass (W, nbody, 3) and (W, nbody, 4) arrays")
        with self.server.atomic():
            for handle, mesh in zip(self.handles, self.meshes):
                handle.batched_positions = (xpos[:, mesh.body] + self.offsets).astype(np.float32)
                handle.batched_wxyzs = xquat[:, mesh.body].astype(np.float32)

    def select(self, world: int | None) -> None:
        """Draw world ``world`` (or none) in :data:`HIGHLIGHT_RGB`."""
        if world == self.selected:
            return
        self.selected = world
        with self.server.atomic():
            for handle, mesh in zip(self.handles, self.meshes):
                handle.batched_colors = self._colors(mesh, world)

    def shown_position(self, world: int, base_pos: np.ndarray) -> np.ndarray:
        """Where world ``world``'s point ``base_pos`` (3,) [m] appears on the page (its display offset added)."""
        return np.asarray(base_pos, np.float64) + self.offsets[world]


def follow(server, target: np.ndarray) -> None:
    """Move every connected browser's camera so it looks at ``target`` (3,) [m], keeping its own viewing offset."""
    target = np.asarray(target, np.float64)
    for client in server.get_clients().values():
        cam = client.camera
        offset = np.asarray(cam.position, np.float64) - np.asarray(cam.look_at, np.float64)
        with client.atomic():
            # Position first: viser's position setter moves look_at along with it, which would undo a look_at set
            # before it (the view then flipped between two wrong ones every frame).
            cam.position = target + offset
            cam.look_at = target
