"""The trainer benchmarks measure any training preset: ``--set preset=NAME`` picks the preset the other overrides
change (the robust preset's randomisation, diverse starts and pushes against the torque preset, in one process)."""

from __future__ import annotations

import pytest

from lab.benchmarks import common
from tocabi_torchrl.config import preset_config


def test_a_preset_override_picks_the_preset_and_the_rest_goes_on_top():
    overrides = common.parse_overrides(["preset=robust", "ppo.cuda_graph=off"])
    assert overrides == {"preset": "robust", "ppo.cuda_graph": "off"}
    cfg = common.run_config(16, 2, overrides, "/tmp/unused", "n", "cpu")
    robust = preset_config("robust")
    assert cfg.preset == "robust" and cfg.ppo.cuda_graph == "off"
    assert cfg.env.pushes == robust.env.pushes and cfg.env.dynamics == robust.env.dynamics
    assert cfg.env.num_envs == 16 and cfg.total_env_steps == 2 * 16 * robust.ppo.steps_per_env
    assert overrides == {"preset": "robust", "ppo.cuda_graph": "off"}  # the caller's dict is not changed
    default = common.run_config(16, 2, {}, "/tmp/unused", "n", "cpu")
    assert default.preset == "default" and default.env.pushes != robust.env.pushes
    with pytest.raises(ValueError, match="unknown preset 'robsut'"):
        common.run_config(16, 2, {"preset": "robsut"}, "/tmp/unused", "n", "cpu")
