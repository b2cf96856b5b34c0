"""The metric table: one MetricSpec per score column, and every list of metrics derived from it.

A metric is named here once. The paired statistics, the report's tables and headline, the compare command,
the benchmark's regression gates, the inspect scorers and the table in docs/metrics.md all read ``METRICS``
(through the functions below), so none of them keeps a list of names of its own. Adding a metric is one row
here; a metric no scoring stage writes yet brings its function as ``compute`` (evaluation.cells adds its
column to every row).

The table lives in evaluation, the stage that writes the score rows: everything that reads it (report,
inspect, the benchmark) comes later, and it imports only the rubric's items, so ``definitions`` (the first
evaluation module) can derive its lists from it.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Literal

from vlmproprio.scoring import ITEMS

if TYPE_CHECKING:
    import numpy as np

    from vlmproprio.episodes import Episode
    from vlmproprio.scoring import CaptionScore
    from vlmproprio.segmentation import SweepPoint
    from vlmproprio.transcripts import Transcript

# how a value and a difference of it print: int (whole number), count (a mean of counts or a 0-100 score, one
# decimal), rate (a share, in percent; differences in percentage points), f1 (a 0-1 score, two decimals),
# ratio (three decimals)
Unit = Literal["int", "count", "rate", "f1", "ratio"]
# what the number is about: the episodes behind a mean, the parse, the rubric's verdict on one item of the
# final caption, the final caption as a whole, the scene captions, the segmentation, the similarity trace
Kind = Literal["episodes", "parse", "rubric", "caption", "scene", "segmentation", "similarity"]
# how the benchmark gates a cell's value: exactly (YAML baselines) or within a tolerance (CSV baselines)
Gate = Literal["", "exact", "float"]
Report = Literal["", "captions", "segmentation"]


@dataclass(frozen=True)
class CellView:
    """What a cell's row is computed from: the argument of a MetricSpec's ``compute``."""

    transcript: Transcript
    episode: Episode
    final: CaptionScore  # the rubric on the final caption (an empty text when it is missing)
    scenes: Sequence[CaptionScore]
    frame_status: Sequence[str]  # ok | recovered | missing, per frame
    at_threshold: SweepPoint  # the segmentation at the fixed threshold
    trace: np.ndarray  # the similarity trace of consecutive frame captions
    threshold: float


@dataclass(frozen=True)
class MetricSpec:
    """One score column: how it is labelled and printed, and which readers use it.

    ``name`` is the column of scores/rows.csv (and aggregate.csv) the readers take the value from; ``compute``
    is None when a scoring stage writes that column already, else the function that gives a cell's value.
    """

    name: str
    label: str
    unit: Unit
    kind: Kind
    paired: bool = False  # compared between conditions, paired by episode (scores/paired.*)
    gated: Gate = ""
    gate_key: str = ""  # exact gates: the value's dotted path in the YAML baseline
    primary: bool = False  # the metric of a pre-registered primary hypothesis (the packaged claims.yml)
    compare: bool = False  # what the compare command compares by default
    report: Report = ""  # the report's aggregate table that shows it
    headline: bool = False  # in the report's summary table
    compute: Callable[[CellView], float | int | None] | None = None


def _final_items() -> tuple[MetricSpec, ...]:
    """The rubric's verdicts on the final caption: per item mentioned, correct and wrong (0 or 1)."""
    out = []
    for item in ITEMS:
        for what in ("mentioned", "correct", "wrong"):
            out.append(
                MetricSpec(
                    f"final_{item}_{what}",
                    f"{item} {what}",
                    "rate",
                    "rubric",
                    paired=what == "correct" or (item, what) == ("trajectory", "mentioned"),
                    gated="exact",
                    gate_key=f"final_caption.{item}.{what}",
                    primary=(item, what) == ("trajectory", "correct"),
                    compare=what == "correct" or (item, what) == ("trajectory", "mentioned"),
                    report="captions" if what != "wrong" else "",
                    headline=(item, what) == ("trajectory", "correct"),
                )
            )
    return tuple(out)


def _scene_items() -> tuple[MetricSpec, ...]:
    """The shares of a cell's scene captions that mention / get right / get wrong each item."""
    return tuple(
        MetricSpec(f"scene_{item}_{what}", f"scene {item} {what}", "rate", "scene", gated="float")
        for item in ITEMS
        for what in ("mentioned", "correct", "wrong")
    )


def _boundary_prf() -> tuple[MetricSpec, ...]:
    """Boundary precision, recall and F1 at the fixed threshold, at a tolerance of 0, 1 and 2 frames."""
    return tuple(
        MetricSpec(
            f"seg_{m}_tol{t}",
            "F1 @thr" if (m, t) == ("f1", 1) else f"seg {m} tol{t}",
            "f1",
            "segmentation",
            gated="float",
            compare=(m, t) == ("f1", 1),
            report="segmentation" if (m, t) == ("f1", 1) else "",
        )
        for t in (0, 1, 2)
        for m in ("p", "r", "f1")
    )


def _chance(metric: str, unit: Unit, labels: tuple[str, str, str] | None = None) -> tuple[MetricSpec, ...]:
    """A fixed-threshold score's random-chance baseline, evenly spaced baseline and lift over chance."""
    words = metric.replace("_", " ")
    chance, even, lift = labels or (f"seg {words} chance", f"seg {words} even", f"seg {words} lift")
    return (
        MetricSpec(f"seg_{metric}_chance", chance, unit, "segmentation", gated="float"),
        MetricSpec(f"seg_{metric}_even", even, unit, "segmentation", gated="float"),
        MetricSpec(
            f"seg_{metric}_lift",
            lift,
            unit,
            "segmentation",
            gated="float",
            report="segmentation" if metric == "f1_tol1" else "",
        ),
    )


def _seg(name: str, label: str, unit: Unit = "f1", **flags) -> MetricSpec:
    return MetricSpec(name, label, unit, "segmentation", **flags)


# The order is every derived list's order: the report's columns, the paired metrics, the gates' CSV columns.
# fmt: off
METRICS: tuple[MetricSpec, ...] = (
    MetricSpec("n_episodes", "n", "int", "episodes", report="captions"),
    *_final_items(),
    MetricSpec("final_all_correct", "all correct", "rate", "caption", paired=True, gated="exact",
               gate_key="final_caption.all_correct", compare=True, report="captions", headline=True),
    MetricSpec("final_words", "words", "count", "caption", paired=True, gated="exact",
               gate_key="final_caption.words", compare=True, report="captions", headline=True),
    MetricSpec("final_hits", "hits", "f1", "caption", gated="exact", gate_key="final_caption.keyword_hits"),
    MetricSpec("final_hits_per_word", "hits/word", "ratio", "caption", paired=True, gated="float", compare=True,
               report="captions"),
    MetricSpec("scene_words", "scene words", "count", "scene", gated="float"),
    *_scene_items(),
    MetricSpec("scene_all_correct", "scene all correct", "rate", "scene", gated="float"),
    _seg("seg_threshold", "seg threshold", gated="exact", gate_key="segmentation.threshold"),
    _seg("seg_gt_boundaries", "true boundaries", "count", gated="exact",
         gate_key="segmentation.ground_truth_boundaries", report="segmentation"),
    _seg("seg_points", "points @thr", "count", gated="exact", gate_key="segmentation.points_at_threshold",
         compare=True, report="segmentation"),
    *_boundary_prf(),
    _seg("seg_f1_tol1_gebd", "F1 @thr (GEBD rule)"),
    _seg("seg_edit", "edit @thr", "count", gated="float"),
    _seg("seg_edit_unmerged", "seg edit unmerged", "count", gated="float"),
    _seg("seg_f1_at_10", "seg f1 at 10", gated="float"),
    _seg("seg_f1_at_25", "seg f1 at 25", gated="float"),
    _seg("seg_f1_at_50", "seg f1 at 50", gated="float"),
    _seg("seg_frame_acc", "seg frame acc", gated="float"),
    *_chance("f1_tol1", "f1", ("chance F1 @thr", "seg f1 tol1 even", "F1 lift @thr")),
    *_chance("edit", "count"),
    *_chance("f1_at_25", "f1"),
    # at the threshold chosen out of sample (leave one episode out): what the paired tests compare
    _seg("seg_loo_threshold", "LOO thr", report="segmentation"),
    _seg("seg_loo_points", "points LOO", "count", paired=True, report="segmentation"),
    _seg("seg_loo_f1_tol1", "F1 LOO", paired=True, compare=True, report="segmentation"),
    # the same points by GEBD's greedy matching rule (segmentation.boundary_prf_gebd): never above the maximum
    _seg("seg_loo_f1_tol1_gebd", "F1 LOO (GEBD rule)", report="segmentation"),
    _seg("seg_loo_f1_tol1_chance", "chance F1", report="segmentation"),
    _seg("seg_loo_f1_tol1_even", "even F1", report="segmentation"),
    _seg("seg_loo_f1_tol1_lift", "F1 lift", paired=True, compare=True, report="segmentation"),
    # the content-free baselines (evaluation.chance.CONTENT_FREE_RULE): a metronome beats random chance, not these
    _seg("seg_loo_f1_tol1_periodic", "periodic F1"),
    _seg("seg_loo_f1_tol1_shift", "shifted F1"),
    _seg("seg_loo_f1_tol1_cf", "content-free F1", report="segmentation"),
    _seg("seg_loo_f1_tol1_lift_cf", "F1 lift (content-free)", paired=True, primary=True, compare=True,
         report="segmentation", headline=True),
    _seg("seg_loo_edit", "edit LOO", "count", report="segmentation"),
    _seg("seg_loo_edit_chance", "chance edit", "count"),
    _seg("seg_loo_edit_lift", "edit lift", "count", paired=True, report="segmentation"),
    _seg("seg_loo_edit_lift_cf", "edit lift (content-free)", "count", paired=True),
    _seg("seg_loo_f1_at_25", "F1@25 LOO", report="segmentation"),
    _seg("seg_loo_f1_at_25_lift", "F1@25 lift", paired=True),
    _seg("seg_loo_f1_at_50", "F1@50 LOO"),
    _seg("seg_groups_f1_tol1", "group-edge F1", gated="float", report="segmentation"),
    MetricSpec("sim_mean", "sim mean", "f1", "similarity", gated="float"),
    MetricSpec("sim_min", "sim min", "f1", "similarity", gated="float"),
    MetricSpec("n_frames", "n frames", "f1", "parse", gated="exact", gate_key="parse.frames"),
    MetricSpec("frames_missing", "frames missing", "count", "parse", gated="exact", gate_key="parse.frames_missing",
               report="segmentation"),
    MetricSpec("frames_recovered", "frames recovered", "f1", "parse", gated="exact",
               gate_key="parse.frames_recovered"),
    MetricSpec("n_scenes", "n scenes", "f1", "parse", gated="exact", gate_key="parse.scenes"),
    MetricSpec("scenes_missing", "scenes missing", "rate", "parse", gated="exact", gate_key="parse.scenes_missing"),
    MetricSpec("final_missing", "final missing", "rate", "parse", gated="exact", gate_key="parse.final_missing"),
)
# fmt: on

BY_NAME: dict[str, MetricSpec] = {m.name: m for m in METRICS}


# ---------------------------------------------------------------------------------------------- derived lists


def names(keep: Callable[[MetricSpec], bool], table: Iterable[MetricSpec] = METRICS) -> tuple[str, ...]:
    """The names of the table's metrics that ``keep`` accepts, in the table's order."""
    return tuple(m.name for m in table if keep(m))


def paired_metrics(table: Iterable[MetricSpec] = METRICS) -> tuple[str, ...]:
    return names(lambda m: m.paired, table)


def caption_metrics(table: Iterable[MetricSpec] = METRICS) -> tuple[str, ...]:
    """The paired metrics of the final caption: the rubric's items, then its totals."""
    return names(lambda m: m.paired and m.kind in ("rubric", "caption"), table)


def final_totals(table: Iterable[MetricSpec] = METRICS) -> tuple[str, ...]:
    """The paired totals of the final caption (every caption table reports them after the rubric items)."""
    return names(lambda m: m.paired and m.kind == "caption", table)


def segmentation_paired(table: Iterable[MetricSpec] = METRICS) -> tuple[str, ...]:
    return names(lambda m: m.paired and m.kind == "segmentation", table)


def compare_metrics(table: Iterable[MetricSpec] = METRICS) -> tuple[str, ...]:
    return names(lambda m: m.compare, table)


def report_columns(report: Report, table: Iterable[MetricSpec] = METRICS) -> tuple[str, ...]:
    return names(lambda m: m.report == report, table)


def headline_metrics(table: Iterable[MetricSpec] = METRICS) -> tuple[str, ...]:
    return names(lambda m: m.headline, table)


def primary_metrics(table: Iterable[MetricSpec] = METRICS) -> tuple[str, ...]:
    return names(lambda m: m.primary, table)


def gated_metrics(gate: Gate, table: Iterable[MetricSpec] = METRICS) -> tuple[str, ...]:
    return names(lambda m: m.gated == gate, table)


def computed_columns(view: CellView, table: Iterable[MetricSpec] = METRICS) -> dict:
    """A cell's values of the metrics no scoring stage writes, by their ``compute``."""
    return {m.name: m.compute(view) for m in table if m.compute is not None}


# ---------------------------------------------------------------------------------------------- docs

DOC_START = "<!-- metric table: generated from vlmproprio.evaluation.metrics.METRICS -->"
DOC_END = "<!-- end of metric table -->"


def _yes(flag: bool) -> str:
    return "yes" if flag else ""


def markdown_table(table: Iterable[MetricSpec] = METRICS) -> str:
    """The metric table as docs/metrics.md shows it (between DOC_START and DOC_END)."""
    lines = [
        "| column | label | unit | kind | paired | gated | primary | compare | report |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for m in table:
        report = m.report + (" (headline)" if m.headline else "")
        cells = (f"`{m.name}`", m.label, m.unit, m.kind, _yes(m.paired), m.gated, _yes(m.primary), _yes(m.compare))
        lines.append("| " + " | ".join((*cells, report)) + " |")
    return "\n".join(lines) + "\n"
