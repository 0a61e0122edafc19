"""Package ``__init__`` files whose public names load on first use (PEP 562).

A package that imported every submodule up front made ``import tocabi_torchrl.envs.config`` (a dataclass) load
torch, torchrl and mujoco-warp through ``envs/__init__``: seconds before ``--help`` could answer. With
:func:`lazy_names`, ``from tocabi_torchrl.envs import TocabiWalk`` still works and loads only what it names.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable, Mapping

__all__ = ["lazy_names"]


def lazy_names(namespace: dict, sources: Mapping[str, tuple[str, ...]]) -> tuple[Callable, Callable]:
    """The module ``__getattr__`` and ``__dir__`` of the package whose ``globals()`` is ``namespace`` and whose public
    names are ``{submodule: names}``.

    A name is imported from its submodule when first read, then kept in the package's namespace; a submodule's own
    name (``tocabi_torchrl.sim.health``) imports it, as the eager ``__init__`` made every one an attribute."""
    package = namespace["__name__"]
    owner = {name: module for module, names in sources.items() for name in names}

    def __getattr__(name: str):
        module = owner.get(name)
        if module is not None:
            value = getattr(importlib.import_module(f"{package}.{module}"), name)
            namespace[name] = value
            return value
        if not name.startswith("__"):
            try:
                return importlib.import_module(f"{package}.{name}")
            except ModuleNotFoundError as err:
                if err.name != f"{package}.{name}":
                    raise
        raise AttributeError(f"module {package!r} has no attribute {name!r}")

    def __dir__() -> list[str]:
        return sorted({*namespace, *owner})

    return __getattr__, __dir__
