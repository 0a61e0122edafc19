"""Environment throughput against raw mujoco-warp stepping of the same model, in one process.

    python -m lab.benchmarks.env_throughput --num_envs 1024 4096 16384 --steps 200

Policy steps/s, legs PD-held: raw mujoco-warp, bare ``TocabiWalk.step``, ``make_env``'s transformed step, and the
collectors' ``step_and_maybe_reset`` eager and as a CUDA graph. Targets: env / raw >= 0.9 at 4096; transforms <= 10 %
of the env step. On the CPU, ``--backend mujoco`` against ``--backend warp`` compares the two physics backends.
``--reset_pass reduced --name env_throughput_reduced`` measures the reduced reset pass (only the collectors' rows
reset worlds) beside the committed full-pass report.
"""

from __future__ import annotations

import argparse
import gc

import torch

from tocabi_torchrl.sim import RESET_PASSES

from . import common

NAME = "env_throughput"


def _rate(steps: int, transformed: bool, autoreset: bool = False, **kwargs) -> tuple[float, float]:
    from tocabi_torchrl import make_env
    from tocabi_torchrl.envs import TocabiWalk

    env = (make_env if transformed else TocabiWalk)(seed=0, max_episode_steps=10**6, control_mode="torque", **kwargs)
    rate = common.env_rate(env, steps, autoreset=autoreset)
    if kwargs.get("cuda_graph") and not env.graph_captured:
        raise RuntimeError("the step was not captured as a CUDA graph (see the warning above)")
    upright = float((getattr(env, "base_env", env).sim.base_pos[:, 2] > 0.8).float().mean())
    del env
    gc.collect()
    torch.cuda.empty_cache()
    return rate, upright


def measure(n: int, steps: int, raw_steps: int, device: str, backend: str, reset_pass: str = "full") -> dict:
    raw = common.raw_policy_steps_per_second(n, raw_steps, device) if raw_steps else None
    kw = {"num_envs": n, "device": device, "backend": backend, "reset_pass": reset_pass}
    (bare, upright), (transformed, _) = _rate(steps, False, **kw), _rate(steps, True, **kw)
    auto = [_rate(steps, True, True, cuda_graph=g, **kw)[0] for g in ((False, True) if device == "cuda" else (False,))]
    auto += [None] * (2 - len(auto))  # the graph needs CUDA
    ratio = lambda x: x / raw if raw and x else None
    return {"num_envs": n, "backend": backend, "reset_pass": reset_pass, "raw_policy_steps_per_s": raw,
            "env_steps_per_s": bare,
            "make_env_steps_per_s": transformed, "autoreset_steps_per_s": auto[0], "env_over_raw": ratio(bare),
            "autoreset_graph_steps_per_s": auto[1], "make_env_over_raw": ratio(transformed),
            "autoreset_over_raw": ratio(auto[0]), "autoreset_graph_over_raw": ratio(auto[1]),
            "transform_share_of_env_step": bare / transformed - 1.0, "upright_fraction_after_run": upright}


def render(data: dict, out) -> str:
    res, f3 = data["results"], lambda x: common.fmt(x, ".3f")
    n = [r["num_envs"] for r in res]
    name = data["meta"].get("name", NAME)
    common.plot(out / f"{name}.png", [{"lines": {label: (n, [r[key] for r in res]) for key, label in (
        ("raw_policy_steps_per_s", "raw mujoco-warp"), ("env_steps_per_s", "TocabiWalk"),
        ("make_env_steps_per_s", "make_env")) if res[0][key]}, "xscale": "log", "xlabel": "parallel envs",
        "ylabel": "policy steps/s"}])
    return common.page("Environment throughput", data, common.table(
        ("envs", "raw policy steps/s", "TocabiWalk steps/s", "env / raw", "make_env steps/s", "make_env / raw",
         "transforms' share of env step", "step_and_maybe_reset / raw (eager)", "(CUDA graph)"),
        [(r["num_envs"], common.fmt(r["raw_policy_steps_per_s"]), common.fmt(r["env_steps_per_s"]),
          f3(r["env_over_raw"]), common.fmt(r["make_env_steps_per_s"]), f3(r["make_env_over_raw"]),
          f"{100 * r['transform_share_of_env_step']:.1f} %", f3(r["autoreset_over_raw"]),
          f3(r["autoreset_graph_over_raw"])) for r in res]) + f"\n\n![env throughput]({name}.png)")


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--num_envs", type=int, nargs="+", default=[1024, 4096, 16384],
                        help="robot counts, one measurement each (default: 1024 4096 16384)")
    parser.add_argument("--steps", type=int, default=200,
                        help="policy steps timed per env and step kind, after 10 untimed (default: 200)")
    parser.add_argument("--raw_steps", type=int, default=200, help="raw mujoco-warp steps timed (0: skip)")
    parser.add_argument("--device", default="cuda", help="cuda, or cpu (a smoke run, or the CPU backends)")
    parser.add_argument("--backend", default="auto", choices=("auto", "warp", "mujoco"), help="physics backend")
    parser.add_argument("--reset_pass", default="full", choices=RESET_PASSES, help="env.sim.reset_pass of the envs")
    parser.add_argument("--name", default=NAME, help="report name (<out>/<name>.json, .md, .png)")
    parser.add_argument("--out", default=str(common.DOCS), help="folder of the report (default: docs/benchmarks; "
                        "a CPU measurement goes to runs/benchmarks_cpu instead)")
    args = parser.parse_args(argv)
    if args.steps < 1 or args.raw_steps < 0 or min(args.num_envs) < 1:
        parser.error(f"--steps must be >= 1, --raw_steps >= 0 and --num_envs >= 1, got {args.steps}, "
                     f"{args.raw_steps} and {args.num_envs}")
    common.require_cuda(parser, args.device, "pass --device cpu for a CPU run (with --backend mujoco or warp)")
    results = [measure(n, args.steps, args.raw_steps, args.device, args.backend, args.reset_pass)
               for n in args.num_envs]
    data = {"meta": common.meta(NAME, argv, args.device, name=args.name), "results": results}
    print(common.publish(args.out, args.name, data, render, measured_on=args.device))


if __name__ == "__main__":
    main()
