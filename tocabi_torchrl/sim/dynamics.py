"""Per-world dynamics randomisation: each world's link masses, joint damping, armature and contact friction, drawn
again at every reset.

==================== ==================================== ========== ==============================================
field                distribution                         unit       per what
==================== ==================================== ========== ==============================================
``mass_scale``       mass and inertia tensor × s,         1          world and body (every body but the world body
                     s ~ U(low, high)                                and mocap bodies): the density changes
``joint_damping``    damping + d, d ~ U(low, high)        N·m·s/rad  world and joint dof (the 33 hinge dofs of the
                                                                     legs and upper body; not the free joint)
``armature_scale``   armature × a, a ~ U(low, high)       1          world and joint dof (as ``joint_damping``)
``friction_scale``   sliding friction of every geom × f,  1          world: every contact's sliding friction, the
                     f ~ U(low, high)                                ground's included, is the model's × f
==================== ==================================== ========== ==============================================

The defaults are the identity (``(1, 1)``, ``(0, 0)``): nothing is drawn, no model field becomes per-world and the
physics is exactly the model's.

Friction is a scale rather than an absolute coefficient so that it keeps the model's ratios (a contact's sliding
friction is the larger of its two geoms', so scaling every geom by f scales every contact by f) and ``(1, 1)`` is
off. The shipped TOCABI's geoms all have sliding friction 1, so on it the scale is also the absolute coefficient:
MuJoCo Playground's floor friction U(0.4, 1.0) is ``friction_scale=(0.4, 1.0)``. The torsional and rolling
coefficients are left alone.

How it reaches the physics: the simulator is built with ``SimConfig.per_world_fields`` = :attr:`~DynamicsRandomization
.sim_fields` (the fields a configured range needs), which gives those model fields one row per world (mujoco-warp
declares them batched: its kernels read row ``worldid % rows``; the C MuJoCo backend gives each world its own
``MjModel``). :meth:`WorldDynamics.reset` writes the flagged worlds' rows of the simulator's ``model_fields`` in place,
with masks only (no host sync, no re-recorded graph), before the reset's forward pass reads them.

Derived model quantities:

- ``body_subtreemass`` (the mass of each body's subtree, which ``subtree_com`` divides by) is recomputed per world
  from the drawn masses whenever the masses change.
- ``dof_invweight0`` / ``body_invweight0`` (the inverse inertia at ``qpos0`` that scales each constraint's
  regularisation R) stay the nominal model's on both backends, so the two agree: recomputing them per world needs
  a solve with M per dof and body (``mujoco_warp.set_const``: hundreds of launches per reset). A world with masses
  × s then has its constraints regularised as if it had the nominal ones: R relative to its true inverse inertia
  is about × s, so a heavier world's contacts are slightly softer and a lighter one's slightly stiffer (a
  second-order change of the contact's give; the forces still carry the drawn weight, as the tests check).
  ``actuator_acc0``, the other inertia constant, is read by muscle actuators only, which TOCABI has none of.
"""

from __future__ import annotations

import mujoco
import torch

# The config lives in a module without torch and MuJoCo, for the config tree; this path names it too.
from .dynamics_config import DynamicsRandomization

__all__ = ["DynamicsRandomization", "WorldDynamics"]


class WorldDynamics:
    """The per-world draw of a :class:`DynamicsRandomization`, in the shape of an actuator stage
    (``tocabi_torchrl.control.actuators``): :meth:`setup` once, then :meth:`reset` with :attr:`draws` uniforms per
    world at every reset.

    Parameters, (N, ...) float32 tensors on the simulator's device, updated in place (never rebound):
    :attr:`mass_scale` (N, nbody) (1 for the world and mocap bodies), :attr:`joint_damping` (N, J) [N·m·s/rad] added,
    :attr:`armature_scale` (N, J), :attr:`friction_scale` (N,), with J the joint dofs (:attr:`dofs`). A range that is
    off keeps its identity and writes nothing.

    Uniform lanes: ``u[:, :B]`` the B randomised bodies' masses (:attr:`bodies`), then J damping, J armature and one
    friction lane, whichever ranges are on, so turning one range on leaves the others' draws as they were.
    """

    def __init__(self, config: DynamicsRandomization):
        config.validate()
        self.config = config
        self.draws = 0

    def setup(self, sim) -> None:
        """Take the simulator's per-world model fields (``sim.model_fields``) and allocate the parameters for its
        ``num_worlds`` worlds. Raises ``ValueError`` when the simulator lacks a field a configured range writes."""
        cfg, mj, n = self.config, sim.mj_model, sim.num_worlds
        fields = getattr(sim, "model_fields", {})
        missing = [f for f in cfg.sim_fields if f not in fields]
        if missing:
            raise ValueError(f"the simulator has no per-world {missing}: build it with SimConfig(per_world_fields="
                             f"{cfg.sim_fields!r}) (DynamicsRandomization.sim_fields) so each world has its own rows")
        self.fields = {name: fields[name] for name in cfg.sim_fields}
        dev, f32 = sim.device, torch.float32
        #: Body ids whose mass is drawn: every body but the world body and the (immovable) mocap bodies.
        self.bodies = [b for b in range(1, mj.nbody) if mj.body_mocapid[b] < 0]
        #: Dof ids of the joints (hinges and slides): every dof but the free joint's.
        self.dofs = [d for d in range(mj.nv) if mj.jnt_type[mj.dof_jntid[d]] != mujoco.mjtJoint.mjJNT_FREE]
        nb, nd = len(self.bodies), len(self.dofs)
        self.draws = nb + 2 * nd + 1
        self._bodies_t = torch.tensor(self.bodies, dtype=torch.int64, device=dev)
        self._dofs_t = torch.tensor(self.dofs, dtype=torch.int64, device=dev)
        self.mass_scale = torch.ones(n, mj.nbody, dtype=f32, device=dev)
        self.joint_damping = torch.zeros(n, nd, dtype=f32, device=dev)
        self.armature_scale = torch.ones(n, nd, dtype=f32, device=dev)
        self.friction_scale = torch.ones(n, dtype=f32, device=dev)
        # The model's values, in each field's dtype (float32 on mujoco-warp, float64 on C MuJoCo).
        self._nominal = {name: torch.as_tensor(getattr(mj, name), device=dev).to(t.dtype)
                         for name, t in self.fields.items()}
        if cfg.on("mass_scale"):
            # subtree[j, b] = 1 where body b is body j or one of its ancestors: subtreemass = mass @ subtree.
            subtree = torch.zeros(mj.nbody, mj.nbody, dtype=torch.float64)
            for j in range(mj.nbody):
                b = j
                while True:
                    subtree[j, b] = 1.0
                    if b == 0:
                        break
                    b = int(mj.body_parentid[b])
            self._subtree = subtree.to(dev)

    def _where(self, mask: torch.Tensor, name: str, new: torch.Tensor) -> None:
        field = self.fields[name]
        flag = mask.view(-1, *([1] * (field.dim() - 1)))
        torch.where(flag, new.to(field.dtype), field, out=field)

    def reset(self, mask: torch.Tensor, u: torch.Tensor) -> None:
        """Redraw the parameters of the worlds flagged in ``mask`` (N,) bool from ``u`` (N, :attr:`draws`) uniforms in
        [0, 1) and write their rows of the simulator's model fields, in place; the other worlds' rows are untouched
        (``torch.where``, so no host sync)."""
        cfg, nb, nd = self.config, len(self.bodies), len(self.dofs)
        m = mask.unsqueeze(-1)
        if cfg.on("mass_scale"):
            lo, hi = (float(v) for v in cfg.mass_scale)
            drawn = self.mass_scale.index_copy(1, self._bodies_t, lo + (hi - lo) * u[:, :nb])
            torch.where(m, drawn, self.mass_scale, out=self.mass_scale)
            dtype = self.fields["body_mass"].dtype
            mass = self._nominal["body_mass"] * self.mass_scale.to(dtype)
            self._where(mask, "body_mass", mass)
            self._where(mask, "body_inertia", self._nominal["body_inertia"] * self.mass_scale.to(dtype).unsqueeze(-1))
            # float64 matmul: exact sums of at most nbody terms, and never TF32 on a GPU.
            self._where(mask, "body_subtreemass", mass.to(torch.float64) @ self._subtree)
        if cfg.on("joint_damping"):
            lo, hi = (float(v) for v in cfg.joint_damping)
            torch.where(m, lo + (hi - lo) * u[:, nb:nb + nd], self.joint_damping, out=self.joint_damping)
            nominal = self._nominal["dof_damping"]
            added = nominal.new_zeros(mask.shape[0], nominal.shape[0]).index_copy_(
                1, self._dofs_t, self.joint_damping.to(nominal.dtype))
            self._where(mask, "dof_damping", nominal + added)
        if cfg.on("armature_scale"):
            lo, hi = (float(v) for v in cfg.armature_scale)
            torch.where(m, lo + (hi - lo) * u[:, nb + nd:nb + 2 * nd], self.armature_scale, out=self.armature_scale)
            nominal = self._nominal["dof_armature"]
            scale = nominal.new_ones(mask.shape[0], nominal.shape[0]).index_copy_(
                1, self._dofs_t, self.armature_scale.to(nominal.dtype))
            self._where(mask, "dof_armature", nominal * scale)
        if cfg.on("friction_scale"):
            lo, hi = (float(v) for v in cfg.friction_scale)
            torch.where(mask, lo + (hi - lo) * u[:, nb + 2 * nd], self.friction_scale, out=self.friction_scale)
            nominal = self._nominal["geom_friction"]  # (ngeom, 3): sliding, torsional, rolling
            f = self.friction_scale.to(nominal.dtype)
            one = torch.ones_like(f)
            self._where(mask, "geom_friction", nominal * torch.stack((f, one, one), dim=-1).unsqueeze(1))

    def nominal(self, mask: torch.Tensor) -> None:
        """Give the worlds flagged in ``mask`` (N,) bool the model's own dynamics (identity parameters, the model's
        field values), in place: the env's worlds that are not randomised (``TocabiWalk.set_randomized_worlds``)."""
        self.mass_scale.masked_fill_(mask.unsqueeze(-1), 1.0)
        self.joint_damping.masked_fill_(mask.unsqueeze(-1), 0.0)
        self.armature_scale.masked_fill_(mask.unsqueeze(-1), 1.0)
        self.friction_scale.masked_fill_(mask, 1.0)
        for name, field in self.fields.items():
            self._where(mask, name, self._nominal[name].expand_as(field))
