"""Export a checkpoint's deterministic actor to ONNX (and optionally TorchScript), with its contract beside it.

:func:`load_policy` is the one place that reads a checkpoint (through ``rl.checkpoint`` and ``rl.trainer``); every
other function works on the :class:`LoadedPolicy` it returns. The ONNX graph maps the policy input ``observation``
(batch, 237) (the normalised observation history, exactly what the TorchRL actor reads) to ``action`` (batch, 13),
the Gaussian mean, unclipped; the contract says how to build the input and how to clip and apply the output.
"""

from __future__ import annotations

import io
import json
import os
from dataclasses import dataclass
from pathlib import Path

import torch
from torch import nn

from ..rl.atomic import atomic_write_bytes, atomic_write_text
from ..transforms.normalize import freeze_running_statistics
from .contract import build_contract, sha256_bytes

__all__ = [
    "ONNX_INPUT",
    "ONNX_OPSET",
    "ONNX_OUTPUT",
    "DeterministicActor",
    "ExportResult",
    "LoadedPolicy",
    "export_onnx",
    "export_policy",
    "load_policy",
]

ONNX_INPUT = "observation"
ONNX_OUTPUT = "action"
ONNX_OPSET = 18


@dataclass
class LoadedPolicy:
    """A checkpoint's run config, its agent and a one-robot CPU env built with the run's settings.

    Attributes:
        checkpoint: the ``.pt`` file read.
        config: the run's config (currently ``rl.config.PPOConfig``).
        config_dict: the config as plain values (hashed into the contract).
        agent: the trainer's agent with the checkpoint's weights.
        env: the run's ``TransformedEnv`` (1 env, CPU, C MuJoCo), its transforms holding the checkpoint's state.
        iteration, env_steps: training progress saved in the checkpoint.
    """

    checkpoint: Path
    config: object
    config_dict: dict
    agent: object
    env: object
    iteration: int
    env_steps: int


def load_policy(checkpoint: str | os.PathLike, num_envs: int = 1, **env_overrides) -> LoadedPolicy:
    """Read ``checkpoint`` (a ``.pt`` file or a run folder) safely and rebuild its agent and env on the CPU.

    This is the only function of the export that knows the checkpoint and config API; ``env_overrides`` go to
    ``rl.trainer.build_env`` (e.g. ``command=...`` for evaluation).
    """
    from ..rl.checkpoint import apply_checkpoint, checkpoint_file, config_from_checkpoint, read_checkpoint
    from ..rl.trainer import build_agent, build_env

    path = checkpoint_file(checkpoint)
    state = read_checkpoint(path)
    cfg = config_from_checkpoint(state, path)
    device = torch.device("cpu")
    env = build_env(cfg, device, num_envs=num_envs, **env_overrides)
    agent = build_agent(cfg, env.observation_spec["observation"].shape[-1], env.action_spec.shape[-1], device)
    apply_checkpoint(state, agent, env=env, path=path)
    freeze_running_statistics(env)  # the contract states the checkpoint's statistics, frozen
    return LoadedPolicy(checkpoint=path, config=cfg, config_dict=cfg.to_dict(), agent=agent, env=env,
                        iteration=int(state["iteration"]), env_steps=int(state["env_steps"]))


class DeterministicActor(nn.Module):
    """The actor's mean network: (batch, obs_dim) float32 policy input -> (batch, act_dim) mean action."""

    def __init__(self, actor):
        super().__init__()
        from ..rl.actors import gaussian_head

        self.mean_net = gaussian_head(actor).mean_net

    def forward(self, observation: torch.Tensor) -> torch.Tensor:
        return self.mean_net(observation)


def export_onnx(module: nn.Module, obs_dim: int) -> bytes:
    """The ONNX bytes of ``module`` with a dynamic batch dimension (input ``observation``, output ``action``)."""
    module = module.eval()
    example = torch.zeros(2, obs_dim)
    buffer = io.BytesIO()
    with torch.no_grad():
        torch.onnx.export(module, (example,), buffer, input_names=[ONNX_INPUT], output_names=[ONNX_OUTPUT],
                          opset_version=ONNX_OPSET, dynamo=False,
                          dynamic_axes={ONNX_INPUT: {0: "batch"}, ONNX_OUTPUT: {0: "batch"}})
    return buffer.getvalue()


@dataclass
class ExportResult:
    onnx: Path
    contract: Path
    torchscript: Path | None


def _refuse_overwrite(paths: list[Path], overwrite: bool) -> None:
    existing = [str(p) for p in paths if p.exists()]
    if existing and not overwrite:
        raise FileExistsError(f"{', '.join(existing)} exist(s); pass --overwrite (overwrite=True) to replace them")


def export_policy(checkpoint: str | os.PathLike, out: str | os.PathLike, torchscript: bool = False,
                  overwrite: bool = False) -> ExportResult:
    """Export ``checkpoint`` to ``out`` (``.onnx``) and the contract ``out`` with ``.json``; with ``torchscript``,
    also a traced TorchScript module ``out`` with ``.ts.pt``. Files are written atomically and never replace an
    existing file unless ``overwrite``."""
    out = Path(out)
    if out.suffix != ".onnx":
        raise ValueError(f"--out must name a .onnx file, got {out}")
    contract_path = out.with_suffix(".json")
    ts_path = out.with_suffix(".ts.pt") if torchscript else None
    _refuse_overwrite([p for p in (out, contract_path, ts_path) if p is not None], overwrite)
    policy = load_policy(checkpoint)
    actor = DeterministicActor(policy.agent.actor)
    obs_dim = policy.env.observation_spec["observation"].shape[-1]
    data = export_onnx(actor, obs_dim)
    contract = build_contract(policy, onnx_file=out.name, onnx_sha256=sha256_bytes(data), input_name=ONNX_INPUT,
                              output_name=ONNX_OUTPUT, opset=ONNX_OPSET)
    atomic_write_bytes(out, data)
    atomic_write_text(contract_path, json.dumps(contract, indent=1) + "\n")
    if ts_path is not None:
        buffer = io.BytesIO()
        with torch.no_grad():
            torch.jit.save(torch.jit.trace(actor.eval(), torch.zeros(1, obs_dim)), buffer)
        atomic_write_bytes(ts_path, buffer.getvalue())
    return ExportResult(out, contract_path, ts_path)
