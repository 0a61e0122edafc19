"""``make_env``: the default ``TransformedEnv(TocabiWalk(...), Compose(...))`` of the walking task."""

from __future__ import annotations

import dataclasses

import torch
from torchrl.envs import TransformedEnv

from .envs import TocabiWalk, TocabiWalkConfig
from .transforms import TransformConfig, default_transforms

__all__ = ["make_env", "SyncFreeTransformedEnv"]

_TRANSFORM_FIELDS = {f.name for f in dataclasses.fields(TransformConfig)}


class SyncFreeTransformedEnv(TransformedEnv):
    """A ``TransformedEnv`` whose automatic resets never read device values on the host.

    TorchRL's ``step_and_maybe_reset`` asks ``done.any()`` on the host every step to decide whether to reset, and
    its partial-reset merge asks ``_reset.all()``: each is a GPU->CPU synchronisation that stalls the Python side
    until the physics graph has finished, so no host work overlaps GPU work. Here every step runs a masked reset
    (a no-op for unflagged worlds, sync-free by construction) and merges the reset rows with ``where``. The price is
    one masked-reset launch per step, which on the GPU is cheaper than the stall; on the CPU the stock behaviour is
    kept (``make_env`` picks this class only on CUDA).
    """

    def maybe_reset(self, tensordict):
        tensordict.set("_reset", tensordict.get("done").clone())
        return self.reset(tensordict, select_reset_only=True)

    def _reset_check_done(self, tensordict, tensordict_reset) -> None:
        # The env builds all-False done flags on reset rows; TorchRL's re-check would cost a host read.
        return None

    def _reset_proc_data(self, tensordict, tensordict_reset):
        if tensordict is None or "_reset" not in tensordict.keys():
            return super()._reset_proc_data(tensordict, tensordict_reset)
        reset = tensordict.pop("_reset").reshape(self.batch_size)
        tensordict.where(~reset, other=tensordict_reset.exclude("_reset"), out=tensordict, pad=0,
                         update_batch_size=True)
        return tensordict


def make_env(
    num_envs: int = 4096,
    device: str | torch.device = "cuda",
    preset: str = "reference",
    seed: int | None = None,
    sync_free_resets: bool | None = None,
    **overrides,
) -> TransformedEnv:
    """The walking task as the policy sees it: ``observation`` (num_envs, 237), ``reward`` (num_envs, 1),
    ``("reward_terms", name)`` per term, ``step_count``, ``episode_reward`` and the env's raw signals.

    Args:
        num_envs, device, seed: see :class:`~tocabi_torchrl.envs.TocabiWalk`.
        preset: transform preset (``"reference"``: 5 observations two steps apart + 4 actions, fixed reference
            normalisation, the 13 reference reward terms, reward 0 on terminating steps; ``"tocabilab"``: the
            consecutive history layout). See :data:`tocabi_torchrl.transforms.PRESETS`.
        sync_free_resets: use :class:`SyncFreeTransformedEnv` (default: on CUDA devices only).
        overrides: fields of :class:`~tocabi_torchrl.envs.TocabiWalkConfig` (e.g. ``control_mode="pd"``,
            ``max_episode_steps=1000``) and of :class:`~tocabi_torchrl.transforms.TransformConfig`
            (e.g. ``reward_weights={"qpos": 0.5}``, ``normalization="running"``); a name in neither raises.
    """
    env_fields = set(TocabiWalkConfig.__dataclass_fields__)
    unknown = set(overrides) - env_fields - _TRANSFORM_FIELDS
    if unknown:
        raise TypeError(f"make_env got unknown option(s) {sorted(unknown)}; valid options are the fields of "
                        "TocabiWalkConfig and TransformConfig")
    env_kwargs = {k: v for k, v in overrides.items() if k in env_fields}
    tf_kwargs = {k: v for k, v in overrides.items() if k in _TRANSFORM_FIELDS}
    base = TocabiWalk(num_envs=num_envs, device=device, seed=seed, **env_kwargs)
    # One truncation clock: the transforms' step counter follows the env's episode length.
    tf_kwargs.setdefault("max_episode_steps", base.cfg.max_episode_steps)
    if sync_free_resets is None:
        sync_free_resets = base.device.type == "cuda"
    cls = SyncFreeTransformedEnv if sync_free_resets else TransformedEnv
    return cls(base, default_transforms(preset, **tf_kwargs))
