"""Training throughput while the live viewer streams, against the same run's iterations without it (issue 52: the
streaming run keeps >= 0.97x).

    python -m lab.benchmarks.viewer_overhead --num_envs 4096 --iterations 24 --out /tmp/viewer_overhead
    python -m lab.benchmarks.viewer_overhead --device cpu --num_envs 8 --iterations 8 --warmup 2 --out /tmp/vo_cpu  # smoke

Each env count runs in a fresh process: the default preset with ``--viewer.enabled`` serving on ``--port`` (bound on
127.0.0.1; no browser is needed: the scene updates are sent to whoever connects), ``--worlds`` streamed every
``--every`` policy steps. After ``--warmup`` iterations (streaming) the stream is switched per iteration in ABBA
blocks (off, on, on, off, ...), so a slow drift of the rate falls on both sides equally; the page's drawing thread
keeps running throughout. The ratio is the streaming iterations' env steps per second over the others'. With
``--baseline`` (the default) a second process trains the same config without any viewer, a cross-check across
processes (noisier than the paired ratio). Writes ``<out>/viewer_overhead.{json,md}`` and ``viewer_overhead.png``
(each iteration's rate, by state).
"""

from __future__ import annotations

import argparse
import json
import shutil
from pathlib import Path

from . import common

NAME = "viewer_overhead"
#: The issue's requirement: training with the viewer streaming keeps at least this fraction of the rate without it.
REQUIRED_RATIO = 0.97


def streaming(iteration: int, warmup: int) -> bool:
    """Whether the stream runs during 1-based ``iteration``: always in the warm-up, then ABBA blocks (off, on, on,
    off, ...)."""
    k = iteration - warmup - 1
    return k < 0 or k % 4 in (1, 2)


def measure(n: int, iterations: int, warmup: int, device: str, run_dir: str, overrides: dict, viewer: dict) -> dict:
    """One training run of ``n`` envs in this process; ``viewer`` None: without the viewer (the baseline)."""
    from tocabi_torchrl.viewer import ViewerConfig
    from tocabi_torchrl.viewer.training import TrainingView

    mode = "baseline" if viewer is None else "alternating"
    cfg = common.run_config(n, warmup + iterations, overrides, run_dir, f"{NAME}_{mode}_{n}", device)
    shutil.rmtree(Path(run_dir) / cfg.name, ignore_errors=True)
    views: list = []
    replacements = {}
    if viewer is not None:
        cfg.viewer = ViewerConfig(enabled=True, host="127.0.0.1", **viewer)

        def live_view(cfg_, env):  # the trainer's own view, its stream switched as each iteration is logged
            view = TrainingView(cfg_.viewer, env.base_env.sim)
            publish = view.publish

            def publish_then_switch(iteration, metrics):
                publish(iteration, metrics)
                view.stream.active = streaming(iteration + 1, warmup)

            view.publish = publish_then_switch
            views.append(view)
            return view

        replacements["_live_view"] = live_view
    with common.trainer_patched(replacements, []):
        result, rows = common.train(cfg)
    walls = [float(r["wall_s"]) for r in rows]
    steps = [float(r["env_steps"]) for r in rows]
    per_it = []
    for i in range(1, len(rows)):  # the first iteration has no start mark of its own
        it = int(rows[i]["iteration"])
        on = viewer is not None and streaming(it, warmup)
        per_it.append({"iteration": it, "streaming": on, "seconds": walls[i] - walls[i - 1],
                       "env_steps": steps[i] - steps[i - 1]})
    timed = [r for r in per_it if r["iteration"] > warmup]

    def rate(sel):
        sel = list(sel)
        return sum(r["env_steps"] for r in sel) / sum(r["seconds"] for r in sel) if sel else None

    record = {"num_envs": n, "mode": mode, "overrides": overrides, "viewer": viewer, "iterations": result.iterations,
              "env_graph": result.env_graph, "per_iteration": per_it,
              "rate_all": rate(timed)}
    if viewer is not None:
        view = views[0]
        on, off = rate(r for r in timed if r["streaming"]), rate(r for r in timed if not r["streaming"])
        record.update(rate_streaming=on, rate_off=off, ratio=on / off if on and off else None,
                      copies=view.stream.copies, skipped=view.stream.skipped, frames_drawn=view.frames,
                      port=viewer["port"])
    return record


def render(data: dict, out) -> str:
    rows, panels = [], []
    for r in data["results"]:
        base = r.get("baseline")
        ratio_base = r["rate_streaming"] / base["rate_all"] if base and r.get("rate_streaming") else None
        rows.append([f"{r['num_envs']:,}", common.fmt(r["rate_off"]), common.fmt(r["rate_streaming"]),
                     common.fmt(r["ratio"], ".3f"), common.fmt(base and base["rate_all"]),
                     common.fmt(ratio_base, ".3f"), r["viewer"]["worlds"], r["viewer"]["every"],
                     f"{r['copies']:,}", f"{r['skipped']:,}", f"{r['frames_drawn']:,}",
                     "yes" if r["ratio"] and r["ratio"] >= REQUIRED_RATIO else "no"])
        on = [x for x in r["per_iteration"] if x["streaming"]]
        off = [x for x in r["per_iteration"] if not x["streaming"]]
        panels.append({"lines": {
            "streaming": ([x["iteration"] for x in on], [x["env_steps"] / x["seconds"] for x in on]),
            "not streaming": ([x["iteration"] for x in off], [x["env_steps"] / x["seconds"] for x in off])},
            "hlines": [(REQUIRED_RATIO * r["rate_off"], f"{REQUIRED_RATIO}x not streaming")] if r["rate_off"] else [],
            "xlabel": "iteration", "ylabel": "env steps / s", "title": f"{r['num_envs']:,} envs"})
    common.plot(Path(out) / f"{NAME}.png", panels, "training rate with and without the viewer streaming")
    table = common.table(["envs", "off [steps/s]", "streaming [steps/s]", "streaming / off", "no viewer [steps/s]",
                          "streaming / no viewer", "worlds", "every", "copies", "skipped", "frames drawn",
                          f">= {REQUIRED_RATIO}"], rows)
    body = f"""
Training iterations of one run alternate (ABBA blocks after the warm-up) between the live viewer streaming (a host
copy of `worlds` worlds' body poses every `every` policy steps, on a side CUDA stream; the page drawn at <= 30 fps
by its thread, no browser connected) and not streaming (the server and its thread still up). "no viewer" is a
separate process training the same config without any viewer. Requirement: streaming / off >= {REQUIRED_RATIO}.

{table}

![rates](./{NAME}.png)
"""
    return common.page("Live viewer: training throughput while streaming", data, body)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--num_envs", type=int, nargs="+", default=[4096],
                        help="robot counts, each measured in a fresh process (default: 4096)")
    parser.add_argument("--iterations", type=int, default=24, help="timed iterations (a multiple of 4: ABBA blocks)")
    parser.add_argument("--warmup", type=int, default=4, help="iterations first, streaming, not timed")
    parser.add_argument("--worlds", type=int, default=16, help="worlds streamed (viewer.worlds, <= 64)")
    parser.add_argument("--every", type=int, default=8, help="policy steps between copies (viewer.every)")
    parser.add_argument("--port", type=int, default=8080, help="port the viewer binds (on 127.0.0.1)")
    parser.add_argument("--baseline", action=argparse.BooleanOptionalAction, default=True,
                        help="also train the same config without any viewer, in another process")
    parser.add_argument("--set", nargs="*", default=[], metavar="FIELD=VALUE", help="config overrides")
    parser.add_argument("--device", default="cuda", help="cuda, or cpu for a smoke run of the script")
    parser.add_argument("--run_dir", default=f"/tmp/tocabi_bench_runs/{NAME}",
                        help=f"scratch folder of the training runs (default: /tmp/tocabi_bench_runs/{NAME})")
    parser.add_argument("--out", required=True, help="folder of viewer_overhead.{json,md,png}")
    parser.add_argument("--child", choices=("alternating", "baseline"), help="one run in this process (internal)")
    args = parser.parse_args(argv)
    if args.iterations < 4 or args.warmup < 1 or min(args.num_envs) < 1:
        parser.error("--iterations must be >= 4, --warmup >= 1 and --num_envs >= 1")
    common.require_cuda(parser, args.device, "pass --device cpu for a smoke run of the script")
    overrides = common.parse_overrides(args.set)
    viewer = {"port": args.port, "worlds": args.worlds, "every": args.every}
    if args.child:
        record = measure(args.num_envs[0], args.iterations, args.warmup, args.device, args.run_dir, overrides,
                         viewer if args.child == "alternating" else None)
        print("RESULT " + json.dumps(record), flush=True)  # what common.run_child reads
        return
    options = ["--iterations", str(args.iterations), "--warmup", str(args.warmup), "--worlds", str(args.worlds),
               "--every", str(args.every), "--port", str(args.port), "--device", args.device,
               "--run_dir", args.run_dir, "--out", args.out, "--set", *args.set]
    results = []
    for n in args.num_envs:
        record = common.run_child(NAME, ["alternating", "--num_envs", str(n), *options])
        if args.baseline:
            record["baseline"] = common.run_child(NAME, ["baseline", "--num_envs", str(n), *options])
        results.append(record)
        print(f"{n} envs: streaming / off = {common.fmt(record['ratio'], '.3f')}", flush=True)
    data = {"meta": common.meta(NAME, argv, args.device), "results": results}
    print(common.publish(args.out, NAME, data, render, measured_on=args.device))


if __name__ == "__main__":
    main()
