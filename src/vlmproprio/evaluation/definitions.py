"""The names scoring shares with its readers: the scores' version, the metrics compared, the settings of a score.

The metric lists are defined once here: the paired statistics use PAIRED_METRICS, and the report and
the compare command build theirs from CAPTION_METRICS and FINAL_TOTALS, so the three cannot drift apart.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

# the scores' version lives with the stamp that records it; importable from here too, beside the metric lists
from vlmproprio.run_folder import SCORES_VERSION as SCORES_VERSION
from vlmproprio.segmentation import DEFAULT_THRESHOLD, THRESHOLDS
from vlmproprio.stats import DEFAULT_N_BOOT, DEFAULT_N_PERM, DEFAULT_SEED

# the final caption's totals: every caption table and comparison reports them after the rubric items
FINAL_TOTALS = ("final_all_correct", "final_words", "final_hits_per_word")
CAPTION_METRICS = (
    "final_object_correct",
    "final_action_correct",
    "final_trajectory_mentioned",
    "final_trajectory_correct",
    *FINAL_TOTALS,
)
PAIRED_METRICS = (
    *CAPTION_METRICS,
    # segmentation at the out-of-sample (leave-one-episode-out) threshold; lifts are over random chance
    "seg_loo_points",
    "seg_loo_f1_tol1",
    "seg_loo_f1_tol1_lift",
    "seg_loo_edit_lift",
    "seg_loo_f1_at_25_lift",
)


@dataclass(frozen=True)
class ScoreSettings:
    """How a run is scored: the segmentation thresholds and the paired statistics (recorded in meta.json)."""

    threshold: float = DEFAULT_THRESHOLD
    thresholds: Sequence[float] = THRESHOLDS
    comparisons: Sequence[tuple[str, str]] | None = None  # None: default_comparisons of the run's conditions
    n_boot: int = DEFAULT_N_BOOT
    n_perm: int = DEFAULT_N_PERM
    seed: int = DEFAULT_SEED
