"""The base class of the transforms whose reset output is computed like a step's."""

from __future__ import annotations

import weakref

from tensordict import TensorDictBase
from torchrl.envs.transforms import Compose, Transform

__all__ = ["CallOnReset", "check_specs_once", "flatten_chain", "transforms_after", "transforms_before"]


def parent_of(transform: Transform):
    """``transform.parent`` (the env in front of it, or None), with a message for a ``Compose`` inside another
    ``Compose``, where torchrl's lookup fails with a bare ``IndexError``."""
    try:
        return transform.parent
    except IndexError as err:
        raise ValueError(f"{type(transform).__name__} sits in a Compose nested inside another Compose, where torchrl "
                         "cannot find the env in front of it; flatten the chain, e.g. Compose(*default_transforms(), "
                         "MyTransform()), or add to an env with env.append_transform(MyTransform())") from err


def transforms_before(transform: Transform) -> list[Transform]:
    """The transforms in front of ``transform`` in its env's chain (nested ``Compose`` flattened); empty when it
    belongs to no env. For checks of a transform's place in the chain."""
    return flatten_chain([getattr(parent_of(transform), "transform", None)])


def flatten_chain(transforms) -> list[Transform]:
    """``transforms`` (transforms or ``Compose``, ``None`` skipped) as one flat list, in order."""
    found = []
    for t in transforms:
        if t is not None:
            found.extend(flatten_chain(t.transforms) if isinstance(t, Compose) else [t])
    return found


def transforms_after(transform: Transform) -> list[Transform]:
    """The transforms behind ``transform`` in its env's chain, in order, nested ``Compose`` flattened; empty when it
    belongs to no env (torchrl's ``container`` of a ``Compose`` outside an env raises). For checks of a
    transform's place in the chain."""
    try:
        box = transform.container  # the env, for a transform anywhere in an env's chain
    except ValueError:  # in no Compose nor env
        return []
    chain = flatten_chain([box if isinstance(box, Compose) else getattr(box, "transform", None)])
    index = next((i for i, t in enumerate(chain) if t is transform), None)
    return [] if index is None else chain[index + 1:]


def _env_of(container):
    """The env a transform's container stands for: the container itself, or the env of the ``Compose`` it is in
    (None while the ``Compose`` is in none)."""
    if isinstance(container, Compose):
        ref = container.__dict__.get("_container")
        return ref() if ref is not None else None
    return container


def check_specs_once(transform: Transform) -> None:
    """Run ``transform``'s spec checks against what the env in front of it provides, once, at its first reset.

    TorchRL computes specs lazily, so a chain built by hand (a transform in the wrong place, a misspelt key, a layout
    that does not fit) would reach the transform's first reset before anything read its specs, and fail there on a
    missing key with a bare ``TypeError``; the spec checks (``_checks.require_spec``) name the problem and the fix.
    A host flag: nothing reads the device."""
    if getattr(transform, "_specs_checked", False):
        return
    parent = parent_of(transform)
    if parent is not None:
        transform.transform_observation_spec(parent.observation_spec.clone())
    transform._specs_checked = True


class CallOnReset(Transform):
    """A :class:`~torchrl.envs.transforms.Transform` that writes its outputs into the reset tensordict too.

    TorchRL's default ``_reset`` leaves the reset tensordict alone, so the first observation of an episode would lack
    the keys the transform adds. A subclass of this one applies its ``_call`` there as well: the reset state gets the
    same keys, computed the same way, as every step.
    """

    def set_container(self, container) -> None:
        # torchrl's Compose.set_container takes a chain from the env it belongs to when it is given to a second
        # TransformedEnv, without a word: both envs then run one chain, and with equal batch sizes one env's resets
        # fill the other's history. Refused here (the chain is put back first: the refusal leaves the first env as it
        # was); a chain its env has let go of (env.transform = other) may go to another.
        env = _env_of(container)
        owner_ref = self.__dict__.get("_owner_env")
        owner = owner_ref() if owner_ref is not None else None
        taken = owner is not None and env is not None and owner is not env
        if taken and getattr(owner, "_transform", None) is container:
            container.set_container(owner)  # torchrl cleared the chain's containers all the way down: put them back
            raise RuntimeError(f"this transform chain ({type(self).__name__} in it) belongs to another env already: "
                               "one chain holds one env's state (the history of its observations); build one chain "
                               "per env, e.g. default_transforms() for each, or transform.clone()")
        super().set_container(container)
        if env is not None:
            self.__dict__["_owner_env"] = weakref.ref(env)

    def clone(self):
        copy = super().clone()
        copy.__dict__.pop("_owner_env", None)  # a clone belongs to no env yet
        return copy

    def __getstate__(self):
        state = super().__getstate__()
        state.pop("_owner_env", None)  # a weak reference cannot be pickled; an unpickled copy belongs to no env yet
        return state

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        if "_owner_env" not in self.__dict__:  # a copy (deepcopy, pickle) belongs to the env that first resets it
            ref = self.__dict__.get("_container")
            env = _env_of(ref()) if ref is not None else None
            if env is not None:
                self.__dict__["_owner_env"] = weakref.ref(env)
        check_specs_once(self)
        guards = self.__dict__.get("_guards_chain")
        if guards is None:  # one transform per chain checks its env below on every reset: the first of this kind
            guards = self._guards_chain = not any(isinstance(t, CallOnReset) for t in transforms_before(self))
        parent = parent_of(self) if guards else None
        if parent is not None and parent.batch_size != tensordict_reset.batch_size:
            # torchrl moves a Compose given to a second TransformedEnv there without a word; the first env then
            # fails inside torchrl's StepCounter with a shape error. (Sizes only: no device read.)
            raise RuntimeError(f"{type(self).__name__} belongs to another env now (batch {tuple(parent.batch_size)}, "
                               f"this reset's {tuple(tensordict_reset.batch_size)}): a transform chain was given to "
                               "a second TransformedEnv; build one chain per env, e.g. default_transforms() for each")
        return self._call(tensordict_reset)
