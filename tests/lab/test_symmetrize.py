"""lab/analysis/symmetrize.py: a trained policy made left-right symmetric after the fact."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from lab.analysis import symmetrize
from tocabi_torchrl.rl.actors import gaussian_head
from tocabi_torchrl.rl.checkpoint import config_from_checkpoint, load_checkpoint, read_checkpoint
from tocabi_torchrl.rl.symmetry import EquivariantMean

SHIPPED = Path(__file__).resolve().parents[2] / "assets" / "policies" / "tocabi_walk_robust.pt"


def _agent(path):
    from tocabi_torchrl.rl.trainer import build_agent

    state = read_checkpoint(path)
    cfg = config_from_checkpoint(state, path)
    agent = build_agent(cfg, 237, 13, torch.device("cpu"))
    load_checkpoint(path, agent)
    return cfg, agent


def test_the_copy_wraps_the_trained_network_and_is_symmetric(tmp_path):
    if not SHIPPED.is_file():
        pytest.skip("shipped robust policy not present")
    out = symmetrize.symmetrize(SHIPPED, tmp_path / "sym.pt")
    cfg, agent = _agent(out)
    original_cfg, original = _agent(SHIPPED)
    assert cfg.ppo.symmetry == "equivariant" and original_cfg.ppo.symmetry != "equivariant"
    # Everything else is the run's own config (not the one-robot env the copy was made with).
    assert cfg.env.num_envs == original_cfg.env.num_envs and cfg.ppo.minibatch_size == original_cfg.ppo.minibatch_size
    mean, trained = gaussian_head(agent.actor).mean_net, gaussian_head(original.actor).mean_net
    assert isinstance(mean, EquivariantMean)
    for mine, theirs in zip(mean.net.state_dict().values(), trained.state_dict().values(), strict=True):
        assert torch.equal(mine, theirs)  # f is the trained network, unchanged
    for mine, theirs in zip(agent.critic.state_dict().values(), original.critic.state_dict().values(), strict=True):
        assert torch.equal(mine, theirs)
    assert mean.obs_mirror.offset.abs().max() > 0  # the checkpoint's normaliser statistics, not the identity
    o = torch.randn(16, 237) * 0.3
    with torch.no_grad():
        torch.testing.assert_close(mean(mean.obs_mirror(o)), mean.action_mirror(mean(o)), atol=1e-5, rtol=0)
        # The symmetric mean is the average of the trained policy and its mirror image: not the trained one.
        assert not torch.allclose(mean(o), trained(o), atol=1e-3)
    with pytest.raises(FileExistsError, match="exists"):
        symmetrize.symmetrize(SHIPPED, out)
    with pytest.raises(ValueError, match="symmetric already"):
        symmetrize.symmetrize(out, tmp_path / "again.pt")
