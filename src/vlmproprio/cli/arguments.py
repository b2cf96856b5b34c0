"""The arguments several commands share (fixtures, cache, lists, run folder, encoder, workers), and a sub-command
with its texts."""

from __future__ import annotations

import argparse
from collections.abc import Callable
from pathlib import Path

from vlmproprio.cli.texts import MAINTAINER_COMMANDS, TEXTS
from vlmproprio.options import CACHE_HELP, FIXTURES_HELP


def fixtures_of(args: argparse.Namespace, *, must_exist: bool = True) -> Path:
    """--fixtures, else $VLMPROPRIO_FIXTURES, else the repository's (vlmproprio.locations)."""
    from vlmproprio.locations import resolve_fixtures

    return resolve_fixtures(args.fixtures, must_exist=must_exist)


def cache_root_of(args: argparse.Namespace) -> Path:
    """--cache-dir, else $VLMPROPRIO_CACHE, else the user cache directory."""
    from vlmproprio.locations import cache_root

    return cache_root(args.cache_dir)


def command(sub, name: str, func: Callable[[argparse.Namespace], int]) -> argparse.ArgumentParser:
    """The sub-command ``name`` (of ``cassette``: "cassette NAME"), with its texts from TEXTS, running ``func``."""
    help, description = TEXTS[name]
    if name in MAINTAINER_COMMANDS:  # a sub-parser given no help is left out of the command list
        p = sub.add_parser(name.split()[-1], description=description or help)
    else:
        p = sub.add_parser(name.split()[-1], help=help, description=description)
    p.set_defaults(func=func)
    return p


def add_fixtures(p: argparse.ArgumentParser, help: str = FIXTURES_HELP) -> None:
    p.add_argument("--fixtures", type=Path, default=None, metavar="DIR", help=help)


def add_cache_dir(p: argparse.ArgumentParser) -> None:
    """One option for the cache root everywhere; --cache and --embedding-cache are the older names."""
    p.add_argument("--cache-dir", type=Path, default=None, metavar="DIR", help=CACHE_HELP)
    p.add_argument("--cache", "--embedding-cache", dest="cache_dir", type=Path, help=argparse.SUPPRESS)


def add_list(p, flag: str, help: str, metavar: str = "LIST", *, spaces: bool = False) -> None:
    """A list option: a comma list, repeatable (``spaces``: space-separated values accepted too)."""
    if spaces:
        help += "; space-separated values are accepted too"
        p.add_argument(flag, action="extend", nargs="+", metavar=metavar, help=help)
    else:
        p.add_argument(flag, action="append", metavar=metavar, help=help)


def add_no_progress(p: argparse.ArgumentParser) -> None:
    p.add_argument("--no-progress", action="store_true", help="no progress bar")


# The commands that read a run (score, report, show) take its folder first and its fixtures from run.json.
RUN_FIXTURES_HELP = "fixture folder (default: the one in RUN_DIR/run.json)"


def add_run_dir(p: argparse.ArgumentParser) -> None:
    p.add_argument("run_dir", type=Path, metavar="RUN_DIR", help="run directory (the --out of the run command)")


def nonempty_argument(text: str) -> str:
    """argparse ``type`` of a name or path kept as text (``--encoder``): empty is a usage error, not the default."""
    if not text.strip():
        raise argparse.ArgumentTypeError("an empty value; give a name or a path")
    return text


def add_encoder(p, folder_help: str, batch_help: str) -> None:
    """The sentence encoder of the caption embeddings (score, cassette embed)."""
    p.add_argument("--encoder", type=nonempty_argument, default=None, metavar="PATH", help=folder_help)
    p.add_argument("--encoder-batch-size", type=int, default=8, help=batch_help)


def add_workers(p: argparse.ArgumentParser, what: str, results: str) -> None:
    p.add_argument(
        "--workers",
        metavar="N",
        help=f"processes for {what} (default: $VLMPROPRIO_WORKERS, else the usable cores, at most 4); "
        f"the {results} are the same with any number",
    )


def path_argument(text: str) -> Path:
    """argparse ``type`` of every path option and argument: ``--out ''`` is a usage error, not the current folder
    (``Path('')`` is ``.``), and so is a path of spaces only."""
    if not text.strip():
        raise argparse.ArgumentTypeError("an empty path; give a file or folder name")
    return Path(text)
