"""Segmentation at every threshold of a sweep, scored against the ground-truth frame phases."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from vlmproprio.segmentation.metrics import (
    IOU_THRESHOLDS,
    PRF,
    TOLERANCES,
    Truth,
    edit_score_unmerged,
    iou_key,
    score_masks,
    truth_of,
)
from vlmproprio.segmentation.trace import THRESHOLDS, boundaries_at


@dataclass(frozen=True)
class SweepPoint:
    threshold: float
    points: int
    prf: dict[int, PRF]  # by tolerance
    edit: float  # MS-TCN segmental edit score
    segmental: dict[str, float]  # f1_at_10/25/50, frame_acc
    edit_unmerged: float

    def flat(self) -> dict:
        d: dict = {"threshold": self.threshold, "points": self.points}
        for tol, m in sorted(self.prf.items()):
            d[f"p_tol{tol}"] = m.precision
            d[f"r_tol{tol}"] = m.recall
            d[f"f1_tol{tol}"] = m.f1
        d["edit"] = self.edit
        d.update(self.segmental)
        d["edit_unmerged"] = self.edit_unmerged
        return d


def _score_distinct_masks(masks: np.ndarray, truth: Truth, tolerances: Sequence[int]) -> dict[str, np.ndarray]:
    """``score_masks(masks, ...)``, each distinct row scored once (most thresholds of a sweep cut a trace at the
    same points). The same numbers: every metric is computed row by row, and the widths the rows are padded
    to (the most points, the most merged segments) are those of the whole set, whose extreme rows stay in."""
    first: dict[bytes, int] = {}
    inverse = np.array([first.setdefault(row.tobytes(), i) for i, row in enumerate(masks)], dtype=np.int64)
    if len(first) == len(masks):
        return score_masks(masks, truth, tolerances)
    rows = np.array(sorted(first.values()), dtype=np.int64)
    slot = np.empty(len(masks), dtype=np.int64)
    slot[rows] = np.arange(len(rows))
    scores = score_masks(masks[rows], truth, tolerances)
    return {name: values[slot[inverse]] for name, values in scores.items()}


def sweep(
    trace: np.ndarray,
    true_labels: Sequence[str],
    thresholds: Sequence[float] = THRESHOLDS,
    tolerances: Sequence[int] = TOLERANCES,
) -> list[SweepPoint]:
    """Segmentation at each threshold against the ground-truth frame phases (one ``score_masks`` call)."""
    n = len(true_labels)
    t = np.asarray(trace, dtype=np.float64)
    if len(t) != max(n - 1, 0):
        raise ValueError(f"trace of length {len(t)} for {n} frames (expected {max(n - 1, 0)})")
    truth = truth_of(true_labels)
    masks = np.stack([t < thr for thr in thresholds]) if len(thresholds) else np.zeros((0, n - 1), dtype=bool)
    sc = _score_distinct_masks(masks, truth, tolerances)
    m = len(truth.boundaries)
    out = []
    unmerged_of: dict[tuple[int, ...], float] = {}  # neighbouring thresholds often give the same points
    for i, thr in enumerate(thresholds):
        k = int(sc["points"][i])
        prf = {
            tol: PRF(
                float(sc[f"p_tol{tol}"][i]),
                float(sc[f"r_tol{tol}"][i]),
                float(sc[f"f1_tol{tol}"][i]),
                int(sc[f"tp_tol{tol}"][i]),
                k,
                m,
            )
            for tol in tolerances
        }
        seg = {iou_key(tau): float(sc[iou_key(tau)][i]) for tau in IOU_THRESHOLDS}
        seg["frame_acc"] = float(sc["frame_acc"][i])
        pts = tuple(boundaries_at(t, thr))
        if pts not in unmerged_of:
            unmerged_of[pts] = edit_score_unmerged(pts, true_labels)
        unmerged = unmerged_of[pts]
        out.append(SweepPoint(thr, k, prf, float(sc["edit"][i]), seg, unmerged))
    return out


def evaluate_segmentation(
    trace: np.ndarray,
    true_labels: Sequence[str],
    threshold: float,
    tolerances: Sequence[int] = TOLERANCES,
) -> SweepPoint:
    """Segmentation at one threshold against the ground-truth frame phases."""
    return sweep(trace, true_labels, (threshold,), tolerances)[0]
