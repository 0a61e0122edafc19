"""Every command line the user docs show still parses with today's options: each ``python recipes/X.py ...``,
``python lab/.../X.py ...``, ``python -m lab....`` and ``python -m tocabi_torchrl....`` of README.md, docs/*.md and
docs/concepts/*.md, in a fenced block (a backslash continues a line) or in inline code, runs in this process up to its
argument parsing and stops there, so a renamed or removed option fails here instead of in a reader's terminal.

In-process (``runpy``) rather than a subprocess per command: the scripts parse before they import torch or mujoco,
so the cost is the parsers' modules, loaded once. Argparse's ``parse_args`` (and the recipes' ``RecipeParser``'s) is
patched to stop the script once the real parse has succeeded; ``recipes/ppo_walk.py`` parses with tyro in
``rl.config.check_command_line``, which is patched to go on, as the recipe's ``main`` does, to
``rl.launch.launch_config`` (the values checked against the preset, on a machine with CUDA, which the docs' GPU
commands are written for) and stop there. ``--help`` exits 0 and passes. The run/benchmark record folders
(docs/training/<preset>/<run>/, docs/benchmarks/<x>/) are not read.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import os
import re
import runpy
import shlex
import signal
import sys
import warnings
from pathlib import Path
from unittest import mock

import pytest

from tocabi_torchrl.cli import RecipeParser

REPO = Path(__file__).resolve().parents[1]
#: Generated pages, whose commands are records of how each row was made (scripts and options as they were then):
#: docs/benchmarks.md (lab.benchmarks.page) and docs/adapters_table.md (lab.library_table).
GENERATED = ("benchmarks.md", "adapters_table.md")
#: A fenced code block, its fences included.
FENCE = re.compile(r"^```[^\n]*\n.*?^```", flags=re.DOTALL | re.MULTILINE)
#: A command of the docs' forms, up to the end of its line (of its code span), a comment, ``;``, ``)`` or ``&&``.
COMMAND = re.compile(r"python (?:recipes/|lab/|-m (?:lab|tocabi_torchrl)\b)[^\n#;)`&]*")
#: Commands shown with a placeholder where arguments go, and the command checked in their place (None: none).
PLACEHOLDERS = {
    # docs/evaluation.md: "..." stands for the run's other options
    "python recipes/ppo_walk.py ... --eval_test robust": "python recipes/ppo_walk.py --eval_test robust",
    # docs/architecture.md: any benchmark module's name
    "python -m lab.benchmarks.<name>": None,
    # docs/training.md: any run's folder
    "python -m tocabi_torchrl.rl.curves runs/<name> curves.png": "python -m tocabi_torchrl.rl.curves runs/x curves.png",
}


def pages() -> list[Path]:
    docs = REPO / "docs"
    return [REPO / "README.md", *sorted(p for p in docs.glob("*.md") if p.name not in GENERATED),
            *sorted((docs / "concepts").glob("*.md"))]


def doc_commands() -> list[tuple[str, str]]:
    """``(page:line, command)`` of every command of :func:`pages`, in page order, whitespace collapsed."""
    found = []
    for page in pages():
        # A backslash-newline becomes two spaces, so that offsets (and so line numbers) stay the page's.
        text = page.read_text().replace("\\\n", "  ")
        spans = [(m.start(), m.group()) for m in FENCE.finditer(text)]
        prose = FENCE.sub(lambda m: re.sub(r"[^\n]", " ", m.group()), text)  # the blocks blanked, offsets kept
        spans += [(m.start(1), m.group(1).replace("\n", " ")) for m in re.finditer(r"`([^`]+)`", prose)]
        for start, span in sorted(spans):
            for match in COMMAND.finditer(span):
                line = text.count("\n", 0, start + match.start()) + 1
                found.append((f"{page.relative_to(REPO)}:{line}", " ".join(match.group().split())))
    return found


class _Parsed(BaseException):
    """Raised once a script's command line has parsed, to stop it there (a BaseException: no ``except Exception`` of
    the script takes it for an error of its own)."""


def _stop_after(parse):
    def parse_then_stop(*args, **kwargs):
        parse(*args, **kwargs)
        raise _Parsed

    return parse_then_stop


def _check_then_launch(check):
    """``rl.config.check_command_line`` (tyro), then what ``recipes/ppo_walk.py``'s main does with the same command
    line: ``rl.launch.launch_config``, here as on a machine with CUDA; then stop."""

    def check_then_stop(argv, prog=None, description=""):
        from tocabi_torchrl.rl.config import option_value
        from tocabi_torchrl.rl.launch import launch_config

        check(argv, prog, description)
        if option_value(argv, "resume") is None:  # a resume's options are checked against its run, not written here
            try:
                launch_config(argv, cuda_available=True, prog=prog)
            except ValueError as err:  # a value the config refuses: main() says so in one line
                raise SystemExit(f"error: {err}") from None
        raise _Parsed

    return check_then_stop


def parse_only(command: str) -> str | None:
    """Run ``command`` (``python SCRIPT ...`` or ``python -m MODULE ...``) in this process, from the repository root,
    up to its argument parsing: None if it parsed (or answered ``--help``), else what it printed and how it exited."""
    import tocabi_torchrl.rl.config as run_config

    argv = shlex.split(command)
    assert argv[0] == "python", command
    out = io.StringIO()
    saved = sys.argv[:], os.getcwd(), signal.getsignal(signal.SIGINT)  # ppo_walk sets its Ctrl-C handler on load
    with contextlib.ExitStack() as stack:
        stack.enter_context(mock.patch.object(argparse.ArgumentParser, "parse_args",
                                              _stop_after(argparse.ArgumentParser.parse_args)))
        stack.enter_context(mock.patch.object(RecipeParser, "parse_args", _stop_after(RecipeParser.parse_args)))
        stack.enter_context(mock.patch.object(run_config, "check_command_line",
                                              _check_then_launch(run_config.check_command_line)))
        # pytest's assertion rewriter claims modules named like tests (lab/experiments/obstacle_test.py) and gives
        # runpy no code for them: the scripts are run by Python's own finders, as a reader's shell runs them.
        stack.enter_context(mock.patch.object(sys, "meta_path", [finder for finder in sys.meta_path
                                                                 if type(finder).__name__ != "AssertionRewritingHook"]))
        stack.enter_context(contextlib.redirect_stdout(out))
        stack.enter_context(contextlib.redirect_stderr(out))
        stack.enter_context(warnings.catch_warnings())
        warnings.simplefilter("ignore")  # runpy's note on a module that an earlier command's script imported
        try:
            os.chdir(REPO)
            if argv[1] == "-m":
                sys.argv = [argv[2], *argv[3:]]
                runpy.run_module(argv[2], run_name="__main__", alter_sys=True)
            else:
                sys.argv = [str(REPO / argv[1]), *argv[2:]]
                runpy.run_path(str(REPO / argv[1]), run_name="__main__")
        except _Parsed:
            return None
        except SystemExit as stop:
            if stop.code in (0, None):  # --help
                return None
            return f"exited with {stop.code!r}:\n{out.getvalue()}"
        finally:
            sys.argv, cwd, handler = saved
            os.chdir(cwd)
            signal.signal(signal.SIGINT, handler)
    return f"ran to its end without parsing a command line:\n{out.getvalue()}"


COMMANDS = doc_commands()


def test_the_docs_commands_are_found_and_every_placeholder_is_still_shown():
    # A change to the pages' markup that hid the commands from the extraction would pass every test below.
    assert len(COMMANDS) >= 40, COMMANDS
    assert {page.split(":")[0] for page, _ in COMMANDS} >= {"README.md", "docs/training.md", "docs/evaluation.md"}
    shown = {command for _, command in COMMANDS}
    assert not set(PLACEHOLDERS) - shown, "allowed placeholders that no page shows any more: drop them"


@pytest.mark.parametrize(("where", "command"), COMMANDS, ids=[where for where, _ in COMMANDS])
def test_a_doc_command_parses(where, command):
    checked = PLACEHOLDERS.get(command, command)
    if checked is None:
        pytest.skip(f"{command!r} is a placeholder")
    if re.search(r"<\w+>|\.\.\.", checked):
        pytest.fail(f"{where}: {command!r} has a placeholder; list it in PLACEHOLDERS with the command to check")
    error = parse_only(checked)
    assert error is None, f"{where}: {command!r} does not parse with today's options; {error}"


@pytest.mark.parametrize(("command", "said"), [
    ("python recipes/play.py --policy ppo --num_env 8", "did you mean --num_envs"),  # argparse (RecipeParser)
    ("python -m lab.benchmarks.time_to_walk train --preset torque --nme x", "unrecognized arguments: --nme"),
    ("python recipes/ppo_walk.py --env.num_env 8", "--env.num_env"),  # tyro
    ("python recipes/ppo_walk.py --env.num_envs 0", "num_envs"),  # a value the config refuses (launch_config)
])
def test_a_misspelt_option_or_a_refused_value_is_caught(command, said):
    # The stops above must come after the real parse: else every command would pass.
    error = parse_only(command)
    assert error is not None and said in " ".join(error.replace("│", " ").split()), error
