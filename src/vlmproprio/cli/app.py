"""main: parse the command line, run the sub-command with secrets masked in its output, one line per known error."""

from __future__ import annotations

import argparse
import contextlib
import sys
from collections.abc import Callable, Sequence

from vlmproprio.cli.console import ScrubbingStream, scrub_log_records
from vlmproprio.cli.parser import build_parser, refuse_non_finite
from vlmproprio.errors import VlmproprioError, one_line


def main(argv: Sequence[str] | None = None) -> int:
    """The ``vlmproprio`` command: its exit status. Ctrl-C at any point (parsing included) is one line and 130; a
    reader that leaves (``| head -c 1``) ends it quietly with 0, whenever the pipe breaks, flushes included."""
    out, err = sys.stdout, sys.stderr
    try:
        return _main(argv)
    except KeyboardInterrupt:
        sys.stdout, sys.stderr = out, err
        _say_interrupted()
        return 130
    except BrokenPipeError:  # the reader left; not an error of ours
        sys.stdout, sys.stderr = out, err
        _stdout_to_devnull()
        return 0
    finally:
        _flush_quietly(out)
        _flush_quietly(err)


def _say_interrupted() -> None:
    with contextlib.suppress(OSError, ValueError):  # stderr closed or gone too: the exit status still says it
        print("vlmproprio: interrupted", file=sys.stderr)


def _stdout_to_devnull() -> None:
    """Point stdout's descriptor at /dev/null: the interpreter's own flush at exit must not fail again on the
    broken pipe (which prints "Exception ignored ... BrokenPipeError")."""
    import os

    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        os.close(devnull)
    except (OSError, ValueError, AttributeError):  # no real descriptor (a test's captured stream)
        pass


def _flush_quietly(stream) -> None:
    """Flush a console stream; a pipe that broke meanwhile sends what is left to /dev/null instead."""
    if stream is None:
        return
    try:
        stream.flush()
    except BrokenPipeError:
        if stream is sys.stdout:
            _stdout_to_devnull()
    except (OSError, ValueError):  # closed by the command or the reader: nothing more can be written
        pass


def _reader_left(stream) -> bool:
    """Whether ``stream`` (stdout) is a pipe whose reader has gone: a BrokenPipeError from anything else (a socket
    a library writes to) is an error to report, not a quiet end."""
    import select

    try:
        fd = stream.fileno()
    except (OSError, ValueError, AttributeError):  # no descriptor (a test's captured stream): assume it was ours
        return True
    if not hasattr(select, "poll"):
        return True
    poller = select.poll()
    poller.register(fd, select.POLLOUT)
    return any(events & (select.POLLERR | select.POLLHUP) for _, events in poller.poll(0))


def _main(argv: Sequence[str] | None) -> int:
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
        result = func(args)
        sys.stdout.flush()  # a reader that left shows here, inside the handlers below
        return result
    except KeyboardInterrupt:
        raise  # main's
    except Exception as exc:
        if isinstance(exc, BrokenPipeError) and _reader_left(out):
            raise  # main's: the reader of our output left
        if not isinstance(exc, VlmproprioError) and is_write_failure(exc):
            # a write that did not go through vlmproprio.io (a library's own file): still one line
            exc = write_error(getattr(exc, "filename", None) or "a file", exc)
        if args.debug or not isinstance(exc, VlmproprioError):
            import traceback

            print(scrub(traceback.format_exc()), end="", file=sys.stderr)
            return 1 if not isinstance(exc, VlmproprioError) else 2
        print(f"vlmproprio: error: {one_line(scrub(str(exc)))}", file=sys.stderr)
        return 2
    finally:
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
