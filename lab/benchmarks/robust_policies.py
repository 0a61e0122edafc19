"""The robust gait test of several policies side by side (by default the three shipped policies trained on the
nominal robot, ``SHIPPED``; ``--policies`` replaces that list, so name the shipped ones too to test the robust one
beside them), one table.

    python -m lab.benchmarks.robust_policies --out docs/benchmarks/robust --overwrite
    python -m lab.benchmarks.robust_policies --policies runs/robust/checkpoints/best.pt --num_envs 1024

Each policy gets ``tocabi_torchrl.evaluation.robust`` (four cases of ``--num_envs`` robots, 8 s, one batch): its
``robust.json`` and ``robust.png`` go to ``<out>/<policy>/``, the table of every policy and case to
``<out>/robust_policies.{json,md,png}`` with the command, date and hardware, and the seconds each test took (the
policies of one kind share one test env, so the first one's seconds include its build; two policies of one file
name, e.g. two runs' ``latest.pt``, are told apart by their run folder's name; one checkpoint named twice is
refused). The table is written again after each policy, so a call stopped partway keeps the policies it finished
(marked partial). An ``--out`` that holds a table already is refused unless ``--overwrite``.
``--cases nominal commands`` runs those cases alone (the ``diverse`` verdict of ``time_to_walk``); a policy then
passes those cases, not the robust test. A case has the full test's start states and draws only when every case
before it in the test's order runs too (``nominal commands`` do, though the commands case's re-drawn commands
differ with the number of cases); another subset (``--cases nominal robust_1.0``) draws other robots of the same
distribution: a screen, not the verdict.
``--stop_on_fail`` tests the policies in the order given and stops after the first that does not pass: given a run's
marks from the last back (``wall_00720s.pt wall_00690s.pt ...``), it finds the earliest mark of the passing run of
marks at the end without testing the marks before a failure (the time-to-walk search; a mark before that failure
may pass again, untested). The table names the mark it stopped at.
"""

from __future__ import annotations

import argparse
import math
import time
from pathlib import Path

from . import common
from .page import kick_note

NAME = "robust_policies"
NUMBERS = {1: "one", 2: "two", 3: "three", 4: "four"}
SHIPPED = ("tocabi_walk_ppo", "tocabi_walk_torque", "tocabi_walk_model_based")
POLICIES = Path(__file__).resolve().parents[2] / "assets" / "policies"
#: The columns of the table: (label, path in a case summary, format).
COLUMNS = (("survival", "survival", ".3f"), ("distance mean [m]", "forward_distance_m.mean", ".2f"),
           ("drift p95 [m]", "lateral_drift_m.p95", ".2f"), ("tracking [m/s]", "tracking_error_mps.mean", ".3f"),
           ("instantaneous [m/s]", "instant_speed_error_mps.mean", ".3f"))
#: What the two speed columns are (docs/evaluation.md), and what the first was in a report made before the second.
SPEED_NOTE = ("tracking: the error of the velocity averaged over one gait cycle; instantaneous: the mean "
              "instantaneous speed error, gait sway included")
LEGACY_NOTE = ("tracking: the mean instantaneous speed error, gait sway included, as the test measured it before "
               "its cycle-mean tracking error and instantaneous column")


def _value(summary: dict, path: str):
    """The value at ``path`` (dotted) of a case summary; None where it has none (missing, NaN: the table shows "-",
    the JSON null)."""
    for part in path.split("."):
        summary = summary.get(part) if isinstance(summary, dict) else None
    return None if isinstance(summary, float) and not math.isfinite(summary) else summary


def check_policy(path: str | Path) -> None:
    """Read ``path`` as a training checkpoint (an exported policy or a damaged file raises ``CheckpointError``), so
    that a bad file is named before any test runs."""
    from tocabi_torchrl.rl.checkpoint import read_checkpoint, verified_checkpoint_file

    read_checkpoint(verified_checkpoint_file(path))


def labels(policies: list[Path]) -> list[str]:
    """One name per policy for its report folder and table rows: the file's stem, or, where two policies share it,
    the run folder's name before it (``runA_latest``), then a number if they still do."""
    stems = [p.stem for p in policies]
    names = []
    for p, stem in zip(policies, stems):
        run = next((q.name for q in p.absolute().parents if q.name and q.name != "checkpoints"), "")
        names.append(f"{run}_{stem}" if stems.count(stem) > 1 and run else stem)
    unique: list[str] = []
    for name in names:
        label, k = name, 0
        while (k == 0 and names.count(name) > 1) or label in unique:  # a repeated name is numbered from 1
            k += 1
            label = f"{name}_{k}"
        unique.append(label)
    return unique


def measure(policy: Path, out: Path, num_envs: int, seconds: float, device: str,
            cases: tuple[str, ...] | None = None, label: str | None = None, envs: dict | None = None) -> dict:
    """The robust test of one policy into ``out/label``, and its table row. ``envs``: the test envs kept across the
    policies of one call (evaluate_robust_run's), so that marks of one run share one env; a row's seconds then
    include the env's build for the first policy of its kind only."""
    from tocabi_torchrl.evaluation.robust import CASES, evaluate_robust_run, robust_passes

    label = label or policy.stem
    start = time.perf_counter()
    # replace: main refused an --out holding a table unless --overwrite; a policy's report that a stopped call left
    # without its table row is tested again into its own folder
    report = evaluate_robust_run(policy, num_envs=num_envs, device=device, out_dir=out / label, seconds=seconds,
                                 cases=cases, replace=True, envs=envs)
    took = time.perf_counter() - start
    run = tuple(report["cases"])
    # Some cases alone: whether the policy passes those (the report's own "passes" is the whole test's).
    passes = report["passes"] if set(run) == set(CASES) else robust_passes(report, run)
    cases = {name: {"passes": c["passes"], **{path: _value(c, path) for _, path, _ in COLUMNS},
                    "checks": {p: {"value": v["value"], "needs": v["needs"], "pass": v["pass"]}
                               for p, v in c["checks"].items()}}
             for name, c in report["cases"].items()}
    print(f"{label}: {'passes' if passes else 'does not pass'} {_what(run)} ({took:.0f} s)", flush=True)
    return {"policy": label, "file": str(policy), "passes": passes, "seconds": took,
            "push_kind": report["settings"]["push_kind"], "cases": cases}


def _what(cases) -> str:
    """What a result passes or not: the robust test (all four cases), or the cases it ran."""
    from tocabi_torchrl.evaluation.robust import CASES

    if set(cases) == set(CASES):
        return "the robust test"
    return ("the cases " if len(cases) > 1 else "the case ") + ", ".join(cases)


def _cell(value, check: dict | None, spec: str) -> str:
    """A table cell: ``value`` in ``spec``, ✗ when its ``check`` failed, with as many more decimals as it takes not to
    read as the other verdict (a drift of 0.3032 against <= 0.3 shows 0.303 ✗, not 0.30 ✗)."""
    from tocabi_torchrl.evaluation.output import rounded_against

    if value is None or check is None:
        return common.fmt(value, spec) + ("" if check is None or check["pass"] else " ✗")
    op, limit = check["needs"].split()
    text = rounded_against(value, float(limit), check["pass"], "min" if op == ">=" else "max", int(spec[1:-1]))
    return text + ("" if check["pass"] else " ✗")


def render(data: dict, out: Path) -> str:
    rows = []
    for r in data["results"]:
        for name, c in r["cases"].items():
            cells = [_cell(c.get(path), c["checks"].get(path), spec) for _, path, spec in COLUMNS]
            rows.append([r["policy"], name, *cells, "pass" if c["passes"] else "FAIL"])
    lines = [common.table(["policy", "case", *[label for label, _, _ in COLUMNS], "case verdict"], rows), ""]
    untested, stopped = data["meta"].get("untested", 0), data["meta"].get("stopped_on_fail")
    if stopped:
        lines.insert(0, f"Stopped on the first policy that did not pass, {stopped} (--stop_on_fail): {untested} more "
                        f"polic{'ies' if untested > 1 else 'y'} of the command not tested.\n")
    elif untested:
        lines.insert(0, f"Partial: {untested} more polic{'ies' if untested > 1 else 'y'} of the command not tested "
                        "yet (the table is written after each policy).\n")
    lines += [f"- {r['policy']}: {'passes' if r['passes'] else 'does not pass'} {_what(r['cases'])}; "
              f"{r['seconds']:.0f} s for its {NUMBERS[len(r['cases'])]} case{'s' if len(r['cases']) > 1 else ''} "
              f"([report]({r['policy']}/robust.json))"
              for r in data["results"]]
    _plot(data, out / f"{NAME}.png")
    s = data["meta"]
    legacy = any("instant_speed_error_mps.mean" not in c for r in data["results"] for c in r["cases"].values())
    kicks = kick_note(data["results"])
    return common.page("The robust gait test of the policies", data,
                       f"{s['num_envs']} robots per case, {s['seconds']:g} s, one batch per policy; ✗: a threshold "
                       f"of the case missed; {LEGACY_NOTE if legacy else SPEED_NOTE}; {kicks} (docs/evaluation.md)."
                       "\n\n"
                       + "\n".join(lines) + f"\n\n![]({NAME}.png)")


def _plot(data: dict, path: Path) -> None:
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return
    results = data["results"]
    cases = list(results[0]["cases"]) if results else []
    fig, ax = plt.subplots(figsize=(7, 3.5))
    width = 0.8 / max(len(results), 1)
    for i, r in enumerate(results):
        ax.bar([k + i * width for k in range(len(cases))], [r["cases"][c]["survival"] or 0.0 for c in cases], width,
               label=r["policy"])
    ax.set_xticks([k + 0.4 - width / 2 for k in range(len(cases))], cases)
    ax.set(ylabel="survival", ylim=(0, 1.05), title="robust gait test: survival per case")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(prog="python -m lab.benchmarks.robust_policies",
                                     description=__doc__.split("\n")[0])
    parser.add_argument("--policies", nargs="+", default=[str(POLICIES / f"{p}.pt") for p in SHIPPED],
                        help="checkpoints or run folders, which replace the default: the three shipped policies "
                             "trained on the nominal robot (assets/policies/*.pt but the robust one)")
    parser.add_argument("--num_envs", type=int, default=1024, help="robots per case (default: 1024)")
    parser.add_argument("--seconds", type=float, default=8.0, help="length of each case [s] (default: 8)")
    parser.add_argument("--device", default="cuda", help="cuda, cuda:N or cpu (default: cuda)")
    parser.add_argument("--out", default=str(common.DOCS / "robust"),
                        help="folder of the reports and the table (default: docs/benchmarks/robust, the published "
                             "table of the shipped policies; a CPU measurement goes to "
                             "runs/benchmarks_cpu/robust instead)")
    parser.add_argument("--overwrite", action="store_true", help="replace a table --out holds already")
    parser.add_argument("--cases", nargs="+", default=None, metavar="CASE",
                        help="run these cases alone (default: all four), e.g. nominal commands")
    parser.add_argument("--stop_on_fail", action="store_true",
                        help="stop after the first policy (in the order given) that does not pass; with a run's "
                             "marks from the last back, the earliest mark of its passing run of marks at the end")
    args = parser.parse_args(argv)
    from tocabi_torchrl.evaluation.robust import CASES

    unknown = [c for c in args.cases or () if c not in CASES]
    if unknown:
        parser.error(f"--cases: unknown case(s) {unknown}; choose from {list(CASES)}")
    missing = [p for p in args.policies if not Path(p).exists()]
    if missing:
        parser.error(f"--policies: no such file or run folder: {', '.join(missing)}")
    if args.num_envs < 1 or not args.seconds > 0:
        parser.error(f"--num_envs must be >= 1 and --seconds > 0, got {args.num_envs} and {args.seconds}")
    from tocabi_torchrl.evaluation.gait_test import policy_dt
    from tocabi_torchrl.evaluation.robust import RobustTestConfig
    from tocabi_torchrl.rl.checkpoint import CheckpointError, checkpoint_file

    if not args.out.strip():  # Path("") is the current folder: an unset variable in "--out $DIR" wrote the table there
        parser.error("--out is empty: give a folder for the reports (or leave --out out for the default)")
    common.require_cuda(parser, args.device, "pass --device cpu")
    from tocabi_torchrl.device import check_device

    try:  # a misspelt device ("gpu") or a cuda:K past the GPUs: one line now, not a traceback from the first test
        check_device(args.device)
    except (ValueError, RuntimeError) as err:
        parser.error(f"--device: {err}")
    out = common.report_dir(args.out, args.device)
    if out.exists() and not out.is_dir():
        parser.error(f"--out {out} is a file, not a folder: give a folder for the reports")
    if (out / f"{NAME}.json").exists() and not args.overwrite:
        parser.error(f"--out {out} holds a table already ({NAME}.json); pass --overwrite to replace it, or choose "
                     "another folder")
    # Every setting and file before the first test: a bad third policy once ended the call after two had run.
    try:
        RobustTestConfig(num_envs=args.num_envs, seconds=args.seconds,
                         cases=tuple(c for c in CASES if c in (args.cases or CASES))).validate(policy_dt())
        for policy in args.policies:
            check_policy(policy)
        # One file named twice (a run folder and its latest.pt, a repeated path) would be tested twice into two rows
        # of the same numbers, each under a made-up name.
        files = [checkpoint_file(policy).resolve() for policy in args.policies]
        twice = sorted({p for p, f in zip(args.policies, files) if files.count(f) > 1})
        if twice:
            parser.error(f"--policies names one checkpoint more than once ({', '.join(twice)}); give each policy once")
    except (ValueError, CheckpointError) as err:
        parser.error(str(err))
    try:  # a folder that cannot be made (a file on its path, no permission): said now, not after an env build
        out.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        parser.error(f"--out {out}: cannot create the folder ({err.strerror or err}); give a folder that can be made")
    names = labels([Path(p) for p in args.policies])
    data = {"meta": common.meta(NAME, argv, on=args.device, num_envs=args.num_envs, seconds=args.seconds),
            "results": []}
    envs: dict = {}  # one env per kind of policy (evaluation.robust.batch_key), built once for all its marks
    for i, policy in enumerate(args.policies):
        data["results"].append(measure(Path(policy), out, args.num_envs, args.seconds, args.device,
                                       args.cases and tuple(args.cases), names[i], envs))
        # The table after every policy, not only at the end: a call stopped partway (a time limit, Ctrl-C) keeps the
        # table of the policies it finished, and says how many it was asked for.
        left = len(args.policies) - i - 1
        stop = args.stop_on_fail and left and not data["results"][-1]["passes"]
        if left:
            data["meta"]["untested"] = left
        else:
            data["meta"].pop("untested", None)
        if stop:
            data["meta"]["stopped_on_fail"] = names[i]
        text = common.publish(out, NAME, data, render)
        if stop:
            print(f"stopped after {names[i]}, which does not pass (--stop_on_fail): {left} more not tested", flush=True)
            break
    print(text)


if __name__ == "__main__":
    main()
