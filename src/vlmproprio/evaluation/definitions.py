"""The names scoring shares with its readers: the scores' version, the metrics compared, the settings of a score.

The metric lists are derived from the one metric table (evaluation.metrics): the paired statistics use
PAIRED_METRICS; the report, compare and the inspect scorers read the table too, so none can drift apart.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

# the scores' version lives with the stamp that records it; importable from here too, beside the metric lists
from vlmproprio.evaluation.metrics import caption_metrics, final_totals, paired_metrics
from vlmproprio.options import check_range
from vlmproprio.run_folder import SCORES_VERSION as SCORES_VERSION
from vlmproprio.segmentation import DEFAULT_THRESHOLD, THRESHOLDS
from vlmproprio.stats import DEFAULT_N_BOOT, DEFAULT_N_PERM, DEFAULT_SEED

# derived from the metric table (evaluation.metrics.METRICS), in its order
FINAL_TOTALS = final_totals()  # the final caption's totals: caption tables report them after the rubric items
CAPTION_METRICS = caption_metrics()
PAIRED_METRICS = paired_metrics()  # the rubric's, then segmentation at the out-of-sample threshold


@dataclass(frozen=True)
class ScoreSettings:
    """How a run is scored: the segmentation thresholds and the paired statistics (recorded in meta.json)."""

    threshold: float = DEFAULT_THRESHOLD
    thresholds: Sequence[float] = THRESHOLDS
    comparisons: Sequence[tuple[str, str]] | None = None  # None: default_comparisons of the run's conditions
    n_boot: int = DEFAULT_N_BOOT
    n_perm: int = DEFAULT_N_PERM
    seed: int = DEFAULT_SEED

    def __post_init__(self) -> None:
        # every front door (CLI, Python API, inspect and lmms-eval tasks) builds these: NaN would pass a range
        # check (every comparison with it is false) and score no boundary at all
        for name, values in (("threshold", [self.threshold]), ("thresholds", list(self.thresholds))):
            for x in values:
                check_range(name, float(x), 0.0, 1.0)
