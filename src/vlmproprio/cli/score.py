"""The score command: a run's scores (and, with --judge, a judge model's agreement with the rubric), its verdicts."""

from __future__ import annotations

import argparse
from pathlib import Path

from vlmproprio.cli.arguments import (
    RUN_FIXTURES_HELP,
    add_cache_dir,
    add_encoder,
    add_fixtures,
    add_no_progress,
    add_run_dir,
    add_workers,
    cache_root_of,
    command,
)
from vlmproprio.cli.backend_options import add_kind_options, backend_settings
from vlmproprio.options import DEFAULT_MODE, MODE_HELP, MODES, check_range


def cmd_score(args: argparse.Namespace) -> int:
    from vlmproprio.embeddings import DEFAULT_BATCH_SIZE, DEFAULT_THREADS, encoder_spec
    from vlmproprio.evaluation import score_run
    from vlmproprio.evaluation.frame_table import FRAMES_CSV
    from vlmproprio.parallel import parse_workers

    check_range("--threshold", args.threshold, 0.0, 1.0)
    check_range("--encoder-batch-size", args.encoder_batch_size, 1)
    check_range("--encoder-threads", args.encoder_threads, 1)
    default = (args.encoder, args.encoder_batch_size, args.encoder_threads) == (
        None,
        DEFAULT_BATCH_SIZE,
        DEFAULT_THREADS,
    )
    # the default encoder is resolved by score_run: from its package, or (torch-free) from the models' sidecars
    embedding_cache = cache_root_of(args) / "embeddings"
    spec = (
        None
        if default
        else encoder_spec(args.encoder, batch_size=args.encoder_batch_size, threads=args.encoder_threads)
    )
    score = dict(
        fixtures=args.fixtures,
        encoder=spec,
        embedding_cache=embedding_cache,
        threshold=args.threshold,
        progress=not args.no_progress,
        claims=args.claims,
        workers=None if args.workers is None else parse_workers(args.workers, "--workers"),
    )
    tables = _score_with_judge(args, score) if args.judge else score_run(args.run_dir, **score)
    csv_path = args.run_dir / "scores" / FRAMES_CSV
    t = tables.timing
    e = t["embeddings"]
    print(
        f"scored {len(tables.rows)} transcripts into {args.run_dir / 'scores'} in {t['total_s']:.1f} s "
        f"(embeddings: {e['sidecar']} from sidecars, {e['cached']} cached, {e['computed']} computed); "
        f"per-frame table {csv_path}"
    )
    if tables.judge is not None:
        agr = tables.judge["agreement"]
        kappas = ", ".join(
            f"{k} {v['kappa']:.2f}" if v["kappa"] is not None else f"{k} -" for k, v in agr["items"].items()
        )
        print(
            f"judge {args.judge}: {agr['n']} final captions, {agr['unparsed']} unparsed; rubric vs judge kappa: {kappas}"
        )
    _print_headline(args.run_dir)
    _print_verdicts(tables.verdicts)
    return 0


def _print_headline(run_dir) -> None:
    """The headline means per model and condition, as `report` prints them: the numbers on screen, not a path."""
    from vlmproprio.report.data import load_run_scores
    from vlmproprio.report.terminal import terminal_summary

    print(terminal_summary(load_run_scores(run_dir)), end="")


def _print_verdicts(doc: dict) -> None:
    """The verdict on each primary hypothesis and every sanity warning, one line each."""
    from vlmproprio.verdicts import format_combined, format_verdict

    for w in doc.get("warnings", []):
        print(f"WARNING {w['model']}: {w['message']}")
    for c in doc.get("combined", []):  # the questions first, then the hypotheses that answer them
        print(f"claim {c['model']}: {format_combined(c)}")
    for v in doc.get("verdicts", []):
        print(f"verdict {v['model']}: {format_verdict(v)}")


def _score_with_judge(args: argparse.Namespace, score: dict):
    """score_run with a judge model whose requests go through the response cache and cassettes like captioning."""
    from vlmproprio.answering import open_answerer
    from vlmproprio.evaluation import read_run_manifest, resolve_fixtures, score_run

    # through the bounded JSON loader: a damaged run.json is one line naming it, as everywhere else
    fixtures = resolve_fixtures(args.run_dir, read_run_manifest(args.run_dir), args.fixtures)
    settings = backend_settings(args, cassette_dir=fixtures / "responses")
    with open_answerer(args.judge, args.judge_mode, settings, cache_root_of(args)) as judge:
        return score_run(args.run_dir, **score, judge=judge)


def add_score(sub) -> None:
    p = command(sub, "score", cmd_score)
    add_run_dir(p)
    add_fixtures(p, RUN_FIXTURES_HELP)
    p.add_argument(
        "--threshold", type=float, default=0.65, help="similarity threshold for boundaries, in [0, 1] (default 0.65)"
    )
    add_encoder(
        p,
        "local sentence-transformers folder (default: all-MiniLM-L6-v2)",
        "fixed encoder batch size (part of the cache key)",
    )
    p.add_argument("--encoder-threads", type=int, default=1, help="torch threads while encoding (default 1)")
    add_cache_dir(p)
    add_no_progress(p)
    _add_judge_options(p.add_argument_group("judge model (optional; the rubric stays the reference)"))
    p.add_argument(
        "--claims",
        type=Path,
        default=None,
        metavar="FILE",
        help="pre-registered primary hypotheses (default: the packaged claims.yml; format in docs/metrics.md)",
    )
    add_workers(p, "scoring a large run", "scores")


def _add_judge_options(g) -> None:
    g.add_argument(
        "--judge",
        metavar="MODEL",
        help="also grade the final captions with this model (registry name, hf:, openai:); its agreement with "
        "the rubric (Cohen's kappa) goes to scores/judge.json and the report",
    )
    g.add_argument(
        "--judge-mode",
        choices=MODES,
        default=DEFAULT_MODE,
        help="as `run --mode`: " + MODE_HELP,
    )
    add_kind_options(g, "score")  # --judge-threads (hf), --base-url and --api-key-env (openai)
