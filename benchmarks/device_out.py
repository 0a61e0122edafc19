"""Pack a GPU-machine command's results into ``$OUT`` so that all of them come back, or say what did not.

A device call brings back at most 8 files of at most 16 MiB each and about 60 MB in all; what is past either limit
is left out whole, and a tar split across files is then unreadable from the first missing part on (the fifth
session lost its rows' resume states so). This packs the given paths into independent tars (each extracts on its
own), in the order given and, within a path, smallest file first, until the budget is used; the files that do not
fit are listed in ``$OUT/manifest.txt`` with the tars' contents, so the next call can bring them::

    python3 benchmarks/device_out.py $OUT runs/library_table/table.json runs/logs runs/library_table --skip '*/resume_old/*'
    # here: for f in <files_at>/part_*.tar; do tar xf "$f"; done

Standard library only: it runs on the GPU machine before anything is installed.
"""

from __future__ import annotations

import argparse
import fnmatch
import tarfile
from pathlib import Path

MIB = 1 << 20
#: tar's own bytes per member (header and padding to 512), kept free in each part
TAR_OVERHEAD = 1536


def gather(paths: list[str], skip: list[str]) -> list[Path]:
    """The files under ``paths``, in the order given and, within a path, smallest first; each file once."""
    seen, files = set(), []
    for top in map(Path, paths):
        found = [top] if top.is_file() else sorted((p for p in top.rglob("*") if p.is_file()),
                                                   key=lambda p: (p.stat().st_size, str(p)))
        for path in found:
            if path not in seen and not any(fnmatch.fnmatch(str(path), pattern) for pattern in skip):
                seen.add(path)
                files.append(path)
    return files


def plan(files: list[Path], part_bytes: int, budget_bytes: int, max_parts: int) -> tuple[list[list[Path]], list[Path]]:
    """Assign ``files`` to at most ``max_parts`` tars of at most ``part_bytes`` each and ``budget_bytes`` in all, in
    order (a file that fits in no open part is left behind, later smaller ones may still go); returns (parts, left)."""
    parts: list[list[Path]] = []
    sizes: list[int] = []
    left: list[Path] = []
    for path in files:
        size = path.stat().st_size + TAR_OVERHEAD
        room = budget_bytes - sum(sizes)
        target = next((i for i, used in enumerate(sizes) if used + size <= part_bytes), None)
        if size > room or (target is None and (len(parts) == max_parts or size > part_bytes)):
            left.append(path)
            continue
        if target is None:
            parts.append([])
            sizes.append(0)
            target = len(parts) - 1
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
    parts, left = plan(gather(args.paths, args.skip), int(args.part_mib * MIB), int(args.budget_mib * MIB),
                       args.max_files - 1)
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
    (args.out / "manifest.txt").write_text("\n".join(lines) + "\n")
    print(f"device_out: {sum(map(len, parts))} files in {len(parts)} tars; {len(left)} left behind "
          f"(listed in {args.out / 'manifest.txt'})")
    return parts, left


if __name__ == "__main__":
    main()
