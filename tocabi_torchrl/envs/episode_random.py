"""Per-episode random numbers that depend only on (seed, env index, episode number), never on call order.

A reset draws its random initial conditions (start row of the motion, first command) from a counter-based hash
instead of a stateful generator. Each env's episode k then starts the same way whichever reset path ran and however
often it was called: TorchRL's reset-only-when-done path and the sync-free reset-every-step path give identical
rollouts, and a run is reproducible from its seed. Integer ops only: sync-free on any device. On eager CUDA steps
the hash is one warp kernel with the same numbers (:mod:`~tocabi_torchrl.envs.episode_hash`).
"""

from __future__ import annotations

import torch

__all__ = ["episode_uniform", "episode_normal", "EpisodeDraws", "LaneDraws", "stream_lanes", "box_muller", "hash_seed"]

_MASK = (1 << 62) - 1


def _mix(x: torch.Tensor) -> torch.Tensor:
    """Scramble non-negative int64 values (an xorshift-multiply finaliser kept inside 62 bits to avoid sign bits)."""
    for mult in (0x2545F4914F6CDD1D, 0x27BB2EE687B0B0FD):
        x = x ^ (x >> 31)
        x = (x * (mult & _MASK)) & _MASK
    return x ^ (x >> 29)


def hash_seed(seed: int) -> int:
    """The 32-bit key the hash reads for an env seed in [0, 2**63 - 1]: the seed itself below 2**32, and above, its
    low half mixed with its high half, so that seeds differing only above bit 31 draw other episodes (they once drew
    the same). On the host, once per seed."""
    seed = int(seed)
    high = int(_mix(torch.tensor(seed >> 32, dtype=torch.int64)))  # 0 stays 0
    return (seed ^ high) & 0xFFFFFFFF


def stream_lanes(stream: int, k: int, device) -> torch.Tensor:
    """(k,) int64 hash lanes of ``stream``: one per uniform, disjoint across streams for k <= 256."""
    return torch.arange(k, dtype=torch.int64, device=device) + (stream << 8)


def _hash(seed: int | torch.Tensor, env_ids: torch.Tensor, episode: torch.Tensor, lanes: torch.Tensor,
          scrambled: torch.Tensor) -> torch.Tensor:
    """(num_envs, L) uniforms of the lanes ``lanes`` (L,); ``scrambled`` is ``lanes * 0xC2B2AE3D`` (int64)."""
    base = (env_ids.to(torch.int64) * 0x9E3779B1 + episode.to(torch.int64) * 0x85EBCA77 + (seed & 0xFFFFFFFF)) & _MASK
    x = _mix(_mix(base.unsqueeze(-1) ^ scrambled) + lanes)
    return (x & 0xFFFFFF).to(torch.float32) / float(1 << 24)


def episode_uniform(seed: int | torch.Tensor, env_ids: torch.Tensor, episode: torch.Tensor, stream: int,
                    k: int) -> torch.Tensor:
    """(num_envs, k) float32 uniforms in [0, 1) for each env's ``episode`` (num_envs,) int64 and a ``stream`` id.

    ``seed``: a Python int or a 0-d int64 tensor on the envs' device (same numbers either way)."""
    lanes = stream_lanes(stream, k, env_ids.device)
    return _hash(seed, env_ids, episode, lanes, lanes * 0xC2B2AE3D)


class EpisodeDraws:
    """The uniforms of several streams for one key in one hash pass: ``{stream: (num_envs, k)}``, each equal to
    ``episode_uniform(seed, env_ids, key, stream, k)`` bit for bit (the hash is elementwise in its lanes).

    A step that draws from many streams (start row, actuators, dynamics, pushes, sensor biases) runs the ~30 integer
    ops of the hash once instead of once per stream: on a GPU each op is a kernel of the captured step graph.

    Args:
        streams: ``{stream id: uniforms per env}``; a stream with 0 uniforms is left out.
        device: where the lane constants live (the env's device).

    >>> import torch
    >>> ids, ep = torch.arange(4), torch.zeros(4, dtype=torch.int64)
    >>> draws = EpisodeDraws({0: 3, 17: 8}, "cpu")(7, ids, ep)
    >>> torch.equal(draws[17], episode_uniform(7, ids, ep, stream=17, k=8)), tuple(draws[0].shape)
    (True, (4, 3))
    """

    def __init__(self, streams: dict[int, int], device: torch.device | str):
        self.streams = {int(s): int(k) for s, k in streams.items() if k > 0}
        too_many = {s: k for s, k in self.streams.items() if k > 256}
        if too_many:  # lane j of stream s is (s << 8) + j: beyond 256 it would reuse the next stream's lanes
            raise ValueError(f"EpisodeDraws: a stream holds at most 256 uniforms per key, got {too_many}")
        device = torch.device(device)
        parts = [stream_lanes(s, k, device) for s, k in self.streams.items()]
        self._flat = LaneDraws(torch.cat(parts) if parts else torch.zeros(0, dtype=torch.int64, device=device))

    def __call__(self, seed: int | torch.Tensor, env_ids: torch.Tensor, key: torch.Tensor) -> dict[int, torch.Tensor]:
        """``{stream: (num_envs, k)}`` float32 uniforms in [0, 1) of each env's ``key`` (num_envs,) int64."""
        if not self.streams:  # nothing to draw: no hash ops at all
            return {}
        return dict(zip(self.streams, self.flat(seed, env_ids, key).split(list(self.streams.values()), dim=-1)))

    def flat(self, seed: int | torch.Tensor, env_ids: torch.Tensor, key: torch.Tensor) -> torch.Tensor:
        """(num_envs, Σk) the same uniforms side by side, the streams in the order given (no split)."""
        return self._flat(seed, env_ids, key)


class LaneDraws:
    """The uniforms of an explicit list of hash lanes, in that list's order, in one hash pass: ``(num_envs, L)``.

    Lane ``(stream << 8) + j`` (:func:`stream_lanes`) gives uniform j of ``stream``, the number
    ``episode_uniform(seed, env_ids, key, stream, k)[:, j]`` holds. For a caller that wants several streams'
    uniforms in an order of its own (interleaved, or split differently from the streams) without a gather after
    the hash: the order is paid once, when the lanes are built.

    Args:
        lanes: (L,) int64 hash lanes, on the envs' device.

    >>> import torch
    >>> ids, ep = torch.arange(3), torch.zeros(3, dtype=torch.int64)
    >>> lanes = torch.cat((stream_lanes(5, 4, "cpu")[2:], stream_lanes(9, 1, "cpu")))
    >>> u = LaneDraws(lanes)(0, ids, ep)
    >>> torch.equal(u[:, :2], episode_uniform(0, ids, ep, stream=5, k=4)[:, 2:]), tuple(u.shape)
    (True, (3, 3))
    """

    def __init__(self, lanes: torch.Tensor):
        if lanes.dtype != torch.int64 or lanes.dim() != 1:
            raise ValueError(f"LaneDraws takes (L,) int64 lanes, got {tuple(lanes.shape)} {lanes.dtype}")
        self.lanes = lanes.contiguous()
        self._scrambled = self.lanes * 0xC2B2AE3D
        self._streams: dict = {}  # warp's wrappers of PyTorch's CUDA streams, for the one-kernel hash

    def __call__(self, seed: int | torch.Tensor, env_ids: torch.Tensor, key: torch.Tensor) -> torch.Tensor:
        """(num_envs, L) float32 uniforms in [0, 1) of each env's ``key`` (num_envs,) int64.

        On CUDA with a tensor ``seed``, outside CUDA graph capture, one warp kernel computes them
        (:func:`~tocabi_torchrl.envs.episode_hash.hash_uniforms`, the same numbers); elsewhere ~30 torch ops do."""
        if key.is_cuda and isinstance(seed, torch.Tensor) and not torch.cuda.is_current_stream_capturing():
            from .episode_hash import hash_uniforms  # warp only where it runs

            return hash_uniforms(seed, env_ids.to(torch.int64).contiguous(), key.to(torch.int64).contiguous(),
                                 self.lanes, self._scrambled, self._streams)
        return _hash(seed, env_ids, key, self.lanes, self._scrambled)


def episode_normal(seed: int | torch.Tensor, env_ids: torch.Tensor, episode: torch.Tensor, stream: int,
                   k: int) -> torch.Tensor:
    """(num_envs, k) float32 standard normals for each env's ``episode`` (Box-Muller over :func:`episode_uniform`'s
    uniforms of the same key: 2k lanes of ``stream``)."""
    return box_muller(episode_uniform(seed, env_ids, episode, stream, 2 * k))


def box_muller(u: torch.Tensor) -> torch.Tensor:
    """(num_envs, k) standard normals from (num_envs, 2k) uniforms in [0, 1): the cosine of each Box-Muller pair
    (radius from the first k, angle from the last k), as :func:`episode_normal` draws them."""
    k = u.shape[-1] // 2
    radius = torch.sqrt(-2.0 * torch.log1p(-u[:, :k]))  # 1 - u in (0, 1]: log is finite
    return radius * torch.cos(2.0 * torch.pi * u[:, k:])
