"""Integrity of the torch files this package reads (checkpoints, ``policy.pt``): the zip CRCs, checked on every read.

``torch.save`` writes a zip archive whose entries each carry a CRC-32, tensor data included (stored uncompressed, but
still with its CRC). ``torch.load`` never checks those CRCs, so bits flipped on disk or in a copy inside a tensor's
data load silently as slightly different weights: a policy that exports, evaluates and resumes as if nothing were
wrong. :func:`zip_damage` reads every entry once and compares its CRC (about a millisecond per megabyte), so each
reader can refuse such a file before unpickling it. :func:`load_error_detail` gives the readable line of a load that
failed. The module imports only the standard library.
"""

from __future__ import annotations

import os
import re
import zipfile

__all__ = ["load_error_detail", "zip_damage"]


def zip_damage(path: str | os.PathLike) -> str | None:
    """What is damaged in the torch zip file at ``path``, or ``None`` when every entry matches its CRC-32.

    A file that is not a zip archive at all (truncated before its directory, a legacy pickle, another kind of file)
    also gives ``None``: there is no CRC to check, and ``torch.load`` itself says what it is not."""
    if not zipfile.is_zipfile(path):
        return None
    try:
        with zipfile.ZipFile(path) as archive:
            bad = archive.testzip()
    except (zipfile.BadZipFile, OSError, EOFError, ValueError, NotImplementedError) as err:
        # a damaged local header or entry size: the archive's directory no longer matches its contents
        return f"its zip structure is damaged ({type(err).__name__}: {err})"
    return None if bad is None else f"entry {bad!r} fails its CRC-32 check (its bytes changed after it was written)"


def load_error_detail(err: Exception) -> str:
    """The line of a failed ``torch.load(weights_only=True)`` that says what is wrong (the refused global, or what
    could not be read), without torch's advice to turn ``weights_only`` off, which must not be followed for a file
    from outside, and without its terminal colour codes."""
    text = re.sub(r"\x1b\[[0-9;]*m", "", str(err))
    lines = [line.strip() for line in text.splitlines()]
    found = (next((line for line in lines if "GLOBAL" in line), None)
             or next((line for line in lines if "Unsupported" in line), None))
    if found is None:
        return text.split(". ")[0].strip()
    return found.removeprefix("WeightsUnpickler error: ").split(" by default")[0]
