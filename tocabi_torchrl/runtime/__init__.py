"""A torch-free runtime for exported policies: numpy, mujoco (for the sim-to-sim driver) and onnxruntime only (the
sim-to-sim recipe's progress bar adds tqdm).

* :mod:`.contract`: :func:`load_contract`, :class:`ContractError`, :data:`CONTRACT_VERSION`
* :mod:`.policy`: :class:`PolicyRuntime` (observation, history, phase clock, ONNX, leg commands at the control rate)
* :mod:`.mujoco_driver`: :func:`run_sim2sim`, C MuJoCo robots driven through the runtime (``recipes/sim2sim.py``)
* :mod:`.randomization`: the contract's ``trained_under`` section, and the training randomisation, pushes and start
  velocities in numpy for the driver

Nothing here imports torch or torchrl (``tests/test_runtime.py`` checks it in a fresh interpreter).
"""

from .contract import CONTRACT_FORMAT, CONTRACT_VERSION, ContractError, check_contract, load_contract
from .policy import Command, PolicyRuntime, RobotState

__all__ = [
           "CONTRACT_FORMAT",
           "CONTRACT_VERSION",
           "Command",
           "ContractError",
           "PolicyRuntime",
           "RobotState",
           "check_contract",
           "load_contract",
]
