"""Pack a GPU-machine command's results into ``$OUT`` so that all of them come back, or say what did not.

A device call brings back at most 8 files of at most 16 MiB each and about 60 MB in all; what is past either limit
is left out whole, and a tar split across files is then unreadable from the first missing part on (the fifth
session lost its rows' resume states so). This packs the given paths into independent tars (each extracts on its
own), in the order given and, within a path, smallest file first, until the budget is used; the files that do not
fit are listed in ``$OUT/manifest.txt`` with the tars' contents, so the next call can bring them. A given path that
does not exist is listed there too, and fails the command (exit status 1) once the rest is packed::

    python3 benchmarks/device_out.py $OUT runs/library_table/table.json runs/logs runs/library_table --skip '*/resume_old/*'
    # here: for f in <files_at>/part_*.tar; do tar xf "$f"; done

Standard library only: it runs on the GPU machine before anything is installed.
"""

from __future__ import annotations

import argparse
import fnmatch
import io
import sys
import tarfile
from pathlib import Path

MIB = 1 << 20
#: the manifest's bytes per listed file beyond its path ("  PATH\n"), and per part or section heading, kept free
MANIFEST_LINE, MANIFEST_HEADING = 3, 80


def gather(paths: list[str], skip: list[str]) -> tuple[list[Path], list[str]]:
    """The files under ``paths``, in the order given and, within a path, smallest first; each file once. And the
    paths that do not exist (a misspelt one once packed nothing, without a word)."""
    seen, files, missing = set(), [], []
    for top in map(Path, paths):
        if not top.exists():
            missing.append(str(top))
            continue
        found = [top] if top.is_file() else sorted((p for p in top.rglob("*") if p.is_file()),
                                                   key=lambda p: (p.stat().st_size, str(p)))
        for path in found:
            if path not in seen and not any(fnmatch.fnmatch(str(path), pattern) for pattern in skip):
                seen.add(path)
                files.append(path)
    return files, missing


def member_bytes(path: Path, tar: tarfile.TarFile) -> int:
    """The bytes ``tar.add(path)`` writes for a file: its header blocks as ``tar`` makes them (a PAX header, for a
    fractional mtime or a name over 100 characters, adds 1,024 or more) and its data padded to 512."""
    tar.inodes.clear()  # each file whole: a hard link to one in another part is not one in its own tar
    info = tar.gettarinfo(path)
    blocks = -(-info.size // tarfile.BLOCKSIZE) if info.isreg() else 0
    return len(info.tobuf(tar.format, tar.encoding, tar.errors)) + blocks * tarfile.BLOCKSIZE


def tar_bytes(members: int) -> int:
    """A tar's size on disk from its members' bytes: two zero blocks end it, padded to a whole 10 KiB record."""
    return -(-(members + 2 * tarfile.BLOCKSIZE) // tarfile.RECORDSIZE) * tarfile.RECORDSIZE


def plan(files: list[Path], part_bytes: int, budget_bytes: int, max_parts: int) -> tuple[list[list[Path]], list[Path]]:
    """Assign ``files`` to at most ``max_parts`` tars of at most ``part_bytes`` each and ``budget_bytes`` in all (their
    sizes on disk), in order (a file that fits in no open part is left behind, later smaller ones may still go);
    returns (parts, left)."""
    parts: list[list[Path]] = []
    sizes: list[int] = []  # each part's members' bytes
    left: list[Path] = []
    with tarfile.open(fileobj=io.BytesIO(), mode="w") as probe:  # headers as main()'s tars make them
        for path in files:
            size, total, target = member_bytes(path, probe), sum(map(tar_bytes, sizes)), None
            for i, used in enumerate([*sizes, None][:max_parts]):  # the open parts in order, then a new one
                grown = tar_bytes((used or 0) + size)
                if grown <= part_bytes and total - (0 if used is None else tar_bytes(used)) + grown <= budget_bytes:
                    target = i
                    break
            if target is None:
                left.append(path)
                continue
            if target == len(parts):
                parts.append([])
                sizes.append(0)
            parts[target].append(path)
            sizes[target] += size
    return parts, left


def main(argv=None) -> tuple[list[list[Path]], list[Path]]:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("out", type=Path, help="the call's $OUT folder")
    parser.add_argument("paths", nargs="+", help="files or folders, most important first")
    parser.add_argument("--part_mib", type=float, default=15.0, help="largest tar [MiB] (default: 15)")
    parser.add_argument("--budget_mib", type=float, default=56.0, help="all tars together [MiB] (default: 56)")
    parser.add_argument("--max_files", type=int, default=8, help="files a call brings back, manifest included")
    parser.add_argument("--skip", action="append", default=[], help="glob of paths to leave out (repeatable)")
    args = parser.parse_args(argv)
    if args.max_files < 2:
        parser.error("--max_files must leave room for the manifest and one tar (>= 2)")
    files, missing = gather(args.paths, args.skip)
    # The manifest comes back within the budget too: room for every file's line, the headings and the missing paths.
    manifest = sum(len(str(p).encode(errors="surrogateescape")) + MANIFEST_LINE for p in [*files, *missing])
    manifest += MANIFEST_HEADING * (args.max_files + 2)
    parts, left = plan(files, int(args.part_mib * MIB), int(args.budget_mib * MIB) - manifest, args.max_files - 1)
    args.out.mkdir(parents=True, exist_ok=True)
    lines = []
    for k, members in enumerate(parts):
        name = f"part_{k}.tar"
        with tarfile.open(args.out / name, "w") as tar:
            for path in members:
                tar.add(path)
        lines += [f"{name}: {len(members)} files, {(args.out / name).stat().st_size / MIB:.1f} MiB"]
        lines += [f"  {p}" for p in members]
    lines += [f"left behind ({len(left)} files, {sum(p.stat().st_size for p in left) / MIB:.1f} MiB):"]
    lines += [f"  {p}" for p in left]
    lines += [f"missing ({len(missing)} paths given that do not exist):", *[f"  {p}" for p in missing]] if missing else []
    (args.out / "manifest.txt").write_text("\n".join(lines) + "\n")
    print(f"device_out: {sum(map(len, parts))} files in {len(parts)} tars; {len(left)} left behind "
          f"(listed in {args.out / 'manifest.txt'})")
    if missing:  # after packing the rest: what the call made still comes back
        sys.exit(f"error: device_out: no such file or folder: {', '.join(missing)} (misspelt?); the rest is packed")
    return parts, left


if __name__ == "__main__":
    main()
