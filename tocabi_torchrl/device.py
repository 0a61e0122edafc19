"""The one check of a ``device`` argument, so that ``make_env``, ``TocabiWalk`` and the trainer reject a bad one with
the same clear message instead of a raw torch error."""

from __future__ import annotations

import torch

__all__ = ["check_device"]


def check_device(device) -> torch.device:
    """``device`` as a ``torch.device``; ``ValueError`` for anything but ``"cuda"``, ``"cuda:K"`` or ``"cpu"`` (or
    the equivalent ``torch.device``), ``RuntimeError`` for CUDA on a machine where torch sees no GPU, or for a
    ``cuda:K`` past the GPUs it sees. ``"cpu:K"`` (and ``torch.device("cpu", K)``) is the one CPU device and comes
    back as plain ``cpu``."""
    try:
        dev = torch.device(device)
    except (RuntimeError, TypeError) as err:
        raise ValueError(f"unknown device {device!r}: use 'cuda', 'cuda:K' or 'cpu'") from err
    if dev.type not in ("cuda", "cpu"):
        raise ValueError(f"unsupported device {dev}: use 'cuda', 'cuda:K' or 'cpu'")
    if dev.type == "cpu":
        # torch has one CPU device: "cpu:0" names it too, but tensors made on "cpu" compare unequal to it, and the env
        # would refuse the policy's actions as being on another device.
        return torch.device("cpu")
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise RuntimeError(f"device {str(device)!r} requested but torch sees no CUDA GPU; pass device='cpu'")
    # Said here, not as "invalid device ordinal" from deep inside the env build (a run folder already claimed).
    if dev.index is not None and dev.index >= (count := torch.cuda.device_count()):
        seen = "1 CUDA GPU (cuda:0)" if count == 1 else f"{count} CUDA GPUs (cuda:0 to cuda:{count - 1})"
        raise RuntimeError(f"device {str(device)!r} requested but torch sees {seen}; pass one of those, or 'cuda'")
    return dev
