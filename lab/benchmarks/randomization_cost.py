"""What a preset's randomisation and perturbations cost in training: its throughput with them against the same preset
without them, in one run (issue "Robust walking": >= 0.95x).

    python -m lab.benchmarks.randomization_cost --preset robust --num_envs 4096 --rounds 2

Each round measures two variants, each in a fresh child process of ``train_throughput`` (the steady training rate
after ``--warmup`` iterations, then the raw mujoco-warp ceiling of standing robots): ``on``, the preset as committed
but with its kicks at full strength from the first step (``ppo.push_ramp=0 0``: a run of a few iterations would
otherwise end before its curriculum lets a kick through; a ``--set ppo.push_ramp`` applies instead), and ``off``,
the same with every piece of :data:`OFF` at its identity (actuator layer, dynamics, sensor biases and noise, pushes,
diverse starts). The order alternates by round (on, off, then off, on, ...), so that neither variant always runs
first and a drift of the GPU's clocks hits both. Each round trains its own seed (``--seeds``; round r the seed r − 1
by default), the same for every variant of the round: the first iterations of a run are a few seconds of robots
flailing under one initial policy, and how hard their physics is to solve depends on that policy (on an H200 at
4,096 envs, one round each of seeds 0-4 gave 0.941-0.956 for the same preset,
docs/benchmarks/randomization/delay_average_cost). Reports every measurement, each round's ratio, and their median.
``--pieces dynamics sensors ...`` also measures ``off`` with each named piece switched on alone (``off+<piece>``),
to see which piece costs what. ``--physics`` also measures each variant's physics alone (``solver_load`` in a child
process: the trainer's steps run eagerly, timed, with the solver iterations of the slowest world), to tell what of
the cost is the physics of kicked, randomised robots and what the rest of the step.

The report goes to ``<out>/<name>.{json,md}``; one that is there already (the committed one, or the previous variant's
of a series of ``--set`` measurements) is refused before anything is measured unless ``--overwrite``: give each
measurement its own ``--name``.
"""

from __future__ import annotations

import argparse
import statistics

from . import common

NAME = "randomization_cost"

#: Every randomisation and perturbation piece at its identity, as ``--set`` items of the training config.
OFF = ("env.control.actuators.delay_substeps=0 0", "env.control.actuators.delay_stride=1",
       "env.control.actuators.delay_average=false", "env.control.actuators.motor_constant=1 1",
       "env.dynamics.mass_scale=1 1", "env.dynamics.joint_damping=0 0", "env.dynamics.armature_scale=1 1",
       "env.dynamics.friction_scale=1 1", "transforms.sensor_noise.joint_pos_bias=0",
       "transforms.sensor_noise.joint_pos_noise_std=0", "transforms.sensor_noise.joint_vel_noise_std=0",
       "transforms.sensor_noise.base_rpy_bias=0", "transforms.sensor_noise.foot_force_bias=0",
       "transforms.sensor_noise.foot_torque_bias=0", "env.pushes.count=0", "env.task.start_joint_vel_std=0",
       "env.task.start_base_vel_std=0")
#: The kicks at full strength from the first step (see the module docstring).
FULL_KICKS = ("ppo.push_ramp=0 0",)
#: The pieces ``--pieces`` can switch on alone over ``off``, each by the :data:`OFF` items (path prefixes) it owns.
PIECES = {"actuators": ("env.control.actuators.",), "dynamics": ("env.dynamics.",),
          "sensors": ("transforms.sensor_noise.",), "pushes": ("env.pushes.",), "starts": ("env.task.start_",)}


def variants(preset: str, extra: list[str], pieces: tuple[str, ...] = ()) -> dict[str, list[str]]:
    """``--set`` items of each variant: ``on``, ``off``, and ``off+<piece>`` for each of ``pieces`` (``off`` with
    that piece as the preset sets it)."""
    unknown = [name for name in pieces if name not in PIECES]
    if unknown:
        raise ValueError(f"unknown piece(s) {unknown}; choose from {list(PIECES)}")
    # The user's items after FULL_KICKS: a --set ppo.push_ramp applies in every variant (it was replaced, unsaid).
    base = [f"preset={preset}", *FULL_KICKS, *extra]
    out = {"on": [*base], "off": [*base, *OFF]}
    for name in pieces:
        kept = [item for item in OFF if not item.startswith(PIECES[name])]
        out[f"off+{name}"] = [*base, *kept]
    return out


def render(data: dict, out) -> str:
    rows = [(r["round"], r.get("seed", 0), r["variant"], common.fmt(r.get("train_env_steps_per_s")),
             common.fmt(r.get("raw_policy_steps_per_s")), common.fmt(r.get("ratio_train_over_raw"), ".2f"))
            for r in data["results"]]
    s = data["summary"]
    body = common.table(("round", "seed", "variant", "train env-steps/s", "raw mujoco-warp policy steps/s",
                         "train / raw"), rows)
    rounds = s.get("round_on_over_off")
    per_round = (" Per round, on / off of the same seed: " + ", ".join(f"{x:.3f}" for x in rounds)
                 + "; their median is the ratio.") if rounds else ""
    body += (f"\n\nMedian training rate: on {common.fmt(s['on_median'])}, off {common.fmt(s['off_median'])} "
             f"env-steps/s; on / off = **{s['on_over_off']:.3f}** (the target is >= 0.95).{per_round}\n")
    for name, ratio in s.get("piece_over_off", {}).items():
        body += f"- {name} alone over off: {ratio:.3f}\n"
    if data.get("physics"):
        rows = [(name, common.fmt(p["ms_per_policy_step"], ".3f"), common.fmt(p["niter_max_over_worlds"], ".2f"),
                 common.fmt(p["niter_mean"], ".2f"), common.fmt(p["niter_max_seen"], ".0f"),
                 common.fmt(p["constraint_rows_per_world"], ".1f"), common.fmt(p["contacts_per_world"], ".1f"))
                for name, p in data["physics"].items()]
        body += ("\n### The physics alone (solver_load, eager steps)\n\n"
                 + common.table(("variant", "physics ms per policy step", "solver iterations, slowest world",
                                 "mean over worlds", "most seen", "constraint rows per world", "contacts per world"),
                                rows)
                 + f"\n\nPhysics time off / on = **{s['physics_off_over_on']:.3f}** (the on / off ratio if everything "
                   "but the physics cost the same in both).\n")
    return common.page("What randomisation costs in training", data, body)


def _measure(module: str, args, raw_steps: int, run_name: str, items: list[str]) -> dict:
    """One variant (``items``) measured by benchmark ``module`` in a child process of its own."""
    return common.run_child(module, [
        "--num_envs", str(args.num_envs), "--iterations", str(args.iterations), "--warmup", str(args.warmup),
        "--raw_steps", str(raw_steps), "--device", args.device, "--run_dir", f"{args.run_dir}/{run_name}",
        "--set", *items])


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--preset", default="robust", help="the training preset whose randomisation is measured")
    p.add_argument("--num_envs", type=int, default=4096, help="robots (parallel envs) of every measurement")
    p.add_argument("--rounds", type=int, default=2, help="alternating on/off measurements of each variant")
    p.add_argument("--iterations", type=int, default=10, help="timed PPO iterations per measurement")
    p.add_argument("--warmup", type=int, default=3, help="untimed PPO iterations before the timed ones")
    p.add_argument("--raw_steps", type=int, default=200, help="raw mujoco-warp steps timed per measurement (0: skip)")
    p.add_argument("--set", nargs="*", default=[], metavar="PATH=VALUE", help="more overrides, for both variants")
    p.add_argument("--seeds", type=int, nargs="*", default=None,
                   help="the training seed of each round, one per round (default: 0, 1, ... --rounds - 1)")
    p.add_argument("--pieces", nargs="*", default=[], choices=list(PIECES),
                   help="also measure off with each of these pieces switched on alone (off+<piece>)")
    p.add_argument("--physics", action="store_true",
                   help="also measure each variant's physics alone (solver_load: eager steps, solver iterations)")
    p.add_argument("--device", default="cuda", help="cuda, or cpu for a smoke run of the script")
    p.add_argument("--run_dir", default="/tmp/tocabi_bench_runs", help="scratch folder of the training runs")
    p.add_argument("--out", default=str(common.DOCS / "randomization"),
                   help="folder of the report <name>.json and .md (default: docs/benchmarks/randomization; "
                        "a CPU measurement goes to runs/benchmarks_cpu/randomization instead)")
    p.add_argument("--name", default=NAME, help=f"the report's file name, <out>/<name>.json (default: {NAME})")
    p.add_argument("--overwrite", action="store_true", help="replace a report <out>/<name>.json that exists already")
    args = p.parse_args(argv)
    if args.rounds < 1 or args.num_envs < 1:
        p.error(f"--rounds and --num_envs take values >= 1, got {args.rounds} and {args.num_envs}")
    if any(item.partition("=")[0].strip() == "seed" for item in args.set):
        p.error("set the rounds' seeds with --seeds, not --set seed=...")
    seeds = list(range(args.rounds)) if args.seeds is None else args.seeds
    if len(seeds) != args.rounds:
        p.error(f"--seeds takes one seed per round: {args.rounds} round(s), got {len(seeds)} seed(s)")
    sets = variants(args.preset, args.set, tuple(args.pieces))
    common.parse_overrides(args.set)  # an option the user gave twice is said once, here
    for items in sets.values():
        # A bad path or value fails here, before any measurement. ``off`` replaces the user's randomisation
        # settings on purpose (its identity items come last): no warning for those.
        common.parse_overrides(items, warn_repeats=False)
    out = common.report_dir(args.out, args.device)
    taken = [out / f"{args.name}.{ext}" for ext in ("json", "md") if (out / f"{args.name}.{ext}").exists()]
    if taken and not args.overwrite:
        # Minutes of measurement would otherwise replace the committed report, or a series of --set variants each
        # the one before it, unsaid.
        p.error(f"{taken[0]} exists; pass --overwrite to replace it, or --name another name (or --out "
                "another folder)")
    results = []
    for r, seed in enumerate(seeds):
        for name in (list(sets) if r % 2 == 0 else list(sets)[::-1]):
            items = [*sets[name], f"seed={seed}"]
            record = _measure("train_throughput", args, args.raw_steps, f"{args.name}_{name}", items)
            results.append({"round": r + 1, "seed": seed, "variant": name, "set": items, **record})
            print(f"round {r + 1} (seed {seed}) {name}: {record.get('train_env_steps_per_s') or 0:,.0f} env-steps/s",
                  flush=True)
    rate = {(x["round"], x["variant"]): x["train_env_steps_per_s"] for x in results}

    def paired(variant: str, over: str) -> list[float]:
        """Each round's ratio of two variants' rates (same seed, same round)."""
        return [rate[(r + 1, variant)] / rate[(r + 1, over)] for r in range(len(seeds))]

    median = {v: statistics.median(x["train_env_steps_per_s"] for x in results if x["variant"] == v) for v in sets}
    summary = {"on_median": median["on"], "off_median": median["off"], "round_on_over_off": paired("on", "off"),
               "on_over_off": statistics.median(paired("on", "off"))}
    if args.pieces:
        summary["piece_over_off"] = {name: statistics.median(paired(f"off+{name}", "off")) for name in args.pieces}
    physics = {}
    if args.physics:
        for name, items in sets.items():
            items = [*items, f"seed={seeds[0]}"]
            physics[name] = _measure("solver_load", args, 1, f"{args.name}_{name}_physics", items)["training"]
            print(f"physics {name}: {physics[name]['ms_per_policy_step']:.3f} ms per policy step", flush=True)
        summary["physics_off_over_on"] = physics["off"]["ms_per_policy_step"] / physics["on"]["ms_per_policy_step"]
    meta = common.meta(NAME, argv, args.device, preset=args.preset, num_envs=args.num_envs, rounds=args.rounds,
                       seeds=seeds)
    data = {"meta": meta, "summary": summary, "results": results, **({"physics": physics} if physics else {})}
    # Without --overwrite, nor over a report that appeared during the measurement.
    print(common.publish(out, args.name, data, render, replace=args.overwrite))


if __name__ == "__main__":
    main()
