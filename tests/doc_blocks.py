"""The Python blocks of a documentation page, run as a reader who copies them would: in order, in one namespace."""

from __future__ import annotations

import os
import re
from pathlib import Path


def python_blocks(page: Path) -> list[str]:
    """The bodies of the fenced ```python blocks of ``page``, in order."""
    return re.findall(r"```python\n(.*?)```", page.read_text(), flags=re.DOTALL)


def run_python_blocks(page: Path, cwd: Path) -> dict:
    """Every Python block of ``page`` executed in order in one namespace, with ``cwd`` as the working directory (a
    block may write files, e.g. a run folder); returns the namespace. A failing block raises with the page's name in
    its traceback."""
    namespace: dict = {}
    before = Path.cwd()
    os.chdir(cwd)
    try:
        for block in python_blocks(page):
            exec(compile(block, str(page), "exec"), namespace)  # noqa: S102 - the project's own documentation
    finally:
        os.chdir(before)
    return namespace
