"""The drawable shapes of a compiled MuJoCo model, merged per body: built once, then only body poses move.

The TOCABI model draws a visual silhouette (group 1, opaque) over translucent collision primitives (group 2,
alpha 0.4); the viewer shows what MuJoCo's own offscreen video shows: every geom except the collision group, the
translucent helpers and the ground plane (the page draws its own grid). Obstacles (mocap boxes added by the scene,
group 0) are kept. A body's geoms of one colour become one triangle mesh in the body's frame (TOCABI's bodies each
draw in one colour), so the page moves all worlds of a body with one call, whatever the number of its geoms.
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np

__all__ = ["BodyMesh", "body_meshes", "geom_mesh", "drawn_geoms"]

#: MuJoCo's geom group of the collision primitives (assets/tocabi/tocabi.xml), hidden like the offscreen video does.
COLLISION_GROUP = 2
#: Geoms more transparent than this are helpers (the pelvis guard box), not part of the silhouette.
MIN_ALPHA = 0.5


@dataclass(frozen=True)
class BodyMesh:
    """A body's drawn geoms of one colour as one mesh in the body frame: ``vertices`` (V, 3) float32 [m], ``faces``
    (F, 3) int32, ``rgb`` (3,) uint8, and ``body`` the MuJoCo body id whose pose (``xpos``/``xquat``) moves it."""

    body: int
    name: str
    vertices: np.ndarray
    faces: np.ndarray
    rgb: tuple[int, int, int]


def drawn_geoms(model: mujoco.MjModel) -> np.ndarray:
    """Ids of the geoms the viewer draws: not the collision group, not translucent helpers, not planes."""
    keep = ((model.geom_group != COLLISION_GROUP) & (model.geom_rgba[:, 3] >= MIN_ALPHA)
            & (model.geom_type != mujoco.mjtGeom.mjGEOM_PLANE))
    return np.flatnonzero(keep)


def geom_mesh(model: mujoco.MjModel, g: int) -> tuple[np.ndarray, np.ndarray]:
    """Geom ``g`` as (vertices (V, 3), faces (F, 3)) in its own frame, from its type and ``geom_size`` (MuJoCo's
    conventions: box half-extents; sphere radius; capsule/cylinder radius and half-length along z; ellipsoid radii;
    mesh: the model's own vertices)."""
    import trimesh  # a dependency of viser

    kind, size = int(model.geom_type[g]), model.geom_size[g]
    t = mujoco.mjtGeom
    if kind == t.mjGEOM_BOX:
        mesh = trimesh.creation.box(extents=2.0 * size)
    elif kind == t.mjGEOM_SPHERE:
        mesh = trimesh.creation.icosphere(subdivisions=2, radius=size[0])
    elif kind == t.mjGEOM_ELLIPSOID:
        mesh = trimesh.creation.icosphere(subdivisions=2, radius=1.0)
        mesh.vertices *= size
    elif kind == t.mjGEOM_CAPSULE:
        mesh = trimesh.creation.capsule(height=2.0 * size[1], radius=size[0], count=(12, 12))
    elif kind == t.mjGEOM_CYLINDER:
        mesh = trimesh.creation.cylinder(radius=size[0], height=2.0 * size[1], sections=16)
    elif kind == t.mjGEOM_MESH:
        m = int(model.geom_dataid[g])
        v0, nv = model.mesh_vertadr[m], model.mesh_vertnum[m]
        f0, nf = model.mesh_faceadr[m], model.mesh_facenum[m]
        return model.mesh_vert[v0:v0 + nv].astype(np.float32), model.mesh_face[f0:f0 + nf].astype(np.int32)
    else:
        raise ValueError(f"geom {g} has type {kind} ({mujoco.mjtGeom(kind).name}), which the viewer cannot draw")
    return np.asarray(mesh.vertices, np.float32), np.asarray(mesh.faces, np.int32)


def _rotate(quat: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Rotate (V, 3) vectors by the unit quaternion ``quat`` (w, x, y, z)."""
    mat = np.zeros(9)
    mujoco.mju_quat2Mat(mat, np.asarray(quat, np.float64))
    return v @ mat.reshape(3, 3).T


def body_meshes(model: mujoco.MjModel) -> list[BodyMesh]:
    """One :class:`BodyMesh` per body and colour that has drawn geoms, in body order (geoms of the world body other
    than planes are drawn in its fixed frame)."""
    groups: dict[tuple[int, tuple[int, int, int]], list[int]] = {}
    for g in drawn_geoms(model):
        rgb = tuple(int(c) for c in np.clip(np.round(255 * model.geom_rgba[g, :3]), 0, 255))
        groups.setdefault((int(model.geom_bodyid[g]), rgb), []).append(int(g))
    out = []
    for (body, rgb), geoms in sorted(groups.items()):
        verts, faces, offset = [], [], 0
        for g in geoms:
            v, f = geom_mesh(model, g)
            verts.append(_rotate(model.geom_quat[g], v) + model.geom_pos[g])
            faces.append(f + offset)
            offset += len(v)
        name = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_BODY, body) or f"body_{body}"
        out.append(BodyMesh(body, name, np.concatenate(verts).astype(np.float32),
                            np.concatenate(faces).astype(np.int32), rgb))
    return out
