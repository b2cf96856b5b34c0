"""The models' commands: models (the registry and what can run here), make-tiny-model."""

from __future__ import annotations

import argparse
import os
from pathlib import Path

from vlmproprio.cli.arguments import add_fixtures, add_list, command
from vlmproprio.cli.backend_options import add_kind_options, backend_settings
from vlmproprio.errors import UsageError
from vlmproprio.options import split_list


def cmd_models(args: argparse.Namespace) -> int:
    from vlmproprio.backends.registry import format_availability
    from vlmproprio.models import format_registry

    if args.plain:
        print(format_registry())
        return 0
    from vlmproprio.locations import FIXTURES_ENV, resolve_fixtures

    try:
        fixtures = resolve_fixtures(args.fixtures)
    except UsageError:
        if args.fixtures is not None or os.environ.get(FIXTURES_ENV):  # a folder named but not there
            raise
        fixtures = None  # none found: the registry is still worth listing
    cassettes = fixtures / "responses" if fixtures else Path("fixtures") / "responses"
    settings = backend_settings(args, cassette_dir=cassettes)
    print(f"cassettes: {cassettes}" + ("" if fixtures else " (no fixture folder found: pass --fixtures)"))
    print(format_availability(settings, split_list(args.model) or None))
    return 0


def cmd_make_tiny_model(args: argparse.Namespace) -> int:
    import time

    from vlmproprio.backends.tiny import build_tiny_model, file_hashes

    t0 = time.perf_counter()
    out = build_tiny_model(args.family, args.out, seed=args.seed)
    size = sum((out / rel).stat().st_size for rel in file_hashes(out))
    print(f"built tiny {args.family} (seed {args.seed}) in {out}: {size:,} bytes, {time.perf_counter() - t0:.1f} s")
    return 0


def add_models(sub) -> None:
    p = command(sub, "models", cmd_models)
    add_fixtures(p)
    add_list(p, "--model", "only these models (default: the whole registry); any name --model takes", "NAMES")
    add_kind_options(p, "models", first=("openai",))  # the server options lead, as the help has listed them
    p.add_argument("--plain", action="store_true", help="only the registry table (name, backend, weights)")


def add_make_tiny_model(sub) -> None:
    p = command(sub, "make-tiny-model", cmd_make_tiny_model)
    from vlmproprio.backends.tiny import FAMILIES  # names only: the module imports no heavy library

    p.add_argument("--family", required=True, help=", ".join(FAMILIES) + " (docs/models.md)")
    p.add_argument("--out", type=Path, required=True, help="output folder")
    p.add_argument("--seed", type=int, default=0)
