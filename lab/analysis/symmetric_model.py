"""TOCABI's MJCF made exactly left-right symmetric: what the mirror-symmetry tests step, and what an analysis runs a
policy on to ask whether a weakness comes from the authored robot's small asymmetries.

The authored model is the real robot's (e.g. Waist2's centre of mass 18 mm off the mid-plane; R_Shoulder1's damping
5.0 against the left's 3.0). The copy gives every right or centre link the mirror image of its left partner's
inertial (a centre link the mean of its own and its mirror's), and every right joint its left partner's damping and
mirrored range; geometry, contacts and actuators are the authored model's, already symmetric::

    PYTHONPATH=. python lab/analysis/symmetric_model.py --out /tmp/tocabi_symmetric.xml
    PYTHONPATH=. python lab/analysis/drift_sources.py --model /tmp/tocabi_symmetric.xml --checkpoint CKPT.pt

The file names the meshes by absolute path (MjSpec's XML), so it can be written anywhere.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import mujoco
import numpy as np

from tocabi_torchrl import robot
from tocabi_torchrl.atomic import atomic_write_text

#: The reflection y -> -y (the robot's sagittal plane is the world's x-z plane in its initial pose).
MIRROR = np.diag([1.0, -1.0, 1.0])


def partner(name: str) -> str:
    """The mirror partner of a body or joint name (``L_`` <-> ``R_``; a centre name is its own).

    >>> partner("L_Knee_Joint"), partner("R_Foot_Link"), partner("Waist2_Link")
    ('R_Knee_Joint', 'L_Foot_Link', 'Waist2_Link')
    """
    return ("R_" + name[2:]) if name.startswith("L_") else ("L_" + name[2:]) if name.startswith("R_") else name


def symmetric_spec() -> mujoco.MjSpec:
    """TOCABI's MJCF (the shipped one) made exactly left-right symmetric (the module docstring), as an ``MjSpec``
    to compile or write (``.to_xml()``); the elbows' ranges differ in the authored model too."""
    spec = robot.load_spec()
    model = spec.compile()
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)

    def world_inertia(i: int) -> np.ndarray:
        rot = data.ximat[i].reshape(3, 3)
        return rot @ np.diag(model.body_inertia[i]) @ rot.T

    for b in range(1, model.nbody):
        name = model.body(b).name
        if name.startswith("L_"):
            continue
        p = model.body(partner(name)).id
        com, inertia = MIRROR @ data.xipos[p], MIRROR @ world_inertia(p) @ MIRROR
        if p == b:
            com, inertia = 0.5 * (data.xipos[b] + com), 0.5 * (world_inertia(b) + inertia)
        rot = data.xmat[b].reshape(3, 3)
        local = rot.T @ inertia @ rot
        body = spec.body(name)
        body.ipos = rot.T @ (com - data.xpos[b])
        body.iquat = [1.0, 0.0, 0.0, 0.0]
        body.fullinertia = [local[0, 0], local[1, 1], local[2, 2], local[0, 1], local[0, 2], local[1, 2]]
        body.mass = model.body_mass[p]
    for j, name in enumerate(robot.JOINT_NAMES):
        if name.startswith("R_"):
            left, right = spec.joint(robot.JOINT_NAMES[robot.MIRROR_JOINT[j]]), spec.joint(name)
            right.damping = left.damping
            right.range = sorted(robot.MIRROR_SIGN[j] * np.asarray(left.range))
    return spec


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--out", type=Path, required=True, help="the MJCF to write (.xml); an existing file is kept")
    args = p.parse_args(argv)
    if args.out.exists():
        p.error(f"{args.out} exists; pass another --out or remove it first")
    atomic_write_text(args.out, symmetric_spec().to_xml())
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
