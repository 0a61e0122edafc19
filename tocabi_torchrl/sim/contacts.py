"""Contact signals from MuJoCo contact sensors: foot-ground, forbidden ground contact, self collision.

MuJoCo's contact sensor (``mjSENS_CONTACT`` with ``data="found"``) counts the contacts whose two geoms match two
criteria (a geom, a body, or a body's subtree). MuJoCo evaluates it inside the physics step (mujoco-warp on the
device, for every world at once), so no Python code ever scans the global contact list. Counts add and subtract like
sets, so the signals of spec §9.1 are signed sums of counts:

* foot contact (per foot): ``found(world body, Foot_Link)``;
* forbidden ground contact: ``found(world body, subtree(base))`` minus ``found(world body, subtree(a))`` for every
  subtree ``a`` of allowed bodies (the ankle/foot chains and the neck/head);
* self collision: ``found(subtree(base), subtree(base))`` (every robot-robot contact, counted once) minus the contacts
  that involve a body outside ``robot.SELF_COLLISION_BODIES`` (the neck subtree), with inclusion-exclusion for
  contacts between two such subtrees.

"Ground" is every geom attached to the world body (spec §9.1: "the world body (id 0)"), and also every body of the
scene outside the robot: each subtree that hangs from the world body beside the robot's (obstacles, see
``envs.obstacles``). Each such *scene root* gets the same three ground sensors (per foot, whole robot) and the allowed
subtrees' ones, and the signals add its counts to the world body's, so a foot on an obstacle is foot contact and a
forbidden body on it is forbidden ground contact. A model with scene roots has two more signal rows,
``SCENE_SIGNAL_NAMES``: a foot touches a scene body (the env's ``obstacle_contact``). A model without them gets exactly
the sensors and rows it had before scene roots were counted. The allowed subtrees are not written by hand: they are
derived from ``robot.GROUND_FORBIDDEN_BODIES`` / ``robot.SELF_COLLISION_BODIES`` and the model's body tree, so the two
lists stay the single source of truth.

``found`` counts every matching contact, also beyond ``Option.contact_sensor_maxmatch`` (that limit only bounds the
per-contact slots, which these sensors do not use), so the sums are exact.
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np
import torch

from .. import robot

__all__ = [
    "CONTACT_SENSOR_PREFIX",
    "SIGNAL_NAMES",
    "SCENE_SIGNAL_NAMES",
    "ContactLayout",
    "ContactSensorError",
    "add_contact_sensors",
    "contact_layout",
    "has_contact_sensors",
    "scene_roots",
]

#: Every sensor added here is named ``CONTACT_SENSOR_PREFIX + ...``; the layout is recovered from these names.
CONTACT_SENSOR_PREFIX = "tocabi_contact/"
#: Rows of the signal matrix: ``foot_contact`` (left, right), ``forbidden_ground_contact``, ``self_collision``.
SIGNAL_NAMES = ("foot_ground_left", "foot_ground_right", "forbidden_ground", "self_collision")
#: The two rows a model with scene roots (obstacles) adds after ``SIGNAL_NAMES``: a foot touches a scene body.
SCENE_SIGNAL_NAMES = ("foot_scene_left", "foot_scene_right")

_WORLD = "world"
_FOUND = 1 << int(mujoco.mjtConDataField.mjCONDATA_FOUND)


class ContactSensorError(ValueError):
    """The model lacks the contact sensors, or its body tree does not fit the contact lists of ``robot``."""


@dataclass(frozen=True)
class _Criterion:
    kind: str  # "body" (the body's own geoms) or "subtree" (the body and all its descendants)
    name: str

    @property
    def objtype(self) -> mujoco.mjtObj:
        return mujoco.mjtObj.mjOBJ_BODY if self.kind == "body" else mujoco.mjtObj.mjOBJ_XBODY


@dataclass(frozen=True)
class _Sensor:
    name: str
    obj: _Criterion
    ref: _Criterion


@dataclass(frozen=True)
class ContactLayout:
    """Where the contact counts live in ``sensordata`` and how signals combine them.

    Attributes:
        names: sensor names, in sensordata order (``count`` of them).
        adr: (count,) int, sensordata column of each sensor's ``found`` value.
        weights: (rows, count) float; signal ``k`` of a world is ``weights[k] @ found > 0.5`` (rows:
            :attr:`signal_names`: ``SIGNAL_NAMES``, then ``SCENE_SIGNAL_NAMES`` in a model with scene roots).
    """

    names: tuple[str, ...]
    adr: np.ndarray
    weights: np.ndarray

    @property
    def count(self) -> int:
        return len(self.names)

    @property
    def signal_names(self) -> tuple[str, ...]:
        """Names of the weight rows (4, or 6 with scene roots)."""
        return (SIGNAL_NAMES + SCENE_SIGNAL_NAMES)[: len(self.weights)]

    def signals(self, sensordata: torch.Tensor) -> torch.Tensor:
        """(N, rows) bool signals (rows of :attr:`signal_names`) from (N, nsensordata) sensor values, in torch.

        The same sums as mujoco-warp's ``kernels.derive_signals``; counts are small integers, exact in float32.
        """
        found = sensordata[:, torch.as_tensor(self.adr, dtype=torch.int64, device=sensordata.device)]
        weights = torch.as_tensor(self.weights, dtype=sensordata.dtype, device=sensordata.device)
        return found @ weights.T > 0.5

    def describe(self) -> str:
        """One line per signal, e.g. ``self_collision = +self/all - self/neck_Link``."""
        lines = []
        for k, sig in enumerate(self.signal_names):
            terms = [
                f"{'+' if w > 0 else '-'}{'' if abs(w) == 1 else abs(w)}{n.removeprefix(CONTACT_SENSOR_PREFIX)}"
                for w, n in zip(self.weights[k], self.names)
                if w != 0
            ]
            lines.append(f"{sig} = {' '.join(terms)} > 0")
        return "\n".join(lines)


def _tree_of_spec(spec: mujoco.MjSpec) -> dict[str, str | None]:
    """Body name -> parent name (``None`` for the world body) of a spec."""
    tree: dict[str, str | None] = {_WORLD: None}
    for body in spec.bodies:
        if body.name != _WORLD:
            tree[body.name] = body.parent.name if body.parent is not None else _WORLD
    return tree


def _tree_of_model(model: mujoco.MjModel) -> dict[str, str | None]:
    """Body name -> parent name (``None`` for the world body) of a compiled model."""
    names = [mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_BODY, b) or _WORLD for b in range(model.nbody)]
    return {names[b]: (None if b == 0 else names[model.body_parentid[b]]) for b in range(model.nbody)}


def _subtree(tree: dict[str, str | None], root: str) -> set[str]:
    out = {root}
    changed = True
    while changed:
        changed = False
        for child, parent in tree.items():
            if parent in out and child not in out:
                out.add(child)
                changed = True
    return out


def _excluded_subtrees(tree: dict[str, str | None], robot_bodies: set[str], included: set[str]) -> list[str]:
    """Roots of the subtrees that together hold exactly the robot bodies outside ``included``.

    Raises if an included body hangs below an excluded one (a subtree criterion could not separate them).
    """
    excluded = robot_bodies - included
    roots = sorted(b for b in excluded if tree[b] not in excluded)
    for root in roots:
        stray = _subtree(tree, root) & included
        if stray:
            raise ContactSensorError(
                f"body {root!r} is excluded from a contact list but its descendants {sorted(stray)} are included; "
                "subtree contact sensors cannot express that split (adjust the lists in tocabi_torchrl/robot.py)"
            )
    return roots


def scene_roots(tree: dict[str, str | None]) -> list[str]:
    """The bodies hanging from the world body whose subtrees do not hold the robot (obstacles), sorted by name."""
    return sorted(b for b, parent in tree.items()
                  if parent == _WORLD and robot.BASE_BODY not in _subtree(tree, b))


def _plan(tree: dict[str, str | None]) -> tuple[list[_Sensor], np.ndarray]:
    """The sensors to add and the (rows, count) signal weights, derived from ``robot``'s body lists and the body
    tree."""
    missing = [b for b in (robot.BASE_BODY,) + robot.FOOT_BODIES + robot.SELF_COLLISION_BODIES if b not in tree]
    if missing:
        raise ContactSensorError(f"the model lacks robot bodies {missing} needed for the contact sensors")
    robot_bodies = _subtree(tree, robot.BASE_BODY)
    stray = (set(robot.SELF_COLLISION_BODIES) | set(robot.GROUND_FORBIDDEN_BODIES)) - robot_bodies
    if stray:
        raise ContactSensorError(f"bodies {sorted(stray)} are not below {robot.BASE_BODY!r}")

    ground = _Criterion("body", _WORLD)
    whole = _Criterion("subtree", robot.BASE_BODY)
    p = CONTACT_SENSOR_PREFIX
    sensors = [
        _Sensor(f"{p}ground/foot_left", ground, _Criterion("body", robot.FOOT_BODIES[0])),
        _Sensor(f"{p}ground/foot_right", ground, _Criterion("body", robot.FOOT_BODIES[1])),
        _Sensor(f"{p}ground/all", ground, whole),
        _Sensor(f"{p}self/all", whole, whole),
    ]
    scene = scene_roots(tree)
    rows: list[dict[str, float]] = [
        {sensors[0].name: 1.0},
        {sensors[1].name: 1.0},
        {sensors[2].name: 1.0},
        {sensors[3].name: 1.0},
    ] + [{} for _ in SCENE_SIGNAL_NAMES if scene]
    allowed = _excluded_subtrees(tree, robot_bodies, set(robot.GROUND_FORBIDDEN_BODIES))
    for root in allowed:
        s = _Sensor(f"{p}ground/{root}", ground, _Criterion("subtree", root))
        sensors.append(s)
        rows[2][s.name] = -1.0
    self_roots = _excluded_subtrees(tree, robot_bodies, set(robot.SELF_COLLISION_BODIES))
    for root in self_roots:
        # Contacts between this excluded subtree and any robot geom, each counted once.
        s = _Sensor(f"{p}self/{root}", _Criterion("subtree", root), whole)
        sensors.append(s)
        rows[3][s.name] = -1.0
    for i, a in enumerate(self_roots):
        for b in self_roots[i + 1 :]:
            # A contact between two excluded subtrees was subtracted twice above: add it back once.
            s = _Sensor(f"{p}self/{a}+{b}", _Criterion("subtree", a), _Criterion("subtree", b))
            sensors.append(s)
            rows[3][s.name] = 1.0
    for body in scene:
        # The same ground sums over this scene body's subtree; its foot counts also feed the scene rows.
        where = _Criterion("subtree", body)
        feet = [_Sensor(f"{p}scene:{body}/foot_{side}", where, _Criterion("body", foot))
                for side, foot in zip(("left", "right"), robot.FOOT_BODIES)]
        sensors += feet
        for k, s in enumerate(feet):
            rows[k][s.name] = 1.0
            rows[len(SIGNAL_NAMES) + k][s.name] = 1.0
        s = _Sensor(f"{p}scene:{body}/all", where, whole)
        sensors.append(s)
        rows[2][s.name] = 1.0
        for root in allowed:
            s = _Sensor(f"{p}scene:{body}/{root}", where, _Criterion("subtree", root))
            sensors.append(s)
            rows[2][s.name] = -1.0
    weights = np.array([[row.get(s.name, 0.0) for s in sensors] for row in rows])
    return sensors, weights


def has_contact_sensors(model_or_spec: mujoco.MjModel | mujoco.MjSpec) -> bool:
    """Whether ``add_contact_sensors`` was already applied (checks the first sensor's name)."""
    first = f"{CONTACT_SENSOR_PREFIX}ground/foot_left"
    if isinstance(model_or_spec, mujoco.MjSpec):
        return model_or_spec.sensor(first) is not None
    return mujoco.mj_name2id(model_or_spec, mujoco.mjtObj.mjOBJ_SENSOR, first) >= 0


def add_contact_sensors(spec: mujoco.MjSpec) -> mujoco.MjSpec:
    """Add the contact-count sensors (``data="found"``) to ``spec`` in place and return it.

    Idempotent: a spec that already has them is returned unchanged. The sensors are position-stage sensors (found
    needs no forces), so they cost one matching pass over the contacts per evaluation.
    """
    if has_contact_sensors(spec):
        return spec
    sensors, _ = _plan(_tree_of_spec(spec))
    for s in sensors:
        spec.add_sensor(
            name=s.name,
            type=mujoco.mjtSensor.mjSENS_CONTACT,
            objtype=s.obj.objtype,
            objname=s.obj.name,
            reftype=s.ref.objtype,
            refname=s.ref.name,
            intprm=[_FOUND, 0, 1],  # dataspec = found only, reduce = none, num = 1 slot
        )
    return spec


def contact_layout(model: mujoco.MjModel) -> ContactLayout:
    """Recover the sensordata addresses and signal weights of the contact sensors of a compiled model."""
    if not has_contact_sensors(model):
        raise ContactSensorError(
            "the model has no TOCABI contact sensors; build it from a spec with "
            "tocabi_torchrl.sim.contacts.add_contact_sensors(spec) before compiling (or pass the spec or the MJCF "
            "path to WarpSim, which adds them)"
        )
    sensors, weights = _plan(_tree_of_model(model))
    adr = []
    for s in sensors:
        sid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SENSOR, s.name)
        if sid < 0:
            raise ContactSensorError(
                f"contact sensor {s.name!r} is missing: the model's contact sensors were built for other body lists; "
                "rebuild it with add_contact_sensors"
            )
        if model.sensor_type[sid] != mujoco.mjtSensor.mjSENS_CONTACT or model.sensor_dim[sid] != 1:
            raise ContactSensorError(f"sensor {s.name!r} is not a one-value contact sensor (data='found', num=1)")
        adr.append(int(model.sensor_adr[sid]))
    return ContactLayout(names=tuple(s.name for s in sensors), adr=np.array(adr, dtype=np.int32), weights=weights)
