"""The README's install and test instructions: what a CPU-only user needs, and CI runs exactly its test command."""

from __future__ import annotations

import re
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def _bash_blocks(text: str) -> list[str]:
    return [b.strip() for b in re.findall(r"```bash\n(.*?)```", text, flags=re.S)]


def test_the_two_commands_serve_a_cpu_only_user():
    text = (REPO / "README.md").read_text()
    two_commands = text[text.index("## Two commands"):text.index("## Quickstart")]
    assert "pip install torch --index-url https://download.pytorch.org/whl/cpu" in two_commands
    blocks = _bash_blocks(two_commands)
    assert blocks == ['pip install -e ".[viz]" && python recipes/ppo_walk.py',
                      'pip install -e ".[test]" && python -m pytest -q']
    assert "--resume runs/ppo_walk" in two_commands and "--name" in two_commands  # what a second run does
    assert "../shared/reference" in two_commands and "skip without it" in two_commands


def test_ci_runs_exactly_the_readme_test_command():
    text = (REPO / "README.md").read_text()
    test_command = _bash_blocks(text[text.index("## Two commands"):text.index("## Quickstart")])[1]
    ci_lines = [line.strip() for line in (REPO / ".ci" / "run").read_text().splitlines() if line.strip()]
    assert ci_lines[-1] == test_command
