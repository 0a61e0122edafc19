"""skrl's TensorBoard scalars of a table row (issue 22), over its calls, as one CSV row per logged timestep.

    python lab/analysis/skrl_events_csv.py RUN_DIR OUT.csv                # RUN_DIR: the row's run folder
    python lab/analysis/skrl_events_csv.py --overwrite RUN_DIR OUT.csv    # replace an existing OUT.csv (else refused)

skrl prints nothing per iteration; what it logs goes to ``RUN_DIR/skrl/ppo/`` for the first call and
``ppo_call<k>/`` for call k (recipes/train_skrl.py). Its trainer timestep restarts at 0 each call, so ``call`` and
``timestep`` together place a row. The table keeps the signals that tell rows apart: the mean step reward, the mean
length and return of the episodes that ended since the last write, the policy's std, the value loss and the
learning rate (skrl's KL-adaptive one). A tag skrl did not write at a timestep (no episode ended) is left empty.
Needs ``tensorboard`` (skrl's own dependency).
"""

from __future__ import annotations

import csv
import re
import sys
from pathlib import Path

FIELDS = {  # CSV column -> skrl's tag
    "step_reward": "Reward / Instantaneous reward (mean)", "episode_length": "Episode / Total timesteps (mean)",
    "episode_return": "Reward / Total reward (mean)", "action_std": "Policy / Standard deviation",
    "value_loss": "Loss / Value loss", "learning_rate": "Learning / Learning rate",
}


def call_dirs(run: Path) -> list[tuple[int, Path]]:
    """``(call, folder)`` for each of the row's skrl log folders, in call order."""
    found = []
    for path in (run / "skrl").glob("ppo*"):
        m = re.fullmatch(r"ppo(?:_call(\d+))?", path.name)
        if m and path.is_dir():
            found.append((int(m.group(1) or 1), path))
    return sorted(found)


def read(run: Path) -> list[dict]:
    """One dict per (call, timestep) with the :data:`FIELDS` skrl wrote there, in order."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    rows: list[dict] = []
    for call, folder in call_dirs(run):
        events = EventAccumulator(str(folder), size_guidance={"scalars": 0})
        events.Reload()
        tags = set(events.Tags()["scalars"])
        by_step: dict[int, dict] = {}
        for column, tag in FIELDS.items():
            for scalar in events.Scalars(tag) if tag in tags else ():
                by_step.setdefault(scalar.step, {"call": call, "timestep": scalar.step})[column] = f"{scalar.value:.6g}"
        rows += [by_step[step] for step in sorted(by_step)]
    return rows


def main(argv: list[str]) -> int:
    """Write the CSV; an error, not an empty file, when the folder holds no skrl scalars, and an error, not a
    replaced file, when OUT.csv exists without ``--overwrite``."""
    overwrite = "--overwrite" in argv
    argv = [a for a in argv if a != "--overwrite"]
    if len(argv) != 2:
        print(__doc__.split("\n\n")[1], file=sys.stderr)
        return 2
    run, out = Path(argv[0]), Path(argv[1])
    if out.suffix != ".csv":  # the arguments swapped, or a file not meant for it, would be written over
        print(f"error: the second argument is the CSV to write and must end in .csv, got {out}; give "
              "RUN_DIR OUT.csv", file=sys.stderr)
        return 2
    if out.exists() and not overwrite:
        print(f"error: {out} exists; pass --overwrite to replace it, or give another OUT.csv", file=sys.stderr)
        return 2
    rows = read(run) if run.is_dir() else []
    if not rows:
        print(f"error: {run}: no skrl scalars under skrl/ppo*/ (a table row's run folder of skrl?)", file=sys.stderr)
        return 1
    with out.open("w", newline="") as fh:
        writer = csv.DictWriter(fh, ["call", "timestep", *FIELDS])
        writer.writeheader()
        writer.writerows(rows)
    print(f"{out}: {len(rows)} timesteps over {rows[-1]['call']} call(s)")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
