"""Environment throughput against raw mujoco-warp stepping of the same model, in one process.

    python -m benchmarks.env_throughput --num_envs 1024 4096 16384 --steps 200

Policy steps/s, legs PD-held on the initial pose (torque mode): raw mujoco-warp (``common.raw_stepper``), bare
``TocabiWalk.step``, ``make_env``'s transformed step (observation history, normalisation, reward terms), and the
collectors' ``step_and_maybe_reset`` eager and captured as a CUDA graph. Targets: env / raw >= 0.9 at 4096, the
transforms' share of the env step <= 10 %.
"""

from __future__ import annotations

import argparse
import gc

import torch

from . import common

NAME = "env_throughput"


def _rate(steps: int, device: str, transformed: bool, autoreset: bool = False, **kwargs) -> tuple[float, object]:
    from tocabi_torchrl import make_env
    from tocabi_torchrl.envs import TocabiWalk

    build = make_env if transformed else TocabiWalk
    env = build(device=device, seed=0, max_episode_steps=10**6, **kwargs)
    rate = common.env_rate(env, steps, autoreset=autoreset)
    if kwargs.get("cuda_graph") and not env.graph_captured:
        raise RuntimeError("the step was not captured as a CUDA graph (see the warning above)")
    upright = float((getattr(env, "base_env", env).sim.base_pos[:, 2] > 0.8).float().mean())
    del env
    gc.collect()
    if device == "cuda":
        torch.cuda.empty_cache()
    return rate, upright


def measure(n: int, steps: int, raw_steps: int, device: str, backend: str = "auto") -> dict:
    raw = common.raw_policy_steps_per_second(n, raw_steps, device) if raw_steps else None
    bare, upright = _rate(steps, device, False, num_envs=n, backend=backend)
    transformed, _ = _rate(steps, device, True, num_envs=n, backend=backend)
    modes = (False, True) if device == "cuda" else (False,)  # the graph needs CUDA
    auto = [_rate(steps, device, True, True, num_envs=n, backend=backend, cuda_graph=g)[0] for g in modes]
    ratio = (lambda x: x / raw) if raw else (lambda x: None)
    return {"num_envs": n, "raw_policy_steps_per_s": raw, "env_steps_per_s": bare, "make_env_steps_per_s": transformed,
            "autoreset_steps_per_s": auto[0], "autoreset_graph_steps_per_s": auto[-1] if len(auto) > 1 else None,
            "env_over_raw": ratio(bare), "make_env_over_raw": ratio(transformed), "autoreset_over_raw": ratio(auto[0]),
            "autoreset_graph_over_raw": ratio(auto[1]) if len(auto) > 1 else None,
            "transform_share_of_env_step": bare / transformed - 1.0, "upright_fraction_after_run": upright}


def render(data: dict, out) -> str:
    f3 = lambda x: common.fmt(x, ".3f")
    rows = [(r["num_envs"], common.fmt(r["raw_policy_steps_per_s"]), common.fmt(r["env_steps_per_s"]),
             f3(r["env_over_raw"]), common.fmt(r["make_env_steps_per_s"]), f3(r["make_env_over_raw"]),
             f"{100 * r['transform_share_of_env_step']:.1f} %", f3(r["autoreset_over_raw"]),
             f3(r["autoreset_graph_over_raw"])) for r in data["results"]]
    plt = common.pyplot()
    if plt is not None:
        fig, ax = plt.subplots(figsize=(7, 4))
        x = range(len(rows))
        for i, (key, label) in enumerate((("raw_policy_steps_per_s", "raw mujoco-warp"),
                                          ("env_steps_per_s", "TocabiWalk"), ("make_env_steps_per_s", "make_env"))):
            ax.bar([k + (i - 1) * 0.27 for k in x], [(r[key] or 0) / 1e3 for r in data["results"]], 0.27, label=label)
        ax.set_xticks(list(x), [str(r["num_envs"]) for r in data["results"]])
        ax.set(xlabel="parallel envs", ylabel="policy steps/s (thousands)")
        ax.legend()
        common.save(fig, out / f"{NAME}.png")
    return common.page("Environment throughput", data, common.table(
        ("envs", "raw policy steps/s", "TocabiWalk steps/s", "env / raw", "make_env steps/s", "make_env / raw",
         "transforms' share of env step", "step_and_maybe_reset / raw (eager)", "(CUDA graph)"), rows)
        + f"\n\n![env throughput]({NAME}.png)")


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--num_envs", type=int, nargs="+", default=[1024, 4096, 16384])
    parser.add_argument("--steps", type=int, default=200)
    parser.add_argument("--raw_steps", type=int, default=200, help="raw mujoco-warp steps timed (0: skip)")
    parser.add_argument("--device", default="cuda", help="cuda, or cpu for a smoke run of the script")
    parser.add_argument("--backend", default="auto", choices=("auto", "warp", "mujoco"),
                        help="physics backend; on the CPU, mujoco (C MuJoCo threads) against warp compares the two")
    parser.add_argument("--out", default=str(common.DOCS))
    args = parser.parse_args(argv)
    results = [measure(n, args.steps, args.raw_steps, args.device, args.backend) for n in args.num_envs]
    print(common.publish(args.out, NAME, {"meta": common.meta(NAME, argv, args.device), "results": results}, render))


if __name__ == "__main__":
    main()
