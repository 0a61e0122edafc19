"""Checkpoints: policy, critic, optimiser, transform state (e.g. running normaliser) and config in one file."""

from __future__ import annotations

from pathlib import Path

import torch
from torch import nn

__all__ = ["save_checkpoint", "load_checkpoint", "CheckpointError"]


class CheckpointError(RuntimeError):
    """A checkpoint is missing, unreadable or does not fit the agent it is loaded into."""


def _transform_state(env) -> dict:
    transform = getattr(env, "transform", None)
    return transform.state_dict() if isinstance(transform, nn.Module) else {}


def save_checkpoint(run_dir: Path, iteration: int, env_steps: int, agent, optimizer, env, cfg,
                    train_seconds: float = 0.0, tag: str | None = None) -> Path:
    """Write ``checkpoints/iter_XXXXXX.pt`` (or ``checkpoints/<tag>.pt``) and refresh ``checkpoints/latest.pt``
    under ``run_dir``. ``train_seconds``: training wall-clock so far, summed over resumed segments."""
    folder = Path(run_dir) / "checkpoints"
    folder.mkdir(parents=True, exist_ok=True)
    state = {
        "iteration": iteration,
        "env_steps": env_steps,
        "agent": agent.state_dict(),
        "optimizer": optimizer.state_dict() if optimizer is not None else None,
        "transforms": _transform_state(env),
        "config": cfg.to_dict(),
        "train_seconds": float(train_seconds),
    }
    path = folder / (f"{tag}.pt" if tag else f"iter_{iteration:06d}.pt")
    torch.save(state, path)
    torch.save(state, folder / "latest.pt")
    return path


def load_checkpoint(path, agent, optimizer=None, env=None, device="cpu") -> dict:
    """Load ``path`` into ``agent`` (and optimiser / env transforms when given); returns the raw state."""
    path = Path(path)
    if path.is_dir():
        path = path / "checkpoints" / "latest.pt" if (path / "checkpoints").is_dir() else path / "latest.pt"
    if not path.is_file():
        raise CheckpointError(f"checkpoint not found: {path} (pass a .pt file or a run folder with checkpoints/)")
    try:
        state = torch.load(path, map_location=device, weights_only=False)
    except Exception as err:
        raise CheckpointError(f"cannot read checkpoint {path}: {err}") from err
    try:
        agent.load_state_dict(state["agent"])
    except (KeyError, RuntimeError) as err:
        raise CheckpointError(f"checkpoint {path} does not fit this agent (network sizes differ?): {err}") from err
    if optimizer is not None and state.get("optimizer"):
        optimizer.load_state_dict(state["optimizer"])
    if env is not None and state.get("transforms") and isinstance(getattr(env, "transform", None), nn.Module):
        env.transform.load_state_dict(state["transforms"], strict=False)
    return state
