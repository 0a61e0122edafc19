"""lab/analysis/symmetric_model.py: TOCABI's MJCF made exactly left-right symmetric (the mirror tests step it)."""

from __future__ import annotations

import doctest

import mujoco
import numpy as np
import pytest

from lab.analysis import symmetric_model
from tocabi_torchrl import robot


def test_docstring_examples_run():
    result = doctest.testmod(symmetric_model)
    assert result.attempted >= 1 and result.failed == 0


def test_every_right_link_is_the_mirror_image_of_its_left_partner():
    """Mass and centre of mass mirror exactly in the copy; in the authored model they do not (Waist2's centre of mass
    is off the mid-plane), so the check can fail."""
    def worst(model: mujoco.MjModel) -> tuple[float, float]:
        data = mujoco.MjData(model)
        mujoco.mj_forward(model, data)
        mass = com = 0.0
        for b in range(1, model.nbody):
            p = model.body(symmetric_model.partner(model.body(b).name)).id
            mass = max(mass, abs(model.body_mass[b] - model.body_mass[p]))
            com = max(com, float(np.abs(symmetric_model.MIRROR @ data.xipos[p] - data.xipos[b]).max()))
        return mass, com

    model = symmetric_model.symmetric_spec().compile()
    sym_mass, sym_com = worst(model)
    assert sym_mass < 1e-9 and sym_com < 1e-9
    assert worst(robot.load_spec().compile())[1] > 1e-3
    # The joints: each right one has its left partner's damping and mirrored range.
    for j, name in enumerate(robot.JOINT_NAMES):
        left = model.joint(robot.JOINT_NAMES[robot.MIRROR_JOINT[j]])
        right = model.joint(name)
        assert model.dof_damping[right.dofadr[0]] == model.dof_damping[left.dofadr[0]], name
        np.testing.assert_allclose(sorted(robot.MIRROR_SIGN[j] * model.jnt_range[left.id]),
                                   model.jnt_range[right.id], err_msg=name)
    # The inertia tensors in the world frame: each right link's is its left partner's mirror image.
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)

    def world_inertia(b: int) -> np.ndarray:
        rot = data.ximat[b].reshape(3, 3)
        return rot @ np.diag(model.body_inertia[b]) @ rot.T

    M = symmetric_model.MIRROR
    for b in range(1, model.nbody):
        p = model.body(symmetric_model.partner(model.body(b).name)).id
        np.testing.assert_allclose(M @ world_inertia(p) @ M, world_inertia(b), atol=1e-9, err_msg=model.body(b).name)


def test_main_writes_a_loadable_model_and_never_overwrites(tmp_path):
    out = tmp_path / "sym.xml"
    assert symmetric_model.main(["--out", str(out)]) == 0
    assert mujoco.MjModel.from_xml_path(str(out)).nbody == robot.load_spec().compile().nbody
    with pytest.raises(SystemExit):
        symmetric_model.main(["--out", str(out)])
