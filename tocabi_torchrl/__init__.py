"""tocabi-torchrl: TorchRL-native, GPU-native reinforcement learning for the TOCABI humanoid.

mujoco-warp steps N TOCABI worlds on one device; ``TocabiWalk`` is a batched TorchRL ``EnvBase`` over them; the
observation history, phase encoding and reward terms are TorchRL transforms; ``recipes/`` holds runnable PPO scripts.
"""

__version__ = "0.1.0"
