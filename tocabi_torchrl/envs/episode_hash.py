"""The episode hash of :mod:`~tocabi_torchrl.envs.episode_random` as one warp kernel, for eager CUDA steps.

In GPU training the masked reset runs after every step, and the hash's ~30 integer torch ops are ~30 kernels of it
(about 2.5 µs each at 4,096 envs). :func:`hash_uniforms` computes the same (num_envs, L) uniforms in one kernel, bit
for bit: uint64 arithmetic keeps the low 64 bits of every product as torch's int64 wrap-around does, and every value
the torch version shifts is non-negative and below 2**63, where a logical shift equals its arithmetic one.
:class:`~tocabi_torchrl.envs.episode_random.LaneDraws` calls it for CUDA tensors outside CUDA graph capture (a
captured step keeps the torch ops, whose launches the graph already removes); on the CPU the torch ops stay.
"""

from __future__ import annotations

import torch
import warp as wp

from ..sim.kernel_cache import quiet_warp_info

__all__ = ["episode_hash", "hash_uniforms"]

_MASK62 = wp.constant(wp.uint64((1 << 62) - 1))
_LOW32 = wp.constant(wp.uint64(0xFFFFFFFF))
_LOW24 = wp.constant(wp.uint64(0xFFFFFF))
_ENV = wp.constant(wp.uint64(0x9E3779B1))
_KEY = wp.constant(wp.uint64(0x85EBCA77))
_MIX1 = wp.constant(wp.uint64(0x2545F4914F6CDD1D))
_MIX2 = wp.constant(wp.uint64(0x27BB2EE687B0B0FD))
_S31 = wp.constant(wp.uint64(31))
_S29 = wp.constant(wp.uint64(29))


@wp.func
def _mix(x: wp.uint64) -> wp.uint64:
    """``episode_random._mix``: two xorshift-multiply rounds kept inside 62 bits, then a last xorshift."""
    x = x ^ (x >> _S31)
    x = (x * _MIX1) & _MASK62
    x = x ^ (x >> _S31)
    x = (x * _MIX2) & _MASK62
    return x ^ (x >> _S29)


@wp.kernel(enable_backward=False)
def episode_hash(seed: wp.array(dtype=wp.int64), env_ids: wp.array(dtype=wp.int64), key: wp.array(dtype=wp.int64),
                 lanes: wp.array(dtype=wp.int64), scrambled: wp.array(dtype=wp.int64),
                 out: wp.array2d(dtype=wp.float32)):
    """``out[i, j]``: the uniform of lane ``lanes[j]`` for world ``env_ids[i]`` and key ``key[i]``."""
    i, j = wp.tid()
    base = (wp.uint64(env_ids[i]) * _ENV + wp.uint64(key[i]) * _KEY + (wp.uint64(seed[0]) & _LOW32)) & _MASK62
    x = _mix(_mix(base ^ wp.uint64(scrambled[j])) + wp.uint64(lanes[j]))
    out[i, j] = wp.float32(wp.int32(x & _LOW24)) / 16777216.0


def hash_uniforms(seed: torch.Tensor, env_ids: torch.Tensor, key: torch.Tensor, lanes: torch.Tensor,
                  scrambled: torch.Tensor, streams: dict | None = None) -> torch.Tensor:
    """(num_envs, L) float32 uniforms, equal to ``episode_random._hash`` of the same arguments, in one launch.

    Args:
        seed: 0-d int64 tensor on the envs' device.
        env_ids, key: (num_envs,) int64, contiguous.
        lanes, scrambled: (L,) int64, contiguous (``scrambled = lanes * 0xC2B2AE3D``).
        streams: a cache of warp's wrappers of PyTorch's streams (the caller's; wrapping costs host time).

    The kernel runs on PyTorch's current stream, ordered with the torch ops around it; nothing waits on the host.
    """
    n, k = env_ids.shape[0], lanes.shape[0]
    out = torch.empty(n, k, dtype=torch.float32, device=env_ids.device)
    if n == 0 or k == 0:
        return out
    quiet_warp_info()  # before warp's first init prints its banner (a simulator usually came first and did this)
    wp.init()  # once per process; a no-op after
    stream = None
    if env_ids.is_cuda:
        current = torch.cuda.current_stream(env_ids.device)
        cache = {} if streams is None else streams
        stream = cache.get(current.cuda_stream)
        if stream is None:
            stream = cache[current.cuda_stream] = wp.stream_from_torch(current)
    wp.launch(episode_hash, dim=(n, k), device=wp.device_from_torch(env_ids.device), stream=stream,
              inputs=[wp.from_torch(seed.reshape(1)), wp.from_torch(env_ids), wp.from_torch(key),
                      wp.from_torch(lanes), wp.from_torch(scrambled)], outputs=[wp.from_torch(out)])
    return out
