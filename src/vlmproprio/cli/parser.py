"""The `vlmproprio` argument parser: every sub-command, in the order `vlmproprio --help` lists them."""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable, Iterator
from pathlib import Path

from vlmproprio.cli.arguments import path_argument
from vlmproprio.cli.cassette import add_cassette
from vlmproprio.cli.fixtures import add_export_dataset, add_fixture_commands, add_import_demos
from vlmproprio.cli.models import add_make_tiny_model, add_models
from vlmproprio.cli.power import add_power
from vlmproprio.cli.report import add_compare, add_leaderboard, add_report
from vlmproprio.cli.run import add_run, add_show
from vlmproprio.cli.score import add_score
from vlmproprio.cli.texts import MAINTAINER_COMMANDS
from vlmproprio.conditions import CONTROLS, PAPER_CONDITIONS
from vlmproprio.errors import UsageError, one_line

EPILOG = """\
typical use:
  vlmproprio verify                          check the shipped fixtures against their manifest
  vlmproprio models                          the models, and which can run here (cassette, weights)
  vlmproprio run --model reference --out runs/reference   caption all 22 episodes under every condition
  vlmproprio report runs/reference           tables, plots and an HTML page for a run
  vlmproprio import-demos demo.hdf5 --out my_fixtures    your own robosuite demos as episodes
  pytest benchmark/ --model tiny-qwen2-vl    the benchmark with its regression gates

lists: --model, --conditions, --episodes ... take a comma list, may be repeated, or both.
fixtures: --fixtures, else $VLMPROPRIO_FIXTURES, else the fixtures/ of the repository you are in.
caches: --cache-dir, else $VLMPROPRIO_CACHE, else the user cache directory (~/.cache/vlmproprio).
maintainer commands (not listed above): {maintainer}; each has --help.
"""


# Sub-commands in the order `vlmproprio --help` lists them.
_SUBCOMMANDS: tuple[Callable[[argparse._SubParsersAction], None], ...] = (
    add_fixture_commands,
    add_import_demos,
    add_make_tiny_model,
    add_run,
    add_models,
    add_cassette,
    add_score,
    add_report,
    add_compare,
    add_leaderboard,
    add_power,
    add_export_dataset,
    add_show,
)


class _Parser(argparse.ArgumentParser):
    """argparse's parser, whose usage errors escape control characters (a value holding a newline stays one
    line); its sub-command parsers are of this class too."""

    def error(self, message: str):
        super().error(one_line(message))


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog="vlmproprio",
        description="Does proprioception make a VLM's captions and subtask segmentations of robot "
        f"episodes better? Record episodes, caption them with a model under {_count(PAPER_CONDITIONS)} state "
        f"conditions and {_count(CONTROLS)} controls, score the captions and segmentations, and report.",
        epilog=EPILOG.format(maintainer=", ".join(sorted(MAINTAINER_COMMANDS))),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--debug", action="store_true", help="show full tracebacks on errors")
    parser.add_argument("--version", action="version", version=f"%(prog)s {_version()}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for add in _SUBCOMMANDS:
        add(sub)
    _uniform_metavars(parser)
    _whole_numbers_take_non_finite(parser)
    _refuse_empty_paths(parser)
    return parser


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("vlmproprio")
    except PackageNotFoundError:  # a source tree on the path without an install
        return "unknown (not installed)"


def _count(items) -> str:
    words = ("no", "one", "two", "three", "four", "five", "six", "seven", "eight", "nine", "ten")
    return words[len(items)] if len(items) < len(words) else str(len(items))


# One metavar style: a short word for what the value is, never the destination's name (FRAME_STRIDE).
METAVARS_BY_DEST = {"base_url": "URL", "api_key_env": "VAR", "episode": "ID", "condition": "COND"}


def _metavar_of(action: argparse.Action) -> str:
    if action.dest in METAVARS_BY_DEST:
        return METAVARS_BY_DEST[action.dest]
    if action.type is int:
        return "N"
    if action.type is float:
        return "X"
    if action.type is Path:
        return "PATH"
    return "NAME"


def _uniform_metavars(parser: argparse.ArgumentParser) -> None:
    """Give every value-taking option without a metavar of its own one from ``_metavar_of``."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub in action.choices.values():
                _uniform_metavars(sub)
        elif action.option_strings and action.nargs != 0 and action.metavar is None and not action.choices:
            action.metavar = _metavar_of(action)


def refuse_non_finite(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    """A UsageError naming the option when any number given is NaN or infinite. argparse's ``float`` takes "nan",
    "inf" and "1e999", and every range check after it (``x < 0 or x > 1``) is false for NaN: one check here, for
    every numeric option of the command that runs (its own, its kinds', any added later), before it starts."""
    for action, value in _given_values(parser, args):
        numbers = value if isinstance(value, list | tuple) else [value]
        for x in numbers:
            if isinstance(x, float) and not math.isfinite(x):
                flag = "/".join(action.option_strings) or action.dest
                raise UsageError(f"{flag} must be a finite number, got {x!r} (NaN and infinity are refused)")


def _given_values(
    parser: argparse.ArgumentParser, args: argparse.Namespace
) -> Iterator[tuple[argparse.Action, object]]:
    """(action, parsed value) of ``parser`` and of the sub-command chosen in ``args``, recursively."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            chosen = getattr(args, action.dest, None)
            if chosen in action.choices:
                yield from _given_values(action.choices[chosen], args)
        elif action.dest != argparse.SUPPRESS and hasattr(args, action.dest):
            yield action, getattr(args, action.dest)


def _whole_number(text: str) -> int | float:
    """argparse's ``int``, except that "nan" and "inf" come through as floats for ``refuse_non_finite`` to
    refuse in its one line, as it does for float options, instead of argparse's usage and "invalid int value"."""
    try:
        return int(text)
    except ValueError:
        try:
            x = float(text)
        except ValueError:
            x = 0.0
        if math.isfinite(x):
            raise  # "1.5", "abc": argparse's own "invalid int value"
        return x


_whole_number.__name__ = "int"  # argparse names the type in its error: "invalid int value: '1.5'"


def _whole_numbers_take_non_finite(parser: argparse.ArgumentParser) -> None:
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub in action.choices.values():
                _whole_numbers_take_non_finite(sub)
        elif action.type is int:
            action.type = _whole_number


def _refuse_empty_paths(parser: argparse.ArgumentParser) -> None:
    """Every option and positional argument of type ``Path`` takes ``path_argument`` instead: one rule for all."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub in action.choices.values():
                _refuse_empty_paths(sub)
        elif action.type is Path:
            action.type = path_argument
