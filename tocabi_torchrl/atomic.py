"""Atomic file writes: a reader (or a crash) sees the old file or the new one, never half of one.

The data go to a temporary file in the target's own folder (so ``os.replace`` is a rename on one file system), are
flushed and fsynced, then renamed over the target; the folder is fsynced so that the rename itself survives a power
cut. A crash mid-write leaves at most a ``*.tmp`` file, which :func:`remove_stale_temp_files` clears. The file gets
the permissions a plain ``open(path, "w")`` would give it: the target's own when it exists, else 0o666 less the umask
(``mkstemp`` alone would leave every checkpoint, export and config readable by its owner only).

A writer that checked at its start that its target did not exist passes ``replace=False``: the temporary file is then
hard-linked to the target, which fails if a file of that name appeared meanwhile, instead of renamed over it.
"""

from __future__ import annotations

import atexit
import contextlib
import errno
import os
import secrets
import tempfile
from pathlib import Path

__all__ = ["atomic_write_bytes", "atomic_write_text", "remove_stale_temp_files", "check_writable", "claim_path",
           "release_claim", "TEMP_SUFFIX"]

#: Suffix of the temporary files written next to their target.
TEMP_SUFFIX = ".tmp"


def atomic_write_bytes(path: str | os.PathLike, data: bytes, replace: bool = True) -> Path:
    """Write ``data`` to ``path`` atomically (temp file in the same folder, fsync, ``os.replace``).

    ``replace=False``: never replace a file at ``path``, even one created while ``data`` was being written; raises
    ``FileExistsError`` (``filename``: ``path``) and leaves that file as it is."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = _create_temp(path)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        if replace:
            if path.exists():  # a rewritten file keeps the mode its owner gave it
                os.chmod(tmp, path.stat().st_mode & 0o7777)
            os.replace(tmp, path)
        else:
            _link_new(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    if not replace:
        Path(tmp).unlink(missing_ok=True)  # the target is its second name now (gone: renamed, no hard links)
    _fsync_dir(path.parent)
    return path


def _link_new(tmp: str, path: Path) -> None:
    """Give the written ``tmp`` the name ``path`` unless that exists: a hard link, which (unlike a rename) fails when
    the name is taken, atomically."""
    try:
        os.link(tmp, path)
    except FileExistsError:
        raise FileExistsError(errno.EEXIST, "a file of this name appeared while this one was being written; it was "
                              "left as it is", str(path)) from None
    except OSError as err:
        if err.errno not in (errno.EPERM, errno.ENOTSUP, errno.EOPNOTSUPP, errno.EMLINK, errno.ENOSYS):
            raise
        # A file system without hard links (e.g. FAT, some network mounts): check, then rename, which leaves a
        # moment for another writer, as a plain write would.
        if path.exists():
            raise FileExistsError(errno.EEXIST, "a file of this name appeared while this one was being written; it "
                                  "was left as it is", str(path)) from None
        os.replace(tmp, path)


def atomic_write_text(path: str | os.PathLike, text: str, replace: bool = True) -> Path:
    """:func:`atomic_write_bytes` for UTF-8 text."""
    return atomic_write_bytes(path, text.encode("utf-8"), replace)


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


#: The claims this process holds: claim file -> [its open descriptor, holding the lock; how many holders]. Process-
#: wide by nature: a lock belongs to the process, and every open_run or evaluation of one folder shares it.
_HELD: dict[Path, list[int]] = {}


def claim_path(path: str | os.PathLike) -> tuple[Path | None, int | None]:
    """Claim the folder ``path`` for this process, so that two processes never write into one folder that each
    found free: an exclusive ``flock`` on ``<parent>/.<name>.claim``, which holds the claimant's process id for
    messages. Returns ``(the claim file, None)``, or ``(None, the holder's process id)`` while another process holds
    the lock (``None`` as the id if it has not written it yet). The kernel drops the lock when its process ends,
    however it ends, so a killed run's claim is free at once; a process may claim a folder it holds again (each
    :func:`release_claim` undoes one claim). Raises ``PermissionError`` (``filename``: the claim file) saying why
    when the claim file cannot be created or opened."""
    claim = Path(path).absolute()
    claim = claim.parent / f".{claim.name}.claim"
    if claim in _HELD:
        _HELD[claim][1] += 1
        return claim, None
    import fcntl  # POSIX; imported here so that the module loads anywhere

    for _ in range(5):
        fd = _open_claim(claim)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(fd)
            return None, _claim_owner(claim)
        try:
            same = os.fstat(fd).st_ino == os.stat(claim).st_ino
        except FileNotFoundError:
            same = False
        if not same:  # its holder removed the file between our open and our lock: lock the file there now
            os.close(fd)
            continue
        os.ftruncate(fd, 0)
        os.write(fd, str(os.getpid()).encode())
        if not _HELD:
            atexit.register(_release_all)
        _HELD[claim] = [fd, 1]
        return claim, None
    return None, None


def _open_claim(claim: Path) -> int:
    """The claim file ``claim`` opened for reading and writing (created if missing, with its folder). A
    ``PermissionError`` says which of the two usual causes it is, for a shared folder: another user's claim file,
    which this user may not write (one of their processes is writing there, or ended without removing it), or a
    folder this user may not write in."""
    try:
        claim.parent.mkdir(parents=True, exist_ok=True)
        return os.open(claim, os.O_CREAT | os.O_RDWR, 0o644)
    except PermissionError as err:
        folder = claim.with_name(claim.name[1:-len(".claim")])
        if os.path.lexists(claim):
            why = (f"cannot open the claim file {claim}: it belongs to another user (one of their processes is writing "
                   f"into {folder}, or one ended without removing it); if none is, remove the file (or ask its owner "
                   "to)")
        else:
            where = f"write in {claim.parent}" if claim.parent.is_dir() else f"create {claim.parent}"
            why = f"cannot create the claim file {claim}: this user may not {where}"
        raise PermissionError(err.errno, why, str(claim)) from None


def release_claim(claim: str | os.PathLike) -> None:
    """Undo one :func:`claim_path` of this process; the last one removes the claim file and drops the lock."""
    claim = Path(claim).absolute()
    held = _HELD.get(claim)
    if held is None:
        return
    held[1] -= 1
    if held[1] > 0:
        return
    del _HELD[claim]
    with contextlib.suppress(FileNotFoundError):
        claim.unlink()  # before the lock goes: a process that opened it meanwhile sees another file and retries
    os.close(held[0])


def _release_all() -> None:
    """At exit: remove every claim file this process still holds (the locks go with the process anyway)."""
    for claim in list(_HELD):
        _HELD[claim][1] = 1
        release_claim(claim)


def _claim_owner(claim: Path) -> int | None:
    try:
        return int(claim.read_text().strip())
    except (OSError, ValueError):
        return None  # gone, or being written
