"""Score a whole run: caption rubric, segmentation sweep and paired statistics into RUN_DIR/scores/.

Reads ``RUN_DIR/run.json`` (for the fixture root) and every transcript under
``RUN_DIR/transcripts/``, loads the ground truth of each episode, and writes:

* ``rows.json`` / ``rows.csv``: one row per (model, episode, condition) with every metric;
* ``aggregate.json`` / ``aggregate.csv``: means per (model, task, condition), task "all" included;
* ``sweep.json`` / ``sweep.csv``: per (model, episode, condition, threshold 0.00..1.00): number of
  segmentation points, boundary P/R/F1 at tolerance 0/1/2 frames, MS-TCN edit score, F1@{10,25,50},
  frame accuracy and the unmerged edit score;
  ``sweep_aggregate.json`` / ``.csv``: their means per (model, task, condition, threshold);
* ``paired.json`` / ``paired.csv``: condition differences paired by episode (bootstrap CI, sign-flip p), each
  marked primary (a pre-registered hypothesis, Holm-corrected) or exploratory (Benjamini-Hochberg q);
* ``verdicts.json``: per model and primary hypothesis supported / not supported / inconclusive, and the
  sanity warnings (vlmproprio.verdicts);

Segmentation is scored at the paper's fixed threshold (columns ``seg_*``) and at a threshold chosen out of
sample (``seg_loo_*``): for each episode, the threshold with the best mean boundary F1 (+-1 frame) on the
*other* episodes of its task, same model and condition (ties: the lowest). Every segmentation metric has
chance baselines for the same number of points (``*_chance``: random positions, exact or 10 000 seeded
draws; ``*_even``: evenly spaced) and its lift over random chance (``*_lift``); ``seg_groups_*`` scores
boundaries at the edges of the pipeline's frame groups. The in-sample best threshold is not a score: it
exists only in the sweep tables (and the report's sweep plot, marked optimistic).
* ``audit.json``: per caption, every matched span with its verdict, and what was expected;
* ``traces.json``: every similarity trace with its predicted and true boundaries;
* ``frames.csv``: one row per (model, episode, condition, frame) for pandas, R or a spreadsheet (frame_table);
* ``meta.json``: encoder name, revision and key, lexicon versions and hashes, settings;
* ``timing.json``: wall times and cache counts -- the only file that differs between repeated runs;
* ``stamp.json``: the digest of exactly the transcripts, run configuration, ground truth, settings and code
  version these scores come from, and the sha256 of every other file (one generation: see below).

Given the same transcripts, fixtures and cached embeddings, every file but
timing.json is byte-identical across runs, processes and machines.

``score_run`` (run.py) is a sequence of stages, each in its own module, passing typed data:

1. inputs.load_run_inputs -> RunInputs: run.json, exactly the run's transcripts, their episodes;
2. captions.embed_captions -> EmbeddedCaptions: frame captions aligned with frames, and their vectors;
3. cells.score_cells -> CellScores: per cell the rubric, the trace, the sweep, the audit;
4. chance.add_segmentation_baselines -> Baselines: out-of-sample thresholds (out_of_sample), chance, lifts;
5. tables.aggregate_tables -> Aggregates; controls.control_correlations; statistics.paired_statistics -> Statistics;
6. meta.score_meta, the optional judge (judge.judge_table), the per-frame table (frame_table), then
   generations: the score files and frames.csv swapped in as one stamped generation.

Every name other modules use is importable from ``vlmproprio.evaluation`` itself, those of the run folder it reads
and stamps (vlmproprio.run_folder) included.
"""

from vlmproprio.evaluation.captions import EmbeddedCaptions, align_frames, embed_captions
from vlmproprio.evaluation.cells import CellScores, FinalCaption, score_cells
from vlmproprio.evaluation.chance import CHANCE_CACHE_VERSION, Baselines, ChanceTable, add_chance
from vlmproprio.evaluation.controls import control_correlations
from vlmproprio.evaluation.definitions import (
    CAPTION_METRICS,
    FINAL_TOTALS,
    PAIRED_METRICS,
    SCORES_VERSION,
    ScoreSettings,
)
from vlmproprio.evaluation.formats import dumps_csv, dumps_json
from vlmproprio.evaluation.generations import GENERATION_PREFIX, score_inputs, swap_in_generation, write_score_tables
from vlmproprio.evaluation.inputs import (
    DEFAULT_GROUP_SIZE,
    RunInputs,
    condition_order,
    frame_group_size,
    frame_texts,
    load_run_inputs,
)
from vlmproprio.evaluation.judge import judge_table
from vlmproprio.evaluation.meta import MISSING_POLICY, score_meta
from vlmproprio.evaluation.out_of_sample import LOO_RULE, SEG_COLUMNS, add_out_of_sample, loo_thresholds
from vlmproprio.evaluation.run import score_run
from vlmproprio.evaluation.statistics import Statistics, default_comparisons, paired_statistics, paired_table
from vlmproprio.evaluation.tables import ID_COLUMNS, Aggregates, ScoreTables, aggregate_tables
from vlmproprio.run_folder import (
    STAMP_FILE,
    ScoreRunError,
    StaleScoresError,
    check_scores,
    code_version,
    read_run_manifest,
    resolve_fixtures,
    run_configuration,
    run_transcript_files,
    transcripts_digest,
)

__all__ = [
    "CAPTION_METRICS",
    "CHANCE_CACHE_VERSION",
    "DEFAULT_GROUP_SIZE",
    "FINAL_TOTALS",
    "GENERATION_PREFIX",
    "ID_COLUMNS",
    "LOO_RULE",
    "MISSING_POLICY",
    "PAIRED_METRICS",
    "SCORES_VERSION",
    "SEG_COLUMNS",
    "STAMP_FILE",
    "Aggregates",
    "Baselines",
    "CellScores",
    "ChanceTable",
    "EmbeddedCaptions",
    "FinalCaption",
    "RunInputs",
    "ScoreRunError",
    "ScoreSettings",
    "ScoreTables",
    "StaleScoresError",
    "Statistics",
    "add_chance",
    "add_out_of_sample",
    "aggregate_tables",
    "align_frames",
    "check_scores",
    "code_version",
    "condition_order",
    "control_correlations",
    "default_comparisons",
    "dumps_csv",
    "dumps_json",
    "embed_captions",
    "frame_group_size",
    "frame_texts",
    "judge_table",
    "load_run_inputs",
    "loo_thresholds",
    "paired_statistics",
    "paired_table",
    "read_run_manifest",
    "resolve_fixtures",
    "run_configuration",
    "run_transcript_files",
    "score_cells",
    "score_inputs",
    "score_meta",
    "score_run",
    "swap_in_generation",
    "transcripts_digest",
    "write_score_tables",
]
