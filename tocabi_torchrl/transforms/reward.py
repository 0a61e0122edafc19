"""The task reward: sum a chosen set of reward terms into ``reward`` and keep every term's value for logging."""

from __future__ import annotations

import copy
from collections.abc import Callable, Mapping, Sequence

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey
from torchrl.data import Composite, Unbounded
from torchrl.envs.transforms import RewardSum, Transform

from tocabi_torchrl.signals import SIGNALS
from tocabi_torchrl.transforms._base import check_specs_once, transforms_before
from tocabi_torchrl.transforms._checks import check_finite
from tocabi_torchrl.transforms.reward_terms import CallableTerm, RewardTerm, check_term
from tocabi_torchrl.transforms.kick_relax_config import KickRelax

__all__ = ["TaskReward"]


class TermKeyError(KeyError):
    """A reward term read a key its step does not hold; printed as its message (a ``KeyError`` prints its repr)."""

    def __str__(self) -> str:
        return str(self.args[0]) if self.args else ""


class TaskReward(Transform):
    """``reward = Σ term(td, next_td)`` over the given terms, each value also written to ``(terms_key, name)``.

    At every step, with ``td`` the root (time t) and ``next_td`` the step's output (time t+1):

    * each term gives a (num_envs, 1) float32 value ``weight · kernel`` (see :mod:`.reward_terms`; the transform
      calls ``term.kernel`` and applies the weights it was built with);
    * if ``zero_on_terminated`` (the reference's behaviour), every term and the reward are 0 where
      ``next_td[terminated_key]`` is True;
    * ``next_td[reward_key]`` (num_envs, 1) is replaced by the sum, and ``next_td[(terms_key, name)]`` holds each
      term's contribution, so the terms add up to the reward.

    * with ``kick_relax`` (a :class:`KickRelax` naming terms), those terms are scaled by ``1 − r`` after a kick
      (``env.pushes``): ``r = clamp(1 − age / seconds, 0, 1) · clamp(speed / full_speed, 0, 1)`` from
      ``next_td["kick_age"]`` [s] and ``next_td["kick_speed"]`` [m/s], the env's latest kick. A kicked robot is
      then paid less for the reference gait's clocked joint positions, contacts and smooth torques while it
      recovers, and the reward's remaining terms (upright, velocity, heading) carry the recovery. The kick times are
      drawn at reset, independent of the policy, so this changes what a recovery is paid for, not when.

    The per-term values are registered as observations (like :class:`~torchrl.envs.transforms.RewardSum`'s
    ``episode_reward``) so that ``reward`` stays the env's single reward key; they are 0 after a reset.

    Args:
        terms: :class:`RewardTerm` instances, or functions ``fn(td, next_td) -> (num_envs, 1)`` (named after the
            function, weight 1). Names must be unique.
        weights: optional ``{name: weight}`` overriding the terms' weights (the terms are copied, not modified).
        zero_on_terminated: zero reward and terms on terminating steps.
        reward_key, terms_key, terminated_key: keys written/read.
        compile: compute all terms with one ``torch.compile``-d function (fused kernels; the first step compiles,
            which takes tens of seconds). Off by default.
        kick_relax: which terms a kick relaxes, and for how long (see above); ``None`` or no terms: none.
    """

    def __init__(
        self,
        terms: Sequence[RewardTerm | Callable],
        weights: Mapping[str, float] | None = None,
        zero_on_terminated: bool = True,
        reward_key: NestedKey = "reward",
        terms_key: str = "reward_terms",
        terminated_key: NestedKey = "terminated",
        compile: bool = False,
        kick_relax: KickRelax | None = None,
    ):
        terms = [self._as_term(t) for t in terms]
        if not terms:
            raise ValueError("TaskReward needs at least one reward term")
        names = [t.name for t in terms]
        dup = sorted({n for n in names if names.count(n) > 1})
        if dup:
            raise ValueError(f"TaskReward: duplicate term names {dup}; give each term a unique name=...")
        weights = dict(weights or {})
        unknown = [n for n in weights if n not in names]
        if unknown:
            raise KeyError(f"TaskReward: weights given for unknown term(s) {unknown}; terms in use: {names}")
        for i, t in enumerate(terms):
            if t.name in weights:
                t = copy.copy(t)
                t.weight = check_finite(weights[t.name], f"weight of reward term {t.name!r}")
                terms[i] = t
        if not isinstance(terms_key, str):
            raise TypeError(f"TaskReward terms_key must be a string, got {terms_key!r}")
        if kick_relax is not None and not isinstance(kick_relax, KickRelax):
            raise TypeError(f"TaskReward kick_relax must be a KickRelax or None, got {kick_relax!r}")
        relax = kick_relax if kick_relax is not None and kick_relax.enabled else None
        if relax is not None:  # (a KickRelax validated its own values when it was made)
            missing = [n for n in relax.terms if n not in names]
            if missing:
                raise KeyError(f"TaskReward: kick_relax names term(s) {missing} that are not in use; terms in use: "
                               f"{names}")
        in_keys = list(dict.fromkeys(k for t in terms for k in (*t.root_keys, *t.next_keys)))
        if relax is not None:
            in_keys += list(KickRelax.KEYS)
        out_keys = [reward_key] + [(terms_key, n) for n in names]
        super().__init__(in_keys=in_keys, out_keys=out_keys)
        self.terms: tuple[RewardTerm, ...] = tuple(terms)
        self.register_buffer("_weights", torch.tensor([t.weight for t in terms], dtype=torch.float32))
        self.kick_relax = relax
        # (n_terms,) 1 for the terms a kick relaxes: one multiply of the stacked terms, no per-term branches.
        self.register_buffer("_relaxed", torch.tensor(
            [float(relax is not None and n in relax.terms) for n in names], dtype=torch.float32))
        self.compile = bool(compile)
        self._compiled = None
        self._checked = False
        self.zero_on_terminated = bool(zero_on_terminated)
        self.reward_key, self.terms_key, self.terminated_key = reward_key, terms_key, terminated_key

    @staticmethod
    def _as_term(t) -> RewardTerm:
        if isinstance(t, type):
            # A class is callable too: taken for a function, it was called with (td, next_td) as its fields at the
            # first step, and failed there naming a TensorDict as the term's name.
            raise TypeError(f"TaskReward got the class {t.__name__} as a term; pass an instance, e.g. {t.__name__}()")
        if isinstance(t, RewardTerm):
            check_term(t)
            return t
        if callable(t):
            name = getattr(t, "__name__", None)
            if not name or name == "<lambda>":
                raise ValueError(
                    f"TaskReward: cannot name the callable {t!r}; wrap it as CallableTerm(name, fn, weight)"
                )
            return CallableTerm(name=name, fn=t)
        raise TypeError(f"TaskReward terms must be RewardTerm instances or callables, got {t!r}")

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(t.name for t in self.terms)

    def set_weight(self, name: str, weight: float) -> None:
        """Change one term's weight in place (e.g. a curriculum); device-side, no host sync."""
        if name not in self.names:
            raise KeyError(f"TaskReward has no term {name!r}; terms in use: {list(self.names)}")
        i = self.names.index(name)
        w = check_finite(weight, f"weight of reward term {name!r}")
        term = copy.copy(self.terms[i])
        term.weight = w
        self.terms = self.terms[:i] + (term,) + self.terms[i + 1 :]
        self._weights[i].fill_(w)

    #: Device copies of this reward's configuration (the terms' weights, which terms a kick relaxes), not learned state.
    _CONFIG_BUFFERS = ("_weights", "_relaxed")

    def clone(self) -> TaskReward:
        copy = super().clone()
        # torchrl's clone is shallow: the copy shared these buffers, which set_weight and an env without kicks change
        # in place, so the original computed the copy's weights while its terms and repr named its own. The compiled
        # function is bound to the original.
        for name in self._CONFIG_BUFFERS:
            setattr(copy, name, getattr(self, name).clone())
        copy._compiled = None
        return copy

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs):
        # A checkpoint's copies were loaded over the terms': an env built with other weights, or with the same number
        # of terms in another order, computed the saved weights while its terms and repr named its own. They stay
        # in the saved state, where a resumed run learns how many terms it trained with (rl/checkpoint.py).
        own = {prefix + name: getattr(self, name) for name in self._CONFIG_BUFFERS if prefix + name in state_dict}
        super()._load_from_state_dict({**state_dict, **own}, prefix, *args, **kwargs)

    def _weighted_terms(self, tensordict: TensorDictBase, next_tensordict: TensorDictBase) -> torch.Tensor:
        """(num_envs, n_terms) weighted term values, zeroed on terminating steps if configured."""
        kernels = [t.kernel(tensordict, next_tensordict) for t in self.terms]
        # One (num_envs, n_terms) tensor: one weight multiply, one where and one sum for all terms, and the per-term
        # entries are views into it. This runs every step, so kernel launches matter more than the arithmetic.
        stacked = torch.cat(kernels, dim=-1).to(torch.float32) * self._weights
        if self.kick_relax is not None:
            k = self.kick_relax
            age, speed = (next_tensordict.get(key) for key in KickRelax.KEYS)  # (N, 1) each, s and m/s
            r = (1.0 - age / k.seconds).clamp(0.0, 1.0) * (speed / k.full_speed).clamp(0.0, 1.0)  # (N, 1)
            stacked = stacked * (1.0 - r * self._relaxed)
        if self.zero_on_terminated:
            stacked = torch.where(next_tensordict.get(self.terminated_key), 0.0, stacked)
        return stacked

    def _signal_reads(self) -> list[tuple[str, str, tuple[int, ...], bool]]:
        """(reader, key, per-env shape, read from the root) of every signal of the table (``signals.SIGNALS``) that a
        term or the kick relaxation reads. Every one, not only the reference terms': a (num_envs,) kick_age
        broadcast along the terms, and a (num_envs, 1) cycle_vel_error summed to a plausible value."""
        reads = [(f"reward term {t.name!r}", k, root) for t in self.terms
                 for root, keys in ((True, t.root_keys), (False, t.next_keys)) for k in keys]
        if self.kick_relax is not None:
            reads += [("kick_relax", k, False) for k in KickRelax.KEYS]
        return [(reader, k, SIGNALS[k].shape, root) for reader, k, root in reads if isinstance(k, str) and k in SIGNALS]

    def _check_signals(self, tensordict: TensorDictBase, next_tensordict: TensorDictBase) -> None:
        """The first step's signals against the table's shapes: the spec check does not see a step that writes
        another shape than its spec says. Metadata only, no device read; a missing key is left to
        :meth:`_check_terms`, which names the declaration to fix."""
        batch = tuple(next_tensordict.batch_size)
        for reader, key, want, root in self._signal_reads():
            value = (tensordict if root else next_tensordict).get(key, None)
            if isinstance(value, torch.Tensor) and tuple(value.shape) != (*batch, *want):
                where = "state at t" if root else "step's result"
                raise ValueError(_wrong_shape(reader, key, want, f"the {where} holds {tuple(value.shape)}"))

    def _check_terms(self, tensordict: TensorDictBase, next_tensordict: TensorDictBase) -> None:
        want = (*next_tensordict.batch_size, 1)
        for t in self.terms:
            try:
                value = t.kernel(tensordict, next_tensordict)
            except KeyError as err:
                # The trainer keeps only the declared keys of the state at t (training_keys): an undeclared read
                # works in env.rollout and fails in training, from deep inside tensordict.
                missing = err.args[0] if err.args else err
                raise TermKeyError(f"reward term {t.name!r} reads a key its step does not hold ({missing}); declare "
                                   "what it reads of the state at t in its root_keys and of the step's result in its "
                                   "next_keys (docs/extending.md)") from err
            if not isinstance(value, torch.Tensor):
                raise TypeError(f"reward term {t.name!r} returned a {type(value).__name__}; it must return a tensor "
                                f"of shape {want} on the env's device")
            shape = tuple(value.shape)
            if shape != want:
                raise ValueError(
                    f"reward term {t.name!r} returned shape {shape}; it must return {want} "
                    "(use keepdim=True in reductions)"
                )
            device = next_tensordict.device
            if device is not None and value.device != device:
                raise ValueError(f"reward term {t.name!r} returned a tensor on {value.device}, the env runs on "
                                 f"{device}: compute it from the step's tensors (or create it on their device)")
            if value.is_complex() or value.dtype == torch.bool:
                raise ValueError(f"reward term {t.name!r} returned {value.dtype}; it must return real numbers "
                                 "(float32)")
            # Once, at the first step (a host sync here only): a term that is NaN or inf in every env is broken,
            # and training would only mask all its frames. (Some envs' NaN can be their physics: the trainer masks
            # those frames and says so.)
            capturing = value.is_cuda and torch.cuda.is_current_stream_capturing()
            if not capturing and value.numel() and not bool(torch.isfinite(value).any()):
                raise ValueError(f"reward term {t.name!r} returned NaN or inf in every env at the first step: guard "
                                 "its division, log or sqrt")

    def _check_terminated(self, next_tensordict: TensorDictBase) -> None:
        """The flags ``zero_on_terminated`` reads: (num_envs, 1) bool (metadata only, no device read)."""
        flags = next_tensordict.get(self.terminated_key, None)
        want = (*next_tensordict.batch_size, 1)
        if flags is None:
            # A missing key failed inside torch.where with a bare TypeError.
            raise KeyError(f"TaskReward zeroes the reward where {self.terminated_key!r} is True, and the step has no "
                           f"such key; pass terminated_key= the env's termination flags, or zero_on_terminated=False")
        if flags.dtype != torch.bool or tuple(flags.shape) != want:
            # (num_envs,) flags broadcast along the terms instead: with as many envs as terms, without an error.
            raise ValueError(f"TaskReward terminated_key {self.terminated_key!r} must be {want} bool flags, got "
                             f"{tuple(flags.shape)} {flags.dtype}; pass the env's termination flags")

    def _step(self, tensordict: TensorDictBase, next_tensordict: TensorDictBase) -> TensorDictBase:
        if not self._checked:
            if self.zero_on_terminated:
                self._check_terminated(next_tensordict)
            self._check_signals(tensordict, next_tensordict)  # before the kernels read them
            self._check_terms(tensordict, next_tensordict)  # once, eagerly: clear errors before any compilation
            self._checked = True
        if self.compile and self._compiled is None:
            self._compiled = torch.compile(self._weighted_terms, dynamic=False)
        stacked = (self._compiled or self._weighted_terms)(tensordict, next_tensordict)
        next_tensordict.set(self.reward_key, stacked.sum(-1, keepdim=True))
        for name, value in zip(self.names, stacked.split(1, dim=-1)):
            next_tensordict.set((self.terms_key, name), value)
        return next_tensordict

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        check_specs_once(self)
        zeros = torch.zeros(
            (*tensordict_reset.batch_size, 1), dtype=torch.float32, device=tensordict_reset.device
        )
        for name in self.names:
            tensordict_reset.set((self.terms_key, name), zeros.clone())
        return tensordict_reset

    def transform_observation_spec(self, observation_spec: Composite) -> Composite:
        self._check_single_reward()
        for t in transforms_before(self):
            if isinstance(t, RewardSum) and self.reward_key in t.in_keys:
                # The bare env's reward is 0 by design: a sum taken in front of this transform sums zeros.
                raise ValueError(f"{type(t).__name__} comes before TaskReward, so it sums the bare env's reward (0 by "
                                 "design); put it after TaskReward")
        available = set(observation_spec.keys(True, True))
        if self.kick_relax is not None and not set(KickRelax.KEYS) <= available:
            # An env without kicks (env.pushes.count 0: no kick_age / kick_speed) has nothing to relax, e.g. a
            # robust preset's policy in a gait test's kick-free case: the reward is the unrelaxed one.
            self.kick_relax = None
            self._relaxed.zero_()
        for t in self.terms:
            missing = [k for k in (*t.root_keys, *t.next_keys) if k not in available]
            if missing:
                # A signal the env reports only with one of its options on: name the option.
                options = [f"{k!r} only with its option {SIGNALS[k].requires!r} on" for k in missing
                           if isinstance(k, str) and k in SIGNALS and SIGNALS[k].requires]
                raise KeyError(
                    f"reward term {t.name!r} reads {missing}, which the environment does not provide; "
                    + (f"the env reports {', '.join(options)}; " if options else "")
                    + "drop the term, or add the signal to the env (see docs/concepts/env-and-signals.md)"
                )
        batch = tuple(observation_spec.shape)
        for reader, key, want, _ in self._signal_reads():
            got = tuple(observation_spec[key].shape)
            if got != (*batch, *want):
                raise ValueError(_wrong_shape(reader, key, want, f"the environment's spec has {got}"))
        terms_spec = Composite(
            {n: Unbounded(shape=(*batch, 1), dtype=torch.float32, device=observation_spec.device) for n in self.names},
            shape=batch,
            device=observation_spec.device,
        )
        observation_spec[self.terms_key] = terms_spec
        return observation_spec

    def _check_single_reward(self) -> None:
        """Refuse a second TaskReward writing this one's reward or terms key: appended to the default chain
        (``env.append_transform(TaskReward([my_term]))``) it replaced the reward with the new term alone, and the terms'
        spec with the new term's, while the earlier terms were still computed and logged as if they counted."""
        for t in transforms_before(self):
            if isinstance(t, TaskReward) and (t.reward_key == self.reward_key or t.terms_key == self.terms_key):
                raise ValueError(f"a second TaskReward ({list(self.names)}) comes after one of terms {list(t.names)} "
                                 f"and would replace its {self.reward_key!r}; give one TaskReward all the terms, e.g. "
                                 "make_env(reward_terms=(*REFERENCE_TERMS, my_term)) or "
                                 "default_transforms(reward_terms=...) (docs/extending.md)")

    def transform_reward_spec(self, reward_spec: Composite) -> Composite:
        if self.reward_key not in reward_spec.keys(True, True):
            reward_spec[self.reward_key] = Unbounded(
                shape=(*reward_spec.shape, 1), dtype=torch.float32, device=reward_spec.device
            )
        return reward_spec

    def __repr__(self) -> str:
        inner = ", ".join(f"{t.name}={t.weight:g}" for t in self.terms)
        relax = "" if self.kick_relax is None else f", kick_relax={self.kick_relax}"
        return f"{type(self).__name__}({inner}, zero_on_terminated={self.zero_on_terminated}{relax})"


def _wrong_shape(reader: str, key: str, want: tuple[int, ...], got: str) -> str:
    fix = "fix the env signal" + (" or use a term written for it" if reader.startswith("reward term") else "")
    return (f"{reader} expects {key!r} of shape {('num_envs', *want)} (docs/concepts/env-and-signals.md), but {got}; "
            f"{fix}")
