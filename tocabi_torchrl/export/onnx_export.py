"""Export a checkpoint's deterministic actor to ONNX (and optionally TorchScript), with its contract beside it.

:func:`load_policy` is the one place that reads a checkpoint (through ``rl.checkpoint`` and ``rl.trainer``); every
other function works on the :class:`LoadedPolicy` it returns. The ONNX graph maps the policy input ``observation``
(batch, 237) (267 for the pelvis-velocity observation; the normalised observation history, exactly what the TorchRL
actor reads) to ``action`` (batch, 13), the Gaussian mean, unclipped; the contract says how to build the input and how
to clip and apply the output.

:func:`export_policy` refuses (:class:`ExportError`) a checkpoint whose actor weights or transform statistics hold
NaN or inf, and an ONNX graph whose output on representative inputs is not finite; everything it writes is
standard JSON (no ``NaN``/``Infinity``). It warns (:class:`AssistFadeWarning`) for a checkpoint saved while the torque
assist was still on: the exported policy runs without it.
"""

from __future__ import annotations

import io
import json
import os
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import nn

from ..atomic import atomic_write_bytes, atomic_write_text, check_writable
from ..transforms.normalize import freeze_running_statistics
from .contract import ExportError, build_contract, sha256_bytes

__all__ = [
    "ONNX_INPUT",
    "ONNX_OPSET",
    "ONNX_OUTPUT",
    "AssistFadeWarning",
    "DeterministicActor",
    "ExportError",
    "ExportResult",
    "LoadedPolicy",
    "assist_at_checkpoint",
    "check_finite_policy",
    "check_onnx_output",
    "export_onnx",
    "export_policy",
    "load_policy",
    "warn_if_assisted",
]

ONNX_INPUT = "observation"
ONNX_OUTPUT = "action"
ONNX_OPSET = 18


@dataclass
class LoadedPolicy:
    """A checkpoint's run config, its agent and a one-robot CPU env built with the run's settings.

    Attributes:
        checkpoint: the ``.pt`` file read.
        config: the run's config (``RunConfig``, in the current schema).
        config_dict: the config as plain values in the current schema (the contract's ``training_config``).
        saved_config: the config exactly as the checkpoint saved it (hashed into the contract: the hash then names
            the checkpoint's training, and stays the same when later versions add config fields).
        agent: the trainer's agent with the checkpoint's weights.
        env: the run's ``TransformedEnv`` (1 env, CPU, C MuJoCo), its transforms holding the checkpoint's state.
        iteration, env_steps: training progress saved in the checkpoint.
    """

    checkpoint: Path
    config: object
    config_dict: dict
    saved_config: dict
    agent: object
    env: object
    iteration: int
    env_steps: int


def load_policy(checkpoint: str | os.PathLike, num_envs: int = 1, **env_overrides) -> LoadedPolicy:
    """Read ``checkpoint`` (a ``.pt`` file or a run folder) safely and rebuild its agent and env on the CPU.

    This is the only function of the export that knows the checkpoint and config API; ``env_overrides`` go to
    ``rl.trainer.build_env`` (e.g. ``command=...`` for evaluation). Raises ``CheckpointError`` when the env
    normalises with running statistics that the checkpoint does not hold.
    """
    from ..rl.checkpoint import checkpoint_file, config_from_checkpoint, read_checkpoint
    from ..rl.trainer import build_env, checkpoint_agent

    path = checkpoint_file(checkpoint)
    state = read_checkpoint(path)
    cfg = config_from_checkpoint(state, path)
    device = torch.device("cpu")
    env = build_env(cfg, device, num_envs=num_envs, **env_overrides)
    agent = checkpoint_agent(state, cfg, env, path)
    freeze_running_statistics(env)  # the contract states the checkpoint's statistics, frozen
    return LoadedPolicy(checkpoint=path, config=cfg, config_dict=cfg.to_dict(), saved_config=dict(state["config"]),
                        agent=agent, env=env,
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


def check_finite_policy(actor: nn.Module, env, checkpoint: Path) -> None:
    """Raise :class:`ExportError` when ``actor``'s parameters or buffers, or ``env``'s transform state
    (normalisation statistics and the like), hold NaN or inf."""
    tensors = [(f"actor.{k}", v) for k, v in actor.state_dict().items()]
    transform = getattr(env, "transform", None)
    if isinstance(transform, nn.Module):
        tensors += [(f"env transform {k}", v) for k, v in transform.state_dict().items()]
    bad = [k for k, v in tensors if v.is_floating_point() and not torch.isfinite(v).all()]
    if bad:
        raise ExportError(f"{checkpoint}: NaN or inf in {bad[:6]}{' ...' if len(bad) > 6 else ''}: the run diverged "
                          "before this checkpoint was saved, and its export would drive the robot with NaN actions. "
                          "Export an earlier checkpoint of the run (checkpoints/iter_*.pt)")


def check_onnx_output(data: bytes, actor: nn.Module, obs_dim: int, checkpoint: Path) -> None:
    """Run the exported graph ``data`` (onnxruntime; the torch ``actor`` when onnxruntime is not installed) on
    representative inputs and raise :class:`ExportError` unless every output is finite."""
    # Zeros: every observation at its normalisation mean and zero past actions; then a typical normalised input.
    inputs = np.zeros((2, obs_dim), dtype=np.float32)
    inputs[1] = np.random.default_rng(0).standard_normal(obs_dim)
    try:
        import onnxruntime as ort
    except ImportError:  # the export extra brings it, but the export itself needs only onnx
        with torch.no_grad():
            output = actor.eval()(torch.from_numpy(inputs)).numpy()
    else:
        options = ort.SessionOptions()
        options.intra_op_num_threads = 1
        onnx_policy = ort.InferenceSession(data, sess_options=options, providers=["CPUExecutionProvider"])
        output = onnx_policy.run([ONNX_OUTPUT], {ONNX_INPUT: inputs})[0]
    if not np.isfinite(output).all():
        raise ExportError(f"{checkpoint}: the exported policy's action is NaN or inf on a representative input (the "
                          "mean observation or a typical one): its weights are non-finite or so large that float32 "
                          "overflows (a diverging run). Export an earlier checkpoint of the run "
                          "(checkpoints/iter_*.pt)")


class AssistFadeWarning(UserWarning):
    """The exported checkpoint was trained with the torque assist still on (β > 0), which the export leaves out."""


def assist_at_checkpoint(policy: LoadedPolicy) -> float:
    """β of the torque assist (``rl/assist.py``) that ``policy``'s training env applied when its checkpoint was
    saved (the trainer's schedule at the checkpoint's ``env_steps``): 0 for a run without the assist or past its
    fade, up to ``ppo.torque_assist`` before the fade."""
    from ..rl.trainer import assist_schedule

    schedule = assist_schedule(policy.config, policy.env)
    return 0.0 if schedule is None else float(schedule(policy.env_steps))


def warn_if_assisted(policy: LoadedPolicy) -> float:
    """Warn (:class:`AssistFadeWarning`) when ``policy`` was trained with the torque assist still on; returns β.

    The assist adds β·limit·PD(reference) to the legs' torques in training only: the exported policy (the
    runtime, sim2sim, the real robot) gets pure torques, as the gait tests do. A policy saved mid-fade may walk
    without it (the robust preset's shipped policy, at β ≈ 0.05, passes the robust test): the gait test says."""
    beta = assist_at_checkpoint(policy)
    if beta > 0.0:
        ppo = policy.config.ppo
        warnings.warn(f"{policy.checkpoint} was saved at {policy.env_steps:,} env steps, while the torque assist "
                      f"was still on: β = {beta:.3f} (it fades from {ppo.torque_assist:g} at "
                      f"{ppo.assist_fade_start:,} to 0 at {ppo.assist_fade_end:,} env steps). The policy trained with "
                      "β·limit·PD assist torque added to its leg torques; the exported policy runs without it. Check "
                      f"that it walks without the assist (python recipes/play.py --checkpoint {policy.checkpoint}, "
                      f"which tests it as exported), or export a checkpoint saved after {ppo.assist_fade_end:,} env "
                      "steps",
                      AssistFadeWarning, stacklevel=3)
    return beta


@dataclass
class ExportResult:
    """What :func:`export_policy` wrote, and the stale TorchScript file it removed (``removed_torchscript``)."""

    onnx: Path
    contract: Path
    torchscript: Path | None
    removed_torchscript: Path | None = None
    #: The policy's reference motion, copied beside the ``.onnx`` when it is none of the shipped motions (the
    #: torch-free runtime looks there, then among the shipped ones); None when a shipped motion is the policy's.
    motion: Path | None = None
    #: β of the torque assist the policy trained with at its checkpoint (0: none, a pure torque or PD policy); the
    #: export runs without it (:func:`warn_if_assisted`).
    assist: float = 0.0


def _motion_beside(motion_file: Path, out: Path, overwrite: bool) -> Path | None:
    """Where the policy's motion must go beside ``out`` for the runtime to find it, or None (a shipped motion,
    or the same file already there). Refuses (``FileExistsError``) another file of the name unless ``overwrite``."""
    from ..robot import asset_path
    from ..runtime.motion import file_sha256

    want = file_sha256(motion_file)
    shipped = asset_path("motions", motion_file.name)
    target = out.with_name(motion_file.name)
    if (shipped.is_file() and file_sha256(shipped) == want) or (target.is_file() and file_sha256(target) == want):
        return None
    if target.exists() and not overwrite:
        raise FileExistsError(f"{target} already exists and is another motion than the policy's ({motion_file}), "
                              "which the runtime reads beside the .onnx; replace it with --overwrite (overwrite=True "
                              "from Python), or export to another folder")
    return target


def _refuse_overwrite(paths: list[Path], overwrite: bool, torchscript: bool) -> None:
    existing = [p for p in paths if p.exists()]
    if existing and not overwrite:
        stale = not torchscript and any(p.name.endswith(".ts.pt") for p in existing)
        note = (" (the .ts.pt is another export's: without --torchscript, --overwrite removes it rather than leave it "
                "beside this export)") if stale else ""
        raise FileExistsError(f"{', '.join(map(str, existing))} already exist(s); replace with --overwrite "
                              f"(overwrite=True from Python){note}")


def export_policy(checkpoint: str | os.PathLike, out: str | os.PathLike, torchscript: bool = False,
                  overwrite: bool = False) -> ExportResult:
    """Export ``checkpoint`` to ``out`` (``.onnx``) and the contract ``out`` with ``.json``; with ``torchscript``,
    also a traced TorchScript module ``out`` with ``.ts.pt``. Files are written atomically and never replace an
    existing file unless ``overwrite``, nor one created while the export runs (``FileExistsError``). Without
    ``torchscript``, an existing ``.ts.pt`` (another export's) counts as an output: it is refused without
    ``overwrite`` and removed with it, after the new files are written. A policy trained on a motion that is none of
    the shipped ones gets that motion copied beside ``out`` (where the torch-free runtime looks for it), an other
    file of its name there replaced only with ``overwrite``.

    Raises :class:`ExportError` for NaN/inf weights or statistics, or a non-finite output (see the module doc).
    Warns (:class:`AssistFadeWarning`) for a checkpoint saved with the torque assist still on (``result.assist``)."""
    out = Path(out)
    if out.suffix != ".onnx":
        raise ValueError(f"--out must name a .onnx file, got {out}")
    contract_path = out.with_suffix(".json")
    ts_path = out.with_suffix(".ts.pt")
    _refuse_overwrite([out, contract_path, ts_path], overwrite, torchscript)
    check_writable(out.parent)  # now, not after loading and tracing the policy
    policy = load_policy(checkpoint)
    actor = DeterministicActor(policy.agent.actor)
    check_finite_policy(actor, policy.env, policy.checkpoint)
    assist = warn_if_assisted(policy)
    obs_dim = policy.env.observation_spec["observation"].shape[-1]
    motion_file = Path(policy.env.base_env.motion.source)
    motion_copy = _motion_beside(motion_file, out, overwrite)
    data = export_onnx(actor, obs_dim)
    check_onnx_output(data, actor, obs_dim, policy.checkpoint)
    contract = build_contract(policy, onnx_file=out.name, onnx_sha256=sha256_bytes(data), input_name=ONNX_INPUT,
                              output_name=ONNX_OUTPUT, opset=ONNX_OPSET)
    try:  # standard JSON only: C++ readers (and load_contract) refuse NaN/Infinity
        text = json.dumps(contract, indent=1, allow_nan=False)
    except ValueError as err:
        raise ExportError(f"{policy.checkpoint}: the contract would hold a NaN or infinite number ({err}), which is "
                          "not JSON; find it in the run's config or statistics and export a sound checkpoint") from err
    # Without overwrite the outputs were free when checked above: a file of their names that appeared during the
    # export (loading, tracing) is someone else's, and is refused rather than replaced.
    try:
        atomic_write_bytes(out, data, replace=overwrite)
        atomic_write_text(contract_path, text + "\n", replace=overwrite)
        if motion_copy is not None:  # a motion of the run's own: the runtime reads it beside the .onnx
            atomic_write_bytes(motion_copy, motion_file.read_bytes(), replace=overwrite)
        removed = None
        if torchscript:
            buffer = io.BytesIO()
            with torch.no_grad():
                torch.jit.save(torch.jit.trace(actor.eval(), torch.zeros(1, obs_dim)), buffer)
            atomic_write_bytes(ts_path, buffer.getvalue(), replace=overwrite)
        elif overwrite and ts_path.exists():  # without overwrite, a .ts.pt there now is not the one refused above
            ts_path.unlink()
            removed = ts_path
    except FileExistsError as err:
        raise FileExistsError(f"{err.filename} appeared while the export ran and was left as it is (the export "
                              "stopped there); export again with --overwrite (overwrite=True from Python) to replace "
                              "it, or to another file") from None
    return ExportResult(out, contract_path, ts_path if torchscript else None, removed, motion_copy, assist)
