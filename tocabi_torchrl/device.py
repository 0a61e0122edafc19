"""The one check of a ``device`` argument, so that ``make_env``, ``TocabiWalk`` and the trainer reject a bad one with
the same clear message instead of a raw torch error."""

from __future__ import annotations

import torch

__all__ = ["check_device"]


def check_device(device) -> torch.device:
    """``device`` as a ``torch.device``; ``ValueError`` for anything but ``"cuda"``, ``"cuda:K"`` or ``"cpu"`` (or
    the equivalent ``torch.device``), ``RuntimeError`` for CUDA on a machine where torch sees no GPU. ``"cpu:K"``
    (and ``torch.device("cpu", K)``) is the one CPU device and comes back as plain ``cpu``."""
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
    return dev
