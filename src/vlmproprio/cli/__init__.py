"""The `vlmproprio` command.

Each sub-command is a small function that imports what it needs when it runs,
so `vlmproprio --help` and replay-only commands never import torch.
Known errors print one line and exit with status 2; `--debug` shows the traceback.

The package: ``parser`` (the argument parser), ``app`` (``main``: dispatch, scrubbed output, errors), one
module per command group (``fixtures``, ``models``, ``run``, ``cassette``, ``score``, ``report``, ``power``)
holding its handlers and its sub-command parsers, the shared ``arguments``, the help ``texts``, the
``console`` (scrubbing, progress bars) and the backends' options (``backend_options``).
"""

import vlmproprio

try:
    from vlmproprio.cli.app import main
    from vlmproprio.cli.parser import build_parser
finally:
    vlmproprio._end_of_start()  # Ctrl-C while importing was handled by vlmproprio/__init__.py; main's from here

__all__ = ["build_parser", "main"]
