"""The Python blocks of docs/concepts/transforms.md and docs/concepts/controllers.md run as they stand on the CPU, in
order in one namespace per page (as tests/test_extending.py runs docs/extending.md's), and the envs they build step.
tests/test_controllers.py and tests/test_actuators.py check the controller and the actuator stage of the second page
in detail; here every block of both pages runs, the first ones included."""

from __future__ import annotations

from pathlib import Path

import torch
from doc_blocks import python_blocks, run_python_blocks

CONCEPTS = Path(__file__).resolve().parents[1] / "docs" / "concepts"


def test_the_transforms_page_s_blocks_build_envs_that_step(tmp_path):
    page = CONCEPTS / "transforms.md"
    assert len(python_blocks(page)) == 2, "transforms.md has a keyword block and a composed-by-hand block"
    ns = run_python_blocks(page, tmp_path)
    td = ns["env"].rollout(2, break_when_any_done=False)
    terms = td["next", "reward_terms"]
    assert sorted(terms.keys()) == ["alive", "body_vel", "foot_contact", "orientation", "qpos"]
    torch.testing.assert_close(terms["alive"], torch.full((4, 2, 1), 0.1))  # the new term, times its weight
    # The composed-by-hand stack is a transform of its own: it goes on a fresh env.
    from torchrl.envs import TransformedEnv

    env = TransformedEnv(ns["TocabiWalk"](num_envs=2, device="cpu"), ns["transforms"])
    td = env.rollout(2, break_when_any_done=False)
    assert td["next", "observation"].shape[:2] == (2, 2) and "body_vel" in td["next", "reward_terms"].keys()


def test_the_controllers_page_s_blocks_build_envs_that_step(tmp_path):
    page = CONCEPTS / "controllers.md"
    assert len(python_blocks(page)) == 3, "controllers.md has an actuator config, a stage and a controller block"
    first = python_blocks(page)[0]
    ns = run_python_blocks(page, tmp_path)
    assert ns["tau"].shape == (4, 12) and ns["chain"].draws == 24  # as the stage block's comments say
    td = ns["env"].rollout(2, break_when_any_done=False)  # the last block's env: the controller of one's own
    assert td["next", "leg_torque"].shape == (8, 2, 12)
    # The first block's env was replaced by the last block's: build it again from the first block alone.
    first_ns: dict = {}
    exec(compile(first, str(page), "exec"), first_ns)  # noqa: S102 - the project's own documentation
    env = first_ns["env"]
    assert env.base_env.cfg.control.actuators.delay_substeps == (4, 20)
    td = env.rollout(2, break_when_any_done=False)
    assert td["next", "leg_torque"].shape == (8, 2, 12)
