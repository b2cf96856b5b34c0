"""The commands that read scores: report (tables, plots, HTML; scoring first when there are none), compare,
leaderboard."""

from __future__ import annotations

import argparse
from pathlib import Path

from vlmproprio.cli.arguments import (
    RUN_FIXTURES_HELP,
    add_cache_dir,
    add_fixtures,
    add_list,
    add_no_progress,
    add_run_dir,
    cache_root_of,
    command,
)
from vlmproprio.cli.console import stages
from vlmproprio.errors import UsageError
from vlmproprio.options import split_list


def score_and_report(run_dir: Path, fixtures: Path | None, cache: Path, *, progress: bool = True) -> int:
    from vlmproprio.evaluation import score_run
    from vlmproprio.report import write_report

    with stages("score + report", 2, progress) as bar:
        score_run(run_dir, fixtures=fixtures, embedding_cache=cache / "embeddings")
        bar.update()
        index = write_report(run_dir, fixtures=fixtures, cache_dir=cache)
        bar.update()
    print_results(run_dir, fixtures)
    print(f"report: {index}")
    return 0


def print_results(run_dir: Path, fixtures: Path | None = None) -> None:
    """The scores on screen: per model the headline means per condition, then the warnings and verdicts."""
    from vlmproprio.report.data import load_run_scores
    from vlmproprio.report.tables import verdict_lines
    from vlmproprio.report.terminal import terminal_summary

    s = load_run_scores(run_dir, fixtures)
    print(terminal_summary(s), end="")
    for line in verdict_lines(s):
        print(line)


def cmd_report(args: argparse.Namespace) -> int:
    from vlmproprio.report import scores_present, write_report

    progress = not args.no_progress
    cache = cache_root_of(args)
    with stages("report", 2, progress) as bar:
        if not scores_present(args.run_dir):
            from vlmproprio.evaluation import score_run

            if not args.run_dir.is_dir():
                raise UsageError(f"{args.run_dir}: run directory not found")
            bar.set_description("report: scoring (no scores yet)")
            score_run(args.run_dir, fixtures=args.fixtures, progress=progress, embedding_cache=cache / "embeddings")
            print(f"scored {args.run_dir} (no scores were there)")
        bar.update()
        bar.set_description("report: tables, plots, page")
        index = write_report(
            args.run_dir,
            fixtures=args.fixtures,
            out=args.out,
            examples=split_list(args.examples) or None,
            trace_conditions=split_list(args.trace_conditions) or None,
            cache_dir=cache,
        )
        bar.update()
    print_results(args.run_dir, args.fixtures)
    print(f"report: {index}")
    return 0


def cmd_compare(args: argparse.Namespace) -> int:
    from vlmproprio.io import atomic_write_text
    from vlmproprio.report import compare_runs

    kwargs = {}
    if args.metrics:
        kwargs["metrics"] = split_list(args.metrics)
    comparison = compare_runs(
        args.run_a,
        args.run_b,
        model_a=args.model_a,
        model_b=args.model_b,
        tasks=split_list(args.task) or None,
        **kwargs,
    )
    text = comparison.to_markdown()
    print(text, end="")
    if args.out:
        atomic_write_text(args.out, text)
        print(f"wrote {args.out}")
    return 0


def add_report(sub) -> None:
    p = command(sub, "report", cmd_report)
    add_run_dir(p)
    add_fixtures(p, RUN_FIXTURES_HELP)
    p.add_argument("--out", type=Path, default=None, help="report folder (default: RUN_DIR/report)")
    add_list(
        p,
        "--examples",
        "episodes for the trace figures, a comma list or repeated (default: the first Door and the first bin episode)",
        "IDS",
    )
    add_list(
        p,
        "--trace-conditions",
        "conditions in the trace figures, a comma list or repeated (default: none,both, as in the paper)",
        "CONDS",
    )
    add_cache_dir(p)
    add_no_progress(p)


def add_compare(sub) -> None:
    p = command(sub, "compare", cmd_compare)
    p.add_argument("run_a", type=Path, metavar="RUN_A", help="scored run directory (A)")
    p.add_argument("run_b", type=Path, metavar="RUN_B", nargs="?", help="scored run directory (B; default RUN_A)")
    p.add_argument("--model-a", help="model of side A")
    p.add_argument("--model-b", help="model of side B")
    add_list(p, "--task", "door, pick_place, all: a comma list or repeated (default: every one)", "TASKS")
    add_list(p, "--metrics", "score columns, a comma list or repeated (default: the main metrics)", "COLS")
    p.add_argument("--out", type=Path, help="also write the comparison as Markdown to this file")


def cmd_leaderboard(args: argparse.Namespace) -> int:
    from vlmproprio.report.leaderboard import LEADERBOARD_METRICS, build_leaderboard, write_leaderboard

    board = build_leaderboard(
        args.runs,
        metrics=split_list(args.metrics) or LEADERBOARD_METRICS,
        a=args.a,
        b=args.b,
        task=args.task,
    )
    print(board.to_markdown(), end="")
    if args.out:
        paths = write_leaderboard(board, args.out)
        print(f"leaderboard: {paths['html']}")
    return 0


def add_leaderboard(sub) -> None:
    p = command(sub, "leaderboard", cmd_leaderboard)
    p.add_argument("runs", type=Path, nargs="+", metavar="RUN_DIR", help="scored run directories (any number)")
    p.add_argument(
        "--a", default="both", metavar="COND", help="condition A of the paired difference A - B (default: both)"
    )
    p.add_argument("--b", default="none", metavar="COND", help="condition B (default: none)")
    p.add_argument("--task", default="all", metavar="TASK", help="door, pick_place or all (default: all)")
    add_list(p, "--metrics", "score columns, a comma list or repeated (default: the headline metrics)", "COLS")
    p.add_argument("--out", type=Path, metavar="DIR", help="also write index.html, leaderboard.md/.png/.json here")
