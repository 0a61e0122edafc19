"""Writing a lab script's report files when the script was not told to overwrite: never over a file, and never
losing the results either.

Such a script checks at its start that its output names are free, then measures for minutes. A file that appears at
one of those names meanwhile (another run beside, a series of variants) must not be replaced, but refusing the write
would throw the measurement away: the results go beside the wanted names instead (``<stem>.<pid><suffix>``), and one
line says where."""

from __future__ import annotations

import os
import sys
from collections.abc import Mapping
from pathlib import Path

from tocabi_torchrl.atomic import atomic_write_text

__all__ = ["write_new_files"]


def _beside(path: Path, attempt: int) -> Path:
    """``path`` with this process's id (and ``-attempt`` after the first) before its suffix."""
    tag = f"{os.getpid()}" + (f"-{attempt}" if attempt else "")
    return path.with_name(f"{path.stem}.{tag}{path.suffix}")


def write_new_files(texts: Mapping[str | os.PathLike, str]) -> list[Path]:
    """Write each text to its path atomically and never over an existing file; returns the paths written, in order.

    When any of the paths exists (it appeared after the script checked), every text is written beside its path
    under one shared tag (``<stem>.<pid>[-n]<suffix>``, so a JSON and its page stay a pair), none of them over a
    file, and one line on stderr names the wanted and the written paths. The files that appeared are left as they
    are."""
    wanted = [Path(p) for p in texts]
    contents = list(texts.values())
    written: list[Path] = []
    for attempt in range(101):
        targets = wanted if attempt == 0 else [_beside(p, attempt - 1) for p in wanted]
        if any(t.exists() for t in targets):  # checked for all before writing any: a pair is written, or none
            continue
        try:
            for target, text in zip(targets, contents, strict=True):
                written.append(atomic_write_text(target, text, replace=False))
        except FileExistsError as err:  # appeared between the check and the write: the next tag
            if err.filename is None or Path(err.filename) not in targets:
                raise
            continue
        break
    else:
        raise FileExistsError(f"no free name beside {wanted[0]} to write the results to")
    stray, written = written[:-len(wanted)], written[-len(wanted):]
    if written != wanted:
        taken = [str(p) for p in wanted if p.exists() and p not in stray]
        also = f" (also in {', '.join(map(str, stray))}, written before the clash)" if stray else ""
        print(f"warning: {', '.join(taken)} appeared while this ran and is left as it is; the results are in "
              f"{', '.join(map(str, written))}{also}", file=sys.stderr, flush=True)
    return written
