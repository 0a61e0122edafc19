"""The walking task for other RL libraries: gymnasium, rsl_rl, Stable-Baselines3 and skrl.

Every adapter builds the same TorchRL env (:func:`build_env`) and steps it through one shared core
(``_core.TensorStepper``): same observations, rewards, terminations and resets as the TorchRL trainer.

=========================  =======================================  ====================================
adapter                    library interface                        data
=========================  =======================================  ====================================
``TocabiVectorEnv``        ``gymnasium.vector.VectorEnv`` (1.x)     torch on the env's device, or numpy
``TocabiRslRlEnv``         ``rsl_rl.env.VecEnv`` (rsl-rl-lib 5.x)   TensorDict on the device, zero-copy
``TocabiSB3VecEnv``        SB3 ``VecEnv`` (stable-baselines3 2.x)   numpy on the host
``TocabiSkrlEnv``          skrl ``Wrapper`` (skrl 2.x)              torch on the env's device
=========================  =======================================  ====================================

Importing this package registers ``TocabiWalk-v0`` with gymnasium (``gymnasium.make_vec("TocabiWalk-v0",
num_envs=...)``); the library adapters import their library only when used, and check its version
(``_versions.SUPPORTED``); gymnasium's is checked on importing this package. ``docs/other-libraries.md`` has the
details.
"""

from __future__ import annotations

from ._versions import SUPPORTED, LibraryVersionError, require

# gymnasium, a core dependency, has its version checked as the optional libraries do, before any adapter module
# (each imported after this package) uses it: an older one (before 1.1, no AutoresetMode) failed with a bare
# ImportError naming neither the version nor the fix.
_gymnasium = require("gymnasium")

from ._build import build_env, task_config  # noqa: E402 (after the check above)

# What a star import takes: the core (gymnasium is a core dependency). The rsl_rl, SB3 and skrl adapters import
# their optional library, so they are imported by name only (``from tocabi_torchrl.adapters import TocabiRslRlEnv``):
# a star import listing them failed on an install without those libraries.
__all__ = [
    "ENV_ID",
    "SUPPORTED",
    "LibraryVersionError",
    "TocabiVectorEnv",
    "build_env",
    "task_config",
]

ENV_ID = "TocabiWalk-v0"

_LAZY = {
    "TocabiVectorEnv": "gymnasium_env",
    "TocabiRslRlEnv": "rsl_rl_env",
    "TocabiSB3VecEnv": "sb3_env",
    "TocabiSkrlEnv": "skrl_env",
}


def __getattr__(name):
    # Each library adapter imports (and version-checks) its library: load it only when asked for.
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(f".{_LAZY[name]}", __name__), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


if ENV_ID not in _gymnasium.registry:
    _gymnasium.register(ENV_ID, entry_point="tocabi_torchrl.adapters.gymnasium_env:single_env_entry_point",
                        vector_entry_point="tocabi_torchrl.adapters.gymnasium_env:make_vector_env")
