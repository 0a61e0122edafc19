"""One safe file format for the policies the library recipes train: ``policy.pt``.

A library's own checkpoint can need unpickling to load (SB3's zip stores cloudpickled objects, and rsl_rl's runner
unpickles its own file), which this package never does, so the recipes also write this file: plain tensors and
JSON-able metadata, written atomically, read back with ``torch.load(weights_only=True)`` (no code runs on load).
The evaluation rebuilds the library's network from ``meta`` and loads ``state_dict`` into it. The file also holds
the day it was written (``written``, UTC, ISO): ``meta``'s ``preset`` is read under the name that recipe has now
(``config.preset_now``), so a policy of a preset renamed since is tested on the task it trained on.
"""

from __future__ import annotations

import datetime
import io
import json
import os
from pathlib import Path

import torch

from ..atomic import atomic_write_bytes
from ..config import preset_now
from ..integrity import load_error_detail, zip_damage

__all__ = ["FORMAT", "META_KINDS", "PolicyFileError", "action_bounds", "load_network", "load_policy", "require_meta",
           "save_policy", "utc_day", "iso_day"]

FORMAT = "tocabi_torchrl.adapters.policy/1"


class PolicyFileError(ValueError):
    """A policy file is missing, unreadable or not in :data:`FORMAT`."""


def save_policy(path: str | os.PathLike, library: str, state_dict: dict, meta: dict) -> Path:
    """Write ``state_dict`` (tensors) and ``meta`` (JSON-able: preset, task options, network sizes) atomically;
    refuses to replace an existing file (``FileExistsError``), even one that appears while this one is written."""
    path = Path(path)
    if path.exists():
        raise FileExistsError(f"{path} exists; choose another output folder (policies are never overwritten)")
    payload = {"format": FORMAT, "library": library, "meta": json.dumps(meta), "written": utc_day(),
               "state_dict": {k: v.detach().cpu() for k, v in state_dict.items()}}
    buffer = io.BytesIO()
    torch.save(payload, buffer)
    # replace=False: a file that appeared at `path` since the check above (another call's) is refused, not replaced
    return atomic_write_bytes(path, buffer.getvalue(), replace=False)


def load_policy(path: str | os.PathLike, library: str) -> tuple[dict, dict]:
    """``(meta, state_dict)`` of a :func:`save_policy` file trained with ``library``: ``meta`` a dict, ``state_dict``
    {name: tensor}. A ``preset`` (text) in ``meta`` is given under its name now (``config.preset_now`` of the day
    the file was written; a file without that day, written before 2026-12-06 when the field came, is read as older
    than every rename). Raises :class:`PolicyFileError` naming what is wrong (a missing or damaged file, another
    format or library, a field that is missing or of the wrong kind)."""
    path = Path(path)
    if not path.is_file():
        raise PolicyFileError(f"no policy file at {path}; the recipes write <out>/policy.pt")
    damage = zip_damage(path)  # torch.load ignores the zip CRCs: flipped bits would load as other weights
    if damage is not None:
        raise PolicyFileError(f"{path} is damaged: {damage}; copy it again from where it came from, or train anew")
    try:
        payload = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as err:  # corrupt, truncated or a pickle that needs code: refuse it
        raise PolicyFileError(f"{path} is not a readable policy file ({type(err).__name__}: "
                              f"{load_error_detail(err)})") from None
    if not isinstance(payload, dict) or payload.get("format") != FORMAT:
        raise PolicyFileError(f"{path} is not a {FORMAT} file")
    # A file that names the format but lacks a field (written by other code, or edited) is refused with the field
    # named, as the rest of this function does, not with a KeyError or a JSON error from inside it.
    broken = f"{path} names {FORMAT} but was not written by save_policy"
    owner = payload.get("library")
    if not isinstance(owner, str):
        raise PolicyFileError(f"{broken}: its 'library' is {owner!r}, not a library's name")
    if owner != library:
        raise PolicyFileError(f"{path} holds a {owner} policy, not a {library} one")
    try:
        meta = json.loads(payload.get("meta"))
    except (TypeError, ValueError):  # not text, or text that is not JSON
        meta = None
    if not isinstance(meta, dict):
        raise PolicyFileError(f"{broken}: its 'meta' is not the text of a JSON object")
    state = payload.get("state_dict")
    if not (isinstance(state, dict) and all(isinstance(k, str) and isinstance(v, torch.Tensor)
                                            for k, v in state.items())):
        raise PolicyFileError(f"{broken}: its 'state_dict' is not a dict of named tensors")
    written = payload.get("written", "")  # absent: a file from before the field, read as older than every rename
    if written != "" and not iso_day(written):
        raise PolicyFileError(f"{broken}: its 'written' is {_shown(written)}, not a day (YYYY-MM-DD)")
    if isinstance(meta.get("preset"), str):
        meta["preset"] = preset_now(meta["preset"], written)
    return meta, state


def utc_day() -> str:
    """Today in UTC as ISO text, ``YYYY-MM-DD``: the day a recipe's file is stamped with (``written``), which
    ``config.preset_now`` compares with a rename's day."""
    return datetime.datetime.now(datetime.timezone.utc).date().isoformat()


def iso_day(value) -> bool:
    """Whether ``value`` is a day as ``save_policy`` writes it: ISO text, ``YYYY-MM-DD``."""
    if not isinstance(value, str) or len(value) != 10:
        return False
    try:
        datetime.date.fromisoformat(value)
    except ValueError:
        return False
    return True


def _real(v) -> bool:
    return type(v) in (int, float)  # JSON's numbers; bool is an int subclass, and True is no bound


#: The kinds of metadata field :func:`require_meta` checks: {kind: (test of a JSON value, what it must be)}.
META_KINDS = {
    "text": (lambda v: isinstance(v, str), "text"),
    "count": (lambda v: type(v) is int and v > 0, "a positive int"),
    "sizes": (lambda v: isinstance(v, list) and all(type(x) is int and x > 0 for x in v), "a list of positive ints"),
    "numbers": (lambda v: isinstance(v, list) and len(v) > 0 and all(_real(x) for x in v), "a list of numbers"),
    "object": (lambda v: isinstance(v, dict) and all(isinstance(k, str) for k in v), "a JSON object"),
}


def require_meta(meta, fields: dict[str, tuple[str, str]], path, needed_for: str, within: str | None = None) -> dict:
    """``meta`` if it holds every field of ``fields`` {name: (kind, what it holds)}, each of its kind in
    :data:`META_KINDS` (e.g. ``{"obs_dim": ("count", "the observation size, e.g. 237")}``); else a
    :class:`PolicyFileError` naming the file ``path``, the first missing or ill-typed field, what it is
    ``needed_for`` (e.g. "the loader needs to rebuild the network") and how to add it. With ``within`` (a field's
    name), ``meta`` is that field's JSON object and the fields named are its keys (e.g. ``train_cfg``'s
    ``"actor"``). The recipes write every field their loader reads; a hand-made or older file may lack some, which
    ended in a bare ``KeyError`` or ``TypeError`` from inside the loader."""
    names = ", ".join(f"'{name}'" for name in fields)
    where = "its metadata" if within is None else f"its metadata's '{within}'"
    if not isinstance(meta, dict):
        raise PolicyFileError(f"{path}: {where} is {type(meta).__name__}, not a dict holding {names}")
    for name, (kind, what) in fields.items():
        test, kind_text = META_KINDS[kind]
        if name not in meta:
            problem = f"{where} has no '{name}' ({what}; {kind_text})"
        elif not test(meta[name]):
            field = f"its metadata's '{name}'" if within is None else f"{where}['{name}']"
            problem = f"{field} is {meta[name]!r}, not {what} ({kind_text})"
        else:
            continue
        if within is None:
            written, update = f"{names} into every policy.pt", f"'{name}': <{kind_text}>"
        else:
            written = f"{names} into every policy.pt's '{within}'"
            update = f"'{within}': {{**meta['{within}'], '{name}': <{kind_text}>}}"
        raise PolicyFileError(
            f"{path}: {problem}, which {needed_for}. The recipes write {written}; for a hand-made or older file, "
            f"load it with load_policy and save it again with '{name}' set: "
            f"save_policy(new_path, library, state_dict, {{**meta, {update}}})")
    return meta


def action_bounds(meta: dict, path) -> tuple[torch.Tensor, torch.Tensor]:
    """``(low, high)``: the (num_actions,) float32 tensors of ``meta``'s ``action_low`` and ``action_high`` (the
    action space's bounds, in the env's action units), after :func:`require_meta` checked they are lists of numbers.
    Raises :class:`PolicyFileError` naming the file when their lengths differ or a low bound is above its high one,
    which gymnasium's ``Box`` refused with its own error naming neither the file nor the fields."""
    low = torch.tensor(meta["action_low"], dtype=torch.float32)
    high = torch.tensor(meta["action_high"], dtype=torch.float32)
    fix = ("set both to the bounds of the env the policy trained in (one per action, e.g. 13 for TOCABI): "
           "save_policy(new_path, library, state_dict, {**meta, 'action_low': [...], 'action_high': [...]})")
    if low.shape != high.shape:
        raise PolicyFileError(f"{path}: its metadata's 'action_low' has {low.numel()} bounds but 'action_high' has "
                              f"{high.numel()}; they must have one each per action: {fix}")
    above = torch.nonzero(~(low <= high)).flatten().tolist()  # ~(<=) also catches NaN
    if above:
        i = above[0]
        raise PolicyFileError(f"{path}: its metadata's 'action_low' is above 'action_high' (or NaN) at {len(above)} "
                              f"action(s), first action {i}: {low[i].item()} > {high[i].item()}; {fix}")
    return low, high


def _shown(value, limit: int = 80) -> str:
    if isinstance(value, list) and len(value) > 4 and all(_real(x) for x in value):
        return f"[{len(value)} numbers]"  # 13 action bounds would hide the sizes that matter
    text = repr(value)
    return text if len(text) <= limit else text[:limit - 3] + "..."


def load_network(path, meta: dict, fields: tuple[str, ...], build, state: dict) -> torch.nn.Module:
    """``build()`` (the library's network rebuilt from the metadata ``fields`` of ``meta``, e.g. ``("obs_dim",
    "hidden")``) with ``state`` {name: tensor} loaded into it. Raises :class:`PolicyFileError` naming the file
    ``path``, ``fields`` with their values, the tensors that differ (their shapes in the file and in the network,
    missing and unexpected names) and the fix, where the library or ``load_state_dict`` raised its own error (a
    field of the right kind but a value that does not match the saved weights: other hidden widths, another
    observation or action size)."""
    described = ", ".join(f"{name}={_shown(meta.get(name))}" for name in fields)
    names = ", ".join(f"'{name}'" for name in fields)
    fix = (f"The weights and the metadata must come from the same training: use the policy.pt the recipe wrote with "
           f"these weights, or save this one again with {names} set to what the weights were trained with: "
           f"save_policy(new_path, library, state_dict, {{**meta, ...}})")
    try:
        net = build()
    except (KeyError, TypeError, ValueError, IndexError) as err:  # the library's own check of a field's value
        raise PolicyFileError(f"{path}: the network its metadata describes ({described}) cannot be built: "
                              f"{type(err).__name__}: {err}. {fix}") from None
    expected = {k: tuple(v.shape) for k, v in net.state_dict().items()}
    got = {k: tuple(v.shape) for k, v in state.items()}
    problems = [f"'{k}' is {got[k]} in the file but {shape} in the network"
                for k, shape in expected.items() if k in got and got[k] != shape]
    missing = [k for k in expected if k not in got]
    unexpected = [k for k in got if k not in expected]
    if missing:
        problems.append(f"the file lacks {len(missing)} tensor(s) the network has ({_shown(missing)})")
    if unexpected:
        problems.append(f"the file has {len(unexpected)} tensor(s) the network lacks ({_shown(unexpected)})")
    if problems:
        shown = "; ".join(problems[:3]) + (f"; and {len(problems) - 3} more" if len(problems) > 3 else "")
        raise PolicyFileError(f"{path}: its state_dict does not fit the network its metadata describes "
                              f"({described}): {shown}. {fix}")
    net.load_state_dict(state)
    return net
