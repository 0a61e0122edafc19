"""What the analysis scripts share: checking their input and output paths, the options of those that drive C MuJoCo
robots through the torch-free runtime, and writing their JSON report with the command that made it (atomically,
never over an existing file)."""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from collections.abc import Sequence
from pathlib import Path

from lab.new_files import write_new_files


def check_paths(parser: argparse.ArgumentParser, checkpoints: Sequence[Path], out: Path | None) -> None:
    """Exit through ``parser`` naming every checkpoint that is not a file, or an ``out`` that exists already."""
    missing = [str(c) for c in checkpoints if not Path(c).is_file()]
    if missing:
        parser.error(f"no such checkpoint: {', '.join(missing)}")
    if out is not None and out.exists():
        parser.error(f"{out} exists; pass another --out or remove it first")


def write_report(out: Path, script: str, argv: Sequence[str] | None, results: list, meta: dict | None = None) -> None:
    """Write ``{"command", "results"}`` (and ``"meta"`` when given: date, hardware, versions) to ``out`` atomically;
    the command is ``script`` (its path from the project root) run with ``argv`` (the process's own arguments when
    None). Never over a file: when one appeared at ``out`` after :func:`check_paths`, the report goes beside it
    (:func:`lab.new_files.write_new_files` says where)."""
    command = f"PYTHONPATH=. python {script} " + " ".join(sys.argv[1:] if argv is None else argv)
    report = {"command": command, **({"meta": meta} if meta else {}), "results": results}
    written = write_new_files({out: json.dumps(report, indent=2) + "\n"})[0]
    print(f"wrote {written}")


def case_parser(doc: str, num_envs: int, seconds: float, robots_help: str = "robots",
                seconds_help: str = "length of the rollout [s]") -> argparse.ArgumentParser:
    """The options of a script that rolls checkpoints out in one case of the robust test: ``--checkpoint`` (one or
    more), ``--case``, ``--num_envs`` and ``--seconds`` (their defaults given); add the script's own and ``--out``,
    then check the paths with :func:`check_paths`."""
    from tocabi_torchrl.evaluation import robust

    parser = argparse.ArgumentParser(description=doc.split("\n\n")[0])
    parser.add_argument("--checkpoint", nargs="+", required=True, type=Path, help="checkpoints (.pt) to test")
    parser.add_argument("--case", default="nominal", choices=tuple(robust.CASES), help="a case of the robust test")
    parser.add_argument("--num_envs", type=int, default=num_envs, help=robots_help)
    parser.add_argument("--seconds", type=float, default=seconds, help=seconds_help)
    return parser


def sim2sim_parser(doc: str, contract: Path, seed_help: str) -> argparse.ArgumentParser:
    """The options of a script that runs robots through the torch-free runtime: ``--contract``, ``--num_robots``,
    ``--seconds``, ``--seed`` and ``--out``; add the script's own, then read them with :func:`sim2sim_args`."""
    parser = argparse.ArgumentParser(description=doc.split("\n\n")[0])
    parser.add_argument("--contract", type=Path, default=contract, help="exported policy's contract (.json)")
    parser.add_argument("--num_robots", type=int, default=32, help="robots per run (default: 32)")
    parser.add_argument("--seconds", type=float, default=4.0, help="length of each run [s]")
    parser.add_argument("--seed", type=int, default=7, help=seed_help)
    parser.add_argument("--out", type=Path, default=None, help="JSON to write (default: print only)")
    return parser


def sim2sim_args(parser: argparse.ArgumentParser, argv: Sequence[str] | None) -> argparse.Namespace:
    """:func:`sim2sim_parser`'s options, checked: the contract exists, ``--out`` does not, counts and lengths > 0."""
    args = parser.parse_args(argv)
    check_paths(parser, [args.contract], args.out)
    if args.num_robots < 1 or not args.seconds > 0:
        parser.error("--num_robots must be >= 1 and --seconds > 0")
    return args


def sim2sim_meta(args: argparse.Namespace, **extra) -> dict:
    """A C MuJoCo report's meta: date, hardware, robots and seconds, then ``extra``."""
    import mujoco

    return {"date": time.strftime("%Y-%m-%d"), "hardware": f"CPU (C MuJoCo {mujoco.__version__}), "
            f"{platform.machine()}", "num_robots": args.num_robots, "seconds": args.seconds, **extra}
