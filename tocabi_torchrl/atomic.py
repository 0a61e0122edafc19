"""Atomic file writes: a reader (or a crash) sees the old file or the new one, never half of one.

The data go to a temporary file in the target's own folder (so ``os.replace`` is a rename on one file system), are
flushed and fsynced, then renamed over the target; the folder is fsynced so that the rename itself survives a power
cut. A crash mid-write leaves at most a ``*.tmp`` file, which :func:`remove_stale_temp_files` clears. The file gets
the permissions a plain ``open(path, "w")`` would give it: the target's own when it exists, else 0o666 less the umask
(``mkstemp`` alone would leave every checkpoint, export and config readable by its owner only).
"""

from __future__ import annotations

import atexit
import contextlib
import errno
import os
import secrets
import tempfile
import time
from pathlib import Path

__all__ = ["atomic_write_bytes", "atomic_write_text", "remove_stale_temp_files", "check_writable", "claim_path",
           "release_claim", "TEMP_SUFFIX"]

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


def claim_path(path: str | os.PathLike) -> tuple[Path | None, int | None]:
    """Claim the folder ``path`` for this process, so that two processes never write into one folder that each
    found free: ``<parent>/.<name>.claim``, created exclusively and holding this process's id. Returns ``(the claim
    file, None)``, or ``(None, the holder's process id)`` while another live process holds it (``None`` as the id
    for a claim made in the last seconds and not yet written). A claim whose process has ended is taken over; the
    end of this process, or :func:`release_claim`, removes it."""
    path = Path(path)
    claim = path.parent / f".{path.name}.claim"
    claim.parent.mkdir(parents=True, exist_ok=True)
    for _ in range(3):  # a stale claim is removed and taken once; another process may race for it
        try:
            fd = os.open(claim, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
        except FileExistsError:
            owner = _claim_owner(claim)
            if owner is not None and owner != os.getpid() and _alive(owner):
                return None, owner
            if owner is None and _fresh(claim):
                return None, None
            if owner == os.getpid():
                return claim, None
            with contextlib.suppress(FileNotFoundError):
                claim.unlink()
            continue
        with os.fdopen(fd, "w") as fh:
            fh.write(str(os.getpid()))
        atexit.register(release_claim, claim)
        return claim, None
    return None, None


def release_claim(claim: str | os.PathLike) -> None:
    """Remove the claim file ``claim`` if this process holds it."""
    claim = Path(claim)
    if _claim_owner(claim) == os.getpid():
        with contextlib.suppress(FileNotFoundError):
            claim.unlink()


def _claim_owner(claim: Path) -> int | None:
    try:
        return int(claim.read_text().strip())
    except (OSError, ValueError):
        return None  # gone, or being written: no owner to wait for


def _fresh(claim: Path) -> bool:
    """Whether ``claim`` (still without its process id) was made in the last seconds: being written, not stale."""
    try:
        return time.time() - claim.stat().st_mtime < 5.0
    except FileNotFoundError:
        return False


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's process
        return True
    return True
