"""`python -m vlmproprio.cli ARGS`: the `vlmproprio` command."""

import sys

from vlmproprio.cli import main

sys.exit(main())
