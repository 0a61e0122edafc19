"""PPO training configuration: the run config tree (:mod:`tocabi_torchrl.config`) and the
command line generated from the tree (one ``--path.to.option`` per leaf, e.g. ``--ppo.lr 3e-4``,
``--env.num_envs 8192``, ``--env.control.mode torque``)."""

from __future__ import annotations

import argparse
import dataclasses
import decimal
import json
from typing import Any

from ..cli import RecipeParser
from ..config import (
    ENV_GRAPH_MODES,
    FLAT_PATHS,
    LOGGERS,
    LR_SCHEDULES,
    PRESETS,
    STD_MODES,
    ConfigError,
    PPOConfig,
    RunConfig,
    field_choices,
    preset_config,
    preset_tree,
)
from ..tree import _unwrap_optional, item_type, leaf_types, parse_leaf

__all__ = ["PPOConfig", "RunConfig", "PRESETS", "preset_config", "preset_tree", "parse_args", "build_parser",
           "LR_SCHEDULES", "STD_MODES", "ENV_GRAPH_MODES", "LOGGERS", "field_choices", "ConfigError"]


def _parse(kind: Any, text: str) -> Any:
    """:func:`~tocabi_torchrl.tree.parse_leaf`, except that an int option also takes a whole number written as a
    float (``2e8``, ``1.5e3``): step budgets read better so. A fraction (``2.5``) is still refused."""
    plain = _unwrap_optional(kind)[0]
    if plain is int and text.lower() != "none":
        try:
            return int(text)
        except ValueError:
            pass
        try:
            number = decimal.Decimal(text.strip())
        except decimal.InvalidOperation:
            number = None
        if number is None or not number.is_finite():
            raise ValueError(f"expected an int (e.g. 200000000 or 2e8), got {text!r}")
        if number != number.to_integral_value():
            raise ValueError(f"expected a whole number (e.g. 200000000 or 2e8), got {text!r}, which has a fraction")
        return int(number)
    return parse_leaf(kind, text)


class _LeafAction(argparse.Action):
    """Parse one leaf's text into ``namespace.overrides[path]`` (so dotted paths need no attribute names), with an
    error naming the option and what it takes."""

    def __init__(self, option_strings, dest, path: str, kind: Any, **kwargs):
        super().__init__(option_strings, dest, **kwargs)
        self.path, self.kind = path, kind

    def __call__(self, parser, namespace, text, option_string=None):
        try:
            value = _parse(self.kind, text)
        except ValueError as err:
            parser.error(f"{option_string} {text!r}: {err} (see --help for what {self.path} takes)")
        overrides = getattr(namespace, "overrides", None) or {}
        overrides[self.path] = value
        namespace.overrides = overrides


class _LegacyAction(argparse.Action):
    """A flat option of the command line before the tree (``--num_envs``): kept so that old command lines work."""

    def __call__(self, parser, namespace, text, option_string=None):
        name = option_string.lstrip("-")
        path = FLAT_PATHS[name]
        if name in ("command_preset", "pd_gains"):
            value = text
        else:
            try:
                value = _parse(leaf_types(RunConfig())[path], text)
            except ValueError as err:
                parser.error(f"{option_string} {text!r}: {err} (the option is now --{path})")
        overrides = getattr(namespace, "overrides", None) or {}
        overrides[name] = value
        namespace.overrides = overrides


def _shown(value: Any) -> str:
    if isinstance(value, tuple) and value and dataclasses.is_dataclass(value[0]):
        return json.dumps([dataclasses.asdict(v) for v in value])
    if isinstance(value, tuple):
        return ",".join(f"{v:g}" if isinstance(v, float) else str(v) for v in value) or "none"
    if value is None or value == "":
        return "none"
    return str(value).lower() if isinstance(value, bool) else str(value)


def build_parser(description: str = "") -> argparse.ArgumentParser:
    """The command line of :func:`parse_args`: ``--preset`` plus one ``--path`` option per leaf of the run config
    tree, each with its one-line description (``rl.options.FIELD_HELP``), allowed values and default. The options
    given land in ``namespace.overrides`` as ``{path: value}``; the flat options of the command line before the
    tree (``--num_envs``, ``--lr``, ...) are still accepted (hidden from ``--help``)."""
    from .options import field_help

    parser = RecipeParser(
        description=description,
        # An abbreviation (--total for --total_env_steps) would silently pick an option, or name a hidden flat one
        # when ambiguous: every option is given by its full name.
        allow_abbrev=False,
        epilog="Options are paths in the run config tree (tocabi_torchrl/config.py). Defaults are the 'default' "
               "preset's; another --preset changes some of them. Tuples are comma-separated; an int option also "
               "takes a whole number written as a float (2e8). With --resume the saved run's options apply and only "
               "those that --resume lists may be given other values.")
    parser.set_defaults(overrides=None)
    defaults = RunConfig()
    choices = field_choices()
    parser.add_argument("--preset", default=None, choices=sorted(PRESETS),
                        help=f"{field_help('preset')}; one of: {', '.join(sorted(PRESETS))} (default: default)")
    for path, kind in leaf_types(defaults).items():
        if path == "preset":
            continue
        default = defaults
        for name in path.split("."):
            default = getattr(default, name)
        text = field_help(path)
        if path in choices:
            text += f"; one of: {', '.join(choices[path])}"
        elif path == "loggers":
            text += f"; any of {', '.join(LOGGERS)}, comma-separated"
        elif isinstance(default, bool):
            text += "; true/false"
        elif item_type(kind) is not None:
            text += f"; a JSON list of {item_type(kind).__name__} objects"
        elif isinstance(default, tuple):
            text += "; comma-separated"
        metavar = ("BOOL" if isinstance(default, bool) else "JSON" if item_type(kind) is not None
                   else "A,B,..." if isinstance(default, tuple) else "VALUE")
        parser.add_argument(f"--{path}", action=_LeafAction, path=path, kind=kind, dest=f"leaf:{path}",
                            default=None, metavar=metavar, help=f"{text} (default: {_shown(default)})")
    for name, path in FLAT_PATHS.items():
        if name != path and f"--{name}" not in parser._option_string_actions:
            parser.add_argument(f"--{name}", action=_LegacyAction, dest=f"legacy:{name}", default=None,
                                help=argparse.SUPPRESS)
    return parser


def given_options(args: argparse.Namespace) -> dict[str, Any]:
    """The options given on the command line (``{path or legacy name: value}``), ``resume`` and ``preset`` included
    when given."""
    out = dict(args.overrides or {})
    if getattr(args, "preset", None) is not None:
        out["preset"] = args.preset
    return out


def parse_args(argv: list[str] | None = None, description: str = "") -> tuple[RunConfig, argparse.Namespace]:
    """Build a :class:`RunConfig` from ``--preset`` plus ``--path value`` overrides (every leaf is an option).

    With ``--resume`` the config starts from the one saved in that run's checkpoint instead, and the explicit
    options may only change the paths ``rl.options.RESUME_SAFE`` lists (``rl.resume.resume_config`` raises
    ``ValueError`` naming any other). ``namespace.overrides`` holds the options given. ``recipes/ppo_walk.py`` uses
    ``rl.launch.launch_config``, which also decides what runs on a machine without CUDA.
    """
    args = build_parser(description).parse_args(argv)
    overrides = given_options(args)
    if overrides.get("resume"):
        from .resume import resume_config

        return resume_config(overrides["resume"], overrides), args
    return preset_config(args.preset or "default", **overrides), args
