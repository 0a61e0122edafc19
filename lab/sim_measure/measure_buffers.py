"""Measure mujoco-warp's contact and constraint buffer usage for TOCABI (the numbers behind ``sim.buffers``).

``python -m lab.sim_measure.measure_buffers [--device cuda] [--num-worlds 16] [--steps 300]`` steps the robot through
standing, falling, thrashing and tangled scenarios, reads the counters after every physics substep and writes
``docs/benchmarks/sim_buffers.{json,md}``.
"""

from __future__ import annotations

import argparse
import json
import math
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from tocabi_torchrl.sim.buffers import NCCDMAX, NCONMAX, NJMAX

__all__ = ["SCENARIOS", "BufferUsage", "ConvexCandidates", "measure", "main"]

#: Scenario name -> what the worlds do (see ``_scenario_state`` / ``_scenario_ctrl``).
SCENARIOS = {
    "standing": "initial pose, legs PD-held on it",
    "limp": "initial pose, zero leg torque: the robot collapses",
    "random_torque": "initial pose, uniform random leg torques in the limits every policy step",
    "drop_back": "dropped on its back from 0.35-0.6 m, random leg torques",
    "drop_front": "dropped on its front from 0.35-0.6 m, random leg torques",
    "drop_side": "dropped on its side from 0.35-0.6 m, random leg torques",
    "tangled": "random joint angles (sd 0.6 rad) and tilt, random leg torques: many self contacts",
}


@dataclass
class BufferUsage:
    """Peaks over all worlds and substeps of one scenario."""

    scenario: str
    num_worlds: int
    substeps: int
    contacts_per_world_max: int
    contacts_per_world_p999: float
    contacts_pool_per_world_max: float  # nacon / num_worlds: what the pooled nconmax must hold
    broadphase_pairs_per_world_max: float  # ncollision / num_worlds
    nefc_max: int
    nefc_p999: float
    ccd_pairs_per_world_max: int  # convex-narrowphase candidates of one geom-type pair in one world
    ccd_pool_per_world_max: float  # the same over all worlds / num_worlds: what the pooled nccdmax must hold


def _quat(axis, angle: float) -> np.ndarray:
    axis = np.asarray(axis, dtype=float) / np.linalg.norm(axis)
    return np.concatenate(([math.cos(angle / 2)], math.sin(angle / 2) * axis))


def _scenario_state(name: str, n: int, rng: np.random.Generator) -> np.ndarray:
    from tocabi_torchrl import robot

    qpos = np.tile(robot.INIT_QPOS, (n, 1))
    if name.startswith("drop_"):
        axis, angle = {"drop_back": ((0, 1, 0), -math.pi / 2), "drop_front": ((0, 1, 0), math.pi / 2)}.get(
            name, ((1, 0, 0), math.pi / 2)
        )
        for w in range(n):
            qpos[w, 3:7] = _quat(axis, angle + rng.normal(0, 0.2))
            qpos[w, 2] = rng.uniform(0.35, 0.6)
    elif name == "tangled":
        qpos[:, 7:] += rng.normal(0, 0.6, (n, robot.NUM_JOINTS))
        for w in range(n):
            qpos[w, 3:7] = _quat(rng.normal(size=3), rng.uniform(-1.2, 1.2))
            qpos[w, 2] = 0.7
    return qpos


def _scenario_ctrl(name: str, qpos: np.ndarray, qvel: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    from tocabi_torchrl import robot

    n = qpos.shape[0]
    ctrl = np.zeros((n, robot.NUM_JOINTS))
    ctrl[:, robot.NUM_LEG_JOINTS :] = robot.INIT_JOINT_POS[robot.NUM_LEG_JOINTS :]
    legs = slice(0, robot.NUM_LEG_JOINTS)
    if name == "standing":
        err = robot.INIT_JOINT_POS[legs] - qpos[:, 7:19]
        ctrl[:, legs] = robot.LEG_KP * err - robot.LEG_KV * qvel[:, 6:18]
    elif name != "limp":
        ctrl[:, legs] = rng.uniform(-1, 1, (n, robot.NUM_LEG_JOINTS)) * robot.LEG_TORQUE_LIMITS
    return ctrl


#: Geom-type pairs of TOCABI's collision geoms that mujoco-warp 4.0 sends through its convex (GJK/EPA) narrowphase:
#: boxes and cylinders among themselves (box-box through its native CCD, the default); the ground plane's pairs are
#: primitive.
CONVEX_TYPES = ("mjGEOM_BOX", "mjGEOM_CYLINDER")


class ConvexCandidates:
    """Counts the convex narrowphase's candidate pairs as mujoco-warp's broadphase passes them (its sphere and OBB
    filters, ``opt.broadphase_filter`` of TOCABI's model), per world and geom-type pair, from the geom poses a
    substep's collision used (``geom_xpos``/``geom_xmat`` after ``mujoco_warp.step``, which integrates ``qpos``
    only). mujoco-warp counts each type pair against ``naccdmax`` separately, so the peak over the type pairs is the
    need."""

    def __init__(self, mj, pairs: np.ndarray):
        import mujoco

        types, convex_types = mj.geom_type, [int(getattr(mujoco.mjtGeom, name)) for name in CONVEX_TYPES]
        convex = np.isin(types[pairs[:, 0]], convex_types) & np.isin(types[pairs[:, 1]], convex_types)
        self.pairs = pairs[convex]
        g1, g2 = self.pairs[:, 0], self.pairs[:, 1]
        margin = mj.geom_margin + mj.geom_gap
        self.margin = margin[g1] + margin[g2]
        self.bound = mj.geom_rbound[g1] + mj.geom_rbound[g2] + self.margin
        aabb = mj.geom_aabb.reshape(-1, 6)
        self.center, self.size = (aabb[g1, :3], aabb[g2, :3]), (aabb[g1, 3:], aabb[g2, 3:])
        kinds = np.sort(np.stack([types[g1], types[g2]], 1), 1)
        self.kinds = [kinds[:, 0] * 100 + kinds[:, 1] == k for k in np.unique(kinds[:, 0] * 100 + kinds[:, 1])]

    def count(self, xpos: np.ndarray, xmat: np.ndarray) -> np.ndarray:
        """(num_worlds, type pairs) candidates, from ``xpos`` (N, ngeom, 3) and ``xmat`` (N, ngeom, 3, 3)."""
        g1, g2 = self.pairs[:, 0], self.pairs[:, 1]
        dif = xpos[:, g2] - xpos[:, g1]
        passed = (dif * dif).sum(-1) <= self.bound**2
        rot = (xmat[:, g1], xmat[:, g2])
        centers = [np.einsum("wpij,pj->wpi", rot[i], self.center[i]) + xpos[:, (g1, g2)[i]] for i in range(2)]
        for axis in (*(rot[0][..., k] for k in range(3)), *(rot[1][..., k] for k in range(3))):  # face normals
            gap = np.abs(((centers[1] - centers[0]) * axis).sum(-1))
            radius = sum(np.abs(np.einsum("wpij,wpi->wpj", rot[i], axis) * self.size[i]).sum(-1) for i in range(2))
            passed &= radius + self.margin >= gap
        return np.stack([passed[:, kind].sum(1) for kind in self.kinds], 1)


def measure(
    scenario: str, num_worlds: int = 16, steps: int = 300, seed: int = 0, device: str = "cpu"
) -> BufferUsage:
    """Step ``num_worlds`` TOCABIs through ``scenario`` for ``steps`` policy steps and record buffer peaks.

    Uses buffers far above the defaults so nothing overflows, and reads the counters after every substep.
    """
    # Checked before the (slow) imports and the model build.
    if scenario not in SCENARIOS:
        raise ValueError(f"unknown scenario {scenario!r}; choose from {sorted(SCENARIOS)}")
    if num_worlds < 1 or steps < 1:  # no world or no step measures nothing: the peaks below would be of nothing
        raise ValueError(f"num_worlds and steps must be at least 1, got num_worlds={num_worlds}, steps={steps}")

    import mujoco_warp as mjw
    import torch
    import warp as wp

    from tocabi_torchrl.sim.config import SimConfig
    from tocabi_torchrl.sim.graph import Recorded
    from tocabi_torchrl.sim.warp_backend import WarpSim

    cfg = SimConfig(num_worlds=num_worlds, device=device, nconmax=160, njmax=400)
    sim = WarpSim(cfg)
    rng = np.random.default_rng(seed)
    dev = sim.device
    mask = torch.ones(num_worlds, dtype=torch.bool, device=dev)
    qpos0 = torch.as_tensor(_scenario_state(scenario, num_worlds, rng), dtype=torch.float32, device=dev)
    sim.reset(mask, qpos0, torch.zeros(sim.nv, device=dev))
    m, d = sim.wp_model, sim.wp_data
    substep = Recorded(lambda: mjw.step(m, d), sim.wp_device, cfg.use_graph)

    per_world, pool, pairs, nefc, ccd_world, ccd_pool = [], [], [], [], [], []
    convex = ConvexCandidates(sim.mj_model, m.nxn_geom_pair_filtered.numpy())
    for _ in range(steps):
        q, v = sim.qpos.cpu().numpy(), sim.qvel.cpu().numpy()
        sim.ctrl.copy_(torch.as_tensor(_scenario_ctrl(scenario, q, v, rng), dtype=torch.float32, device=dev))
        for _ in range(cfg.substeps):
            substep()
            wp.synchronize_device(sim.wp_device)
            nacon = int(d.nacon.numpy()[0])
            worlds = d.contact.worldid.numpy()[: min(nacon, d.naconmax)]
            per_world.append(np.bincount(worlds, minlength=num_worlds).max() if nacon else 0)
            pool.append(nacon / num_worlds)
            pairs.append(int(d.ncollision.numpy()[0]) / num_worlds)
            nefc.append(int(d.nefc.numpy().max()))
            ccd = convex.count(d.geom_xpos.numpy(), d.geom_xmat.numpy().reshape(num_worlds, -1, 3, 3))
            ccd_world.append(int(ccd.max()))
            ccd_pool.append(float(ccd.sum(0).max()) / num_worlds)
    return BufferUsage(
        scenario=scenario,
        num_worlds=num_worlds,
        substeps=len(nefc),
        contacts_per_world_max=int(max(per_world)),
        contacts_per_world_p999=float(np.percentile(per_world, 99.9)),
        contacts_pool_per_world_max=float(max(pool)),
        broadphase_pairs_per_world_max=float(max(pairs)),
        nefc_max=int(max(nefc)),
        nefc_p999=float(np.percentile(nefc, 99.9)),
        ccd_pairs_per_world_max=int(max(ccd_world)),
        ccd_pool_per_world_max=float(max(ccd_pool)),
    )


def _markdown(rows: list[BufferUsage]) -> str:
    """The benchmark page for ``rows`` (one or more measured scenarios)."""
    if not rows:
        raise ValueError("no scenarios to tabulate: measure at least one (--scenarios NAME ...)")
    head = (
        "| scenario | what | contacts in one world, max | p99.9 | contact pool / worlds, max "
        "| broadphase pairs / worlds, max | nefc max | p99.9 | convex pairs in one world, max "
        "| convex pairs / worlds, max |\n"
        "|---|---|---|---|---|---|---|---|---|---|\n"
    )
    body = "".join(
        f"| {r.scenario} | {SCENARIOS[r.scenario]} | {r.contacts_per_world_max} | {r.contacts_per_world_p999:.0f} | "
        f"{r.contacts_pool_per_world_max:.1f} | {r.broadphase_pairs_per_world_max:.1f} | {r.nefc_max} | "
        f"{r.nefc_p999:.0f} | {r.ccd_pairs_per_world_max} | {r.ccd_pool_per_world_max:.1f} |\n"
        for r in rows
    )
    worst_c = max(r.contacts_per_world_max for r in rows)
    worst_j = max(r.nefc_max for r in rows)
    worst_p = max(r.broadphase_pairs_per_world_max for r in rows)
    worst_ccd, worst_ccd_pool = (max(r.ccd_pairs_per_world_max for r in rows),
                                 max(r.ccd_pool_per_world_max for r in rows))
    return (
        "# Contact and constraint buffers for TOCABI (mujoco-warp)\n\n"
        "Generated by `python -m lab.sim_measure.measure_buffers`; counters read after every physics substep "
        f"({rows[0].num_worlds} worlds per scenario, {rows[0].substeps} substeps each).\n\n"
        + head
        + body
        + f"\nChosen: `nconmax = {NCONMAX}` per world (pooled; worst measured {worst_c} contacts in one world and "
        f"{worst_p:.0f} broadphase pairs per world on average), `njmax = {NJMAX}` rows per world (worst measured "
        f"{worst_j}), `nccdmax = {NCCDMAX}` convex-collision pairs per world (pooled, per pair of geom types; worst "
        f"measured {worst_ccd_pool:.1f} per world on average and {worst_ccd} in one world). "
        "Convex pairs are the box and cylinder pairs the broadphase's sphere and OBB filters pass, each slot of "
        "mujoco-warp's EPA scratch ~5 KB. "
        "A scene with more geometry (obstacles, terrain) needs larger values: an overflow marks the world unhealthy "
        "and `WarpSim.check_overflow()` names the setting to raise.\n\n"
        "mujoco-warp generates more contacts than C MuJoCo for the same kind of scene (C MuJoCo peaked at 26 contacts "
        "and 111 rows over similar falls), so the sizes are measured in mujoco-warp itself. Scenarios past the first "
        "forbidden contact (lying, thrashing, tangled) are worst cases: the walking task terminates such worlds.\n"
    )


def _load_rows(path: Path) -> list[BufferUsage]:
    """The rows of a previous run's ``sim_buffers.json``; raises ``ValueError`` saying what the file lacks."""
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError) as err:
        raise ValueError(f"cannot read {path} as JSON ({err})") from err
    if not isinstance(data, list) or not data or not all(isinstance(r, dict) for r in data):
        raise ValueError(f"{path} holds no measured scenarios; expected a non-empty list of rows from a previous run")
    try:
        rows = [BufferUsage(**r) for r in data]
    except TypeError as err:  # missing or unexpected fields
        raise ValueError(f"{path} is not a sim_buffers.json of this version ({err})") from err
    unknown = sorted({r.scenario for r in rows} - set(SCENARIOS))
    if unknown:
        raise ValueError(f"{path} names unknown scenarios {unknown}; known: {list(SCENARIOS)}")
    return rows


def _count(text: str) -> int:
    """argparse type of the counts (worlds, steps): an integer of at least 1, since none measures nothing."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer >= 1, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, got {value}")
    return value


def _write(out: Path, files: dict[str, str]) -> None:
    """Write ``files`` (name -> text) into the folder ``out``, creating it."""
    out.mkdir(parents=True, exist_ok=True)
    for name, text in files.items():
        (out / name).write_text(text)


def main(argv: list[str] | None = None) -> None:
    """CLI: measure the scenarios and write ``sim_buffers.{json,md}``, or re-render the markdown ``--from-json``."""
    p = argparse.ArgumentParser(prog="python -m lab.sim_measure.measure_buffers",
                                description=__doc__.splitlines()[0])
    p.add_argument("--num-worlds", type=_count, default=16, help="robots (worlds) per scenario (default: 16)")
    p.add_argument("--steps", type=_count, default=300, help="policy steps per scenario")
    p.add_argument("--device", default="cpu", help="device mujoco-warp runs on: cpu or cuda (default: cpu)")
    # choices + nargs="+": a misspelt or missing name is refused before minutes of measuring, not at its turn.
    p.add_argument("--scenarios", nargs="+", choices=list(SCENARIOS), default=list(SCENARIOS), metavar="NAME",
                   help=f"scenarios to measure (default: all of {', '.join(SCENARIOS)})")
    p.add_argument("--out", type=Path, default=Path("docs/benchmarks"), help="folder for sim_buffers.{json,md}")
    p.add_argument("--from-json", type=Path, help="re-render the markdown from a previous run's JSON")
    args = p.parse_args(argv)
    if args.out.exists() and not args.out.is_dir():
        p.error(f"--out {args.out} is not a folder; pass the folder to write sim_buffers.json and .md into")
    if args.from_json:
        try:
            markdown = _markdown(_load_rows(args.from_json))
        except ValueError as err:
            p.error(f"--from-json: {err}")
        _write(args.out, {"sim_buffers.md": markdown})
        print(f"wrote {args.out / 'sim_buffers.md'}")
        return
    rows = []
    for i, name in enumerate(args.scenarios):
        rows.append(measure(name, args.num_worlds, args.steps, seed=i, device=args.device))
        print(rows[-1], flush=True)
    # Both texts are made before either file is written: a failure leaves the previous pair as it was.
    json_text = json.dumps([asdict(r) for r in rows], indent=2) + "\n"
    markdown = _markdown(rows)
    _write(args.out, {"sim_buffers.json": json_text, "sim_buffers.md": markdown})
    print(f"wrote {args.out / 'sim_buffers.md'}")


if __name__ == "__main__":
    main()
