"""A stand-in for ``TocabiWalk`` for the transform tests: the keys, shapes, dtypes and specs of the signal table.

The specs come from the same table as the env's (``tocabi_torchrl.signals``, the unconditional rows, or the
``signals`` passed in), and every signal of the table is emitted: a signal added to the table appears here too.

Two modes:

* ``"random"``: every signal is drawn fresh each step (plausible magnitudes), with an optional termination rate, to
  exercise specs, resets and the reward under arbitrary data.
* ``"counter"``: every float signal of env i after policy step k (k = ``episode_step``, 0 after a reset) equals
  ``k + 100·i`` (the phase: ``(k + 100·i) / 1000``), so a test can read which step a value came from.

Signals without a hand-written draw below (a new row, ``healthy``) are generic: floats standard normal in
``"random"`` mode and the counter in ``"counter"`` mode, flags True, integers 0.

``applied_action`` is the clipped action (zeros after a reset), ``episode_step`` counts steps since the env's last
reset, ``truncated`` fires at ``max_episode_steps``. Partial resets (``"_reset"`` (N, 1) bool) redraw only the
flagged envs and return the current state of the others, as the real env does. No host synchronisation.
"""

from __future__ import annotations

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Bounded
from torchrl.envs import EnvBase

from tocabi_torchrl import robot
from tocabi_torchrl.signals import EPISODE_FLAGS, REWARD, SIGNALS, SignalTable

NUM_ACTIONS = robot.NUM_LEG_JOINTS + 1
#: Signals the mock keeps itself (set from the action and the step count), not drawn.
_STATEFUL = ("applied_action", "episode_step")


class MockTocabiWalk(EnvBase):
    """Batched mock env emitting the ``TocabiWalk`` signals (see the module doc)."""

    batch_locked = True

    def __init__(
        self,
        num_envs: int = 4,
        device: str | torch.device = "cpu",
        mode: str = "random",
        max_episode_steps: int = 8000,
        terminate_prob: float = 0.0,
        seed: int = 0,
        signals: SignalTable = SIGNALS,
    ):
        if mode not in ("random", "counter"):
            raise ValueError(f"mode must be 'random' or 'counter', got {mode!r}")
        super().__init__(device=device, batch_size=torch.Size([num_envs]))
        self.num_envs = num_envs
        self.mode = mode
        self.max_episode_steps = max_episode_steps
        self.terminate_prob = terminate_prob
        self.signals = signals.enabled()
        self._gen = torch.Generator(device=self.device)
        self._gen.manual_seed(seed)
        self._state: TensorDict | None = None
        self._env_offset = (100.0 * torch.arange(num_envs, device=self.device, dtype=torch.float32)).unsqueeze(-1)
        # Constants are put on the device once: creating them from host data in a step would copy (and sync).
        f32 = {"dtype": torch.float32, "device": self.device}
        self._identity_quat = torch.tensor([1.0, 0.0, 0.0, 0.0], **f32)
        self._init_joint_pos = torch.as_tensor(robot.INIT_JOINT_POS, **f32)
        self._base_pos = torch.tensor([0.0, 0.0, 0.93], **f32)
        self._neck_pos = torch.tensor([0.0, 0.0, 1.5], **f32)
        self._foot_pos = torch.tensor([[0.11, 0.125, 0.13], [0.11, -0.125, 0.13]], **f32)  # the reference's 0.25 m gap
        self._make_specs()
        self._reset(None)  # the simulator has a state from construction on, like the real env

    # ------------------------------------------------------------------ specs
    def _make_specs(self) -> None:
        n, dev = self.num_envs, self.device
        self.observation_spec = SignalTable(self.signals).composite(n, dev)
        low = torch.tensor([-1.0] * robot.NUM_LEG_JOINTS + [0.0], device=dev).expand(n, NUM_ACTIONS)
        self.action_spec = Bounded(low=low, high=torch.ones_like(low), shape=(n, NUM_ACTIONS), device=dev)
        self.reward_spec = REWARD.spec(n, dev)
        self.done_spec = EPISODE_FLAGS.composite(n, dev)

    # ---------------------------------------------------------------- signals
    def _rand(self, *shape) -> torch.Tensor:
        return torch.rand((self.num_envs, *shape), generator=self._gen, device=self.device)

    def _randn(self, *shape) -> torch.Tensor:
        return torch.randn((self.num_envs, *shape), generator=self._gen, device=self.device)

    def _signals(self, episode_step: torch.Tensor) -> dict[str, torch.Tensor]:
        """Every drawn signal of the table for every env at ``episode_step`` (N, 1), checked against the table."""
        value = episode_step.to(torch.float32) + self._env_offset  # (N, 1), the counter
        out = self._counter_signals(value) if self.mode == "counter" else self._random_signals()
        for row in self.signals:
            if row.name in _STATEFUL:
                continue
            if row.name not in out:
                out[row.name] = self._generic(row, value)
            got = out[row.name]
            if tuple(got.shape) != (self.num_envs, *row.shape) or got.dtype != row.dtype:
                raise AssertionError(f"mock draws {row.name!r} as {tuple(got.shape)} {got.dtype}, the table says "
                                     f"{row.shape} {row.dtype}: update MockTocabiWalk._random_signals")
        return out

    def _generic(self, row, value: torch.Tensor) -> torch.Tensor:
        """A signal without a hand-written draw: floats N(0, 1) (random) or the counter, flags True, ints 0."""
        shape = (self.num_envs, *row.shape)
        if row.dtype == torch.bool:
            return torch.ones(shape, dtype=torch.bool, device=self.device)
        if row.dtype != torch.float32:
            return torch.zeros(shape, dtype=row.dtype, device=self.device)
        if self.mode == "counter":
            return value.reshape(self.num_envs, *([1] * len(row.shape))).expand(shape).clone()
        return self._randn(*row.shape)

    def _counter_signals(self, value: torch.Tensor) -> dict[str, torch.Tensor]:
        return {"phase": value / 1000.0}  # the rest is generic: float signals are the counter itself

    def _random_signals(self) -> dict[str, torch.Tensor]:
        """Plausible magnitudes for the signals the transforms read (drawn in this fixed order)."""
        n = self.num_envs
        quat = torch.nn.functional.normalize(self._identity_quat + 0.2 * self._randn(4), dim=-1)
        neck_quat = torch.nn.functional.normalize(self._identity_quat + 0.2 * self._randn(4), dim=-1)
        force = 100.0 * self._randn(2, 3)
        force[..., 2] = -600.0 * self._rand(2) - 50.0 * self._rand(2)
        init = self._init_joint_pos
        drawn = {
            "joint_pos": init + 0.1 * self._randn(robot.NUM_JOINTS),
            "joint_vel": self._randn(robot.NUM_JOINTS),
            "base_pos": self._base_pos + 0.05 * self._randn(3),
            "base_quat": quat,
            "base_lin_vel": 0.3 * self._randn(3),
            "base_ang_vel": 0.3 * self._randn(3),
            "neck_pos": self._neck_pos + 0.05 * self._randn(3),
            "neck_quat": neck_quat,
            "foot_force": force,
            "foot_torque": 20.0 * self._randn(2, 3),
            "phase": self._rand(1),
            "ref_joint_pos": init + 0.1 * self._randn(robot.NUM_JOINTS),
            "ref_foot_force": -1025.0 * self._rand(2),
            "command": torch.stack((-0.2 + self._rand() * 1.0, -0.2 + self._rand() * 0.4), -1),
            "leg_torque": 50.0 * self._randn(robot.NUM_LEG_JOINTS),
            "foot_contact": self._rand(2) < 0.6,
            "stance": torch.randint(0, 3, (n, 1), generator=self._gen, device=self.device),
        }
        drawn["foot_pos"] = self._foot_pos + 0.05 * self._randn(2, 3)  # drawn last: the others keep their values
        return drawn

    # -------------------------------------------------------------- EnvBase
    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        n, dev = self.num_envs, self.device
        reset = None if tensordict is None else tensordict.get("_reset", None)
        mask = torch.ones((n, 1), dtype=torch.bool, device=dev) if reset is None else reset.reshape(n, 1)
        episode_step = torch.zeros((n, 1), dtype=torch.int64, device=dev)
        fresh = self._signals(episode_step)
        fresh["applied_action"] = torch.zeros((n, NUM_ACTIONS), device=dev)
        fresh["episode_step"] = episode_step
        fresh = TensorDict(fresh, batch_size=[n], device=dev)
        if self._state is None:
            self._state = fresh
        else:
            self._state = fresh.where(mask.squeeze(-1), self._state)  # flagged rows fresh, the others unchanged
        out = self._state.clone()
        false = torch.zeros((n, 1), dtype=torch.bool, device=dev)
        out.update({"done": false, "terminated": false.clone(), "truncated": false.clone()})
        return out

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        n, dev = self.num_envs, self.device
        low, high = self.action_spec.space.low, self.action_spec.space.high
        action = torch.maximum(torch.minimum(tensordict.get("action"), high), low)
        episode_step = self._state.get("episode_step") + 1
        sig = self._signals(episode_step)
        sig["applied_action"] = action.to(torch.float32)
        sig["episode_step"] = episode_step
        self._state = TensorDict(sig, batch_size=[n], device=dev)
        if self.mode == "random" and self.terminate_prob > 0:
            terminated = self._rand(1) < self.terminate_prob
        else:
            terminated = torch.zeros((n, 1), dtype=torch.bool, device=dev)
        truncated = episode_step >= self.max_episode_steps
        out = self._state.clone()
        out.update(
            {
                "reward": torch.zeros((n, 1), dtype=torch.float32, device=dev),
                "terminated": terminated,
                "truncated": truncated,
                "done": terminated | truncated,
            }
        )
        return out

    def _set_seed(self, seed: int | None) -> None:
        if seed is not None:
            self._gen.manual_seed(seed)
