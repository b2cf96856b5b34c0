"""main: parse the command line, run the sub-command with secrets masked in its output, one line per known error."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable, Sequence

from vlmproprio.cli.console import ScrubbingStream, scrub_log_records
from vlmproprio.cli.parser import build_parser, refuse_non_finite
from vlmproprio.errors import VlmproprioError


def main(argv: Sequence[str] | None = None) -> int:
    from vlmproprio.io import is_write_failure, write_error
    from vlmproprio.secrets import scrub

    argv = sys.argv[1:] if argv is None else [str(a) for a in argv]
    _register_url_secrets(argv)
    parser = build_parser()
    args = _parse(parser, argv)
    if not getattr(args, "command", None):
        parser.print_help()
        return 2
    func: Callable[[argparse.Namespace], int] = args.func
    out, err = sys.stdout, sys.stderr
    sys.stdout, sys.stderr = ScrubbingStream(out), ScrubbingStream(err)
    scrub_log_records()
    try:
        refuse_non_finite(parser, args)
        return func(args)
    except KeyboardInterrupt:
        print("vlmproprio: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:  # e.g. show piped into head: the reader left; not an error of ours
        sys.stdout = None  # type: ignore[assignment]  # nothing more can be written
        return 0
    except Exception as exc:
        if not isinstance(exc, VlmproprioError) and is_write_failure(exc):
            # a write that did not go through vlmproprio.io (a library's own file): still one line
            exc = write_error(getattr(exc, "filename", None) or "a file", exc)
        if args.debug or not isinstance(exc, VlmproprioError):
            import traceback

            print(scrub(traceback.format_exc()), end="", file=sys.stderr)
            return 1 if not isinstance(exc, VlmproprioError) else 2
        print(f"vlmproprio: error: {scrub(str(exc))}", file=sys.stderr)
        return 2
    finally:
        for stream in (sys.stdout, sys.stderr):
            stream.flush()
        sys.stdout, sys.stderr = out, err


def _register_url_secrets(argv: Sequence[str]) -> None:
    """The credentials of every URL on the command line (``--base-url http://user:pw@host/v1?code=...``) are
    secrets from the start: the HTTP layer sends them (as ``Authorization: Basic``), a server may quote them,
    and argparse may print a mistyped option's value."""
    from vlmproprio.secrets import register_secret_url

    for arg in argv:
        if "://" in arg:
            register_secret_url(arg)


def _parse(parser: argparse.ArgumentParser, argv: Sequence[str]) -> argparse.Namespace:
    """``parser.parse_args``, its usage errors masked too ("unrecognized arguments: http://user:pw@...")."""
    out, err = sys.stdout, sys.stderr
    sys.stdout, sys.stderr = ScrubbingStream(out), ScrubbingStream(err)
    try:
        return parser.parse_args(argv)
    finally:
        sys.stdout, sys.stderr = out, err
