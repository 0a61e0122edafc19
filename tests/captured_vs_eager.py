"""One GPU check shared by the control-mode tests: an env built with ``cuda_graph=True`` replays the same steps as
an eager one (same seed, same random actions) and never synchronises with the host after the warm-up steps."""

from __future__ import annotations

from collections.abc import Callable, Sequence

import torch


def assert_captured_equals_eager(make_kwargs: dict, keys: Sequence[str], steps: int = 12, warmup: int = 3,
                                 before_step: Callable[[int, object, object], None] | None = None) -> None:
    """Step an eager and a graphed ``make_env(**make_kwargs)`` side by side with the same actions (uniform in
    ±0.05) and compare ``keys`` of each step's ``next`` (rtol/atol 1e-3); from step ``warmup`` on, any host sync
    raises (``torch.cuda.set_sync_debug_mode("error")``). ``before_step(i, eager, graphed)`` runs before step i
    (e.g. to change a device scalar between replays). Asserts the graph was captured."""
    from tocabi_torchrl import make_env

    n = make_kwargs["num_envs"]
    eager, graphed = make_env(cuda_graph=False, **make_kwargs), make_env(cuda_graph=True, **make_kwargs)
    gen = torch.Generator(device="cuda").manual_seed(0)
    td_e, td_g = eager.reset(), graphed.reset()
    for i in range(steps):
        if before_step is not None:
            before_step(i, eager, graphed)
        action = (torch.rand(n, 13, device="cuda", generator=gen) * 2 - 1) * 0.05
        if i >= warmup:
            torch.cuda.set_sync_debug_mode("error")
        try:
            out_e, td_e = eager.step_and_maybe_reset(td_e.set("action", action))
            out_g, td_g = graphed.step_and_maybe_reset(td_g.set("action", action.clone()))
        finally:
            torch.cuda.set_sync_debug_mode(0)
        for key in keys:
            torch.testing.assert_close(out_g["next", key], out_e["next", key], rtol=1e-3, atol=1e-3,
                                       msg=lambda m, i=i, key=key: f"step {i}, {key}: {m}")
    assert graphed.graph_captured
