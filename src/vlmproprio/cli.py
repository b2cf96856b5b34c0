"""The `vlmproprio` command.

Each sub-command is a small function that imports what it needs when it runs,
so `vlmproprio --help` and replay-only commands never import torch.
Known errors print one line and exit with status 2; `--debug` shows the traceback.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable, Sequence
from pathlib import Path

from vlmproprio.errors import VlmproprioError

DEFAULT_FIXTURES = Path("fixtures")

EPILOG = """\
typical use:
  vlmproprio verify                          check the shipped fixtures against their manifest
  vlmproprio run --model reference           caption all 22 episodes under every condition
  vlmproprio report runs/reference           tables, plots and an HTML page for a run
  pytest benchmark/ --model tiny-qwen2-vl    the benchmark with its regression gates
"""


# ---------------------------------------------------------------------------------------------- commands


def cmd_verify(args: argparse.Namespace) -> int:
    from vlmproprio.summary import fixture_summary, format_summary

    print(format_summary(fixture_summary(args.fixtures)))
    return 0


def cmd_manifest(args: argparse.Namespace) -> int:
    from vlmproprio.episodes import write_manifest

    path = write_manifest(args.fixtures)
    print(f"wrote {path}")
    return 0


def cmd_record(args: argparse.Namespace) -> int:
    from vlmproprio.record.recorder import record_all

    record_all(args.fixtures, episode_ids=args.episodes, contact_sheets=args.contact_sheets)
    return 0


# ---------------------------------------------------------------------------------------------- parser


def _add_fixtures(p: argparse.ArgumentParser) -> None:
    p.add_argument("--fixtures", type=Path, default=DEFAULT_FIXTURES, help="fixture folder (default: ./fixtures)")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="vlmproprio",
        description="Does proprioception make a VLM's captions and subtask segmentations of robot "
        "episodes better? Record episodes, caption them with a model under four state conditions "
        "and four controls, score the captions and segmentations, and report.",
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--debug", action="store_true", help="show full tracebacks on errors")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")

    p = sub.add_parser("verify", help="check fixtures against their manifest and summarise them")
    _add_fixtures(p)
    p.set_defaults(func=cmd_verify)

    p = sub.add_parser("manifest", help="rewrite fixtures/manifest.json from the files present")
    _add_fixtures(p)
    p.set_defaults(func=cmd_manifest)

    p = sub.add_parser(
        "record",
        help="(re)record the episodes with robosuite (needs the [record] extra)",
        description="Re-record episodes with the scripted operators. Bit-identical on this machine kind "
        "(pinned mujoco, EGL or OSMesa rendering). Writes episodes, the manifest and a contact sheet.",
    )
    _add_fixtures(p)
    p.add_argument("--episodes", nargs="+", metavar="ID", help="only these episode ids (default: all 22)")
    p.add_argument(
        "--contact-sheets",
        type=Path,
        default=Path("runs/contact_sheets"),
        help="folder for one contact sheet per episode (default: runs/contact_sheets)",
    )
    p.set_defaults(func=cmd_record)

    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "command", None):
        parser.print_help()
        return 2
    func: Callable[[argparse.Namespace], int] = args.func
    try:
        return func(args)
    except KeyboardInterrupt:
        print("vlmproprio: interrupted", file=sys.stderr)
        return 130
    except Exception as exc:
        if args.debug or not isinstance(exc, VlmproprioError):
            raise
        print(f"vlmproprio: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
