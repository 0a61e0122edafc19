"""Left-right mirror symmetry of the walking task, and PPO's symmetry augmentation (``ppo.symmetry="augment"``).

TOCABI is left-right symmetric: reflecting a state about the pelvis's x-z plane (y -> -y) gives another state whose
physics is the mirror image, and a policy that walks well should answer the mirrored state with the mirrored action.
The reflection acts on what the policy sees and does as a signed permutation:

* joints: left and right swap, the roll/yaw-type joints flip sign (:data:`~tocabi_torchrl.robot.MIRROR_JOINT`,
  :data:`~tocabi_torchrl.robot.MIRROR_SIGN`, derived from the MJCF's joint axes);
* base roll and yaw flip, pitch stays; the commanded vy flips, vx stays;
* the foot sensors swap feet; the moment about x (an axial vector's x component) flips, Fz and My stay;
* the gait phase moves by half a cycle (the mirrored walk is the same walk half a cycle later, with the other foot
  leading): with harmonic k the sin/cos pair becomes ``(-1)^k`` times itself, so with one harmonic both flip;
* the 13 actions: the 12 leg actions mirror like the joints (a torque or a position residual about a joint axis
  transforms like that joint's angle), the phase rate stays.

The policy input is normalised per step (``(x - mean)/std``, the statistics being the normaliser's), so in that space
the mirror is affine: ``y_i = g_i·x_{p(i)} + b_i`` with ``g_i = s_i·std_{p(i)}/std_i`` and
``b_i = (s_i·mean_{p(i)} − mean_i)/std_i``. It equals ``normalise(mirror(raw))`` whatever the statistics (the
reference's are close to, but not exactly, mirror symmetric); with an observation clip, clipped entries mirror only
approximately (the clip is applied again after the mirror).

All maps work on batched ``(N, D)`` tensors with precomputed index and gain tensors: one gather and an in-place
multiply-add, no host reads, nothing allocated but the output, so they run inside the captured PPO update.

:class:`SymmetryAugmentLoss` doubles each PPO mini-batch with its mirror image (observations and actions mirrored;
advantages, value targets and the old log-probabilities kept): the idea of rsl_rl's symmetry augmentation.
:class:`EquivariantMean` instead makes the policy's mean action symmetric by construction (``ppo.symmetry``
"equivariant").
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from tensordict import TensorDictBase
from torch import nn

from .. import robot

# The config's values (``ppo.symmetry``), defined with the config tree (which reads without torch), named here too.
from ..config import SYMMETRY_MODES
from ..transforms.layouts import REFERENCE_HISTORY, REFERENCE_OBS_LAYOUT, HistoryLayout, ObsComponent
from ..transforms.privileged import PRIVILEGED_MIRROR
from .rollout_guard import PROXIMAL_KEY, mean_over_valid, ratio_statistics

__all__ = ["SYMMETRY_MODES", "ACTION_DIM", "obs_step_mirror_map", "action_mirror_map", "policy_input_mirror_map",
           "SignedPermutation", "PolicyInputMirror", "mirror_qpos", "mirror_qvel", "SymmetryAugmentLoss",
           "find_normalization", "normalization_statistics", "make_policy_input_mirror", "make_symmetry_loss",
           "refresh_statistics", "EquivariantMean", "make_equivariant_mean", "set_equivariant_statistics",
           "apply_checkpoint_policy"]

#: 12 leg actions + the phase rate.
ACTION_DIM = robot.NUM_LEG_JOINTS + 1

_LEG_PERM = tuple(robot.MIRROR_JOINT[robot.LEGS])
_LEG_SIGN = tuple(robot.MIRROR_SIGN[robot.LEGS])


def _component_map(component: ObsComponent, phase_harmonics: int) -> tuple[tuple[int, ...], tuple[float, ...]]:
    """(perm, sign) of one observation block, indices local to the block."""
    name, h = component.name, phase_harmonics
    rules = {
        "base_rpy": ((0, 1, 2), (-1.0, 1.0, -1.0)),  # roll, pitch, yaw of the pelvis
        "leg_joint_pos": (_LEG_PERM, _LEG_SIGN),
        "leg_joint_vel": (_LEG_PERM, _LEG_SIGN),
        # Half a cycle later: sin(2πk(p + 1/2)) = (-1)^k sin(2πkp), cos likewise.
        "phase_sin": (tuple(range(h)), tuple(float((-1) ** k) for k in range(1, h + 1))),
        "phase_cos": (tuple(range(h)), tuple(float((-1) ** k) for k in range(1, h + 1))),
        "command": ((0, 1), (1.0, -1.0)),  # vx, vy
        "foot_force_z": ((1, 0), (1.0, 1.0)),  # [left, right]: swap feet
        "foot_torque_x": ((1, 0), (-1.0, -1.0)),  # a moment is an axial vector: its x component flips
        "foot_torque_y": ((1, 0), (1.0, 1.0)),
        "base_lin_vel": ((0, 1, 2), (1.0, -1.0, 1.0)),  # pelvis frame: the sideways velocity flips
        "base_ang_vel": ((0, 1, 2), (-1.0, 1.0, -1.0)),  # an axial vector: roll and yaw rates flip
    }
    if name not in rules:
        raise ValueError(f"no mirror rule for the observation block {name!r} (key {component.key!r}); the symmetry "
                         f"maps know {sorted(rules)}: add a rule to tocabi_torchrl/rl/symmetry.py for a new block")
    return rules[name]


def obs_step_mirror_map(layout: Sequence[ObsComponent] = REFERENCE_OBS_LAYOUT,
                        phase_harmonics: int = 1) -> tuple[list[int], list[float]]:
    """(perm, sign) of the per-step observation: the mirrored observation is ``sign * x[perm]`` (37 values each for
    :data:`~tocabi_torchrl.transforms.layouts.REFERENCE_OBS_LAYOUT`). Raises ``ValueError`` for a block it has no
    rule for."""
    perm: list[int] = []
    sign: list[float] = []
    for component in layout:
        p, s = _component_map(component, phase_harmonics)
        perm += [len(perm) + i for i in p]
        sign += list(s)
    return perm, sign


def action_mirror_map() -> tuple[list[int], list[float]]:
    """(perm, sign) of the 13 actions: the legs as their joints, the phase rate (last) unchanged."""
    return [*_LEG_PERM, robot.NUM_LEG_JOINTS], [*_LEG_SIGN, 1.0]


def policy_input_mirror_map(history: HistoryLayout = REFERENCE_HISTORY,
                            obs_map: tuple[Sequence[int], Sequence[float]] | None = None,
                            action_map: tuple[Sequence[int], Sequence[float]] | None = None,
                            ) -> tuple[list[int], list[float]]:
    """(perm, sign) of the whole policy input of ``history``: each of its K observations mirrored by ``obs_map``
    (default :func:`obs_step_mirror_map`), each of its M actions by ``action_map`` (default
    :func:`action_mirror_map`); K·D + M·A values (237 for the reference)."""
    op, os_ = obs_map if obs_map is not None else obs_step_mirror_map()
    ap, as_ = action_map if action_map is not None else action_mirror_map()
    perm: list[int] = []
    sign: list[float] = []
    for p, s in [(op, os_)] * history.num_obs + [(ap, as_)] * history.num_actions:
        perm += [len(perm) + i for i in p]
        sign += list(s)
    return perm, sign


def _check_map(perm: Sequence[int], sign: Sequence[float]) -> None:
    n = len(perm)
    if len(sign) != n or sorted(perm) != list(range(n)):
        raise ValueError(f"a mirror map needs a permutation of range({n}) and {n} signs, got {list(perm)!r}, "
                         f"{list(sign)!r}")
    for i, j in enumerate(perm):
        # A reflection is its own inverse: partners swap back, with the same sign on both sides.
        if perm[j] != i or sign[j] != sign[i] or abs(sign[i]) != 1.0:
            raise ValueError(f"mirror map entry {i} -> {j} is not an involution with signs ±1 (perm[{j}] = {perm[j]}, "
                             f"signs {sign[i]}, {sign[j]})")


class SignedPermutation(nn.Module):
    """``y = gain * x[..., perm] + offset`` over the last dimension, for ``(..., D)`` float tensors.

    Built from a mirror map (perm, sign): ``gain = sign``, ``offset = 0``. :class:`PolicyInputMirror` sets gain and
    offset for normalised blocks. The index, gain and offset are buffers (they move with ``.to(device)``); a call
    allocates only its output.
    """

    def __init__(self, perm: Sequence[int], sign: Sequence[float]):
        super().__init__()
        _check_map(perm, sign)
        self.register_buffer("perm", torch.tensor(list(perm), dtype=torch.long))
        self.register_buffer("sign", torch.tensor(list(sign), dtype=torch.float32))
        self.register_buffer("gain", self.sign.clone())
        self.register_buffer("offset", torch.zeros(len(perm), dtype=torch.float32))

    @property
    def dim(self) -> int:
        return self.perm.numel()

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if not torch.jit.is_tracing() and x.shape[-1] != self.dim:  # static under an export's trace
            raise ValueError(f"{type(self).__name__} maps {self.dim} values, got a tensor of shape {tuple(x.shape)}")
        out = x.index_select(-1, self.perm)
        return out.mul_(self.gain).add_(self.offset)


class PolicyInputMirror(SignedPermutation):
    """The mirror of the policy input: its K stored observations are normalised (``(x - loc)/scale``, ``D`` values
    each), its M stored actions raw.

    Args:
        history: the input's layout.
        obs_map, action_map: mirror maps of one observation and one action (defaults: the reference's).
        loc, scale: (D,) the normaliser's statistics (``FixedNormalization.loc``/``scale``, or a
            ``RunningNormalization``'s mean and sqrt(var + eps)); None: the observations are raw (``normalization
            "none"``). :meth:`set_statistics` changes them in place (a running normaliser's, before each update).
        clip: the normaliser's clip of the observation, applied again after the mirror (None: no clip).
    """

    def __init__(self, history: HistoryLayout = REFERENCE_HISTORY,
                 obs_map: tuple[Sequence[int], Sequence[float]] | None = None,
                 action_map: tuple[Sequence[int], Sequence[float]] | None = None,
                 loc: torch.Tensor | None = None, scale: torch.Tensor | None = None, clip: float | None = None):
        obs_map = obs_map if obs_map is not None else obs_step_mirror_map()
        action_map = action_map if action_map is not None else action_mirror_map()
        super().__init__(*policy_input_mirror_map(history, obs_map, action_map))
        self.history = history
        self.obs_dim = len(obs_map[0])
        self.register_buffer("obs_perm", torch.tensor(list(obs_map[0]), dtype=torch.long))
        self.register_buffer("obs_sign", torch.tensor(list(obs_map[1]), dtype=torch.float32))
        #: Entries of the flat input that hold observations: the first K·D (the actions follow them).
        self.obs_entries = history.num_obs * self.obs_dim
        self.clip = clip
        if loc is not None or scale is not None:
            self.set_statistics(loc, scale)

    @torch.no_grad()
    def set_statistics(self, loc: torch.Tensor | None, scale: torch.Tensor | None) -> None:
        """Use the normaliser statistics ``loc``, ``scale`` (D,) for the observation blocks, in place (a captured
        update reads the same buffers). ``None`` for both: raw observations."""
        d = self.obs_dim
        if (loc is None) != (scale is None):
            raise ValueError("PolicyInputMirror.set_statistics: give both loc and scale, or neither (raw observations)")
        if loc is None:
            gain, offset = self.obs_sign, torch.zeros_like(self.obs_sign)
        else:
            loc = torch.as_tensor(loc, dtype=torch.float32, device=self.gain.device).reshape(-1)
            scale = torch.as_tensor(scale, dtype=torch.float32, device=self.gain.device).reshape(-1)
            if loc.numel() != d or scale.numel() != d:
                raise ValueError(f"PolicyInputMirror: the observation has {d} values but the statistics have "
                                 f"{loc.numel()} and {scale.numel()}")
            gain = self.obs_sign * scale[self.obs_perm] / scale
            offset = (self.obs_sign * loc[self.obs_perm] - loc) / scale
        k = self.history.num_obs
        self.gain[: self.obs_entries].copy_(gain.repeat(k))
        self.offset[: self.obs_entries].copy_(offset.repeat(k))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        out = super().forward(x)
        if self.clip is not None:  # only the observations: the stored actions are not normalised
            out[..., : self.obs_entries].clamp_(-self.clip, self.clip)
        return out


class EquivariantMean(nn.Module):
    """A mean-action network that is left-right symmetric by construction (``ppo.symmetry="equivariant"``):
    ``μ(o) = ½·(f(o) + A·f(M·o))``, ``f`` the wrapped network, ``M`` the policy input's mirror and ``A`` the action's.

    Then ``μ(M·o) = A·μ(o)`` for every input, whatever ``f``'s weights (``M`` and ``A`` are involutions): the mirrored
    state gets the mirrored action at every point of training, with no term in the loss and no mirrored frames in the
    batch. Where the augmentation's mirrored frames fall outside PPO's clip at a small action σ, and a mirror loss
    can be outweighed (docs/training.md, "Left-right symmetry"), this cannot drift from symmetric. The two passes of
    ``f`` run as one, over a (2, N, input_dim) stack (``f`` must act on the last dimension, as an MLP does).

    The input is normalised, so ``M`` is :class:`PolicyInputMirror` with the normaliser's statistics (its buffers,
    saved in checkpoints; :func:`set_equivariant_statistics` sets them from the env). Exact for inputs inside the
    normaliser's clip; a clipped entry mirrors approximately (the clip is applied again after the mirror).

    Args:
        net: ``f``, (..., input_dim) -> (..., action_dim).
        obs_mirror: the policy input's :class:`PolicyInputMirror`.
        action_mirror: the action's :class:`SignedPermutation` (:func:`action_mirror_map`).

    Input (N, input_dim) normalised policy input; output (N, action_dim) mean action.

    >>> import torch
    >>> mean = EquivariantMean(torch.nn.Linear(237, ACTION_DIM), PolicyInputMirror(),
    ...                        SignedPermutation(*action_mirror_map()))
    >>> o = torch.randn(4, 237)
    >>> torch.allclose(mean(mean.obs_mirror(o)), mean.action_mirror(mean(o)), atol=1e-6)
    True
    """

    def __init__(self, net: nn.Module, obs_mirror: PolicyInputMirror, action_mirror: SignedPermutation):
        super().__init__()
        if obs_mirror.clip is not None:
            raise ValueError("EquivariantMean applies the normaliser's clip itself (a buffer, so that a checkpoint "
                             "keeps it): build the PolicyInputMirror without one and call set_statistics")
        self.net, self.obs_mirror, self.action_mirror = net, obs_mirror, action_mirror
        #: The normaliser's clip of the observation entries, applied again after the mirror (float32 max: none).
        self.register_buffer("clip", torch.tensor(torch.finfo(torch.float32).max, device=obs_mirror.gain.device))

    @torch.no_grad()
    def set_statistics(self, loc: torch.Tensor | None, scale: torch.Tensor | None, clip: float | None) -> None:
        """The normaliser's statistics (D,) and clip (None for raw observations or no clip), in place."""
        self.obs_mirror.set_statistics(loc, scale)
        self.clip.fill_(torch.finfo(torch.float32).max if clip is None else float(clip))

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        if not torch.jit.is_tracing() and obs.shape[-1] != self.obs_mirror.dim:  # static under an export's trace
            raise ValueError(f"EquivariantMean: the mirror maps a policy input of {self.obs_mirror.dim} values, got "
                             f"shape {tuple(obs.shape)}")
        mirrored = self.obs_mirror(obs)
        entries = self.obs_mirror.obs_entries
        mirrored = torch.cat((torch.clamp(mirrored[..., :entries], -self.clip, self.clip), mirrored[..., entries:]),
                             dim=-1)
        # One pass over both, stacked on a leading axis of 2 (not concatenated along the batch: an export keeps its
        # batch size dynamic).
        both = self.net(torch.stack((obs, mirrored)))
        return 0.5 * (both[0] + self.action_mirror(both[1]))


def make_equivariant_mean(net: nn.Module, transforms_config, obs_dim: int, act_dim: int) -> EquivariantMean:
    """:class:`EquivariantMean` around ``net`` for the policy input of ``transforms_config`` (a ``TransformConfig``:
    layout, history, phase harmonics), with raw statistics until :func:`set_equivariant_statistics` (or a loaded
    checkpoint) sets the normaliser's. Raises ``ValueError`` when ``obs_dim``/``act_dim`` do not fit the maps."""
    cfg = transforms_config
    mirror = PolicyInputMirror(cfg.history, obs_step_mirror_map(cfg.obs_layout, cfg.phase_harmonics))
    if obs_dim != mirror.dim or act_dim != ACTION_DIM:
        raise ValueError(f"ppo.symmetry='equivariant' mirrors a policy input of {mirror.dim} values (layout "
                         f"{cfg.history}) and TOCABI's {ACTION_DIM} actions; this policy has {obs_dim} inputs and "
                         f"{act_dim} actions")
    device = next(net.parameters()).device
    # Everything on the network's device: a buffer left on the CPU would fail the first CUDA update (a clamp with a
    # CPU bound), though the collector's own device-mapped copy would not show it.
    return EquivariantMean(net, mirror, SignedPermutation(*action_mirror_map())).to(device)


def set_equivariant_statistics(module: nn.Module, env) -> bool:
    """Give every :class:`EquivariantMean` in ``module`` the statistics and clip of ``env``'s observation normaliser
    (in place: a captured update and the collector's copy read the same buffers). Returns whether ``module`` has one.
    Call it once the normaliser holds its statistics (after a resume's load too), and before each update while a
    running normaliser moves."""
    found = False
    norm = find_normalization(env)
    for m in module.modules():
        if isinstance(m, EquivariantMean):
            m.set_statistics(*normalization_statistics(norm), getattr(norm, "clip", None))
            found = True
    return found


def apply_checkpoint_policy(state: dict, agent, cfg, env, path) -> None:
    """``apply_checkpoint`` for a checkpoint's policy (a gait test, play, the viewer, an export): the trained weights
    and ``env``'s normaliser state, then, with ``cfg.ppo.symmetric_policy``, the trained actor made the symmetric
    policy the checkpoint gives, its mean network wrapped in :class:`EquivariantMean` with ``env``'s normaliser
    statistics (in place). Training loads with ``apply_checkpoint`` alone. Called again (one env per case), the
    wrapper is taken off for the weights and put back with the new env's statistics."""
    from .actors import gaussian_head
    from .checkpoint import apply_checkpoint

    head = gaussian_head(agent.actor)
    wrapped = cfg.ppo.symmetric_policy and isinstance(head.mean_net, EquivariantMean)
    if wrapped:
        head.mean_net = head.mean_net.net  # the trained network, which the checkpoint's weights are of
    apply_checkpoint(state, agent, env=env, path=path)
    if cfg.ppo.symmetric_policy:
        obs_dim, act_dim = env.observation_spec["observation"].shape[-1], env.action_spec.shape[-1]
        head.mean_net = make_equivariant_mean(head.mean_net, cfg.transforms.transform_config(), obs_dim, act_dim)
        set_equivariant_statistics(agent.actor, env)


# ------------------------------------------------------------------------------------------------ simulator state
def _flip(n: int, idx: Sequence[int], device) -> torch.Tensor:
    s = torch.ones(n, dtype=torch.float32, device=device)
    s[list(idx)] = -1.0
    return s


def mirror_qpos(qpos: torch.Tensor) -> torch.Tensor:
    """(N, 7 + 33) the mirror image of TOCABI's ``qpos`` (free base, then the joints in ``robot.JOINT_NAMES`` order):
    base y -> -y, the quaternion (w, x, y, z) -> (w, -x, y, -z) (``M·R·M`` with ``M = diag(1, -1, 1)``), the joints by
    :data:`~tocabi_torchrl.robot.MIRROR_JOINT`/``MIRROR_SIGN``. For tests and analyses (it allocates)."""
    joints = torch.as_tensor(robot.MIRROR_JOINT, device=qpos.device)
    base = qpos[..., :7] * _flip(7, (1, 4, 6), qpos.device).to(qpos.dtype)
    sign = torch.as_tensor(robot.MIRROR_SIGN, dtype=qpos.dtype, device=qpos.device)
    return torch.cat((base, qpos[..., 7:].index_select(-1, joints) * sign), dim=-1)


def mirror_qvel(qvel: torch.Tensor) -> torch.Tensor:
    """(N, 6 + 33) the mirror image of ``qvel``: the base's world linear velocity (vx, -vy, vz), its local angular
    velocity, an axial vector, (-wx, wy, -wz), the joints as in :func:`mirror_qpos`."""
    joints = torch.as_tensor(robot.MIRROR_JOINT, device=qvel.device)
    base = qvel[..., :6] * _flip(6, (1, 3, 5), qvel.device).to(qvel.dtype)
    sign = torch.as_tensor(robot.MIRROR_SIGN, dtype=qvel.dtype, device=qvel.device)
    return torch.cat((base, qvel[..., 6:].index_select(-1, joints) * sign), dim=-1)


# ------------------------------------------------------------------------------------------------ PPO augmentation
#: Per-frame values a mirrored frame shares with its original: the return estimates, the old policy's probability of
#: the original action (rsl_rl's augmentation keeps it too; so is the proximal policy's, for a decoupled update) and
#: the masks.
_KEPT = ("advantage", "value_target", "state_value", "action_log_prob", "sample_log_prob", PROXIMAL_KEY,
         "frame_valid", "shifted_valid", ("next", "reward"), ("next", "done"), ("next", "terminated"),
         ("next", "truncated"))


class SymmetryAugmentLoss(nn.Module):
    """A PPO loss that sees each mini-batch of B frames doubled to 2B: the frames, then their mirror images.

    The mirrored half has ``observation`` (and ``("next", "observation")``) mirrored by ``obs_mirror`` and
    ``action`` and the old policy's ``loc`` by ``action_mirror``; ``scale`` and the torque assist's
    ``("next", "leg_assist")`` (a per-leg-joint torque) are permuted (and signed) likewise. Advantages, value targets,
    old values and old log-probabilities are kept: the mirrored action is taken to be as good, and as probable under
    the old policy, as the original (the augmentation of rsl_rl's symmetry module). Any other key raises, so that a new
    signal in the batch is not silently left unmirrored. The batch size is fixed (2B), so a captured update step
    stays valid.

    The logged ``kl_approx`` and ``clip_fraction`` are those of the original half, as in rsl_rl: the mirrored half's
    log-ratio compares the new policy's mirrored action with the old policy's original one, which differ as long as
    the policy is not symmetric, and counting them would move the KL-adaptive learning rate for that reason. They
    are read from ``ClipPPOLoss._log_weight`` (TorchRL 0.14's per-frame log-ratio), wrapped on the instance; a loss
    without it keeps its own values.

    That log-ratio also limits the augmentation: once the policy is a little asymmetric at a small action σ, every
    mirrored frame lies outside PPO's clip and adds no gradient (docs/training.md, "Left-right symmetry"). With
    ``mirror_loss`` > 0 the output also holds ``loss_symmetry = mirror_loss · mean((μ(M·o) − A·μ(o))²)`` over
    the frames and actions, μ the policy's mean (``head``), each side pulled towards the other's mirror image
    (rsl_rl's mirror loss, over the doubled batch): it acts at any σ.

    Args:
        ppo_loss: the PPO loss (``ClipPPOLoss``); ``in_keys`` is its own.
        obs_mirror: :class:`PolicyInputMirror` of the policy input.
        action_mirror: :class:`SignedPermutation` of the action (:func:`action_mirror_map`).
        head: the actor's :class:`~tocabi_torchrl.rl.actors.GaussianHead` (shares its parameters), for the mirror
            loss.
        mirror_loss: the mirror loss's weight (0: no ``loss_symmetry``).
    """

    def __init__(self, ppo_loss: nn.Module, obs_mirror: SignedPermutation, action_mirror: SignedPermutation,
                 head: nn.Module | None = None, mirror_loss: float = 0.0):
        super().__init__()
        if mirror_loss > 0 and head is None:
            raise ValueError("SymmetryAugmentLoss: a mirror_loss > 0 needs the actor's head (its mean action)")
        self.ppo_loss, self.obs_mirror, self.action_mirror = ppo_loss, obs_mirror, action_mirror
        self.head, self.mirror_loss = head, float(mirror_loss)
        p = action_mirror.perm
        # |sign| for the std, and the legs' map for the (N, 12) assist torque.
        self.register_buffer("_scale_perm", p.clone())
        self.register_buffer("_leg_perm", p[: robot.NUM_LEG_JOINTS].clone())
        self.register_buffer("_leg_sign", action_mirror.sign[: robot.NUM_LEG_JOINTS].clone())
        # The asymmetric critic's true-state input (ppo.critic_privileged), by its own signed permutation, on the
        # mirrors' device: nothing moves the loss module itself.
        self.register_buffer("_priv_perm", torch.tensor(PRIVILEGED_MIRROR[0], dtype=torch.int64, device=p.device))
        self.register_buffer("_priv_sign", torch.tensor(PRIVILEGED_MIRROR[1], device=p.device))
        self._last_log_weight = None
        if hasattr(ppo_loss, "_log_weight") and hasattr(ppo_loss, "_clip_bounds"):
            log_weight = ppo_loss._log_weight

            def recorded(*args, **kwargs):
                # (log_weight, dist, kl_approx, log_is_weight), each (2B, 1): kept for this forward's statistics.
                self._last_log_weight = out = log_weight(*args, **kwargs)
                return out

            ppo_loss._log_weight = recorded

    @property
    def in_keys(self) -> list:
        return list(self.ppo_loss.in_keys)

    @property
    def loss_mask_key(self):
        """The wrapped loss's mask key (read by ``AssistAbsorbLoss``, which wraps this one)."""
        return getattr(self.ppo_loss, "loss_mask_key", None)

    def mirror_batch(self, td: TensorDictBase) -> TensorDictBase:
        """The mirror image of the frames ``td`` (batch dims first), a new tensordict of the same keys."""
        out = td.empty()
        for key in td.keys(True, True):
            value = td.get(key)
            if key in ("observation", ("next", "observation")):
                value = self.obs_mirror(value)
            elif key in ("action", "loc"):
                value = self.action_mirror(value)
            elif key == "scale":
                value = value.index_select(-1, self._scale_perm)
            elif key == ("next", "leg_assist"):
                value = value.index_select(-1, self._leg_perm) * self._leg_sign
            elif key in ("privileged", ("next", "privileged")):
                value = value.index_select(-1, self._priv_perm) * self._priv_sign
            elif key not in _KEPT:
                raise KeyError(f"SymmetryAugmentLoss: the mini-batch holds {key!r}, which it has no mirror rule for; "
                               f"add one to tocabi_torchrl/rl/symmetry.py (or keep the key out of the loss's batch)")
            out.set(key, value)
        return out

    def forward(self, td: TensorDictBase) -> TensorDictBase:
        b = td.batch_size[0]
        self._last_log_weight = None
        out = self.ppo_loss(torch.cat([td, self.mirror_batch(td)], dim=0))
        if self._last_log_weight is not None:
            log_weight, _, kl_approx, _ = self._last_log_weight
            self._last_log_weight = None
            # Over the original frames the loss mask keeps, as the PPO terms are (rollout_guard.GuardedClipPPOLoss).
            kl, clipped = ratio_statistics(log_weight[:b], kl_approx[:b], self.ppo_loss._clip_bounds, td,
                                           self.loss_mask_key)
            out.set("kl_approx", kl)
            out.set("clip_fraction", clipped)
        if self.mirror_loss > 0:
            out.set("loss_symmetry", self.mirror_loss * self._mirror_loss(td))
        return out

    def _mirror_loss(self, td: TensorDictBase) -> torch.Tensor:
        """mean((μ(M·o) − A·μ(o))²) over the frames the PPO loss keeps and every action. Each side is pulled towards
        the other's mirror image, held fixed: the frame and its mirror image both act as the original, as in the
        doubled batch (pulling only μ(M·o) let the weights it shares with μ(o) move μ(o) away)."""
        obs = td["observation"]
        loc, _ = self.head(obs)
        loc_of_mirror, _ = self.head(self.obs_mirror(obs))
        # A is a signed permutation: |μ(o) − A·μ(M·o)| = |A·μ(o) − μ(M·o)|, so the two halves have one value.
        # NaN-free before squaring: a broken frame is masked below, but 0 × NaN would still reach the gradients.
        gap_mirror = torch.nan_to_num(loc_of_mirror - self.action_mirror(loc).detach())
        gap_original = torch.nan_to_num(loc - self.action_mirror(loc_of_mirror).detach())
        per_frame = 0.5 * (gap_mirror.square() + gap_original.square()).mean(-1)
        return mean_over_valid(per_frame, td, self.loss_mask_key)


def find_normalization(env) -> nn.Module | None:
    """The observation normaliser among ``env``'s transforms (``FixedNormalization`` or ``RunningNormalization``),
    or None (``normalization="none"``)."""
    from ..transforms.normalize import FixedNormalization, RunningNormalization

    for module in getattr(env, "transform", nn.Module()).modules():
        if isinstance(module, (FixedNormalization, RunningNormalization)):
            return module
    return None


def normalization_statistics(norm: nn.Module | None) -> tuple[torch.Tensor | None, torch.Tensor | None]:
    """(loc, scale) the normaliser ``norm`` divides by, as float32 (None, None without one)."""
    from ..transforms.normalize import FixedNormalization

    if norm is None:
        return None, None
    if isinstance(norm, FixedNormalization):
        return norm.loc, norm.scale
    return norm._loc_scale()


def make_policy_input_mirror(env, transforms_config) -> PolicyInputMirror:
    """The :class:`PolicyInputMirror` of ``env``'s policy input: the layout of ``transforms_config`` (a
    ``TransformConfig``), the statistics and clip of the env's normaliser, on the env's device."""
    # Read first: the spec also sizes a running normaliser's statistics, which start empty without initial values.
    size = env.observation_spec["observation"].shape[-1]
    norm = find_normalization(env)
    cfg = transforms_config
    mirror = PolicyInputMirror(cfg.history, obs_step_mirror_map(cfg.obs_layout, cfg.phase_harmonics),
                               clip=getattr(norm, "clip", None)).to(env.device)
    if size != mirror.dim:
        raise ValueError(f"ppo.symmetry: the policy input has {size} values but the mirror map of its layout "
                         f"{cfg.history} has {mirror.dim}")
    mirror.set_statistics(*normalization_statistics(norm))
    return mirror


def make_symmetry_loss(ppo_loss: nn.Module, env, transforms_config, head: nn.Module | None = None,
                       mirror_loss: float = 0.0) -> SymmetryAugmentLoss:
    """:class:`SymmetryAugmentLoss` around ``ppo_loss`` for ``env`` (see :func:`make_policy_input_mirror`), with the
    mirror loss of weight ``mirror_loss`` on ``head``'s mean action when > 0."""
    action_dim = env.action_spec.shape[-1]
    if action_dim != ACTION_DIM:
        raise ValueError(f"ppo.symmetry needs TOCABI's {ACTION_DIM} actions (12 legs + phase rate), got {action_dim}")
    action_mirror = SignedPermutation(*action_mirror_map()).to(env.device)
    return SymmetryAugmentLoss(ppo_loss, make_policy_input_mirror(env, transforms_config), action_mirror, head,
                               mirror_loss)


def refresh_statistics(loss: SymmetryAugmentLoss, env) -> None:
    """Copy the env's normaliser statistics into the loss's mirror (a running normaliser's move every step); in
    place, so a captured update reads them."""
    loss.obs_mirror.set_statistics(*normalization_statistics(find_normalization(env)))
