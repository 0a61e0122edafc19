"""The simulation model both backends build: a private compiled copy with the contact sensors and solver overrides."""

from __future__ import annotations

import copy
import os

import mujoco

from .. import robot
from .config import SimConfig
from .contacts import add_contact_sensors, contact_layout

__all__ = ["ModelSource", "compile_model"]

ModelSource = mujoco.MjModel | mujoco.MjSpec | str | os.PathLike | None


def _check_tocabi(model: mujoco.MjModel | mujoco.MjSpec, source: ModelSource) -> None:
    """Refuse a model that is not TOCABI before the contact sensors are looked up or added by body name (which
    failed with a list of the bodies they need, repeated, naming neither the file nor what was wrong)."""
    missing = robot.missing_names(model)
    if missing:
        where = (f"model {os.fspath(source)!r}" if isinstance(source, (str, os.PathLike))
                 else f"the mujoco.{type(model).__name__} passed as model")
        shown = ", ".join(missing[:3]) + (f" and {len(missing) - 3} more" if len(missing) > 3 else "")
        raise robot.RobotAssetError(
            f"{where} is not a TOCABI model: it lacks {shown}; pass a TOCABI MJCF with the names of "
            "tocabi_torchrl.robot (JOINT_NAMES, ACTUATOR_NAMES, ...), or None for the shipped assets/tocabi/tocabi.xml")


def _compile(source: ModelSource) -> mujoco.MjModel:
    """A private, compiled model with the contact sensors (the caller's spec or model is never modified)."""
    if isinstance(source, mujoco.MjModel):
        _check_tocabi(source, source)
        contact_layout(source)  # raises a clear error if the sensors are missing
        return copy.deepcopy(source)
    if isinstance(source, mujoco.MjSpec):
        spec = source.copy()
    elif source is None or isinstance(source, (str, os.PathLike)):
        spec = robot.load_spec(source)
    else:
        raise TypeError(
            f"model must be a mujoco.MjModel, a mujoco.MjSpec, an MJCF path or None (the shipped robot), "
            f"got {type(source).__name__}"
        )
    _check_tocabi(spec, source)
    add_contact_sensors(spec)
    try:
        return spec.compile()
    except Exception as err:
        raise ValueError(f"cannot compile the simulation model: {err}") from err


def compile_model(source: ModelSource, cfg: SimConfig) -> mujoco.MjModel:
    """Compile ``source`` (see :class:`~tocabi_torchrl.sim.WarpSim`), apply ``cfg``'s explicit solver overrides and
    check the robot's names; ``None`` overrides keep what the model file says."""
    mj = _compile(source)
    if cfg.solver_iterations is not None:
        mj.opt.iterations = cfg.solver_iterations
    if cfg.solver_ls_iterations is not None:
        mj.opt.ls_iterations = cfg.solver_ls_iterations
    if cfg.solver_tolerance is not None:
        mj.opt.tolerance = cfg.solver_tolerance
    robot.validate_model(mj, source="simulation model")
    return mj
