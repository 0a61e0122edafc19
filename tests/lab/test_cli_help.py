"""Every command-line option of the lab's scripts says what it is in ``--help``: each ``add_argument`` call under
``lab/`` carries a ``help=`` text (read from the source with ``ast``, so no script is imported or run)."""

from __future__ import annotations

import ast
from pathlib import Path

LAB = Path(__file__).resolve().parents[2] / "lab"


def options_without_help(root: Path = LAB) -> list[str]:
    """``file:line:option`` of each ``add_argument(...)`` call under ``root`` that has no ``help`` keyword."""
    missing = []
    for path in sorted(root.rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
            if not (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute)
                    and node.func.attr == "add_argument"):
                continue
            # A ``**kwargs`` splat may carry the help; only a call that cannot is flagged.
            if any(k.arg == "help" or k.arg is None for k in node.keywords):
                continue
            names = "/".join(a.value for a in node.args if isinstance(a, ast.Constant)) or ast.unparse(node)
            missing.append(f"{path.relative_to(root.parent)}:{node.lineno}:{names}")
    return missing


def test_every_lab_option_has_help():
    missing = options_without_help()
    assert not missing, "add_argument calls without help= (add a text saying what the value is, its unit):\n" + \
        "\n".join(missing)
