"""The recipes' command lines: a parser whose errors are one short message, and the options every library recipe
shares.

Only the standard library is imported here, so that a recipe can build its parser and parse its command line before
it loads torch, torchrl and mujoco (seconds): ``--help`` and a misspelt option then answer at once.
"""

from __future__ import annotations

import argparse
import difflib
import os
import sys
from collections.abc import Iterable, Sequence

__all__ = ["RecipeParser", "add_viewer_options", "base_parser", "hidden_sizes", "listed_spelling", "suggest_options"]


def suggest_options(given: str, known: Iterable[str], limit: int = 2) -> list[str]:
    """The known option strings closest to ``given`` (``--num_env`` -> ``['--num_envs', ...]``), best first; an
    ``=value`` attached to ``given`` is ignored."""
    name = given.split("=", 1)[0]
    return difflib.get_close_matches(name, sorted(set(known)), n=limit, cutoff=0.7)


def listed_spelling(value: str, choices: Iterable) -> str | None:
    """The one string of ``choices`` equal to ``value`` but for case (``"Linear"`` -> ``"linear"``), or None when
    none is, or more than one (then the caller's own "invalid choice" error stands). The recipes' options and the run
    config (:func:`tocabi_torchrl.config.canonical_choices`) both take named values in any case through this."""
    same = [choice for choice in choices if isinstance(choice, str) and choice.lower() == value.lower()]
    return same[0] if len(same) == 1 else None


class RecipeParser(argparse.ArgumentParser):
    """An :class:`argparse.ArgumentParser` whose errors are short: the one ``error:`` line, without the usage, which
    for the generated command lines runs to dozens of lines that bury the line that matters. An unknown option also
    gets the nearest known one (``did you mean --num_envs?``) and a second line pointing to ``--help``. Exit status
    2, as argparse's.

    Options are taken by their full names only (``allow_abbrev`` defaults to False): an abbreviation would silently
    pick an option (``--num_env 8`` meaning ``--num_envs``), where a misspelt one should be the error above.

    An option of named values (string ``choices``) takes them in any case and gives the listed spelling
    (``--test Robust`` -> ``"robust"``), as the config's named values do (``--ppo.lr_schedule Linear``)."""

    def __init__(self, *args, **kwargs):
        kwargs.setdefault("allow_abbrev", False)
        super().__init__(*args, **kwargs)

    def parse_args(self, args: Sequence[str] | None = None, namespace: argparse.Namespace | None = None):
        namespace, extras = self.parse_known_args(args, namespace)
        if extras:
            self.exit(2, f"{self.prog}: error: {self._unknown(extras)}\n"
                         f"{self.prog}: {self._help_command()} lists every option\n")
        return namespace

    def _unknown(self, extras: list[str]) -> str:
        """argparse's message for arguments it did not take, with the nearest known option of each unknown one."""
        known = [option for action in self._actions for option in action.option_strings]
        guesses = [guess for extra in extras if extra[:1] in self.prefix_chars
                   for guess in suggest_options(extra, known)]
        message = f"unrecognized arguments: {' '.join(extras)}"
        if guesses:
            message += f"; did you mean {' or '.join(dict.fromkeys(guesses))}?"
        return message

    def _get_value(self, action: argparse.Action, arg_string: str):
        # argparse's own conversion, then a named value given in another case -> its listed spelling; a value listed
        # in no case (or in two) is left for argparse's "invalid choice" error.
        value = super()._get_value(action, arg_string)
        choices = action.choices
        if isinstance(value, str) and choices is not None and value not in choices:
            return listed_spelling(value, choices) or value
        return value

    def refuse_without(self, args: argparse.Namespace, on: bool, switch: str, names: Iterable[str]) -> None:
        """An error for each option of ``names`` given another value than its default while ``switch`` (the option
        they belong to; ``on``: whether it is given) is not: it would be ignored without a word."""
        for name in names:
            if not on and getattr(args, name) != self.get_default(name):
                self.error(f"--{name} applies with {switch} only, which is not given; add {switch}, or leave "
                           f"--{name} out")

    def error(self, message: str):
        # The message names the option and what it takes; the usage added nothing but length.
        self.exit(2, f"{self.prog}: error: {message}\n")

    def _help_command(self) -> str:
        """The command that prints this parser's ``--help``, as the user would type it."""
        script = sys.argv[0] if sys.argv and os.path.basename(sys.argv[0]) == self.prog else None
        return f"python {script} --help" if script and script.endswith(".py") else f"{self.prog} --help"


#: The gait tests an evaluation can run (docs/evaluation.md): the run config's ``eval_test``, the library recipes'
#: ``--eval_test`` and ``adapters.evaluate``'s ``test`` (here, in the stdlib-only module every one of them imports).
GAIT_TESTS = ("standard", "robust")


def base_parser(description: str, num_envs: int, iterations: int,
                presets: Iterable[str] = ()) -> argparse.ArgumentParser:
    """Options every library recipe takes: envs, device, iteration budget, seed, output folder, gait test size.
    ``presets``: the preset names ``--preset`` lists (``tocabi_torchrl.config.PRESETS``, which this module, imported
    by the config, cannot import itself)."""
    parser = RecipeParser(description=description)
    parser.add_argument("--num_envs", type=int, default=num_envs,
                        help=f"robots simulated at once (default: {num_envs})")
    parser.add_argument("--device", default="auto", help="auto (CUDA if present, else cpu), cpu, cuda or cuda:N "
                        "(default: auto)")
    parser.add_argument("--iterations", type=int, default=iterations,
                        help=f"PPO iterations (rollout + update) to train (default: {iterations})")
    parser.add_argument("--max_minutes", type=float, default=0.0,
                        help="stop after this many minutes of training, summed over --resume calls (default: 0 = no "
                             "limit)")
    parser.add_argument("--checkpoint_minutes", type=float, default=0.0,
                        help="also save the policy every this many minutes of training (default: 0 = off)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the env and the library (default: 0)")
    names = f", one of {', '.join(sorted(presets))}" if presets else ""
    parser.add_argument("--preset", default="default", metavar="NAME",
                        help=f"task preset of tocabi_torchrl.config{names} (default: default)")
    parser.add_argument("--out", required=True, help="output folder; must not exist yet (runs are never overwritten)")
    parser.add_argument("--resume", action="store_true",
                        help="continue the run in --out (from its resume.json) instead of starting a new one; the "
                             "task and network options must be the ones it started with")
    parser.add_argument("--eval_envs", type=int, default=256,
                        help="robots in the gait test after training, per case in the robust test (default: 256; "
                             "0 = skip it)")
    parser.add_argument("--eval_seconds", type=float, default=8.0,
                        help="length of the gait test [s], of each case in the robust test (default: 8)")
    parser.add_argument("--eval_test", choices=GAIT_TESTS, default="standard",
                        help="the gait test after training: standard, the 8 s test at one command (summary.json, "
                             "knees.png); robust, diverse starts with the nominal, changing-command, randomised and "
                             "pushed cases (robust.json, robust.png; docs/evaluation.md) (default: standard)")
    return parser


def add_viewer_options(parser: argparse.ArgumentParser, viewer_help: str) -> None:
    """``--viewer`` (its help: ``viewer_help``), ``--viewer_host`` and ``--viewer_port`` on ``parser``, with the
    defaults of the run config's viewer section (:class:`~tocabi_torchrl.viewer.config.ViewerConfig`, torch-free)."""
    from .viewer.config import ViewerConfig

    page = ViewerConfig()
    parser.add_argument("--viewer", action="store_true", help=f"{viewer_help} (default: off)")
    parser.add_argument("--viewer_host", default=page.host,
                        help=f"address the page is served on; 0.0.0.0 for every interface (default: {page.host})")
    parser.add_argument("--viewer_port", type=int, default=page.port,
                        help=f"TCP port of the page (default: {page.port})")


def hidden_sizes(text: str) -> tuple[int, ...]:
    """The type of the recipes' ``--hidden``: comma-separated layer sizes, each at least 1 (``"256,256"``)."""
    try:
        sizes = tuple(int(x) for x in text.split(","))
    except ValueError:
        sizes = ()
    if not sizes or min(sizes) < 1:
        raise argparse.ArgumentTypeError(f"must be comma-separated layer sizes >= 1 (e.g. 256,256), got {text!r}")
    return sizes
