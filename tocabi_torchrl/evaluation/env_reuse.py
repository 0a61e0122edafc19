"""One test env for many policies: its transform state as built, put back before each policy.

A checkpoint's transform state loads leniently (a resumed run may add transforms, ``apply_checkpoint``), so in an env
kept for the next policy a buffer that a checkpoint lacks (one saved without its env, say) would keep what the policy
before it loaded (its fixed normaliser statistics, say), and a running normaliser would look trained to a policy
given none. An evaluation that reuses an env keeps it under a key with :func:`build_sections` (so that a policy of
another config never meets it), calls :func:`remember_built_state` once when it builds it and
:func:`restore_built_state` before each policy.

>>> import torch
>>> class Env:  # stands in for a TransformedEnv: only its ``transform`` is read
...     transform = torch.nn.Linear(1, 1)
>>> env = Env()
>>> with torch.no_grad():
...     _ = env.transform.bias.fill_(1.0)
>>> remember_built_state(env)
>>> with torch.no_grad():
...     _ = env.transform.bias.fill_(5.0)  # a policy's checkpoint loaded into the env
>>> restore_built_state(env)
>>> env.transform.bias.tolist()
[1.0]
"""
from __future__ import annotations

import json

from ..tree import to_dict

#: The attribute the env keeps its built transform state in.
_BUILT_STATE = "_built_transform_state"


def remember_built_state(env) -> None:
    """Keep a copy of ``env.transform``'s state as it is now (right after building the env), on the env."""
    setattr(env, _BUILT_STATE, {k: v.clone() for k, v in env.transform.state_dict().items()})


def restore_built_state(env) -> None:
    """Put ``env.transform``'s state back to the copy :func:`remember_built_state` kept (nothing for an env without
    one), in place: buffers are copied into, so their storage, which a captured step graph reads, stays."""
    built = getattr(env, _BUILT_STATE, None)
    if built is not None:
        env.transform.load_state_dict(built)


def build_sections(cfg) -> str:
    """What building a run config's env reads (its ``env`` and ``transforms`` sections, the privileged critic's
    observation and the assist's sensed joints), as a string for a cache key: a policy of another control mode,
    observation or normalisation never meets an env built for another (a PD policy run in a torque env falls)."""
    return json.dumps({"env": to_dict(cfg.env), "transforms": to_dict(cfg.transforms),
                       "ppo": [cfg.ppo.critic_privileged, cfg.ppo.assist_pd_sensed]}, sort_keys=True)
