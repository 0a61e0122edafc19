"""Gather what the per-library table's unfinished rows need to go on in a later session, on a fresh GPU machine.

A row (``recipes/library_table.py``) resumes from its run folder: the library recipes from ``resume.json`` and the
state file it names under ``resume/``, TorchRL from ``checkpoints/latest.pt``. A session's GPU machine starts bare,
so these come back with each call (``benchmarks/table_call.sh`` packs them right after the logs) and travel
again from here. This copies, for each run folder given, only those files (and ``result.json``), plus the table's
json, into ``--out`` (default ``.tablecarry``, which git ignores), keeping their paths, so that a device call that
carries the folder can put them back where the table looks::

    python -m benchmarks.table_carry runs/library_table/h100.json runs/library_table/rsl_rl_torque_4096_*
    # in the device call, carry [".tablecarry", ...]; first:  cp -a .tablecarry/runs/. runs/ && sleep 1 && S=$(date +%s)

The snapshots stay here, where their gait tests run. The folder is refused over ``--max_mib`` (what travels beside
the working tree and the staged wheels of the same call), and an existing ``--out`` is replaced only with
``--replace``.
"""

from __future__ import annotations

import argparse
import json
import math
import shutil
import sys
from pathlib import Path

MIB = 1 << 20


def row_files(run: Path) -> list[Path]:
    """The files a row's next call resumes from: ``resume.json``, the state it names and ``result.json`` (library
    recipes), or ``checkpoints/latest.pt`` (TorchRL). ``ValueError`` if the folder has neither."""
    if (run / "resume.json").is_file():
        try:
            state = run / json.loads((run / "resume.json").read_text())["state"]
        except (ValueError, KeyError, TypeError) as err:
            raise ValueError(f"{run}/resume.json is not a resume point its recipe wrote ({err!r})") from None
        if not state.is_file():
            raise ValueError(f"{run}: resume.json names {state}, which is not there")
        return [run / "resume.json", state, *[p for p in (run / "result.json",) if p.is_file()]]
    if (run / "checkpoints" / "latest.pt").is_file():
        return [run / "checkpoints" / "latest.pt"]
    raise ValueError(f"{run}: nothing to resume from (no resume.json, no checkpoints/latest.pt); a row that never "
                     "saved (or a folder the table set aside as <run>_killed<k>) needs nothing carried")


def gather(paths: list[Path], out: Path, max_mib: float, replace: bool = False) -> list[Path]:
    """Copy the table json(s) and each run folder's resume files into ``out`` under their own relative paths;
    returns the copies. Checks everything before copying anything."""
    files: list[Path] = []
    for path in paths:
        if path.is_file():
            files.append(path)
        elif path.is_dir():
            files += row_files(path)
        else:
            raise ValueError(f"{path}: no such file or run folder")
    for path in files:
        if path.is_absolute():
            raise ValueError(f"{path}: give paths relative to the repository root, as the device call's are")
    here = out.resolve()
    if here == Path.cwd().resolve() or any(here in (p.resolve(), *p.resolve().parents) for p in files):
        raise ValueError(f"--out {out} holds what it would carry (or is the repository): name a folder of its own")
    total = sum(p.stat().st_size for p in files) / MIB
    if total > max_mib:
        raise ValueError(f"{total:.1f} MiB to carry, over --max_mib {max_mib:g}: carry fewer rows per call")
    if out.exists():
        if not replace:
            raise ValueError(f"{out} exists; pass --replace to write it anew")
        shutil.rmtree(out)
    copies = []
    for path in files:
        copy = out / path
        copy.parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(path, copy)
        copies.append(copy)
    print(f"{len(copies)} files, {total:.1f} MiB in {out}")
    return copies


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("paths", nargs="+", type=Path, help="the table's json and the rows' run folders")
    parser.add_argument("--out", type=Path, default=Path(".tablecarry"))
    parser.add_argument("--max_mib", type=float, default=14.0,
                        help="most MiB to carry (default 14: beside the working tree and .devwheels/b)")
    parser.add_argument("--replace", action="store_true", help="write --out anew if it exists")
    args = parser.parse_args(argv)
    if not 0 < args.max_mib < math.inf:  # NaN: the cap compares false and is off
        parser.error(f"--max_mib must be a positive number of MiB, got {args.max_mib}")
    try:
        gather(args.paths, args.out, args.max_mib, args.replace)
    except ValueError as err:
        sys.exit(f"table_carry: {err}")


if __name__ == "__main__":
    main()
