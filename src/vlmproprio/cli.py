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

    record_all(args.fixtures, episode_ids=args.episodes, contact_sheet=not args.no_contact_sheet)
    return 0


def cmd_score(args: argparse.Namespace) -> int:
    from vlmproprio.embeddings import encoder_spec
    from vlmproprio.evaluation import score_run

    spec = encoder_spec(args.encoder, batch_size=args.encoder_batch_size, threads=args.encoder_threads)
    tables = score_run(
        args.run_dir,
        fixtures=args.fixtures,
        encoder=spec,
        embedding_cache=args.embedding_cache,
        threshold=args.threshold,
    )
    t = tables.timing
    e = t["embeddings"]
    print(
        f"scored {len(tables.rows)} transcripts into {args.run_dir / 'scores'} in {t['total_s']:.1f} s "
        f"(embeddings: {e['cached']} cached, {e['computed']} computed)"
    )
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
    p.add_argument("--no-contact-sheet", action="store_true", help="skip writing contact sheets")
    p.set_defaults(func=cmd_record)

    p = sub.add_parser(
        "score",
        help="score a run: caption rubric, segmentation sweep, paired statistics -> RUN_DIR/scores/",
        description="Score every transcript of a run against the fixtures' ground truth and write tables "
        "(rows, aggregate, threshold sweep, paired statistics, audit) to RUN_DIR/scores/. Frame-caption "
        "embeddings are cached in RUN_DIR/embeddings, so re-scoring needs no torch.",
    )
    p.add_argument("run_dir", type=Path, metavar="RUN_DIR", help="run directory written by `vlmproprio run`")
    p.add_argument("--fixtures", type=Path, default=None, help="fixture folder (default: the one in RUN_DIR/run.json)")
    p.add_argument("--threshold", type=float, default=0.65, help="similarity threshold for boundaries (default 0.65)")
    p.add_argument(
        "--encoder", default=None, metavar="PATH", help="local sentence-transformers folder (default: all-MiniLM-L6-v2)"
    )
    p.add_argument("--encoder-batch-size", type=int, default=8, help="fixed encoder batch size (part of the cache key)")
    p.add_argument("--encoder-threads", type=int, default=1, help="torch threads while encoding (default 1)")
    p.add_argument(
        "--embedding-cache", type=Path, default=None, help="embedding cache folder (default RUN_DIR/embeddings)"
    )
    p.set_defaults(func=cmd_score)

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
