"""A run's commands: run (caption episodes with models under each condition), show (a cell's prompts again)."""

from __future__ import annotations

import argparse
import sys
from dataclasses import replace
from pathlib import Path

from vlmproprio.cli.arguments import (
    RUN_FIXTURES_HELP,
    add_cache_dir,
    add_fixtures,
    add_list,
    add_no_progress,
    add_run_dir,
    add_workers,
    cache_root_of,
    command,
    fixtures_of,
)
from vlmproprio.cli.backend_options import add_backend_options, backend_settings
from vlmproprio.cli.cassette import embed_recorded_sidecars
from vlmproprio.cli.report import score_and_report
from vlmproprio.errors import UsageError
from vlmproprio.options import (
    CONDITIONS_HELP,
    DEFAULT_CONDITIONS,
    DEFAULT_MODE,
    EPISODES_HELP,
    MODE_HELP,
    MODEL_HELP,
    MODES,
    check_range,
    split_list,
)


def _check_run_ranges(args: argparse.Namespace) -> None:
    """Numbers whose range argparse cannot check; the messages the backends and pipeline would give, earlier."""
    if args.max_new_tokens is not None and args.max_new_tokens < 1:
        raise UsageError(f"--max-new-tokens must be at least 1, got {args.max_new_tokens}")
    check_range("--k", args.k, 1)
    check_range("--frame-stride", args.frame_stride, 1)
    check_range("--max-images-p3", args.max_images_p3, 0)
    check_range("--batch-size", args.batch_size, 1)
    check_range("--threads", args.threads, 1)
    check_range("--batch-tokens", args.batch_tokens, 1)


def cmd_run(args: argparse.Namespace) -> int:
    from vlmproprio.conditions import parse_conditions
    from vlmproprio.parallel import parse_workers
    from vlmproprio.pipeline import PipelineSettings
    from vlmproprio.prompts import PromptOptions
    from vlmproprio.runner import RunPlan, answer_problem_warning, run

    _check_run_ranges(args)
    fixtures = fixtures_of(args)
    models = split_list(args.model)
    if not models:
        raise UsageError("empty model name (--model NAME; see `vlmproprio models`)")
    cache_root = cache_root_of(args)
    plan = RunPlan(
        models=tuple(models),
        conditions=tuple(parse_conditions(args.conditions or DEFAULT_CONDITIONS)),
        fixtures=fixtures,
        out=args.out or Path("runs") / "latest",
        episode_ids=tuple(split_list(args.episodes)) or None,
        mode=args.mode,
        cache_dir=cache_root,
        pipeline=PipelineSettings(
            k=args.k,
            frame_stride=args.frame_stride,
            max_images_p3=args.max_images_p3,
            prompt=PromptOptions(example=not args.no_example, version=args.prompt_version),
        ),
        max_new_tokens=args.max_new_tokens,
        thinking={"on": True, "off": False}.get(args.thinking),
        backend=backend_settings(args, home=cache_root),
        progress=not args.no_progress,
        workers=None if args.workers is None else parse_workers(args.workers, "--workers"),
        allow_empty_answers=args.allow_empty_answers,
    )
    if args.limit is not None:
        plan = replace(plan, episode_ids=_first_episodes(plan, args.limit))
    if args.dry_run:
        from vlmproprio.preview import format_costs, preview_run

        print(format_costs(preview_run(plan)), end="")
        print("dry run: no model was called and nothing was written")
        return 0
    runs = run(plan)
    if args.mode == "record":
        embed_recorded_sidecars(runs, plan.out, plan.fixtures)
    for r in runs:
        print(f"{r.name}: {len(r.transcripts)} transcripts in {plan.out} ({r.mode}); {answer_summary(r)}")
        warning = answer_problem_warning(r)
        if warning:
            print(f"warning: {warning}", file=sys.stderr)
    if args.report:
        return score_and_report(plan.out, fixtures, cache_root, progress=not args.no_progress)
    return 0


def _first_episodes(plan, limit: int) -> tuple[str, ...]:
    """``--limit N``: the first N of the chosen episodes (of every episode when none were named)."""
    from vlmproprio.episodes import list_episode_ids

    check_range("--limit", limit, 1)
    ids = plan.episode_ids or tuple(list_episode_ids(plan.fixtures))
    return tuple(ids[:limit])


def answer_summary(r) -> str:
    """Where a model run's answers came from: replayed from a cassette, from the response cache, or computed."""
    hits, misses = r.stats.get("hits", 0), r.stats.get("misses", 0)
    if r.model.is_rules:
        return f"{hits} answers from the response cache, {misses} computed by rules (no model)"
    if r.mode == "replay":
        return f"{misses} answers replayed from the cassette, 0 model calls"
    text = f"{hits} answers from the response cache, {misses} computed by the model"
    return text + (f"; cassette {r.cassette}" if r.cassette else "")


def cmd_show(args: argparse.Namespace) -> int:
    from vlmproprio.show import format_shown, rerender

    shown = rerender(args.run_dir, args.episode, args.condition, model=args.model, fixtures=args.fixtures)
    print(format_shown(shown), end="")
    differ = sum(not s.matches for s in shown)
    print(f"{len(shown)} requests; {len(shown) - differ} match the keys the run recorded, {differ} differ")
    return 0 if not differ else 1


def add_run(sub) -> None:
    p = command(sub, "run", cmd_run)
    add_fixtures(p)
    p.add_argument("--model", action="append", required=True, metavar="NAMES", help=MODEL_HELP)
    add_list(p, "--conditions", CONDITIONS_HELP, "CONDS")
    add_list(p, "--episodes", EPISODES_HELP, "IDS", spaces=True)
    p.add_argument("--mode", choices=MODES, default=DEFAULT_MODE, help=MODE_HELP)
    p.add_argument("--out", type=Path, help="run directory (default: runs/latest)")
    add_cache_dir(p)
    p.add_argument("--report", action="store_true", help="also score the run and write its report")
    p.add_argument(
        "--dry-run",
        action="store_true",
        help="print the requests per model, process and condition, the images sent and the answers already "
        "cached, then stop: no model is called, nothing is written",
    )
    p.add_argument(
        "--limit", type=int, metavar="N", help="only the first N episodes (of --episodes, or of all): a quick try"
    )
    p.add_argument(
        "--allow-empty-answers",
        action="store_true",
        help="record: write answers that hold no caption (empty, refused, filtered, tool calls) or came from "
        "another model into the cassette too (refused by default)",
    )
    add_workers(
        p, "captioning with a model that is not called (the rule-based captioners, a cassette's replay)", "transcripts"
    )
    add_no_progress(p)
    _add_method_options(p.add_argument_group("method"))
    add_backend_options(p)


def _add_method_options(g) -> None:
    """run: how the paper's method is applied (the prompts and frames a model sees)."""
    g.add_argument("--k", type=int, default=5, help="frames per group (default 5, the paper's)")
    g.add_argument(
        "--frame-stride",
        type=int,
        default=1,
        help="use every n-th sampled frame (default 1: every 20 sim steps, the paper's)",
    )
    g.add_argument("--max-images-p3", type=int, help="cap on images in Process 3 for small-context models")
    g.add_argument("--no-example", action="store_true", help="leave the worked cube-stacking example out")
    g.add_argument(
        "--prompt-version",
        choices=("suite", "paper-verbatim"),
        default="suite",
        help="suite (default): texts that say only what the condition sends; paper-verbatim: the paper's texts as printed",
    )
    g.add_argument("--max-new-tokens", type=int, help="per answer (default: the model's, 512; tiny test models 64)")
    g.add_argument(
        "--thinking",
        choices=("on", "off"),
        help="a reasoning model's thinking switch: enable_thinking in an hf model's chat template, chat_template_kwargs "
        "for a vLLM/SGLang server (default: the template's own; part of the cache key when given)",
    )


def add_show(sub) -> None:
    p = command(sub, "show", cmd_show)
    add_run_dir(p)
    p.add_argument("--episode", required=True, help="episode id, e.g. door_00")
    p.add_argument("--condition", required=True, help="condition, e.g. both")
    p.add_argument("--model", help="model name or slug (default: the run's only model)")
    add_fixtures(p, RUN_FIXTURES_HELP)
