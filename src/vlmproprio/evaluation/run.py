"""score_run: a run's transcripts to RUN_DIR/scores/, as a sequence of stages (see the package docstring)."""

from __future__ import annotations

import time
from collections.abc import Sequence
from pathlib import Path

from vlmproprio.evaluation.captions import EmbeddedCaptions, embed_captions
from vlmproprio.evaluation.cells import score_cells
from vlmproprio.evaluation.chance import Baselines, add_segmentation_baselines
from vlmproprio.evaluation.controls import control_correlations
from vlmproprio.evaluation.definitions import ScoreSettings
from vlmproprio.evaluation.frame_table import FRAMES_CSV, frame_table_text
from vlmproprio.evaluation.generations import score_file_texts, score_inputs, swap_in_generation
from vlmproprio.evaluation.inputs import RunInputs, load_run_inputs
from vlmproprio.evaluation.judge import judge_table
from vlmproprio.evaluation.meta import score_meta
from vlmproprio.evaluation.statistics import paired_statistics
from vlmproprio.evaluation.tables import ScoreTables, aggregate_tables
from vlmproprio.parallel import resolve_workers
from vlmproprio.segmentation import DEFAULT_THRESHOLD, THRESHOLDS
from vlmproprio.stats import DEFAULT_N_BOOT, DEFAULT_N_PERM, DEFAULT_SEED
from vlmproprio.verdicts import load_claims


class _Stages:
    """The progress bar over a score's stages (load, embed, score, statistics, write) and the wall time of each."""

    def __init__(self, progress: bool) -> None:
        from tqdm import tqdm

        self._bar = tqdm(total=5, desc="score: loading", unit="stage", disable=not progress or None, leave=False)
        self.start = self._last = time.perf_counter()
        self.seconds: dict[str, float] = {}  # per stage, in order

    def lap(self, stage: str) -> float:
        """Record the seconds since the previous lap (or the start) as ``stage``'s."""
        now = time.perf_counter()
        self.seconds[stage], self._last = now - self._last, now
        return self.seconds[stage]

    def done(self, stage: str, next_stage: str) -> None:
        """``stage`` is over (lap and a step of the bar); ``next_stage`` starts."""
        self.lap(stage)
        self._bar.update()
        self._bar.set_description(f"score: {next_stage}")

    def close(self) -> None:
        self._bar.update()
        self._bar.close()


def _timing(seconds: dict[str, float], baselines: Baselines, captions: EmbeddedCaptions) -> dict:
    return {
        "load_s": seconds["load"],
        "embed_s": seconds["embed"],
        "score_segment_s": seconds["score"],
        "chance_s": seconds["chance"],
        "chance": {"computed": baselines.computed, "cached": baselines.cached, "precomputed": baselines.precomputed},
        "stats_s": seconds["stats"],
        "embeddings": captions.embedding_stats,
    }


def _write(inputs: RunInputs, tables: ScoreTables, workers: int) -> None:
    """Write the tables and the per-frame table as a new generation of RUN_DIR/scores/, stamped with the digests
    of their inputs."""
    meta, judged = tables.meta, tables.judge
    score_settings = {k: meta[k] for k in ("encoder", "segmentation", "stats")} | {
        "judge": judged["backend"] if judged else None
    }
    stamp = score_inputs(
        inputs.run_dir,
        inputs.manifest,
        inputs.transcript_files,
        inputs.fixtures,
        inputs.episode_ids,
        score_settings,
        meta["lexicons"],
        inputs.transcript_documents if len(inputs.transcript_documents) == len(inputs.transcript_files) else None,
    )
    # the per-frame table goes into the same stamped generation: every caller of score_run gets it
    files = score_file_texts(tables, workers) | {FRAMES_CSV: frame_table_text(tables, inputs.transcripts)}
    swap_in_generation(inputs.run_dir, files, stamp)


def score_run(
    run_dir: str | Path,
    fixtures: str | Path | None = None,
    encoder=None,
    *,
    embedding_cache: str | Path | None = None,
    chance_cache: str | Path | None = None,
    threshold: float = DEFAULT_THRESHOLD,
    thresholds: Sequence[float] = THRESHOLDS,
    comparisons: Sequence[tuple[str, str]] | None = None,
    n_boot: int = DEFAULT_N_BOOT,
    n_perm: int = DEFAULT_N_PERM,
    seed: int = DEFAULT_SEED,
    verify: bool = True,
    write: bool = True,
    judge=None,
    sidecars: Sequence[str | Path] | None = None,
    progress: bool = False,
    claims: str | Path | None = None,
    workers: int | None = None,
) -> ScoreTables:
    """Score every transcript of a run and (by default) write RUN_DIR/scores/, the per-frame table frames.csv
    (frame_table) included.

    ``encoder`` is an ``embeddings.EncoderSpec`` (default: the packaged all-MiniLM-L6-v2); embeddings are cached
    in ``embedding_cache`` (default <cache root>/embeddings, shared by every run: its entries are keyed
    by encoder and text), so re-scoring a run needs no torch. Chance baselines are cached in ``chance_cache``
    (default: next to the embedding cache, ``<cache root>/chance``). ``judge`` (off by
    default) is any vlmproprio Backend that also grades the final captions; its agreement with the rubric
    goes to scores/judge.json. Frame-caption vectors are read first from ``sidecars`` (default: the
    ``<fixtures>/responses/<model>.embeddings.npz`` of the run's models; ``()``: none), so a replayed
    cassette is scored without loading the encoder. ``progress`` shows a bar over the stages (load, embed,
    score, statistics, write). ``claims`` is the file of pre-registered primary hypotheses (default: the
    packaged vlmproprio/claims.yml); their verdicts and the sanity warnings go to scores/verdicts.json.
    ``workers``: processes for scoring the cells of a large run and rendering its score files (default:
    ``$VLMPROPRIO_WORKERS``, else the usable cores, at most 4; see vlmproprio.parallel); the scores are the same
    with any number."""
    workers = resolve_workers(workers)
    stages = _Stages(progress)
    claim_set = load_claims(claims)
    settings = ScoreSettings(threshold, thresholds, comparisons, n_boot, n_perm, seed)
    inputs = load_run_inputs(Path(run_dir), fixtures, verify)
    stages.done("load", "embedding captions")
    captions = embed_captions(inputs, encoder, embedding_cache, sidecars)
    stages.done("embed", "rubric and segmentation")
    cells = score_cells(inputs, captions, settings.thresholds, settings.threshold, workers)
    stages.lap("score")
    chance_dir = Path(chance_cache) if chance_cache is not None else captions.cache_dir.parent / "chance"
    baselines = add_segmentation_baselines(inputs, cells, settings.thresholds, chance_dir)
    stages.done("chance", "paired statistics")
    tables = aggregate_tables(inputs, cells)
    controls = control_correlations(inputs.fixtures, inputs.episodes, inputs.conditions)
    stats = paired_statistics(tables.rows, inputs.conditions, cells.outputs, settings, claim_set, baselines.group_size)
    stages.done("stats", "writing")
    meta = score_meta(inputs, captions, cells.lexicons, baselines, controls, stats, settings)
    scores = ScoreTables(
        **vars(tables),
        paired=stats.paired,
        audit=cells.audit,
        traces=cells.traces,
        meta=meta,
        timing=_timing(stages.seconds, baselines, captions),
        verdicts=stats.verdicts,
    )
    if judge is not None:  # grades the final captions; its agreement with the rubric goes to scores/judge.json
        scores.judge = judge_table(judge, cells.finals)
        scores.timing["judge_s"] = stages.lap("judge")
    if write:
        _write(inputs, scores, workers)
    stages.close()
    scores.timing["total_s"] = time.perf_counter() - stages.start
    return scores
