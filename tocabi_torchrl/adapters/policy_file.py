"""One safe file format for the policies the library recipes train: ``policy.pt``.

A library's own checkpoint can need unpickling to load (SB3's zip stores cloudpickled objects, and rsl_rl's runner
unpickles its own file), which this package never does, so the recipes also write this file: plain tensors and
JSON-able metadata, written atomically, read back with ``torch.load(weights_only=True)`` (no code runs on load).
The evaluation rebuilds the library's network from ``meta`` and loads ``state_dict`` into it.
"""

from __future__ import annotations

import io
import json
import os
from pathlib import Path

import torch

from ..atomic import atomic_write_bytes
from ..integrity import zip_damage

__all__ = ["FORMAT", "META_KINDS", "PolicyFileError", "load_policy", "require_meta", "save_policy"]

FORMAT = "tocabi_torchrl.adapters.policy/1"


class PolicyFileError(ValueError):
    """A policy file is missing, unreadable or not in :data:`FORMAT`."""


def save_policy(path: str | os.PathLike, library: str, state_dict: dict, meta: dict) -> Path:
    """Write ``state_dict`` (tensors) and ``meta`` (JSON-able: preset, task options, network sizes) atomically;
    refuses to replace an existing file."""
    path = Path(path)
    if path.exists():
        raise FileExistsError(f"{path} exists; choose another output folder (policies are never overwritten)")
    payload = {"format": FORMAT, "library": library, "meta": json.dumps(meta),
               "state_dict": {k: v.detach().cpu() for k, v in state_dict.items()}}
    buffer = io.BytesIO()
    torch.save(payload, buffer)
    return atomic_write_bytes(path, buffer.getvalue())


def load_policy(path: str | os.PathLike, library: str) -> tuple[dict, dict]:
    """``(meta, state_dict)`` of a :func:`save_policy` file trained with ``library``: ``meta`` a dict, ``state_dict``
    {name: tensor}. Raises :class:`PolicyFileError` naming what is wrong (a missing or damaged file, another format
    or library, a field that is missing or of the wrong kind)."""
    path = Path(path)
    if not path.is_file():
        raise PolicyFileError(f"no policy file at {path}; the recipes write <out>/policy.pt")
    damage = zip_damage(path)  # torch.load ignores the zip CRCs: flipped bits would load as other weights
    if damage is not None:
        raise PolicyFileError(f"{path} is damaged: {damage}; copy it again from where it came from, or train anew")
    try:
        payload = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as err:  # corrupt, truncated or a pickle that needs code: refuse it
        from ..rl.checkpoint import load_error_detail  # what is wrong, not torch's advice to load it unsafely

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
    return meta, state


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


def require_meta(meta, fields: dict[str, tuple[str, str]], path, needed_for: str) -> dict:
    """``meta`` if it holds every field of ``fields`` {name: (kind, what it holds)}, each of its kind in
    :data:`META_KINDS` (e.g. ``{"obs_dim": ("count", "the observation size, e.g. 237")}``); else a
    :class:`PolicyFileError` naming the file ``path``, the first missing or ill-typed field, what it is
    ``needed_for`` (e.g. "the loader needs to rebuild the network") and how to add it. The recipes write every field
    their loader reads; a hand-made or older file may lack some, which ended in a bare ``KeyError`` or ``TypeError``
    from inside the loader."""
    names = ", ".join(f"'{name}'" for name in fields)
    if not isinstance(meta, dict):
        raise PolicyFileError(f"{path}: its metadata is {type(meta).__name__}, not a dict holding {names}")
    for name, (kind, what) in fields.items():
        test, kind_text = META_KINDS[kind]
        if name not in meta:
            problem = f"its metadata has no '{name}' ({what}; {kind_text})"
        elif not test(meta[name]):
            problem = f"its metadata's '{name}' is {meta[name]!r}, not {what} ({kind_text})"
        else:
            continue
        raise PolicyFileError(
            f"{path}: {problem}, which {needed_for}. The recipes write {names} into every policy.pt; for a "
            f"hand-made or older file, load it with load_policy and save it again with '{name}' set: "
            f"save_policy(new_path, library, state_dict, {{**meta, '{name}': <{kind_text}>}})")
    return meta
