"""tocabi-torchrl: TorchRL-native, GPU-native reinforcement learning for the TOCABI humanoid.

mujoco-warp steps N TOCABI worlds on one device; ``TocabiWalk`` is a batched TorchRL ``EnvBase`` over them; the
observation history, phase encoding and reward terms are TorchRL transforms; ``recipes/`` holds runnable PPO scripts.
"""

__version__ = "0.1.0"


def __getattr__(name):
    # Imported on first use: `import tocabi_torchrl` (e.g. for robot facts) should not load warp and torchrl.
    if name == "make_env":
        from .factory import make_env

        return make_env
    raise AttributeError(f"module 'tocabi_torchrl' has no attribute {name!r}")


__all__ = ["make_env", "__version__"]
