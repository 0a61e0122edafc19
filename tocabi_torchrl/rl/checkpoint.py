"""Checkpoints: policy, critic, optimiser, transform state (e.g. running normaliser) and config in one file.

Reading a file never runs code from it: :func:`read_checkpoint` is the one reader (training's ``--resume``,
evaluation and ``recipes/play.py`` all use it). It first checks the zip CRC-32 of every entry
(:func:`tocabi_torchrl.integrity.zip_damage`: ``torch.load`` ignores them, so bits flipped in a tensor's data would load
as other weights) and that the file is not an exported policy (an ONNX model or its JSON contract, which
``recipes/sim2sim.py`` runs); it then loads with ``torch.load(weights_only=True)``, which accepts tensors and plain
containers only, and checks the keys, the types and the config against :data:`SCHEMA_VERSION`, and that the policy's
weights and the normalisers' statistics are finite (NaN or inf there: the run diverged, and a policy whose actions turn
into NaN would still look plausible, as the env reads them as 0). Anything that does not fit raises
:class:`CheckpointError` naming the file and what is wrong. Checkpoints written
before the schema was versioned (no ``schema_version``) read as version 0; config fields they lack take their
defaults. Versions 0 and 1 hold the flat ``PPOConfig`` dict of before the run config tree, which this version refuses
with a message saying so (``config.config_from_dict``). Version 2 holds the tree (``RunConfig.to_dict()``) with the
history layout as ``transforms.preset`` and the reward weights as ``"term=weight"`` entries, read by their current
names; version 3 (the shipped policies) holds the tree as it is now.

Since the reference motion can be a file of one's own, a checkpoint also holds that file's sha256
(``motion_sha256``); :func:`apply_checkpoint` refuses an env whose motion file differs (older files lack it).

Writing is atomic (:mod:`tocabi_torchrl.atomic`): a crash leaves the previous ``latest.pt`` intact.
Old ``iter_*.pt`` files are pruned after each save (``RunConfig.checkpoint_keep_last`` / ``checkpoint_keep_every``).
"""

from __future__ import annotations

import io
import json
import os
import re
from pathlib import Path

import torch
from torch import nn

from ..atomic import atomic_write_bytes
from ..config import ConfigError, RunConfig, config_from_dict
from ..device import check_device
from ..integrity import load_error_detail, zip_damage

__all__ = ["save_checkpoint", "write_policy_file", "load_checkpoint", "read_checkpoint", "apply_checkpoint",
           "checkpoint_file", "config_from_checkpoint", "align_transform_state", "prune_checkpoints", "run_folder_of",
           "is_run_checkpoint", "verified_checkpoint_file", "CheckpointError", "DamagedCheckpointError",
           "ExportedPolicyError", "SCHEMA_VERSION"]

#: Version of the checkpoint layout and config schema written by :func:`save_checkpoint`. Bump it when a change
#: means older code would misread a new file; :func:`read_checkpoint` refuses files from a newer version.
SCHEMA_VERSION = 3

_ITER_FILE = re.compile(r"^iter_(\d+)\.pt$")
#: Every name a run gives its checkpoints: ``latest.pt``, ``iter_<n>.pt``, ``wall_<seconds>s.pt`` (config.wall_tag).
_RUN_FILE = re.compile(r"^(?:latest|iter_\d+|wall_\d+s)\.pt$")


def is_run_checkpoint(path: str | os.PathLike) -> bool:
    """Whether ``path``'s file name is one a training run gives its checkpoints (not an exported or shipped policy).

    >>> [is_run_checkpoint(n) for n in ("latest.pt", "iter_120.pt", "wall_00540s.pt", "tocabi_walk_torque.pt")]
    [True, True, True, False]
    """
    return _RUN_FILE.match(Path(path).name) is not None


class CheckpointError(RuntimeError):
    """A checkpoint is missing, unreadable, damaged or does not fit the agent it is loaded into."""


class DamagedCheckpointError(CheckpointError):
    """A checkpoint file that is truncated or corrupt (its zip's CRCs, or a load that stops partway): another copy
    or another checkpoint of the run can stand in for it."""


class ExportedPolicyError(CheckpointError):
    """The file given as a checkpoint is an exported policy (an ONNX model, its JSON contract or its TorchScript
    module): ``recipes/sim2sim.py`` runs those. ``contract``: the contract to pass it (``None`` when the model has
    none beside it)."""

    def __init__(self, path: Path, kind: str, contract: Path | None, options: str = ""):
        self.path, self.kind, self.contract = path, kind, contract
        if contract is not None:
            run = f"run it with: python recipes/sim2sim.py --contract {contract}{options}"
        else:
            run = (f"run it with recipes/sim2sim.py, which needs its contract: {_contract_beside(path)} is missing "
                   f"(export the run again with python -m tocabi_torchrl.export to write both)")
        super().__init__(f"{path} is an exported policy ({kind}), not a training checkpoint (.pt): play.py, export "
                         f"and --resume read a run's checkpoints; {run}")


# --------------------------------------------------------------------------------------------------------- writing
def _transform_state(env) -> dict:
    transform = getattr(env, "transform", None)
    return transform.state_dict() if isinstance(transform, nn.Module) else {}


def motion_sha256(env) -> str | None:
    """Hex sha256 of the file ``env``'s reference motion was loaded from (the base env's ``motion.file_sha256``, taken
    when the env read it); None for an env without one, or a motion not read from a file."""
    motion = getattr(getattr(env, "base_env", env), "motion", None)
    return getattr(motion, "file_sha256", "") or None


def _check_motion(state: dict, env, path) -> None:
    """Refuse an env whose reference motion file is not the one the checkpoint trained on: the policy would follow
    other joint targets and phase without a word."""
    saved = state.get("motion_sha256")
    mine = motion_sha256(env) if saved is not None and env is not None else None
    if mine is None or mine == saved:
        return
    base = getattr(env, "base_env", env)
    where = Path(base.motion.source).resolve()
    if getattr(getattr(getattr(base, "cfg", None), "task", None), "motion", None) is None:
        why = ("the shipped motion is not the one the policy trained on (another version of tocabi-torchrl?): use the "
               "version that trained it, or set env.task.motion to the file it trained on")
    else:  # a relative path is found from the working folder, which can hold another file of that name
        why = ("run from the folder the training ran in, if env.task.motion is a relative path, or set it to the "
               "file the policy trained on")
    raise CheckpointError(f"checkpoint {path} was trained on a reference motion of sha256 {saved[:12]}..., but the "
                          f"env's motion {where} is another file ({mine[:12]}...): {why}")


def save_checkpoint(run_dir: Path, iteration: int, env_steps: int, agent, optimizer, env, cfg: RunConfig,
                    train_seconds: float = 0.0, tag: str | None = None) -> Path:
    """Write ``checkpoints/iter_XXXXXX.pt`` (or ``checkpoints/<tag>.pt``) and ``checkpoints/latest.pt`` under
    ``run_dir`` atomically, then prune old iteration files as ``cfg`` says (tagged files are kept). Returns the
    file written. ``train_seconds``: training wall-clock so far, summed over resumed segments."""
    folder = Path(run_dir) / "checkpoints"
    state = {
        "schema_version": SCHEMA_VERSION,
        "iteration": iteration,
        "env_steps": env_steps,
        "agent": agent.state_dict(),
        "optimizer": optimizer.state_dict() if optimizer is not None else None,
        "transforms": _transform_state(env),
        "config": cfg.to_dict(),
        "train_seconds": float(train_seconds),
    }
    motion = motion_sha256(env)
    if motion is not None:  # what the policy followed: a rebuild that finds another file is refused (_check_motion)
        state["motion_sha256"] = motion
    buffer = io.BytesIO()
    torch.save(state, buffer)  # serialised once, written twice
    data = buffer.getvalue()
    path = atomic_write_bytes(folder / (f"{tag}.pt" if tag else f"iter_{iteration:06d}.pt"), data)
    atomic_write_bytes(folder / "latest.pt", data)
    prune_checkpoints(folder, cfg.checkpoint_keep_last, cfg.checkpoint_keep_every)
    return path


def write_policy_file(checkpoint: str | os.PathLike, out: str | os.PathLike, overwrite: bool = False) -> Path:
    """Write the policy of ``checkpoint`` (a ``.pt`` file or a run folder) to ``out`` for shipping or deployment:
    actor, critic, env-transform state and config, without the optimiser state or the torque assist's teacher
    (training-only). The config is written as this version's whole tree (:func:`config_from_checkpoint`: options
    added since the run take the value it trained with), so a shipped file names every option. The file is read with
    :func:`read_checkpoint` and written atomically; an existing ``out`` raises ``FileExistsError`` unless
    ``overwrite``. Returns ``out``."""
    from ..tree import to_dict

    path = checkpoint_file(checkpoint)
    state = read_checkpoint(path)
    out = Path(out)
    if out.exists() and not overwrite:
        raise FileExistsError(f"{out} exists; pass overwrite=True to replace it")
    policy = {**state, "optimizer": None, "config": to_dict(config_from_checkpoint(state, path)),
              "agent": {part: state["agent"][part] for part in ("actor", "critic")}}
    buffer = io.BytesIO()
    torch.save(policy, buffer)
    # Without overwrite, a file that appeared at `out` since the check above (another export) is refused, not replaced.
    return atomic_write_bytes(out, buffer.getvalue(), replace=overwrite)


def prune_checkpoints(folder: str | os.PathLike, keep_last: int, keep_every: int) -> list[Path]:
    """Delete ``iter_*.pt`` files in ``folder`` except the newest ``keep_last`` (0: keep every file) and those whose
    iteration is a multiple of ``keep_every`` (0: none besides the newest). ``latest.pt`` is never touched.
    Returns the deleted paths."""
    if keep_last <= 0:
        return []
    found = sorted((int(m.group(1)), p) for p in Path(folder).glob("iter_*.pt") if (m := _ITER_FILE.match(p.name)))
    newest = {it for it, _ in found[-keep_last:]}
    removed = []
    for it, path in found:
        if it in newest or (keep_every > 0 and it % keep_every == 0):
            continue
        path.unlink(missing_ok=True)
        removed.append(path)
    return removed


# --------------------------------------------------------------------------------------------------------- reading
def checkpoint_file(path: str | os.PathLike) -> Path:
    """The ``.pt`` file meant by ``path``: the file itself, or of a run folder ``checkpoints/latest.pt`` (the newest
    ``iter_*.pt`` where that is missing)."""
    path = given = Path(path)
    if path.is_dir():
        folder = path / "checkpoints" if (path / "checkpoints").is_dir() else path
        path = _newest_checkpoint(folder)
    if not path.is_file():
        note = _library_folder_note(given) if given.is_dir() else None
        if note is not None:
            raise CheckpointError(f"checkpoint not found in {given}: {note}")
        raise CheckpointError(f"checkpoint not found: {path} (pass a .pt file or a run folder with checkpoints/)")
    return path


def _newest_checkpoint(folder: Path) -> Path:
    """``folder/latest.pt``, or where it is missing (a run killed between writing its first iteration file and
    ``latest.pt``, :func:`save_checkpoint`) the ``iter_*.pt`` of the highest iteration by name (file times put any
    file first after ``cp -r``). Returns ``latest.pt`` when there is neither, for the caller's not-found error."""
    latest = folder / "latest.pt"
    found = sorted((int(m.group(1)), p) for p in folder.glob("iter_*.pt") if (m := _ITER_FILE.match(p.name)))
    return found[-1][1] if found and not latest.is_file() else latest


def run_folder_of(checkpoint: str | os.PathLike) -> Path:
    """The run folder a checkpoint file belongs to: ``<run>/`` for ``<run>/checkpoints/*.pt``, else the file's own
    folder (the inverse of :func:`checkpoint_file` for a run folder)."""
    file = Path(checkpoint)
    return file.parent.parent if file.parent.name == "checkpoints" else file.parent


def read_checkpoint(path: str | os.PathLike, device: str | torch.device = "cpu") -> dict:
    """Load and check the checkpoint at ``path`` (a file or a run folder) without running code from it.

    ``device``: where the tensors are loaded ("cpu", "cuda", "cuda:K" or a ``torch.device``); one that is unknown
    or absent raises ``ValueError`` / ``RuntimeError`` (:func:`~tocabi_torchrl.device.check_device`) before the file
    is read. Returns the state dict with ``schema_version`` filled in (0 for files written before it existed).
    Raises :class:`CheckpointError` naming the file for a missing, truncated, foreign or malformed file, and for one
    whose actor or critic weights or normalisation statistics hold NaN or inf (a diverged run).
    """
    # Checked first: torch.load's own failure for "cuda" on a CPU-only machine read as a damaged file, and a resume
    # then pointed at another checkpoint of the run as if this one were broken.
    device = check_device(device)
    path = verified_checkpoint_file(path)
    try:
        state = torch.load(path, map_location=device, weights_only=True)
    except Exception as err:  # noqa: BLE001 - whatever torch/pickle/zip raise for a bad file, say which file
        text, refused = _load_failure(path, err)
        raise (CheckpointError if refused else DamagedCheckpointError)(text) from err
    _check_layout(state, path)
    state.setdefault("schema_version", 0)
    return state


def _check_integrity(path: Path) -> None:
    damage = zip_damage(path)
    if damage is not None:
        raise DamagedCheckpointError(f"checkpoint {path} is damaged: {damage}. Loading it would give silently "
                                     "different weights. Copy it again from where it came from, or pick another "
                                     "checkpoint of the run (checkpoints/iter_*.pt)")


def _contract_beside(path: Path) -> Path:
    """The JSON contract an export wrote beside its ``.onnx`` or ``.ts.pt`` file ``path``."""
    from ..runtime.contract import contract_beside  # the runtime's rule, which load_contract's errors follow too

    return contract_beside(path)


def _run_config_note(path: Path) -> str | None:
    """A message when ``path`` is a run's ``config.json`` (a JSON object with the run config's sections), else None:
    torch's own error for it reads "Unsupported operand 123"."""
    try:
        with open(path, "rb") as file:
            if file.read(64).lstrip()[:1] != b"{":
                return None
        text = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError):
        return None
    if not (isinstance(text, dict) and {"env", "ppo"} <= text.keys()):
        return None
    return (f"{path} is a run's config (config.json), not a checkpoint: pass the run folder {path.parent} (its "
            f"checkpoints/latest.pt) or a file in {path.parent / 'checkpoints'}")


def _exported_kind(path: Path) -> tuple[str, Path | None] | None:
    """``(what it is, its contract)`` when ``path`` is an exported policy, by its suffix or its first bytes."""
    from ..runtime.contract import CONTRACT_FORMAT, exported_policy_kind

    with open(path, "rb") as file:
        head = file.read(16)
    kind = exported_policy_kind(path, head)
    if kind is not None:
        # A .ts.pt is the export's traced TorchScript module, which torch.load cannot read with weights_only.
        contract = _contract_beside(path)
        return kind, contract if contract.is_file() else None
    if path.suffix == ".json" or head.lstrip()[:1] == b"{":
        try:
            text = json.loads(path.read_text())
        except (UnicodeDecodeError, json.JSONDecodeError):
            return None
        if isinstance(text, dict) and text.get("format") == CONTRACT_FORMAT:
            return "the JSON contract of an ONNX export", path
    return None


def verified_checkpoint_file(path: str | os.PathLike, sim2sim_options: str = "") -> Path:
    """:func:`checkpoint_file` of ``path``, checked before anything unpickles it: an exported policy (an ONNX model,
    its JSON contract or its TorchScript module) raises :class:`ExportedPolicyError`, whose message gives the
    ``recipes/sim2sim.py`` command with ``sim2sim_options`` appended (e.g. `` --num_robots 8``); a run's
    ``config.json`` (its folder is what to pass) and a zip entry failing its CRC-32 (bits flipped on disk or in a
    copy) raise :class:`CheckpointError`. Reads the file once (milliseconds for a policy)."""
    path = checkpoint_file(path)
    found = _exported_kind(path)
    if found is not None:
        raise ExportedPolicyError(path, *found, sim2sim_options)
    note = _run_config_note(path)
    if note is not None:
        raise CheckpointError(note)
    _check_integrity(path)
    return path


def _load_failure(path: Path, err: Exception) -> tuple[str, bool]:
    """The message for a file ``torch.load`` failed on, and whether the load was refused (a pickled global) rather
    than stopped by a broken file."""
    # weights_only refuses a pickled reference to a function or class ("Unsupported global: GLOBAL ..."); other
    # unpickling failures ("Unsupported operand", bad zip) are files that are not pickles at all.
    detail = load_error_detail(err)
    refused = detail if "GLOBAL" in detail else None
    if refused:
        return (f"refusing to load {path}: it holds Python objects other than tensors and plain containers, and "
                f"loading those could run code from the file ({refused}). Checkpoints written by tocabi-torchrl "
                "never do; only load files you trust"), True
    note = _run_config_note(path)
    if note is not None:
        return note, False
    return (f"cannot read checkpoint {path}: not a complete torch checkpoint (truncated, corrupt or another kind of "
            f"file): {type(err).__name__}: {detail[:160]}"), False


#: Who reads a training checkpoint and where one comes from, for the message about a file that is not one.
_READERS = ("play.py (its gait tests and --viewer) and the export read the checkpoints recipes/ppo_walk.py writes "
            "(<run>/checkpoints/) and the shipped policies (play.py --policy ppo)")


def _library_policy_note(state: dict, path: Path) -> str | None:
    """What to say of ``state`` when it is the ``policy.pt`` a library recipe writes (``recipes/train_sb3.py``,
    ``train_rsl_rl.py``, ``train_skrl.py``: :mod:`tocabi_torchrl.adapters.policy_file`); ``None`` otherwise."""
    from ..adapters.policy_file import FORMAT

    if state.get("format") != FORMAT:
        return None
    library = state.get("library")
    recipe = f"recipes/train_{library}.py" if library in ("sb3", "rsl_rl", "skrl") else "a library recipe"
    return (f"{path} is the policy file of {recipe}, whose network is that library's, not a tocabi-torchrl training "
            f"checkpoint: {_READERS}; the library recipe ran its own gait test when its training ended (<out>/eval/)")


def _library_folder_note(folder: Path) -> str | None:
    """:func:`_library_policy_note` of ``folder/policy.pt`` (a library recipe's ``--out`` folder holds one and no
    ``checkpoints/``); ``None`` when there is no such file or it is something else."""
    policy = folder / "policy.pt"
    if not policy.is_file():
        return None
    try:
        state = torch.load(policy, map_location="cpu", weights_only=True)  # tensors and plain values only
    except Exception:  # noqa: BLE001 - not readable: the plain not-found message stands
        return None
    return _library_policy_note(state, policy) if isinstance(state, dict) else None


def _check_layout(state, path: Path) -> None:
    if not isinstance(state, dict):
        raise CheckpointError(f"checkpoint {path} holds a {type(state).__name__}, not a tocabi-torchrl checkpoint")
    version = state.get("schema_version", 0)
    if isinstance(version, bool) or not isinstance(version, int) or version < 0:
        raise CheckpointError(f"checkpoint {path}: schema_version must be an int >= 0, got {version!r}")
    if version > SCHEMA_VERSION:
        raise CheckpointError(f"checkpoint {path} has schema version {version}, newer than this tocabi-torchrl "
                              f"reads ({SCHEMA_VERSION}); upgrade the package to load it")
    expected = {"iteration": int, "env_steps": int, "agent": dict, "config": dict}
    missing = [k for k in expected if k not in state]
    if missing:
        library_policy = _library_policy_note(state, path)
        if library_policy is not None:
            raise CheckpointError(library_policy)
        raise CheckpointError(f"checkpoint {path} lacks {missing}; it has {sorted(state)} (not a tocabi-torchrl "
                              "training checkpoint?)")
    for key, kind in expected.items():
        if not isinstance(state[key], kind) or isinstance(state[key], bool):
            raise CheckpointError(f"checkpoint {path}: {key!r} must be a {kind.__name__}, got "
                                  f"{type(state[key]).__name__}")
    for part in ("actor", "critic"):
        _check_tensor_dict(state["agent"].get(part), f"agent.{part}", path)
        _check_finite(state["agent"][part], f"agent.{part}", path)
    if "teacher" in state["agent"]:  # the torque assist's frozen teacher (rl/assist.py)
        _check_tensor_dict(state["agent"]["teacher"], "agent.teacher", path)
    if state.get("transforms"):
        _check_tensor_dict(state["transforms"], "transforms", path)
        _check_finite({k: v for k, v in state["transforms"].items() if k.rpartition(".")[2] in _STATISTICS},
                      "transforms", path)
    if state.get("optimizer") is not None and not isinstance(state["optimizer"], dict):
        raise CheckpointError(f"checkpoint {path}: 'optimizer' must be a dict or None")
    motion = state.get("motion_sha256")
    if motion is not None and not (isinstance(motion, str) and re.fullmatch(r"[0-9a-f]{64}", motion)):
        raise CheckpointError(f"checkpoint {path}: 'motion_sha256' must be a sha256 (64 lowercase hex digits), got "
                              f"{motion!r}")


def _check_tensor_dict(value, name: str, path: Path) -> None:
    if not isinstance(value, dict):
        raise CheckpointError(f"checkpoint {path}: {name} must be a dict of tensors, got {type(value).__name__}")
    bad = [k for k, v in value.items() if not isinstance(k, str) or not isinstance(v, torch.Tensor)]
    if bad:
        raise CheckpointError(f"checkpoint {path}: {name} entries {bad[:5]} are not named tensors")


#: Buffer names of the observation normalisers' statistics (``FixedNormalization``'s loc and scale,
#: ``RunningNormalization``'s mean, var and count, TorchRL's ``ObservationNorm``'s loc and scale): never legitimately
#: NaN or inf. Other transform state may be (a clip bound of inf, a -inf mask), so only these are checked.
_STATISTICS = frozenset({"loc", "scale", "mean", "var", "count"})


def _check_finite(tensors: dict, name: str, path: Path) -> None:
    """:class:`CheckpointError` naming the first floating tensor of ``tensors`` that holds NaN or inf. The actor
    and critic are checked whole: no parameter or buffer of theirs may be non-finite (the std's log is taken of a
    positive std)."""
    for key, value in tensors.items():
        if (value.is_floating_point() or value.is_complex()) and not bool(torch.isfinite(value).all()):
            what = "NaN" if bool(torch.isnan(value).any()) else "inf"
            raise CheckpointError(f"checkpoint {path}: {name} {key!r} holds {what} values: the training run that "
                                  f"wrote it diverged. Pick an earlier checkpoint of the run (checkpoints/iter_*.pt) "
                                  f"to evaluate, export or resume from, or retrain (e.g. with a lower learning rate)")


def config_from_checkpoint(state: dict, path: str | os.PathLike = "<checkpoint>", strict: bool = False) -> RunConfig:
    """The run's :class:`~tocabi_torchrl.config.RunConfig` as saved in ``state``: the tree (schema 2; fields it lacks
    take their defaults, options renamed since are read by their new name: ``config.config_from_dict``). Raises
    :class:`CheckpointError` for unknown options and for values of the wrong type (a text, a NaN, a bool for a number).

    The value rules of ``RunConfig.validate`` (ranges, combinations) may be newer than the run: a saved value that
    breaks one is a warning naming the rule, so that evaluating or exporting the run still works (the default). With
    ``strict`` (what ``--resume`` uses: the run would train on with those values, which it may not change) it is a
    :class:`CheckpointError` that says so and what can be done instead. A saved option that changes nothing (the
    run's ``config.UnusedOptionError``) is a warning either way: the run trains on exactly as without it."""
    import warnings

    from ..tree import check_field_types

    try:
        cfg = config_from_dict(state["config"])
    except ConfigError as err:
        if err.unknown:
            raise CheckpointError(f"checkpoint {path}: config has unknown field(s) {err.unknown} (written by another "
                                  f"version of tocabi-torchrl?)") from err
        raise CheckpointError(f"checkpoint {path}: the saved config is invalid: {err}") from err
    except (TypeError, ValueError) as err:
        raise CheckpointError(f"checkpoint {path}: config has unknown option(s) or is invalid (written by another "
                              f"version of tocabi-torchrl?): {err}") from err
    try:
        check_field_types(cfg)
    except (TypeError, ValueError) as err:
        raise CheckpointError(f"checkpoint {path}: the saved config is invalid: {err}") from err
    try:
        cfg.validate(allow_unused=True)
    except (TypeError, ValueError) as err:
        if strict:
            raise CheckpointError(
                f"checkpoint {path}: the saved config breaks a rule of this version of tocabi-torchrl ({err}); the "
                f"rule is newer than the run, or the file was edited. A resumed run keeps its saved options, so it "
                f"cannot go on under this rule: continue it with the version that wrote it, or start a new run "
                f"(another --name) with values the rule accepts. Evaluating and exporting it still work") from err
        warnings.warn(f"checkpoint {path}: the saved config breaks a rule of this version of tocabi-torchrl ({err}); "
                      f"the run is loaded as saved (the rule is newer than the run, or the file was edited)",
                      UserWarning, stacklevel=2)
    return cfg


# --------------------------------------------------------------------------------------------------------- loading
def apply_checkpoint(state: dict, agent, optimizer=None, env=None, path: str | os.PathLike = "<checkpoint>") -> None:
    """Copy a :func:`read_checkpoint` state into ``agent`` (and the optimiser / env transforms when given), after
    checking that every tensor fits; a mismatch raises :class:`CheckpointError` listing what differs."""
    saved_mode = (((state.get("config") or {}).get("env") or {}).get("control") or {}).get("mode")
    base = getattr(env, "base_env", env)
    env_mode = getattr(getattr(getattr(base, "cfg", None), "control", None), "mode", None)
    if saved_mode is not None and env_mode is not None and saved_mode != env_mode:
        # Same tensor sizes in every mode: the actions would load, and mean torques to a PD env or the reverse.
        raise CheckpointError(f"checkpoint {path}: a policy of env.control.mode {saved_mode!r}, but the env runs "
                              f"{env_mode!r}: its actions would mean something else there; build the env from the "
                              "checkpoint's config (config_from_checkpoint, or play.py / load_policy)")
    _check_motion(state, env, path)
    current = agent.state_dict()
    for part in ("actor", "critic"):
        _check_fits(state["agent"][part], current[part], f"agent's {part}", path,
                    hint="the run's actor_hidden / critic_hidden / critic_privileged / std_mode / symmetry differ "
                         "from this agent's?")
    transform = getattr(env, "transform", None) if env is not None else None
    saved_transforms = state.get("transforms") or {}
    if saved_transforms and isinstance(transform, nn.Module):
        mine = transform.state_dict()
        saved_transforms = align_transform_state(saved_transforms, mine, path)
        if optimizer is None:
            saved_transforms = _without_reward_state(saved_transforms, transform)
        _check_fits({k: v for k, v in saved_transforms.items() if k in mine}, mine, "env transforms", path,
                    hint="another observation layout or normalisation?", allow_missing=True)
    saved_norm = ((state.get("config") or {}).get("transforms") or {}).get("normalization")
    if saved_norm is not None and isinstance(transform, nn.Module):
        _require_normaliser(saved_norm, transform, path)
    if saved_norm == "running" and isinstance(transform, nn.Module):  # after the alignment (indices may shift)
        _require_running_statistics(saved_transforms, transform, path)
    agent.load_state_dict(state["agent"])
    if optimizer is not None and state.get("optimizer"):
        try:
            optimizer.load_state_dict(state["optimizer"])
        except (KeyError, ValueError, RuntimeError) as err:
            raise CheckpointError(f"checkpoint {path}: the optimiser state does not fit this optimiser ({err}); "
                                  "value_head_lr differs?") from err
    if saved_transforms and isinstance(transform, nn.Module):
        transform.load_state_dict(saved_transforms, strict=False)


def _without_reward_state(saved: dict, transform: nn.Module) -> dict:
    """``saved`` without the state of ``transform``'s reward (``TaskReward``), for a policy loaded to act (no
    optimiser): the policy reads no reward, and the reward keeps its own weights on a load anyway. A run trained with
    terms of its own was refused by play, the gait tests and the export, whose env its config builds with the
    built-in terms; a resumed run (with its optimiser) is still told when its terms differ in number."""
    from ..transforms.reward import TaskReward

    reward = {f"{name}.{buf}" if name else buf for name, module in transform.named_modules()
              if isinstance(module, TaskReward) for buf in TaskReward._CONFIG_BUFFERS}
    return {k: v for k, v in saved.items() if k not in reward}


def _require_normaliser(saved_norm: str, transform: nn.Module, path) -> None:
    """Refuse an env whose policy input is normalised when the checkpoint's was not, or the reverse: the weights
    fit either way (same width), and the policy would act on raw observations, or on ones divided by statistics it
    never saw."""
    from ..transforms.normalize import _Normalization

    env_has = any(isinstance(m, _Normalization) for m in transform.modules())
    if env_has != (saved_norm != "none"):
        raise CheckpointError(f"checkpoint {path}: a policy of transforms.normalization {saved_norm!r}, but the env "
                              f"{'normalises' if env_has else 'does not normalise'} its observations: the policy "
                              "would act on inputs it never saw; build the env from the checkpoint's config "
                              "(config_from_checkpoint, or play.py / load_policy)")


def _require_running_statistics(saved: dict, transform: nn.Module, path) -> None:
    """Refuse a checkpoint of a run with running normalisation that lacks the statistics of the env's normalisers.

    Transform state loads leniently (a resumed run may add transforms), so such a checkpoint would otherwise act,
    be gait-tested or exported with the normaliser's initial statistics instead of those the policy trained with.
    (A caller that gives a fixed-normalisation run's checkpoint an env of its own with a running normaliser chose
    that normaliser's start.)"""
    from ..transforms.normalize import RunningNormalization

    missing = [f"{name}.{buf}" if name else buf for name, module in transform.named_modules()
               if isinstance(module, RunningNormalization) for buf in ("mean", "var", "count")
               if (f"{name}.{buf}" if name else buf) not in saved]
    if missing:
        raise CheckpointError(f"checkpoint {path} lacks the running normalisation statistics {missing} of its env "
                              "(transforms.normalization = 'running'): the policy would run with the initial "
                              "statistics instead of those it was trained with. Use a checkpoint saved with its env "
                              "(save_checkpoint(..., env)), e.g. the run's checkpoints/latest.pt")


def _transform_groups(state: dict) -> dict[tuple[str, str], set[str]]:
    """The keys of a transform chain's state by the transform they belong to: ``("transforms", "3")`` -> names."""
    groups: dict[tuple[str, str], set[str]] = {}
    for key in state:
        parts = key.split(".", 2)
        if len(parts) == 3 and parts[1].isdigit():
            groups.setdefault((parts[0], parts[1]), set()).add(parts[2])
    return groups


def align_transform_state(saved: dict, mine: dict, path: str | os.PathLike = "<checkpoint>") -> dict:
    """``saved`` (a transform chain's state from a checkpoint) with each transform's keys moved to its index in the
    chain ``mine`` belongs to. A transform added or left out (sensor noise, say) shifts the indices of the ones after
    it; the stateful transforms are matched in order by the names of their state (a running normaliser's ``mean``,
    ``var``, ``count``), so a running normaliser's statistics reach the running normaliser wherever it now stands. A
    saved transform that the chain no longer has (running statistics resumed into fixed normalisation) is left
    out, never loaded into another transform."""
    if all(key in mine for key in saved):
        return saved
    have, want = _transform_groups(saved), _transform_groups(mine)
    order = sorted(want, key=lambda g: (g[0], int(g[1])))
    moved: dict[tuple[str, str], tuple[str, str]] = {}
    for group in sorted(have, key=lambda g: (g[0], int(g[1]))):
        match = next((g for g in order if g[0] == group[0] and want[g] == have[group]), None)
        if match is not None:
            moved[group] = match
            order = order[order.index(match) + 1:]
    out = {}
    for key, value in saved.items():
        parts = key.split(".", 2)
        group = (parts[0], parts[1]) if len(parts) == 3 and parts[1].isdigit() else None
        if group is None:
            out[key] = value
        elif group in moved:
            out[f"{moved[group][0]}.{moved[group][1]}.{parts[2]}"] = value
    return out


def _check_fits(saved: dict, current: dict, what: str, path, hint: str, allow_missing: bool = False) -> None:
    problems = []
    if not allow_missing:
        problems += [f"missing {k}" for k in current if k not in saved]
        problems += [f"unexpected {k}" for k in saved if k not in current]
    problems += [f"{k}: file {tuple(saved[k].shape)} vs {tuple(v.shape)}" for k, v in current.items()
                 if k in saved and tuple(saved[k].shape) != tuple(v.shape)]
    if problems:
        shown = "; ".join(problems[:6]) + (f"; ... ({len(problems)} in all)" if len(problems) > 6 else "")
        terms = [k for k, v in current.items() if k.endswith("._weights") and k in saved
                 and tuple(saved[k].shape) != tuple(v.shape)]
        if terms:  # TaskReward's weights: one per reward term
            k = terms[0]
            hint = (f"it was trained with {saved[k].shape[0]} reward terms, this env has {current[k].shape[0]}: a run "
                    "trained with terms of its own (build_env(cfg, ..., reward_terms=...)) goes on from Python with "
                    "an env built with the same terms: train(cfg, env=...)")
        raise CheckpointError(f"checkpoint {path} does not fit this {what} ({hint}): {shown}")


def load_checkpoint(path, agent, optimizer=None, env=None, device="cpu") -> dict:
    """Read ``path`` (a ``.pt`` file or a run folder) with :func:`read_checkpoint` and load it into ``agent``
    (and optimiser / env transforms when given); returns the state."""
    file = checkpoint_file(path)
    state = read_checkpoint(file, device)
    apply_checkpoint(state, agent, optimizer, env, file)
    return state
