"""Per-episode random numbers that depend only on (seed, env index, episode number), never on call order.

A reset draws its random initial conditions (start row of the motion, first command) from a counter-based hash
instead of a stateful generator. Each env's episode k then starts the same way whichever reset path ran and however
often it was called: TorchRL's reset-only-when-done path and the sync-free reset-every-step path give identical
rollouts, and a run is reproducible from its seed. Integer ops only: sync-free on any device.
"""

from __future__ import annotations

import torch

__all__ = ["episode_uniform", "episode_normal"]

_MASK = (1 << 62) - 1


def _mix(x: torch.Tensor) -> torch.Tensor:
    """Scramble non-negative int64 values (an xorshift-multiply finaliser kept inside 62 bits to avoid sign bits)."""
    for mult in (0x2545F4914F6CDD1D, 0x27BB2EE687B0B0FD):
        x = x ^ (x >> 31)
        x = (x * (mult & _MASK)) & _MASK
    return x ^ (x >> 29)


def episode_uniform(seed: int | torch.Tensor, env_ids: torch.Tensor, episode: torch.Tensor, stream: int,
                    k: int) -> torch.Tensor:
    """(num_envs, k) float32 uniforms in [0, 1) for each env's ``episode`` (num_envs,) int64 and a ``stream`` id.

    ``seed``: a Python int or a 0-d int64 tensor on the envs' device (same numbers either way)."""
    base = (env_ids.to(torch.int64) * 0x9E3779B1 + episode.to(torch.int64) * 0x85EBCA77 + (seed & 0xFFFFFFFF)) & _MASK
    lanes = torch.arange(k, dtype=torch.int64, device=env_ids.device) + (stream << 8)
    x = _mix(_mix(base.unsqueeze(-1) ^ (lanes * 0xC2B2AE3D)) + lanes)
    return (x & 0xFFFFFF).to(torch.float32) / float(1 << 24)


def episode_normal(seed: int | torch.Tensor, env_ids: torch.Tensor, episode: torch.Tensor, stream: int,
                   k: int) -> torch.Tensor:
    """(num_envs, k) float32 standard normals for each env's ``episode`` (Box-Muller over :func:`episode_uniform`'s
    uniforms of the same key: 2k lanes of ``stream``)."""
    u = episode_uniform(seed, env_ids, episode, stream, 2 * k)
    radius = torch.sqrt(-2.0 * torch.log1p(-u[:, :k]))  # 1 - u in (0, 1]: log is finite
    return radius * torch.cos(2.0 * torch.pi * u[:, k:])
