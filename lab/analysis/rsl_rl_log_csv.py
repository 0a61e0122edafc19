"""rsl_rl's console logs (a table row's, over one or more resumed calls) as one CSV row per PPO iteration
(issue 22).

    python lab/analysis/rsl_rl_log_csv.py LOG [LOG ...] OUT.csv     # LOGs in order; .xz ones are read as such
    python lab/analysis/rsl_rl_log_csv.py --overwrite LOG OUT.csv   # replace an existing OUT.csv (else refused)

rsl_rl prints a ~30-line block per iteration; the table keeps the signals that tell rows apart (episode length,
reward, the imitation term ``qpos``, the velocity term ``body_vel``, the action std, the value loss) and the rate.
``iteration`` is rsl_rl's own count, which a resumed call continues; ``call`` counts the recipe's start lines
(``+ ... train_rsl_rl.py``) over the logs given, so a row's logs given in order number its calls from 1, and
``call_steps`` is rsl_rl's "Total steps", which restarts each call. A value rsl_rl did not print in an iteration (no
episode ended yet) is left empty.
"""

from __future__ import annotations

import csv
import itertools
import lzma
import re
import sys
from pathlib import Path

FIELDS = {  # CSV column -> rsl_rl's label
    "call_steps": "Total steps", "steps_per_s": "Steps per second", "episode_length": "Mean episode length",
    "episode_reward": "Mean reward", "qpos": "/reward/qpos", "body_vel": "/reward/body_vel",
    "action_std": "Mean action std", "value_loss": "Mean value loss",
}
ITERATION = re.compile(r"Learning iteration (\d+)/")
VALUE = re.compile(r"^\s*(\S.*?):\s+(-?[0-9.]+(?:e-?\d+)?)\s*$")


def parse(lines) -> list[dict]:
    """One dict per iteration block, in log order, with ``iteration``, ``call`` and the :data:`FIELDS` found."""
    labels = {label: column for column, label in FIELDS.items()}
    rows: list[dict] = []
    call = 0
    for line in lines:
        if line.startswith("+ ") and "train_rsl_rl.py" in line:
            call += 1
        elif m := ITERATION.search(line):
            rows.append({"iteration": int(m.group(1)), "call": call})
        elif rows and (m := VALUE.match(line)) and m.group(1) in labels:
            rows[-1].setdefault(labels[m.group(1)], m.group(2))
    return rows


def _lines(path: Path):
    """The lines of a log, read as xz where its name ends in ``.xz``."""
    opener = lzma.open if path.suffix == ".xz" else open
    with opener(path, "rt", errors="replace") as fh:
        yield from fh


def main(argv: list[str]) -> int:
    """Write the CSV; an error, not an empty file, when the logs hold no iteration block, and an error, not a
    replaced file, when OUT.csv exists without ``--overwrite``."""
    overwrite = "--overwrite" in argv
    argv = [a for a in argv if a != "--overwrite"]
    if len(argv) < 2:
        print(__doc__.split("\n\n")[1], file=sys.stderr)
        return 2
    logs, out = [Path(a) for a in argv[:-1]], Path(argv[-1])
    if out.suffix != ".csv":  # LOG LOG without OUT.csv would write the CSV over the last log
        print(f"error: the last argument is the CSV to write and must end in .csv, got {out}; give "
              "LOG [LOG ...] OUT.csv", file=sys.stderr)
        return 2
    if out.exists() and not overwrite:
        print(f"error: {out} exists; pass --overwrite to replace it, or give another OUT.csv", file=sys.stderr)
        return 2
    rows = parse(itertools.chain.from_iterable(_lines(p) for p in logs))
    if not rows:
        print(f"error: {', '.join(map(str, logs))}: no 'Learning iteration' blocks: rsl_rl console logs?",
              file=sys.stderr)
        return 1
    with out.open("w", newline="") as fh:
        writer = csv.DictWriter(fh, ["iteration", "call", *FIELDS])
        writer.writeheader()
        writer.writerows(rows)
    print(f"{out}: {len(rows)} iterations over {rows[-1]['call']} call(s)")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
