"""The base of every error that means bad input or an unavailable resource rather than a bug.

The CLI and the pytest plugin report these in one line (no traceback unless
--debug); anything else is a bug and keeps its traceback.
"""


class VlmproprioError(Exception):
    """Bad input or an unavailable resource; the message says what, where, and what to do."""


class UsageError(VlmproprioError):
    """A wrong flag or value (command line, pytest option, function argument from a user)."""
