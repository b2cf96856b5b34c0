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
from vlmproprio.options import (
    CACHE_HELP,
    CONDITIONS_HELP,
    DEFAULT_CONDITIONS,
    DEFAULT_MODE,
    EPISODES_HELP,
    FIXTURES_HELP,
    MODE_HELP,
    MODEL_HELP,
    MODES,
    check_range,
    split_list,
)

EPILOG = """\
typical use:
  vlmproprio verify                          check the shipped fixtures against their manifest
  vlmproprio models                          the models, and which can run here (cassette, weights)
  vlmproprio run --model reference --out runs/reference   caption all 22 episodes under every condition
  vlmproprio report runs/reference           tables, plots and an HTML page for a run
  vlmproprio import-demos demo.hdf5 --out my_fixtures    your own robosuite demos as episodes
  pytest benchmark/ --model tiny-qwen2-vl    the benchmark with its regression gates

lists: --model, --conditions, --episodes ... take a comma list, may be repeated, or both.
fixtures: --fixtures, else $VLMPROPRIO_FIXTURES, else the fixtures/ of the repository you are in.
caches: --cache-dir, else $VLMPROPRIO_CACHE, else the user cache directory (~/.cache/vlmproprio).
"""


# ---------------------------------------------------------------------------------------------- commands


def fixtures_of(args: argparse.Namespace, *, must_exist: bool = True) -> Path:
    """--fixtures, else $VLMPROPRIO_FIXTURES, else the repository's (vlmproprio.locations)."""
    from vlmproprio.locations import resolve_fixtures

    return resolve_fixtures(args.fixtures, must_exist=must_exist)


def cache_root_of(args: argparse.Namespace) -> Path:
    """--cache-dir, else $VLMPROPRIO_CACHE, else the user cache directory."""
    from vlmproprio.locations import cache_root

    return cache_root(args.cache_dir)


def cmd_verify(args: argparse.Namespace) -> int:
    from vlmproprio.summary import fixture_summary, format_summary

    print(format_summary(fixture_summary(fixtures_of(args))))
    return 0


def cmd_manifest(args: argparse.Namespace) -> int:
    from vlmproprio.episodes import write_manifest

    path = write_manifest(fixtures_of(args))
    print(f"wrote {path}")
    return 0


def cmd_record(args: argparse.Namespace) -> int:
    from vlmproprio.record.recorder import record_all

    fixtures = fixtures_of(args, must_exist=False)
    sheets = args.contact_sheets or Path("runs") / "contact_sheets"
    record_all(fixtures, episode_ids=split_list(args.episodes) or None, contact_sheets=sheets)
    return 0


def cmd_import_demos(args: argparse.Namespace) -> int:
    from vlmproprio.record.demos import import_demos

    results = import_demos(
        args.file,
        args.out,
        args.task,
        camera=args.camera,
        demos=split_list(args.demos) or None,
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
    from vlmproprio.cache import ResponseCache
    from vlmproprio.cassettes import export_cassette, import_cassette
    from vlmproprio.episodes import register_fixture_file
    from vlmproprio.models import resolve_model

    cache_dir = cache_root_of(args)  # the response cache is the cache folder's cache.db
    # an unsafe name is refused before anything is opened
    model = resolve_model(args.model) if args.action == "export" else None
    with ResponseCache(cache_dir) as cache:
        if model is not None:
            cassette_dir = args.cassette_dir or (args.out.parent if args.out else fixtures_of(args) / "responses")
            path = args.out or model.cassette(cassette_dir)
            path, n = export_cassette(cache, model.slug, path, merge=not args.replace)
            manifest = register_fixture_file(path)
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


def _embed_recorded(runs, run_dir: Path, fixtures: Path) -> None:
    """After recording: add the new captions' embeddings to each recorded model's sidecar (vlmproprio.sidecars)."""
    from vlmproprio.sidecars import embed_recorded

    for name, build in embed_recorded(runs, run_dir, fixtures):
        if build is None:
            print(f"no embeddings sidecar for {name}: the encoder is not installed (pip install 'vlmproprio[embed]')")
        else:
            _print_sidecar(name, build)


# command-line option (argparse dest) -> backend setting: the one place the two vocabularies meet
SETTING_OPTIONS = {
    "device": "device",
    "dtype": "dtype",
    "attn": "attn_implementation",
    "batch_size": "max_batch_size",
    "threads": "threads",
    "judge_threads": "threads",
    "static_cache": "static_cache",
    "batch_tokens": "max_batch_tokens",
    "allow_download": "allow_download",
    "base_url": "base_url",
    "api_key_env": "api_key_env",
    "concurrency": "concurrency",
    "timeout": "timeout_s",
}


def backend_settings(args: argparse.Namespace, **paths):
    """The backend settings a command's options give (those it has), plus ``paths`` (cassette_dir, home)."""
    from vlmproprio.backends.settings import BackendSettings

    given = {setting: getattr(args, dest) for dest, setting in SETTING_OPTIONS.items() if hasattr(args, dest)}
    return BackendSettings.of(**given, **paths)


def cmd_models(args: argparse.Namespace) -> int:
    from vlmproprio.backends.registry import format_availability
    from vlmproprio.models import format_registry

    if args.plain:
        print(format_registry())
        return 0
    from vlmproprio.locations import resolve_fixtures

    try:
        fixtures = resolve_fixtures(args.fixtures)
    except UsageError:
        fixtures = None
    cassettes = fixtures / "responses" if fixtures else Path("fixtures") / "responses"
    settings = backend_settings(args, cassette_dir=cassettes)
    print(f"cassettes: {cassettes}" + ("" if fixtures else " (no fixture folder found: pass --fixtures)"))
    print(format_availability(settings, split_list(args.model) or None))
    return 0


def _check_run_ranges(args: argparse.Namespace) -> None:
    """Numbers whose range argparse cannot check; the messages the backends and pipeline would give, earlier."""
    if args.max_new_tokens is not None and args.max_new_tokens < 1:
        raise UsageError(f"--max-new-tokens must be at least 1, got {args.max_new_tokens}")
    check_range("--batch-size", args.batch_size, 1)
    check_range("--threads", args.threads, 1)
    check_range("--batch-tokens", args.batch_tokens, 1)


def cmd_run(args: argparse.Namespace) -> int:
    from vlmproprio.conditions import parse_conditions
    from vlmproprio.parallel import parse_workers
    from vlmproprio.pipeline import PipelineSettings
    from vlmproprio.prompts import PromptOptions
    from vlmproprio.runner import RunPlan, run

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
        backend=backend_settings(args, home=cache_root),
        progress=not args.no_progress,
        workers=None if args.workers is None else parse_workers(args.workers, "--workers"),
    )
    runs = run(plan)
    if args.mode == "record":
        _embed_recorded(runs, plan.out, plan.fixtures)
    for r in runs:
        print(f"{r.name}: {len(r.transcripts)} transcripts in {plan.out} ({r.mode}); {answer_summary(r)}")
    if args.report:
        return _score_and_report(plan.out, fixtures, cache_root, progress=not args.no_progress)
    return 0


def answer_summary(r) -> str:
    """Where a model run's answers came from: replayed from a cassette, from the response cache, or computed."""
    hits, misses = r.stats.get("hits", 0), r.stats.get("misses", 0)
    if r.model.is_rules:
        return f"{hits} answers from the response cache, {misses} computed by rules (no model)"
    if r.mode == "replay":
        return f"{misses} answers replayed from the cassette, 0 model calls"
    text = f"{hits} answers from the response cache, {misses} computed by the model"
    return text + (f"; cassette {r.cassette}" if r.cassette else "")


def _score_and_report(run_dir: Path, fixtures: Path | None, cache: Path, *, progress: bool = True) -> int:
    from vlmproprio.evaluation import score_run
    from vlmproprio.report import write_report

    with _stages("score + report", 2, progress) as bar:
        score_run(run_dir, fixtures=fixtures, embedding_cache=cache / "embeddings")
        bar.update()
        index = write_report(run_dir, fixtures=fixtures, cache_dir=cache)
        bar.update()
    print(f"report: {index}")
    return 0


def _stages(desc: str, total: int, enabled: bool):
    """A progress bar over a command's stages (tqdm, on stderr; off with --no-progress or when not a terminal)."""
    from tqdm import tqdm

    return tqdm(total=total, desc=desc, unit="step", disable=not enabled or None, leave=False)


def cmd_report(args: argparse.Namespace) -> int:
    from vlmproprio.report import scores_present, write_report

    progress = not args.no_progress
    cache = cache_root_of(args)
    with _stages("report", 2, progress) as bar:
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
    _print_verdicts(tables.verdicts)
    return 0


def _print_verdicts(doc: dict) -> None:
    """The verdict on each primary hypothesis and every sanity warning, one line each."""
    from vlmproprio.verdicts import format_verdict

    for w in doc.get("warnings", []):
        print(f"WARNING {w['model']}: {w['message']}")
    for v in doc.get("verdicts", []):
        print(f"verdict {v['model']}: {format_verdict(v)}")


def cmd_power(args: argparse.Namespace) -> int:
    from vlmproprio import power

    base = power.PowerSettings()
    settings = power.PowerSettings(
        alpha=base.alpha if args.alpha is None else args.alpha,
        family=base.family if args.family is None else args.family,
        n_sims=base.n_sims if args.sims is None else args.sims,
        seed=base.seed if args.seed is None else args.seed,
    )
    analysis = power.analyse(
        settings,
        words=power.PAPER_WORDS if args.words is None else tuple(args.words),
        sd_words=power.DEFAULT_SD_WORDS if args.sd_words is None else args.sd_words,
        sd_f1=power.DEFAULT_SD_F1 if args.sd_f1 is None else args.sd_f1,
        correctness=power.DEFAULT_CORRECTNESS if args.correctness is None else tuple(args.correctness),
    )
    print(power.summary_markdown(analysis))
    for path in power.write_power(analysis, args.out):
        print(f"wrote {path}")
    return 0


def cmd_export_dataset(args: argparse.Namespace) -> int:
    from vlmproprio.dataset_export import export_dataset

    episodes = split_list(args.episodes) or None
    summary = export_dataset(fixtures_of(args), args.out, episodes, overwrite=args.overwrite)
    print(summary.line())
    return 0


def _score_with_judge(args: argparse.Namespace, score: dict):
    """score_run with a judge model whose requests go through the response cache and cassettes like captioning."""
    from vlmproprio.answering import open_answerer
    from vlmproprio.evaluation import read_run_manifest, resolve_fixtures, score_run

    # through the bounded JSON loader: a damaged run.json is one line naming it, as everywhere else
    fixtures = resolve_fixtures(args.run_dir, read_run_manifest(args.run_dir), args.fixtures)
    settings = backend_settings(args, cassette_dir=fixtures / "responses")
    with open_answerer(args.judge, args.judge_mode, settings, cache_root_of(args)) as judge:
        return score_run(args.run_dir, **score, judge=judge)


def cmd_show(args: argparse.Namespace) -> int:
    from vlmproprio.show import format_shown, rerender

    shown = rerender(args.run_dir, args.episode, args.condition, model=args.model, fixtures=args.fixtures)
    print(format_shown(shown), end="")
    differ = sum(not s.matches for s in shown)
    print(f"{len(shown)} requests; {len(shown) - differ} match the keys the run recorded, {differ} differ")
    return 0 if not differ else 1


# ---------------------------------------------------------------------------------------------- parser


def _add_fixtures(p: argparse.ArgumentParser, help: str = FIXTURES_HELP) -> None:
    p.add_argument("--fixtures", type=Path, default=None, metavar="DIR", help=help)


def _add_cache_dir(p: argparse.ArgumentParser) -> None:
    """One option for the cache root everywhere; --cache and --embedding-cache are the older names."""
    p.add_argument("--cache-dir", type=Path, default=None, metavar="DIR", help=CACHE_HELP)
    p.add_argument("--cache", "--embedding-cache", dest="cache_dir", type=Path, help=argparse.SUPPRESS)


def _add_list(p, flag: str, help: str, metavar: str = "LIST", *, spaces: bool = False) -> None:
    """A list option: a comma list, repeatable (``spaces``: space-separated values accepted too, as before)."""
    if spaces:
        help += "; space-separated values are accepted too"
        p.add_argument(flag, action="extend", nargs="+", metavar=metavar, help=help)
    else:
        p.add_argument(flag, action="append", metavar=metavar, help=help)


def _add_no_progress(p: argparse.ArgumentParser) -> None:
    p.add_argument("--no-progress", action="store_true", help="no progress bar")


# The commands that read a run (score, report, show) take its folder first and its fixtures from run.json.
RUN_FIXTURES_HELP = "fixture folder (default: the one in RUN_DIR/run.json)"


def _add_run_dir(p: argparse.ArgumentParser) -> None:
    p.add_argument("run_dir", type=Path, metavar="RUN_DIR", help="run directory (the --out of the run command)")


def _add_server(g, base_url_help: str) -> None:
    """Where an openai: model is served (run, models, score --judge)."""
    g.add_argument("--base-url", help=base_url_help)
    g.add_argument("--api-key-env", default="OPENAI_API_KEY", help="environment variable holding the key")


def _add_encoder(p, folder_help: str, batch_help: str) -> None:
    """The sentence encoder of the caption embeddings (score, cassette embed)."""
    p.add_argument("--encoder", default=None, metavar="PATH", help=folder_help)
    p.add_argument("--encoder-batch-size", type=int, default=8, help=batch_help)


# Sub-command texts: the line the top-level --help lists, then the description of the command's own --help.
_TEXTS: dict[str, tuple[str, str | None]] = {
    "verify": (
        "check fixtures against their manifest and summarise them",
        None,
    ),
    "manifest": (
        "rewrite the fixtures' manifest.json from the files present",
        None,
    ),
    "record": (
        "(re)record the episodes with robosuite (needs the [record] extra)",
        "Re-record episodes with the scripted operators. Bit-identical on this machine kind "
        "(pinned mujoco, EGL or OSMesa rendering). Writes episodes, the manifest and a contact sheet.",
    ),
    "import-demos": (
        "import robosuite / robomimic demo.hdf5 demonstrations as episodes (needs the [record] extra)",
        "Replay each demonstration of a robosuite or robomimic demo.hdf5 in its robosuite env, "
        "render a frame every 20 steps as the recorder does, derive states and ground truth, and write episodes "
        "and the manifest into --out (usable as `vlmproprio run --model reference --fixtures OUT`). Tasks: door, "
        "pick_place_cereal, pick_place_can, lift.",
    ),
    "make-tiny-model": (
        "build a tiny random VLM checkpoint for tests (offline, sha256-reproducible)",
        "Build a tiny random checkpoint (real architecture, ~1 MB, gibberish output) into a folder. "
        "Usable as --model hf:DIR; the registry's tiny-* names build theirs on first use.",
    ),
    "run": (
        "caption episodes with a model under each condition (Processes 1-3)",
        "Run the paper's captioning method: for every episode and condition, Process 1 (a caption "
        "per frame, in groups of k), Process 2 (a scene caption per group) and Process 3 (one final "
        "instruction). Answers are cached by content, so an interrupted run resumes where it stopped.",
    ),
    "models": (
        "the model registry, and per model whether it can run here (cassette, weights) and how to get it",
        "List the registry's models. For each: is its cassette in <fixtures>/responses/ (replay), can "
        "it run live here (weights in a local folder or the local Hugging Face cache, an API key or --base-url), "
        "and if not, how to get what is missing.",
    ),
    "cassette export": (
        "cache -> fixtures/responses/<model>.jsonl (merged with what is there)",
        None,
    ),
    "cassette import": (
        "cassette -> response cache",
        None,
    ),
    "cassette embed": (
        "(re)build <fixtures>/responses/<model>.embeddings.npz: the model's caption embeddings",
        "Replay the model (its cassette; the reference captioner computes its answers) over every "
        "episode and condition of the fixtures, embed every frame caption scoring uses, and store the vectors "
        "beside the cassette (updating the manifest), so that scoring the replay needs no torch. Needs the "
        "encoder (the [embed] extra).",
    ),
    "score": (
        "score a run: caption rubric, segmentation sweep, paired statistics -> RUN_DIR/scores/",
        "Score every transcript of a run against the fixtures' ground truth and write tables "
        "(rows, aggregate, threshold sweep, paired statistics, audit) and a per-frame table (frames.csv) to "
        "RUN_DIR/scores/. Frame-caption embeddings are cached in <cache root>/embeddings (see --cache-dir), so "
        "re-scoring needs no torch.",
    ),
    "report": (
        "tables, plots (paper Figs. 5-8) and an HTML page for a run -> RUN_DIR/report/",
        "Write RUN_DIR/report/: report.md (aggregate and paired tables), PNG plots mirroring the "
        "paper's Figs. 5-8 plus boundary F1 vs threshold, and index.html (summary, plots, tables, every "
        "episode's frames beside its captions with the rubric matches highlighted). Scores the run first "
        "if RUN_DIR/scores/ is missing.",
    ),
    "compare": (
        "metric differences between two runs, or two models in one run",
        "Print the differences B - A of the caption and segmentation metrics per task and "
        "condition, paired by episode, with bootstrap 95% CIs and sign-flip p-values. Rows are matched on "
        "model/task/condition; give --model-a/--model-b to compare two models (inside one run: omit RUN_B).",
    ),
    "power": (
        "what 10 Door + 12 bin episodes can detect: power curves and minimal detectable effects",
        "Simulate the suite's paired test (exact sign-flip, stats.py) over the episode structure "
        "(10 Door, 12 bins, 22 pooled) for effects of known size, at Holm's first-step level alpha / family. "
        "Writes power.json, power.md and power_curves.png to --out.",
    ),
    "export-dataset": (
        "the episodes as a Hugging Face datasets folder (Parquet + card; needs the [dataset] extra)",
        "Write the episodes as a Hugging Face `datasets` dataset: OUT/frames (one row per frame: "
        "image, joints, end-effector pose, ground-truth phase and direction; the default config), OUT/episodes "
        "and OUT/phases as Parquet, and a dataset card OUT/README.md. Load it with "
        "datasets.load_dataset(OUT) or load_dataset(OUT, 'episodes').",
    ),
    "show": (
        "the full prompt of every request of one episode and condition of a run",
        "Re-render every request (Processes 1-3) of one (episode, condition) of a run from the settings "
        "recorded in RUN_DIR/run.json, the fixtures and the answers in the transcript, and print each message's "
        "full text (images as their sha256). Each request's cache key is compared with the one the run recorded; "
        "exit status 1 if any differs (the prompts or fixtures changed since).",
    ),
}


def _command(sub, name: str, func: Callable[[argparse.Namespace], int]) -> argparse.ArgumentParser:
    """The sub-command ``name`` (of ``cassette``: "cassette NAME"), with its texts from _TEXTS, running ``func``."""
    help, description = _TEXTS[name]
    p = sub.add_parser(name.split()[-1], help=help, description=description)
    p.set_defaults(func=func)
    return p


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("vlmproprio")
    except PackageNotFoundError:  # a source tree on the path without an install
        return "unknown (not installed)"


# ---------------------------------------------------------------------------------------------- sub-commands


def _add_fixture_commands(sub) -> None:
    """verify, manifest, record: the fixture folder itself."""
    p = _command(sub, "verify", cmd_verify)
    _add_fixtures(p)
    p = _command(sub, "manifest", cmd_manifest)
    _add_fixtures(p)
    p = _command(sub, "record", cmd_record)
    _add_fixtures(p, FIXTURES_HELP + "; written if it does not exist")
    _add_list(p, "--episodes", "only these episode ids, a comma list or repeated (default: all 22)", "IDS", spaces=True)
    p.add_argument(
        "--contact-sheets",
        type=Path,
        default=None,
        help="folder for one contact sheet per episode (default: runs/contact_sheets)",
    )


def _add_import_demos(sub) -> None:
    p = _command(sub, "import-demos", cmd_import_demos)
    p.add_argument("file", type=Path, metavar="FILE.hdf5", help="robosuite or robomimic demo file")
    p.add_argument("--task", help="door | pick_place_cereal | pick_place_can | lift (default: from the file's env)")
    p.add_argument("--out", type=Path, required=True, help="fixture folder to write episodes/ and manifest.json into")
    p.add_argument("--camera", help="camera to render (default: the task's, e.g. vlmproprio_bins for pick-place)")
    _add_list(p, "--demos", "only these demos, e.g. demo_1,demo_3 (default: all)", "NAMES", spaces=True)
    p.add_argument(
        "--replay",
        choices=("auto", "actions", "states"),
        default="auto",
        help="actions: re-simulate the recorded actions, checked bit for bit against the recorded states; states: "
        "set the recorded states; auto: actions when they reproduce every state, else states (default)",
    )
    p.add_argument("--prefix", help="episode id prefix (default: imp_<task>, giving ids like imp_door_01)")
    _add_no_progress(p)


def _add_make_tiny_model(sub) -> None:
    p = _command(sub, "make-tiny-model", cmd_make_tiny_model)
    p.add_argument("--family", required=True, help="qwen2-vl, qwen2.5-vl or llava")
    p.add_argument("--out", type=Path, required=True, help="output folder")
    p.add_argument("--seed", type=int, default=0)


def _add_workers(p: argparse.ArgumentParser, what: str, results: str) -> None:
    p.add_argument(
        "--workers",
        metavar="N",
        help=f"processes for {what} (default: $VLMPROPRIO_WORKERS, else the usable cores, at most 4); "
        f"the {results} are the same with any number",
    )


def _add_run(sub) -> None:
    p = _command(sub, "run", cmd_run)
    _add_fixtures(p)
    p.add_argument("--model", action="append", required=True, metavar="NAMES", help=MODEL_HELP)
    _add_list(p, "--conditions", CONDITIONS_HELP, "CONDS")
    _add_list(p, "--episodes", EPISODES_HELP, "IDS", spaces=True)
    p.add_argument("--mode", choices=MODES, default=DEFAULT_MODE, help=MODE_HELP)
    p.add_argument("--out", type=Path, help="run directory (default: runs/latest)")
    _add_cache_dir(p)
    p.add_argument("--report", action="store_true", help="also score the run and write its report")
    _add_workers(
        p, "captioning with a model that is not called (the rule-based captioners, a cassette's replay)", "transcripts"
    )
    _add_no_progress(p)
    _add_method_options(p.add_argument_group("method"))
    _add_hf_options(p.add_argument_group("local models (hf)"))
    g = p.add_argument_group("OpenAI-compatible servers (openai)")
    _add_server(g, "server URL, e.g. http://127.0.0.1:8000/v1 for vLLM (default: OpenAI)")
    g.add_argument("--concurrency", type=int, default=4, help="requests in flight (default 4)")
    g.add_argument("--timeout", type=float, default=120.0, help="seconds per request (default 120)")


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


def _add_hf_options(g) -> None:
    """run: how a local (hf:) model is loaded and batched."""
    g.add_argument(
        "--allow-download",
        action="store_true",
        help="fetch missing hf: weights from the Hugging Face Hub when it is reachable (default: local files only)",
    )
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


def _add_models(sub) -> None:
    p = _command(sub, "models", cmd_models)
    _add_fixtures(p)
    _add_list(p, "--model", "only these models (default: the whole registry); any name --model takes", "NAMES")
    _add_server(p, "OpenAI-compatible server the openai models would use")
    p.add_argument("--allow-download", action="store_true", help="count hf: weights on the Hub as available")
    p.add_argument("--plain", action="store_true", help="only the registry table (name, backend, weights)")


def _add_cassette(sub) -> None:
    p = sub.add_parser("cassette", help="move recorded answers between the response cache and fixtures/responses/")
    csub = p.add_subparsers(dest="action", metavar="ACTION", required=True)
    pe = _command(csub, "cassette export", cmd_cassette)
    pe.add_argument("--model", required=True, help="model name, as given to --model when the answers were made")
    _add_cache_dir(pe)
    _add_fixtures(pe)
    pe.add_argument("--cassette-dir", type=Path, default=None, help="default: <fixtures>/responses")
    pe.add_argument("--out", type=Path, help="cassette file (default: <cassette-dir>/<model slug>.jsonl)")
    pe.add_argument("--replace", action="store_true", help="start the cassette anew instead of merging")
    pe.add_argument(
        "--no-embed", action="store_true", help="do not (re)build the embeddings sidecar beside the cassette"
    )
    pi = _command(csub, "cassette import", cmd_cassette)
    pi.add_argument("cassette", type=Path, help="a .jsonl cassette")
    _add_cache_dir(pi)
    _add_cassette_embed(csub)


def _add_cassette_embed(csub) -> None:
    pm = _command(csub, "cassette embed", cmd_cassette_embed)
    pm.add_argument("--model", required=True, help="model name (a cassette in <fixtures>/responses/, or reference)")
    _add_fixtures(pm)
    pm.add_argument(
        "--run-dir",
        type=Path,
        action="append",
        metavar="RUN_DIR",
        help="take the captions from this run instead of a replay of the whole benchmark (repeatable)",
    )
    pm.add_argument("--merge", action="store_true", help="add to the encoder's stored vectors instead of replacing")
    _add_encoder(pm, "local sentence-transformers folder", "fixed encoder batch size (default 8)")
    _add_cache_dir(pm)
    _add_no_progress(pm)


def _add_score(sub) -> None:
    p = _command(sub, "score", cmd_score)
    _add_run_dir(p)
    _add_fixtures(p, RUN_FIXTURES_HELP)
    p.add_argument(
        "--threshold", type=float, default=0.65, help="similarity threshold for boundaries, in [0, 1] (default 0.65)"
    )
    _add_encoder(
        p,
        "local sentence-transformers folder (default: all-MiniLM-L6-v2)",
        "fixed encoder batch size (part of the cache key)",
    )
    p.add_argument("--encoder-threads", type=int, default=1, help="torch threads while encoding (default 1)")
    _add_cache_dir(p)
    _add_no_progress(p)
    _add_judge_options(p.add_argument_group("judge model (optional; the rubric stays the reference)"))
    p.add_argument(
        "--claims",
        type=Path,
        default=None,
        metavar="FILE",
        help="pre-registered primary hypotheses (default: the packaged claims.yml; format in docs/metrics.md)",
    )
    _add_workers(p, "scoring a large run", "scores")


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
    g.add_argument("--judge-threads", type=int, default=1, help="torch threads of a local judge (default 1)")
    _add_server(g, "OpenAI-compatible server URL for an openai: judge")


def _add_report(sub) -> None:
    p = _command(sub, "report", cmd_report)
    _add_run_dir(p)
    _add_fixtures(p, RUN_FIXTURES_HELP)
    p.add_argument("--out", type=Path, default=None, help="report folder (default: RUN_DIR/report)")
    _add_list(
        p,
        "--examples",
        "episodes for the trace figures, a comma list or repeated (default: the first Door and the first bin episode)",
        "IDS",
    )
    _add_list(
        p,
        "--trace-conditions",
        "conditions in the trace figures, a comma list or repeated (default: none,both, as in the paper)",
        "CONDS",
    )
    _add_cache_dir(p)
    _add_no_progress(p)


def _add_compare(sub) -> None:
    p = _command(sub, "compare", cmd_compare)
    p.add_argument("run_a", type=Path, metavar="RUN_A", help="scored run directory (A)")
    p.add_argument("run_b", type=Path, metavar="RUN_B", nargs="?", help="scored run directory (B; default RUN_A)")
    p.add_argument("--model-a", help="model of side A")
    p.add_argument("--model-b", help="model of side B")
    _add_list(p, "--task", "door, pick_place, all: a comma list or repeated (default: every one)", "TASKS")
    _add_list(p, "--metrics", "score columns, a comma list or repeated (default: the main metrics)", "COLS")
    p.add_argument("--out", type=Path, help="also write the comparison as Markdown to this file")


def _add_power(sub) -> None:
    p = _command(sub, "power", cmd_power)
    p.add_argument("--alpha", type=float, help="family-wise alpha (default 0.05)")
    p.add_argument(
        "--family", type=int, help="primary hypotheses corrected together with Holm (default 4, as in claims.yml)"
    )
    p.add_argument("--sims", type=int, help="simulated data sets per point (default 1000)")
    p.add_argument("--seed", type=int, help="simulation seed (default: the statistics' seed)")
    pair = dict(type=float, nargs=2)  # a value without and one with state
    p.add_argument(
        "--words",
        **pair,
        metavar=("NONE", "BOTH"),
        help="mean words without and with state (default: the paper's 25.2 35.45)",
    )
    p.add_argument("--sd-words", type=float, help="per-episode SD of the paired word difference (default 10)")
    p.add_argument("--sd-f1", type=float, help="per-episode SD of the paired boundary-F1 difference (default 0.15)")
    p.add_argument(
        "--correctness",
        **pair,
        metavar=("P", "Q"),
        help="P(right) with and without state for the episodes-needed line (default 0.6 0.3)",
    )
    p.add_argument("--out", type=Path, default=Path("runs") / "power", help="output folder (default runs/power)")


def _add_export_dataset(sub) -> None:
    p = _command(sub, "export-dataset", cmd_export_dataset)
    p.add_argument("out", type=Path, metavar="OUT", help="folder to write (must be empty or absent)")
    _add_fixtures(p)
    _add_list(
        p, "--episodes", "export these episodes only, a comma list or repeated (default: all)", "IDS", spaces=True
    )
    p.add_argument("--overwrite", action="store_true", help="replace an earlier export in OUT")


def _add_show(sub) -> None:
    p = _command(sub, "show", cmd_show)
    _add_run_dir(p)
    p.add_argument("--episode", required=True, help="episode id, e.g. door_00")
    p.add_argument("--condition", required=True, help="condition, e.g. both")
    p.add_argument("--model", help="model name or slug (default: the run's only model)")
    _add_fixtures(p, RUN_FIXTURES_HELP)


# Sub-commands in the order `vlmproprio --help` lists them.
_SUBCOMMANDS: tuple[Callable[[argparse._SubParsersAction], None], ...] = (
    _add_fixture_commands,
    _add_import_demos,
    _add_make_tiny_model,
    _add_run,
    _add_models,
    _add_cassette,
    _add_score,
    _add_report,
    _add_compare,
    _add_power,
    _add_export_dataset,
    _add_show,
)


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
    parser.add_argument("--version", action="version", version=f"%(prog)s {_version()}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for add in _SUBCOMMANDS:
        add(sub)
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
    except BrokenPipeError:  # e.g. show piped into head: the reader left; not an error of ours
        sys.stdout = None  # type: ignore[assignment]  # nothing more can be written
        return 0
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
