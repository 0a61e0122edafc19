"""Nested dataclass trees as plain data: dotted paths to their leaves, conversion to and from dicts, and the check of
every bool and number by its declared type. The run config (:mod:`tocabi_torchrl.config`) is such a tree; its
checkpoint entry and ``config.json`` are written and read with these helpers (its command line is tyro's, from the
same tree: :mod:`tocabi_torchrl.rl.config`).

A *section* is a dataclass field whose value is itself a dataclass; every other field is a *leaf*, addressed by its
dotted path (``"ppo.lr"``, ``"env.control.mode"``). Leaf values are plain data: numbers, strings, bools, ``None`` and
tuples of those (lists, as JSON and checkpoints return them, are read back as tuples), or a tuple of small dataclass
*items* (a leaf annotated ``tuple[Item, ...]``, e.g. ``env.scene.obstacles``), written as a list of dicts and given on
the command line as JSON.
"""

from __future__ import annotations

import collections.abc
import copy
import dataclasses
import math
import numbers
import os
import types
import typing
from typing import Any

import numpy as np

from .value_rules import plain_number

__all__ = ["OWN_NUMBER_CHECK", "ConfigError", "build_items", "check_field_types", "from_dict", "get_path", "item_type",
           "leaf_paths", "leaf_types", "replace_paths", "to_dict"]


class ConfigError(ValueError):
    """An unknown option or a bad value in a config tree; the message names the option and the fix. ``unknown``
    lists the unknown keys (dotted paths) when that is the problem."""

    def __init__(self, message: str, unknown: list[str] | None = None):
        super().__init__(message)
        self.unknown = list(unknown or [])


def _is_section(value: Any) -> bool:
    return dataclasses.is_dataclass(value) and not isinstance(value, type)


def _hints(cls: type) -> dict[str, Any]:
    return typing.get_type_hints(cls)


def item_type(kind: Any) -> type | None:
    """The dataclass ``Item`` of a leaf annotated ``tuple[Item, ...]`` (optionally ``| None``), else ``None``."""
    kind = _unwrap_optional(kind)[0]
    if typing.get_origin(kind) is not tuple:
        return None
    args = [a for a in typing.get_args(kind) if a is not Ellipsis]
    if args and dataclasses.is_dataclass(args[0]) and isinstance(args[0], type):
        return args[0]
    return None


def build_items(item: type, value: Any, where: str) -> Any:
    """A tuple-of-items leaf's value with every dict (as :func:`to_dict` writes an item) built into ``item``."""
    if isinstance(value, (dict, item)):  # one item
        value = [value]
    if not isinstance(value, (list, tuple)):
        raise ConfigError(f"config option {where!r} takes a list of {item.__name__} (or of dicts of its fields), "
                          f"got {type(value).__name__}")
    out = []
    for i, v in enumerate(value):
        if isinstance(v, dict):
            try:
                v = from_dict(item, v, f"{where}[{i}].")
            except (TypeError, ValueError) as err:
                raise ConfigError(f"{where}[{i}]: {err}", unknown=getattr(err, "unknown", None)) from None
        elif not isinstance(v, item):
            raise ConfigError(f"{where}[{i}] must be a {item.__name__} or a dict of its fields "
                              f"{[f.name for f in dataclasses.fields(item)]}, got {v!r}")
        out.append(v)
    return tuple(out)


def leaf_paths(tree: Any, prefix: str = "") -> list[str]:
    """Dotted paths of every leaf of ``tree`` (a dataclass instance), in field order."""
    out = []
    for f in dataclasses.fields(tree):
        value = getattr(tree, f.name)
        path = prefix + f.name
        out += leaf_paths(value, path + ".") if _is_section(value) else [path]
    return out


def leaf_types(tree: Any) -> dict[str, Any]:
    """``{dotted path: annotated type}`` of every leaf of ``tree``."""
    out = {}
    for path in leaf_paths(tree):
        *parents, name = path.split(".")
        owner = get_path(tree, ".".join(parents)) if parents else tree
        out[path] = _hints(type(owner))[name]
    return out


def get_path(tree: Any, path: str) -> Any:
    """The value at ``path`` (a leaf or a section); raises :class:`ConfigError` naming an unknown path."""
    value = tree
    for i, name in enumerate(path.split(".")):
        if not _is_section(value) or name not in {f.name for f in dataclasses.fields(value)}:
            where = ".".join(path.split(".")[:i]) or "the config"
            known = [f.name for f in dataclasses.fields(value)] if _is_section(value) else []
            raise ConfigError(f"unknown config option {path!r}: {where} has no {name!r}"
                              + (f"; it has {known}" if known else ""), unknown=[path])
        value = getattr(value, name)
    return value


def replace_paths(tree: Any, values: dict[str, Any]) -> Any:
    """A copy of ``tree`` with each ``{dotted path: value}`` set (the tree itself is not changed). A path may name a
    leaf or a whole section (a dataclass instance, or a dict as :func:`to_dict` writes it).

    The copy owns every section in it: neither ``tree``'s sections nor a section given as a value (a preset's, or a
    module constant such as ``randomize.TOCABI_LAB_DYNAMICS``) is shared, so editing the copy in place changes
    nothing else. Leaves are not copied: a function or a tensor given is the very object."""
    return _replace_paths(_own_sections(tree), {path: _own_sections(value) for path, value in values.items()})


def _own_sections(value: Any) -> Any:
    """``value`` with every section in it (a dataclass instance, also inside tuples, lists and dicts) a new object
    holding the same leaves; other values as they are."""
    if _is_section(value):
        clone = copy.copy(value)  # frozen sections and fields outside __init__ too, without running __post_init__
        for f in dataclasses.fields(value):
            object.__setattr__(clone, f.name, _own_sections(getattr(value, f.name)))
        return clone
    if type(value) in (tuple, list):
        return type(value)(_own_sections(v) for v in value)
    if type(value) is dict:
        return {k: _own_sections(v) for k, v in value.items()}
    return value


def _replace_paths(tree: Any, values: dict[str, Any]) -> Any:
    nested: dict[str, dict[str, Any]] = {}
    direct: dict[str, Any] = {}
    for path, value in values.items():
        get_path(tree, path)  # raises for an unknown path
        head, _, rest = path.partition(".")
        if rest:
            nested.setdefault(head, {})[rest] = value
        else:
            direct[head] = value
    for head, value in list(direct.items()):
        current = getattr(tree, head)
        item = item_type(_hints(type(tree))[head])
        if item is not None:
            direct[head] = build_items(item, value, head)
        elif _is_section(current) and isinstance(value, dict):  # a section given as a dict (as to_dict writes it)
            # Over the section as it is: a dict of some options once reset the others to the class defaults (the
            # robust preset's env.pushes={"calm_fraction": 0.25} trained with no kicks at all).
            direct[head] = from_dict(type(current), _merged(to_dict(current), value), f"{head}.")
        elif _is_section(current) and not isinstance(value, type(current)):
            raise ConfigError(f"config section {head!r} must be a {type(current).__name__} or a dict of its options, "
                              f"got {type(value).__name__}; to set one option give its path, e.g. "
                              f"'{head}.{dataclasses.fields(current)[0].name}'")
    for head, sub in nested.items():
        direct[head] = _replace_paths(direct.get(head, getattr(tree, head)), sub)
    return dataclasses.replace(tree, **direct)


def _merged(base: dict[str, Any], over: dict[str, Any]) -> dict[str, Any]:
    """``base`` with ``over``'s entries on top, sub-dicts (sections) merged the same way."""
    out = dict(base)
    for key, value in over.items():
        out[key] = _merged(out[key], value) if isinstance(value, dict) and isinstance(out.get(key), dict) else value
    return out


def _plain(value: Any) -> Any:
    if _is_section(value):  # an item of a tuple-of-items leaf
        return to_dict(value)
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, os.PathLike):
        return os.fspath(value)
    return value


def to_dict(tree: Any) -> dict[str, Any]:
    """``tree`` as nested dicts of plain values (tuples as lists), ready for JSON or ``torch.save``."""
    out = {}
    for f in dataclasses.fields(tree):
        value = getattr(tree, f.name)
        out[f.name] = to_dict(value) if _is_section(value) else _plain(value)
    return out


def _as_leaf(value: Any) -> Any:
    return tuple(_as_leaf(v) for v in value) if isinstance(value, list) else value


def from_dict(cls: type, data: dict[str, Any], where: str = "") -> Any:
    """Build ``cls`` from nested dicts (as :func:`to_dict` writes them); fields missing from ``data`` keep their
    defaults. Raises :class:`ConfigError` naming any unknown key."""
    if not isinstance(data, dict):
        raise ConfigError(f"config section {where or cls.__name__!r} must be a mapping, got {type(data).__name__}")
    default = cls()
    fields = {f.name: f for f in dataclasses.fields(cls)}
    unknown = sorted(set(data) - set(fields))
    if unknown:
        paths = [where + k for k in unknown]
        raise ConfigError(f"unknown config option(s) {paths}; {where or 'the top level'} knows {sorted(fields)}",
                          unknown=paths)
    values = {}
    hints = _hints(cls)
    for name, value in data.items():
        current = getattr(default, name)
        item = item_type(hints[name])
        if _is_section(current):
            values[name] = from_dict(type(current), value, f"{where}{name}.")
        elif item is not None:
            values[name] = build_items(item, value, f"{where}{name}")
        else:
            values[name] = _as_leaf(value)
    return cls(**values)


def _unwrap_optional(kind: Any) -> tuple[Any, bool]:
    args = typing.get_args(kind)
    if typing.get_origin(kind) in (typing.Union, types.UnionType) and type(None) in args:
        rest = [a for a in args if a is not type(None)]
        return rest[0], True
    return kind, False


#: Field metadata (``field(..., metadata=OWN_NUMBER_CHECK)``) of a number field that :func:`check_field_types`
#: leaves to its section's ``validate``, which checks it and names what is wrong more precisely (e.g. the joint).
OWN_NUMBER_CHECK = types.MappingProxyType({"check_numbers": False})


def _field_hints(cls: type) -> dict[str, Any]:
    """``cls``'s resolved field annotations; where one cannot be resolved (a name only imported for type checking),
    the plain ``"bool"``/``"int"``/``"float"`` strings still count and the rest are left unchecked."""
    try:
        return typing.get_type_hints(cls)
    except (NameError, TypeError):
        plain = {"bool": bool, "int": int, "float": float}
        return {f.name: plain.get(f.type, f.type) if isinstance(f.type, str) else f.type
                for f in dataclasses.fields(cls)}


def _number(kind: type, value: Any, where: str) -> Any:
    """``value`` as a plain Python number of ``kind`` (``float``: any finite real, ints too; ``int``: an int), or a
    ``ValueError`` naming ``where``, the value and what is accepted. A bool is refused (``True`` is not a gain); a
    numpy scalar or a 0-d array or tensor counts as the number it holds (:func:`~tocabi_torchrl.value_rules
    .plain_number`)."""
    plain = plain_number(value)
    if isinstance(plain, bool):
        ok = False
    elif kind is int:
        ok = isinstance(plain, numbers.Integral)
    else:
        try:
            ok = isinstance(plain, numbers.Real) and math.isfinite(plain)
        except OverflowError:  # an int too large for a float
            ok = False
    if not ok:
        accepted = ("an int (not a float, a bool or text)" if kind is int
                    else "a finite number, an int or a float (not NaN, inf, a bool or text)")
        raise ValueError(f"{where} must be {accepted}, got {value!r}")
    return plain


def _number_kinds(kind: Any) -> tuple[tuple[Any, ...], bool] | None:
    """For a ``tuple[float, ...]``/``tuple[int, int]``/``Sequence[float]`` annotation: the per-entry kinds (one
    kind for a variable length) and whether the length is variable; ``None`` for any other annotation."""
    if typing.get_origin(kind) not in (tuple, collections.abc.Sequence):
        return None
    args = typing.get_args(kind)
    variable = not args or Ellipsis in args or typing.get_origin(kind) is not tuple
    kinds = tuple(a for a in args if a is not Ellipsis)
    if not kinds or any(_unwrap_optional(k)[0] not in (int, float) for k in kinds):
        return None
    return kinds, variable


def _numbers(kinds: tuple[Any, ...], variable: bool, value: Any, where: str) -> tuple:
    """A tuple leaf's entries checked by :func:`_number` (entry ``i`` named ``where[i]``), as plain numbers."""
    if isinstance(value, np.ndarray) and value.ndim == 1:
        value = tuple(value)
    n = None if variable else len(kinds)
    if not isinstance(value, (tuple, list)) or (n is not None and len(value) != n):
        what = "finite numbers" if _unwrap_optional(kinds[0])[0] is float else "ints"
        raise ValueError(f"{where} must be a tuple of {what if n is None else f'{n} {what}'}, got {value!r}")
    out = []
    for i, v in enumerate(value):
        kind, optional = _unwrap_optional(kinds[0] if variable else kinds[i])
        out.append(v if v is None and optional else _number(kind, v, f"{where}[{i}]"))
    return tuple(out)


def check_field_types(tree, prefix: str = "") -> None:
    """Raise ``ValueError`` naming the first field of the dataclass ``tree`` (its nested sections and the items of
    its tuple-of-items leaves included) whose value does not fit its annotated bool or number type, by its path
    (``env.control.pd_kp[3]``), with the value and what is accepted: a ``bool`` field takes True or False (a switch
    set from text, ``"no"``, is truthy and would silently turn the option on), a ``float`` field a finite real
    number (an int too), an ``int`` field an int, a tuple of numbers (``tuple[float, ...]``, ``tuple[float,
    float]``, ``Sequence[float]``) finite entries of the annotated length. Without it a gain of NaN ends every
    episode at its first step, an inf command reaches the observation and a number given as text (``"0.6"``) fails
    later as a raw ``TypeError``. ``None`` is taken where the annotation allows it (``float | None``); numpy scalars
    and 0-d arrays or tensors are taken, as plain Python values (frozen trees too); a section (a dataclass field)
    that is not an instance of its class (None, a dict, a number) is named (each failed later as an
    ``AttributeError``); fields of other types are left alone, and so is a number field whose metadata holds
    :data:`OWN_NUMBER_CHECK` (its section's ``validate`` checks it, with a better message)."""
    hints = _field_hints(type(tree))
    for f in dataclasses.fields(tree):
        value = getattr(tree, f.name)
        where = prefix + f.name
        if _is_section(value):
            check_field_types(value, where + ".")
            continue
        kind, optional = _unwrap_optional(hints.get(f.name))
        if value is None and optional:
            continue
        if isinstance(kind, type) and dataclasses.is_dataclass(kind) and not isinstance(value, kind):
            # Anything else failed later as an AttributeError in the section's own checks.
            raise ValueError(f"{where} must be a {kind.__name__}, got {value!r}: give {kind.__name__}(...) "
                             f"({kind.__name__}() for its defaults); a dict of options is built into the section by "
                             "replace_paths (and by make_env's section keywords)")
        tuple_kinds = _number_kinds(kind)
        if kind is bool:
            plain = plain_number(value)
            if not isinstance(plain, bool):
                raise ValueError(f"{where} must be True or False, got {value!r}")
        elif f.metadata.get("check_numbers", True) is False:
            continue
        elif kind in (int, float):
            plain = _number(kind, value, where)
        elif tuple_kinds is not None:
            plain = _numbers(*tuple_kinds, value, where)
            if all(a is b for a, b in zip(plain, value)) and isinstance(value, tuple):
                plain = value  # unchanged: keep the very object
        else:
            if item_type(kind) is not None and isinstance(value, (tuple, list)):
                for i, v in enumerate(value):
                    if _is_section(v):
                        check_field_types(v, f"{where}[{i}].")
            continue
        if plain is not value:
            object.__setattr__(tree, f.name, plain)  # a numpy sweep's value, as a plain one (frozen trees too)
