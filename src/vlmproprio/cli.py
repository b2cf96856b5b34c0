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

from vlmproprio.errors import UsageError, VlmproprioError

DEFAULT_FIXTURES = Path("fixtures")
RESPONSE_CACHE_HELP = "response cache folder (default: $VLMPROPRIO_CACHE/responses, else ./.vlmproprio-cache/responses)"

EPILOG = """\
typical use:
  vlmproprio verify                          check the shipped fixtures against their manifest
  vlmproprio run --model reference           caption all 22 episodes under every condition
  vlmproprio import-demos demo.hdf5 --out my_fixtures    your own robosuite demos as episodes
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

    record_all(args.fixtures, episode_ids=args.episodes, contact_sheets=args.contact_sheets)
    return 0


def cmd_import_demos(args: argparse.Namespace) -> int:
    from vlmproprio.record.demos import import_demos

    results = import_demos(
        args.file,
        args.out,
        args.task,
        camera=args.camera,
        demos=args.demos,
        replay_mode=args.replay,
        prefix=args.prefix,
        progress=not args.no_progress,
    )
    for r in results:
        print(f"{r['episode_id']}: {r['demo']}, {r['steps']} steps, {r['frames']} frames, {r['replay']} replay")
    wall = sum(r["wall_s"] for r in results)
    print(f"imported {len(results)} demos into {args.out} in {wall:.1f} s ({wall / len(results):.1f} s per demo)")
    return 0


def cmd_make_tiny_model(args: argparse.Namespace) -> int:
    import time

    from vlmproprio.backends.tiny import build_tiny_model, file_hashes

    t0 = time.perf_counter()
    out = build_tiny_model(args.family, args.out, seed=args.seed)
    size = sum((out / rel).stat().st_size for rel in file_hashes(out))
    print(f"built tiny {args.family} (seed {args.seed}) in {out}: {size:,} bytes, {time.perf_counter() - t0:.1f} s")
    return 0


def cmd_cassette(args: argparse.Namespace) -> int:
    from vlmproprio.backends.registry import cassette_path, model_slug
    from vlmproprio.cache import ResponseCache, default_cache_dir, export_cassette, import_cassette
    from vlmproprio.episodes import register_fixture_file

    cache_dir = args.cache or default_cache_dir()
    with ResponseCache(cache_dir) as cache:
        if args.action == "export":
            path = args.out or cassette_path(args.model, args.cassette_dir)
            path, n = export_cassette(cache, model_slug(args.model), path, merge=not args.replace)
            manifest = register_fixture_file(path)
            print(f"wrote {n} answers of {args.model} to {path}" + (f" (updated {manifest})" if manifest else ""))
        else:
            model, n = import_cassette(cache, args.cassette)
            print(f"imported {n} new answers of {model} from {args.cassette} into {cache_dir}")
    return 0


def cmd_models(args: argparse.Namespace) -> int:
    from vlmproprio.backends.registry import format_registry

    print(format_registry())
    return 0


def cmd_run(args: argparse.Namespace) -> int:
    from vlmproprio.backends.registry import BackendSettings
    from vlmproprio.conditions import parse_conditions
    from vlmproprio.pipeline import PipelineSettings
    from vlmproprio.prompts import PromptOptions
    from vlmproprio.runner import RunPlan, run

    if args.max_new_tokens is not None and args.max_new_tokens < 1:
        raise UsageError(f"--max-new-tokens must be at least 1, got {args.max_new_tokens}")
    plan = RunPlan(
        models=tuple(args.model),
        conditions=tuple(parse_conditions(args.conditions)),
        fixtures=args.fixtures,
        out=args.out or Path("runs") / "latest",
        episode_ids=tuple(args.episodes) if args.episodes else None,
        mode=args.mode,
        cache_dir=args.cache_dir,
        pipeline=PipelineSettings(
            k=args.k,
            frame_stride=args.frame_stride,
            max_images_p3=args.max_images_p3,
            prompt=PromptOptions(example=not args.no_example),
        ),
        max_new_tokens=args.max_new_tokens,
        backend=BackendSettings(
            device=args.device,
            dtype=args.dtype,
            attn_implementation=args.attn,
            max_batch_size=args.batch_size,
            threads=args.threads,
            static_cache=args.static_cache,
            max_batch_tokens=args.batch_tokens,
            base_url=args.base_url,
            api_key_env=args.api_key_env,
            concurrency=args.concurrency,
            timeout_s=args.timeout,
        ),
        progress=not args.no_progress,
    )
    runs = run(plan)
    for r in runs:
        s = r.stats
        print(
            f"{r.name}: {len(r.transcripts)} transcripts in {plan.out}, "
            f"{s.get('hits', 0)} cached answers, {s.get('misses', 0)} model calls"
            + (f", cassette {r.cassette}" if r.cassette else "")
        )
    if args.report:
        return _score_and_report(plan.out, args.fixtures)
    return 0


def _score_and_report(run_dir: Path, fixtures: Path | None) -> int:
    from vlmproprio.evaluation import score_run
    from vlmproprio.report import write_report

    score_run(run_dir, fixtures=fixtures)
    index = write_report(run_dir, fixtures=fixtures)
    print(f"report: {index}")
    return 0


def _comma_list(text: str | None) -> list[str] | None:
    return [x.strip() for x in text.split(",") if x.strip()] if text else None


def cmd_report(args: argparse.Namespace) -> int:
    from vlmproprio.report import scores_present, write_report

    if not scores_present(args.run_dir):
        from vlmproprio.evaluation import score_run

        if not args.run_dir.is_dir():
            raise UsageError(f"{args.run_dir}: run directory not found")
        score_run(args.run_dir, fixtures=args.fixtures)
        print(f"scored {args.run_dir} (no scores were there)")
    index = write_report(
        args.run_dir,
        fixtures=args.fixtures,
        out=args.out,
        examples=_comma_list(args.examples),
        trace_conditions=_comma_list(args.trace_conditions),
    )
    print(f"report: {index}")
    return 0


def cmd_compare(args: argparse.Namespace) -> int:
    from vlmproprio.io import atomic_write_text
    from vlmproprio.report import compare_runs

    kwargs = {}
    if args.metrics:
        kwargs["metrics"] = _comma_list(args.metrics)
    comparison = compare_runs(
        args.run_a,
        args.run_b,
        model_a=args.model_a,
        model_b=args.model_b,
        tasks=_comma_list(args.task),
        **kwargs,
    )
    text = comparison.to_markdown()
    print(text, end="")
    if args.out:
        atomic_write_text(args.out, text)
        print(f"wrote {args.out}")
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
    p.add_argument(
        "--contact-sheets",
        type=Path,
        default=Path("runs/contact_sheets"),
        help="folder for one contact sheet per episode (default: runs/contact_sheets)",
    )
    p.set_defaults(func=cmd_record)

    p = sub.add_parser(
        "import-demos",
        help="import robosuite / robomimic demo.hdf5 demonstrations as episodes (needs the [record] extra)",
        description="Replay each demonstration of a robosuite or robomimic demo.hdf5 in its robosuite env, "
        "render a frame every 20 steps as the recorder does, derive states and ground truth, and write episodes "
        "and the manifest into --out (usable as `vlmproprio run --fixtures OUT`). Tasks: door, "
        "pick_place_cereal, pick_place_can, lift.",
    )
    p.add_argument("file", type=Path, metavar="FILE.hdf5", help="robosuite or robomimic demo file")
    p.add_argument("--task", help="door | pick_place_cereal | pick_place_can | lift (default: from the file's env)")
    p.add_argument("--out", type=Path, required=True, help="fixture folder to write episodes/ and manifest.json into")
    p.add_argument("--camera", help="camera to render (default: the task's, e.g. vlmproprio_bins for pick-place)")
    p.add_argument("--demos", nargs="+", metavar="NAME", help="only these demos, e.g. demo_1 demo_3 (default: all)")
    p.add_argument(
        "--replay",
        choices=("auto", "actions", "states"),
        default="auto",
        help="actions: re-simulate the recorded actions, checked bit for bit against the recorded states; states: "
        "set the recorded states; auto: actions when they reproduce every state, else states (default)",
    )
    p.add_argument("--prefix", help="episode id prefix (default: imp_<task>, giving ids like imp_door_01)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=cmd_import_demos)

    p = sub.add_parser(
        "make-tiny-model",
        help="build a tiny random VLM checkpoint for tests (offline, sha256-reproducible)",
        description="Build a tiny random checkpoint (real architecture, ~1 MB, gibberish output) into a folder. "
        "Usable as --model hf:DIR; the registry's tiny-* names build theirs on first use.",
    )
    p.add_argument("--family", required=True, help="qwen2-vl, qwen2.5-vl or llava")
    p.add_argument("--out", type=Path, required=True, help="output folder")
    p.add_argument("--seed", type=int, default=0)
    p.set_defaults(func=cmd_make_tiny_model)

    p = sub.add_parser(
        "run",
        help="caption episodes with a model under each condition (Processes 1-3)",
        description="Run the paper's captioning method: for every episode and condition, Process 1 (a caption "
        "per frame, in groups of k), Process 2 (a scene caption per group) and Process 3 (one final "
        "instruction). Answers are cached by content, so an interrupted run resumes where it stopped.",
    )
    _add_fixtures(p)
    p.add_argument(
        "--model",
        action="append",
        required=True,
        help="registry name, hf:<path|id> or openai:<name>; repeat for several (see `vlmproprio models`)",
    )
    p.add_argument(
        "--conditions",
        default="all",
        help="comma list of none, ee, joint, both, both_shuffled, "
        "both_noisy, state_only, primitives; or paper, controls, all (default: all)",
    )
    p.add_argument("--episodes", nargs="+", metavar="ID", help="episode ids (default: every episode in --fixtures)")
    p.add_argument(
        "--mode",
        choices=("live", "record", "replay"),
        default="live",
        help="live: run the model, use and fill the cache (default); record: live and write the answers "
        "to <fixtures>/responses/<model>.jsonl; replay: answers only from that cassette",
    )
    p.add_argument("--out", type=Path, help="run directory (default: runs/latest)")
    p.add_argument(
        "--cache-dir",
        type=Path,
        help=RESPONSE_CACHE_HELP,
    )
    p.add_argument("--report", action="store_true", help="also score the run and write its report")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    g = p.add_argument_group("method")
    g.add_argument("--k", type=int, default=5, help="frames per group (default 5, the paper's)")
    g.add_argument(
        "--frame-stride",
        type=int,
        default=1,
        help="use every n-th sampled frame (default 1: every 20 sim steps, the paper's)",
    )
    g.add_argument("--max-images-p3", type=int, help="cap on images in Process 3 for small-context models")
    g.add_argument("--no-example", action="store_true", help="leave the worked cube-stacking example out")
    g.add_argument("--max-new-tokens", type=int, help="per answer (default: the model's, 512; tiny test models 64)")
    g = p.add_argument_group("local models (hf)")
    g.add_argument("--device", default="cpu", help="cpu | cuda | cuda:N | auto (default cpu)")
    g.add_argument("--dtype", default="auto", help="auto | float32 | bfloat16 | float16 (default auto)")
    g.add_argument("--attn", default="sdpa", help="attention implementation: eager | sdpa | flash_attention_2")
    g.add_argument("--batch-size", type=int, default=8, help="requests per generate() call (default 8)")
    g.add_argument("--threads", type=int, help="torch threads (pin to 1 for bit-identical CPU runs)")
    g.add_argument(
        "--batch-tokens",
        type=int,
        help="cap on a batch's rows x longest prompt, in tokens (default: 16384 on a CPU, none on a GPU)",
    )
    g.add_argument(
        "--static-cache",
        action="store_true",
        help="static KV cache; on a GPU the decode step is compiled (first batches pay ~1 min; pays on long runs)",
    )
    g = p.add_argument_group("OpenAI-compatible servers (openai)")
    g.add_argument("--base-url", help="server URL, e.g. http://127.0.0.1:8000/v1 for vLLM (default: OpenAI)")
    g.add_argument("--api-key-env", default="OPENAI_API_KEY", help="environment variable holding the key")
    g.add_argument("--concurrency", type=int, default=4, help="requests in flight (default 4)")
    g.add_argument("--timeout", type=float, default=120.0, help="seconds per request (default 120)")
    p.set_defaults(func=cmd_run)

    p = sub.add_parser("models", help="list the model registry")
    p.set_defaults(func=cmd_models)

    p = sub.add_parser("cassette", help="move recorded answers between the response cache and fixtures/responses/")
    csub = p.add_subparsers(dest="action", metavar="ACTION", required=True)
    pe = csub.add_parser("export", help="cache -> fixtures/responses/<model>.jsonl (merged with what is there)")
    pe.add_argument("--model", required=True, help="model name, as given to --model when the answers were made")
    pe.add_argument(
        "--cache",
        type=Path,
        help=RESPONSE_CACHE_HELP,
    )
    pe.add_argument("--cassette-dir", type=Path, default=Path("fixtures/responses"))
    pe.add_argument("--out", type=Path, help="cassette file (default: <cassette-dir>/<model slug>.jsonl)")
    pe.add_argument("--replace", action="store_true", help="start the cassette anew instead of merging")
    pe.set_defaults(func=cmd_cassette)
    pi = csub.add_parser("import", help="cassette -> response cache")
    pi.add_argument("cassette", type=Path, help="a .jsonl cassette")
    pi.add_argument(
        "--cache",
        type=Path,
        help=RESPONSE_CACHE_HELP,
    )
    pi.set_defaults(func=cmd_cassette)

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
        "--embedding-cache",
        type=Path,
        default=None,
        help="embedding cache folder (default: $VLMPROPRIO_CACHE/embeddings, else ./.vlmproprio-cache/embeddings)",
    )
    p.set_defaults(func=cmd_score)

    p = sub.add_parser(
        "report",
        help="tables, plots (paper Figs. 5-8) and an HTML page for a run -> RUN_DIR/report/",
        description="Write RUN_DIR/report/: report.md (aggregate and paired tables), PNG plots mirroring the "
        "paper's Figs. 5-8 plus boundary F1 vs threshold, and index.html (summary, plots, tables, every "
        "episode's frames beside its captions with the rubric matches highlighted). Scores the run first "
        "if RUN_DIR/scores/ is missing.",
    )
    p.add_argument("run_dir", type=Path, metavar="RUN_DIR", help="run directory written by `vlmproprio run`")
    p.add_argument("--fixtures", type=Path, default=None, help="fixture folder (default: the one in RUN_DIR/run.json)")
    p.add_argument("--out", type=Path, default=None, help="report folder (default: RUN_DIR/report)")
    p.add_argument(
        "--examples",
        metavar="IDS",
        help="comma list of episodes for the trace figures (default: the first Door and the first bin episode)",
    )
    p.add_argument(
        "--trace-conditions",
        metavar="CONDS",
        help="comma list of conditions in the trace figures (default: none,both, as in the paper)",
    )
    p.set_defaults(func=cmd_report)

    p = sub.add_parser(
        "compare",
        help="metric differences between two runs, or two models in one run",
        description="Print the differences B - A of the caption and segmentation metrics per task and "
        "condition, paired by episode, with bootstrap 95% CIs and sign-flip p-values. Rows are matched on "
        "model/task/condition; give --model-a/--model-b to compare two models (inside one run: omit RUN_B).",
    )
    p.add_argument("run_a", type=Path, metavar="RUN_A", help="scored run directory (A)")
    p.add_argument("run_b", type=Path, metavar="RUN_B", nargs="?", help="scored run directory (B; default RUN_A)")
    p.add_argument("--model-a", help="model of side A")
    p.add_argument("--model-b", help="model of side B")
    p.add_argument("--task", metavar="TASKS", help="comma list of door, pick_place, all (default: every one)")
    p.add_argument("--metrics", metavar="COLS", help="comma list of score columns (default: the main metrics)")
    p.add_argument("--out", type=Path, help="also write the comparison as Markdown to this file")
    p.set_defaults(func=cmd_compare)

    return parser


class _ScrubbingStream:
    """A console stream that masks secrets (vlmproprio.secrets) in everything written to it."""

    def __init__(self, stream) -> None:
        self._stream = stream

    def write(self, text: str) -> int:
        from vlmproprio.secrets import scrub

        self._stream.write(scrub(text) if isinstance(text, str) else text)
        return len(text)

    def __getattr__(self, name: str):
        return getattr(self._stream, name)


def _scrub_log_records() -> None:
    """Mask secrets in every log record (libraries' debug logs included) before any handler sees it."""
    import logging

    from vlmproprio.secrets import scrub

    factory = logging.getLogRecordFactory()
    if getattr(factory, "vlmproprio_scrubs", False):
        return

    def make(*args, **kwargs):
        record = factory(*args, **kwargs)
        try:
            message = record.getMessage()
        except Exception:  # a malformed log call: leave it to logging's own error handling
            return record
        clean = scrub(message)
        if clean != message:
            record.msg, record.args = clean, None
        return record

    make.vlmproprio_scrubs = True  # type: ignore[attr-defined]
    logging.setLogRecordFactory(make)


def main(argv: Sequence[str] | None = None) -> int:
    from vlmproprio.io import is_write_failure, write_error
    from vlmproprio.secrets import scrub

    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "command", None):
        parser.print_help()
        return 2
    func: Callable[[argparse.Namespace], int] = args.func
    out, err = sys.stdout, sys.stderr
    sys.stdout, sys.stderr = _ScrubbingStream(out), _ScrubbingStream(err)
    _scrub_log_records()
    try:
        return func(args)
    except KeyboardInterrupt:
        print("vlmproprio: interrupted", file=sys.stderr)
        return 130
    except Exception as exc:
        if not isinstance(exc, VlmproprioError) and is_write_failure(exc):
            # a write that did not go through vlmproprio.io (a library's own file): still one line
            exc = write_error(getattr(exc, "filename", None) or "a file", exc)
        if args.debug or not isinstance(exc, VlmproprioError):
            import traceback

            print(scrub(traceback.format_exc()), end="", file=sys.stderr)
            return 1 if not isinstance(exc, VlmproprioError) else 2
        print(f"vlmproprio: error: {scrub(str(exc))}", file=sys.stderr)
        return 2
    finally:
        for stream in (sys.stdout, sys.stderr):
            stream.flush()
        sys.stdout, sys.stderr = out, err


if __name__ == "__main__":
    sys.exit(main())
