"""Subtask segmentation from frame captions and its comparison with ground truth.

The modules follow the data: ``trace`` (captions → similarity trace → segmentation points), ``metrics``
(points against ground truth, many sets at once), ``chance`` (the baselines those scores are read against)
and ``sweep`` (every threshold of a trace scored). Each imports only the ones before it; this package
re-exports their public names, so callers import from ``vlmproprio.segmentation``.
"""

from __future__ import annotations

from vlmproprio.segmentation.chance import (
    CHANCE_DRAWS,
    CHANCE_METRICS,
    CHANCE_SEED,
    chance_groups,
    chance_is_exact,
    chance_periodic,
    chance_random,
    chance_shifted,
    evenly_spaced,
    group_edges,
    random_masks,
    random_orders,
    random_positions,
    score_points,
    shifted_positions,
)
from vlmproprio.segmentation.metrics import (
    IOU_THRESHOLDS,
    PRF,
    TOLERANCES,
    Truth,
    boundary_prf,
    edit_score,
    edit_score_unmerged,
    iou_key,
    levenshtein,
    masks_of,
    predicted_segment_labels,
    score_masks,
    score_positions,
    segments_from_labels,
    truth_of,
)
from vlmproprio.segmentation.sweep import SweepPoint, evaluate_segmentation, sweep
from vlmproprio.segmentation.trace import (
    DEFAULT_THRESHOLD,
    THRESHOLDS,
    CosineCache,
    boundaries_at,
    caption_present,
    cosine,
    cosine_trace,
    segment_counts,
    similarity_trace,
)

__all__ = [
    "CHANCE_DRAWS",
    "CHANCE_METRICS",
    "CHANCE_SEED",
    "DEFAULT_THRESHOLD",
    "IOU_THRESHOLDS",
    "PRF",
    "THRESHOLDS",
    "TOLERANCES",
    "CosineCache",
    "SweepPoint",
    "Truth",
    "boundaries_at",
    "boundary_prf",
    "caption_present",
    "chance_groups",
    "chance_is_exact",
    "chance_periodic",
    "chance_random",
    "chance_shifted",
    "cosine",
    "cosine_trace",
    "edit_score",
    "edit_score_unmerged",
    "evaluate_segmentation",
    "evenly_spaced",
    "group_edges",
    "iou_key",
    "levenshtein",
    "masks_of",
    "predicted_segment_labels",
    "random_masks",
    "random_orders",
    "random_positions",
    "score_masks",
    "score_points",
    "score_positions",
    "segment_counts",
    "segments_from_labels",
    "shifted_positions",
    "similarity_trace",
    "sweep",
    "truth_of",
]
