"""docs/concepts/env-and-signals.md's table, generated from the signal table (:mod:`tocabi_torchrl.signals`).

``python -m tocabi_torchrl.signals_doc`` rewrites the table between the two marker lines of
docs/concepts/env-and-signals.md (the prose around it is edited by hand); ``--check`` only reports whether the file is
current (exit status 1 if not), which ``tests/test_signals.py`` also asserts.
"""

from __future__ import annotations

import sys
from pathlib import Path

from .cli import RecipeParser

from .signals import EPISODE_FLAGS, REWARD, SIGNALS, Signal, SignalTable

__all__ = ["BEGIN", "END", "DOC_PATH", "render_table", "with_table", "is_current", "main"]

#: The marker lines around the generated table.
BEGIN = "<!-- BEGIN signal table: generated from tocabi_torchrl/signals.py by python -m tocabi_torchrl.signals_doc -->"
END = "<!-- END signal table -->"
#: docs/concepts/env-and-signals.md of a source checkout.
DOC_PATH = Path(__file__).resolve().parents[1] / "docs" / "concepts" / "env-and-signals.md"


def _row(signal: Signal) -> str:
    dtype = str(signal.dtype).removeprefix("torch.")
    return f"| `{signal.name}` | {signal.shape_text} | {dtype} | {signal.unit or '–'} | {signal.meaning} |"


def render_table(signals: SignalTable = SIGNALS) -> str:
    """The markdown table of ``signals``, the done flags and the reward, between the marker lines."""
    lines = [BEGIN, "| key | shape | dtype | unit | meaning |", "|---|---|---|---|---|"]
    lines += [_row(s) for s in (*signals, *EPISODE_FLAGS, REWARD)]
    return "\n".join([*lines, END])


def with_table(text: str, signals: SignalTable = SIGNALS) -> str:
    """``text`` (a docs/concepts/env-and-signals.md) with the part from ``BEGIN`` to the first ``END`` after it
    replaced by :func:`render_table`; raises ``ValueError`` naming the marker line the page lacks."""
    start = text.find(BEGIN)
    if start < 0:
        raise ValueError(f"the signals page lacks the marker line {BEGIN!r} before its table; add it (and {END!r} "
                         "after)")
    # END is looked for after BEGIN: a stray END above the table must not hide the one that closes it.
    stop = text.find(END, start + len(BEGIN))
    if stop < 0:
        raise ValueError(f"the signals page lacks the marker line {END!r} after {BEGIN!r}; add it below the table")
    return text[:start] + render_table(signals) + text[stop + len(END) :]


def is_current(path: str | Path = DOC_PATH, signals: SignalTable = SIGNALS) -> bool:
    """Whether the table in ``path`` is the one :func:`render_table` makes from ``signals``."""
    text = Path(path).read_text(encoding="utf-8")
    return with_table(text, signals) == text


def main(argv: list[str] | None = None) -> int:
    """Command line: rewrite docs/concepts/env-and-signals.md's table, or with ``--check`` report whether it is
    current."""
    parser = RecipeParser(prog="python -m tocabi_torchrl.signals_doc", description=__doc__.split("\n")[0])
    parser.add_argument("--path", type=Path, default=DOC_PATH, help="the signals page (default: %(default)s)")
    parser.add_argument("--check", action="store_true", help="only check; exit status 1 if the table is stale")
    args = parser.parse_args(argv)
    if args.path.exists() and not args.path.is_file():
        parser.error(f"{args.path} is not a file; pass --path to the docs/concepts/env-and-signals.md of a source "
                     "checkout")
    if not args.path.is_file():
        parser.error(f"{args.path} does not exist; pass --path to the docs/concepts/env-and-signals.md of a source "
                     "checkout")
    try:
        current = is_current(args.path)
    except ValueError as err:  # missing marker lines (or a page that is not UTF-8 text): a one-line usage error
        parser.error(f"--path {args.path}: {err}")
    if current:
        print(f"{args.path}: the signal table is current")
        return 0
    if args.check:
        print(f"{args.path}: the signal table is stale; run python -m tocabi_torchrl.signals_doc", file=sys.stderr)
        return 1
    from .atomic import atomic_write_text  # imported here: only writing needs it

    atomic_write_text(args.path, with_table(args.path.read_text(encoding="utf-8")))
    print(f"{args.path}: signal table rewritten")
    return 0


if __name__ == "__main__":
    sys.exit(main())
