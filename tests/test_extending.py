"""docs/extending.md's code blocks run as they stand on the CPU, in order: the new reward term is computed and
logged, the new controller's torques are what its law gives, and the new task trains two PPO iterations."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from doc_blocks import python_blocks, run_python_blocks

DOC = Path(__file__).resolve().parents[1] / "docs" / "extending.md"


@pytest.fixture(scope="module")
def namespace(tmp_path_factory):
    """Every python block of the page executed in one namespace (the task writes runs/ under a temporary cwd)."""
    assert len(python_blocks(DOC)) == 3, "extending.md has a reward term, a controller and a task block"
    cwd = tmp_path_factory.mktemp("extending")
    ns = run_python_blocks(DOC, cwd)
    ns["cwd"] = cwd
    return ns


def test_the_new_reward_terms_are_computed_and_logged(namespace):
    terms = ("qpos", "body_vel", namespace["PelvisHeight"]())
    env = namespace["make_env"](num_envs=2, device="cpu", reward_terms=terms)
    td = env.rollout(2, break_when_any_done=False)
    z = td["next", "base_pos"][..., 2:3]
    want = 0.2 * torch.exp(-50.0 * (z - 0.92).square())
    torch.testing.assert_close(td["next", "reward_terms", "pelvis_height"], want)
    assert td["next", "reward_terms", "qpos"].shape == (2, 2, 1)


def test_the_new_controller_applies_its_law(namespace):
    env = namespace["make_env"](num_envs=2, device="cpu", control_mode="torque", leg_controller=namespace["StiffPD"]())
    base = env.base_env
    base.sim.forward()  # as in tests/test_controllers.py: the state the first step starts from
    td = env.reset()
    action = torch.zeros(2, 13)
    action[:, :12] = 0.1
    q, qd = base.sim.qpos[:, 7:19].clone(), base.sim.qvel[:, 6:18].clone()
    q_ref = base.motion.joint_targets(base.time, base.init_row)[:, :12]
    out = env.step(td.set("action", action))["next"]
    limits = base.leg_torque_limits
    want = torch.clamp(600.0 * (q_ref + 0.3 * 0.1 - q) - 30.0 * qd, -limits, limits)
    torch.testing.assert_close(out["leg_torque"], want, rtol=1e-5, atol=1e-4)  # float32 at ~500 N·m


def test_the_new_task_trained_and_wrote_its_run(namespace):
    result = namespace["result"]
    assert result.env_steps == 64
    run = namespace["cwd"] / "runs" / "stand"
    assert (run / "checkpoints" / "latest.pt").is_file()
    assert (run / "metrics" / "scalars" / "reward_terms" / "pelvis_height.csv").is_file()


def test_the_new_tasks_policy_loads_to_act_in_the_env_its_config_builds(namespace):
    # Play, the gait tests and the export build the env from the run's config, with the built-in reward terms; the
    # policy reads no reward, yet its checkpoint was refused there for holding the weights of 4 terms, not 13.
    from tocabi_torchrl.evaluation.record import load_policy
    from tocabi_torchrl.transforms import TaskReward

    loaded = load_policy(namespace["cwd"] / "runs" / "stand", num_envs=2, device="cpu")
    td = loaded.env.rollout(2, loaded.actor, break_when_any_done=False)
    assert td["next", "observation"].shape == (2, 2, 237)
    reward = next(t for t in loaded.env.transform if isinstance(t, TaskReward))
    assert len(reward.names) == 13  # the env's own reward, not the checkpoint's
