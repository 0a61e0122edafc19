"""Atomic file writes: a reader (or a crash) sees the old file or the new one, never half of one.

The data go to a temporary file in the target's own folder (so ``os.replace`` is a rename on one file system), are
flushed and fsynced, then renamed over the target; the folder is fsynced so that the rename itself survives a power
cut. A crash mid-write leaves at most a ``*.tmp`` file, which :func:`remove_stale_temp_files` clears. The file gets
the permissions a plain ``open(path, "w")`` would give it: the target's own when it exists, else 0o666 less the umask
(``mkstemp`` alone would leave every checkpoint, export and config readable by its owner only).
"""

from __future__ import annotations

import errno
import os
import secrets
import tempfile
from pathlib import Path

__all__ = ["atomic_write_bytes", "atomic_write_text", "remove_stale_temp_files", "check_writable", "TEMP_SUFFIX"]

#: Suffix of the temporary files written next to their target.
TEMP_SUFFIX = ".tmp"


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> Path:
    """Write ``data`` to ``path`` atomically (temp file in the same folder, fsync, ``os.replace``)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = _create_temp(path)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        if path.exists():  # a rewritten file keeps the mode its owner gave it
            os.chmod(tmp, path.stat().st_mode & 0o7777)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    _fsync_dir(path.parent)
    return path


def atomic_write_text(path: str | os.PathLike, text: str) -> Path:
    """:func:`atomic_write_bytes` for UTF-8 text."""
    return atomic_write_bytes(path, text.encode("utf-8"))


def check_writable(path: str | os.PathLike) -> None:
    """Raise ``OSError`` (``filename``: the folder) unless a file can be created in ``path`` or, while it does not
    exist, in its nearest existing parent: a probe file, created and removed at once, so that a command says so
    before its work instead of at its first write."""
    folder = Path(path)
    while not folder.exists() and folder != folder.parent:
        folder = folder.parent
    if not folder.is_dir():
        raise NotADirectoryError(errno.ENOTDIR, "a file, not a folder", str(folder))
    try:
        with tempfile.TemporaryFile(dir=folder):
            pass
    except OSError as err:
        raise OSError(err.errno, err.strerror or str(err), str(folder)) from None


def remove_stale_temp_files(folder: str | os.PathLike) -> list[Path]:
    """Delete the temporary files a killed writer left in ``folder``; returns what was removed."""
    folder = Path(folder)
    if not folder.is_dir():
        return []
    stale = [p for p in folder.glob(f".*{TEMP_SUFFIX}") if p.is_file()]
    for p in stale:
        p.unlink(missing_ok=True)
    return stale


def _create_temp(path: Path) -> tuple[int, str]:
    """A new temporary file beside ``path``, opened for writing: ``(fd, its path)``. Created with mode 0o666 for the
    kernel to apply the umask, as ``open(path, "w")`` would (``mkstemp`` makes 0o600, and reading the umask means
    setting it, which other threads would see)."""
    flags = os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_BINARY", 0)
    for _ in range(100):
        tmp = path.parent / f".{path.name}.{secrets.token_hex(6)}{TEMP_SUFFIX}"
        try:
            return os.open(tmp, flags, 0o666), str(tmp)
        except FileExistsError:
            continue
    raise FileExistsError(f"could not create a temporary file beside {path}")


def _fsync_dir(folder: Path) -> None:
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:  # e.g. Windows cannot open folders; the rename is still atomic there
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)
