"""The base of every error that means bad input or an unavailable resource rather than a bug.

The CLI and the pytest plugin report these in one line (no traceback unless
--debug); anything else is a bug and keeps its traceback.
"""

from __future__ import annotations

import difflib
from collections.abc import Iterable


def _rebuilt(cls: type, args: tuple, state: dict) -> Exception:
    error = cls.__new__(cls, *args)
    error.args = args
    error.__dict__.update(state)
    return error


class VlmproprioError(Exception):
    """Bad input or an unavailable resource; the message says what, where, and what to do."""

    def __reduce__(self):
        # Sent from a forked worker (vlmproprio.parallel) as it is: class, message and attributes (a replay miss's
        # key and tag). Exception's own pickling calls __init__(*args), which fails for subclasses whose
        # __init__ takes more than the message; the worker's error would then arrive as traceback text only.
        return (_rebuilt, (type(self), self.args, self.__dict__))


class UsageError(VlmproprioError):
    """A wrong flag or value (command line, pytest option, function argument from a user)."""


def did_you_mean(name: str, known: Iterable[str]) -> str:
    """ " (did you mean 'x'?)" for the known names closest to a misspelled one, else ""."""
    close = difflib.get_close_matches(name, list(known), n=2, cutoff=0.6)
    return f" (did you mean {' or '.join(repr(c) for c in close)}?)" if close else ""


# Characters that would break a one-line message or move the terminal's cursor: C0 and C1 controls, DEL, and
# Unicode's line and paragraph separators. A tab stays (it is one line).
_UNPRINTABLE = {c: None for c in (*range(0, 9), *range(10, 32), 127, *range(128, 160), 0x2028, 0x2029)}


def one_line(text: str) -> str:
    """``text`` with every control character escaped (``\\n``, ``\\x1b``, ``\\u2028``) as ``repr`` writes it, so a
    name holding one (an episode id with a newline) cannot split an error line in two or reach the terminal raw."""
    if not any(ord(c) in _UNPRINTABLE for c in text):
        return text
    return "".join(repr(c)[1:-1] if ord(c) in _UNPRINTABLE else c for c in text)
