"""The sweep: segmentation at each threshold, its columns from ``score_masks``, and one threshold on a door episode."""

from __future__ import annotations

import numpy as np
import pytest

from scoring_helpers import door_episode
from vlmproprio.segmentation.metrics import score_masks, truth_of
from vlmproprio.segmentation.sweep import evaluate_segmentation, sweep
from vlmproprio.segmentation.trace import THRESHOLDS


def test_sweep_columns_come_from_score_masks():
    labels = ["a"] * 4 + ["b"] * 4 + ["c"] * 4
    trace = np.array([0.9, 0.9, 0.9, 0.2, 0.9, 0.9, 0.5, 0.3, 0.9, 0.9, 0.9])
    pts = sweep(trace, labels, (0.0, 0.25, 0.4, 1.0))
    assert [p.points for p in pts] == [0, 1, 2, 11]
    assert pts[2].prf[0].f1 == 1.0 and pts[2].edit == 100.0
    assert pts[3].edit_unmerged < 100.0 and pts[3].edit == 100.0  # MS-TCN merges extra points away


def test_evaluate_segmentation_on_a_door_episode():
    ep = door_episode()
    labels = ep.frame_phases
    truth = ep.boundaries()
    assert truth == [1, 2, 4, 7]
    trace = np.full(len(labels) - 1, 0.9)
    trace[truth] = 0.3
    at = evaluate_segmentation(trace, labels, 0.65)
    assert at.points == 4 and at.prf[0].f1 == 1.0 and at.edit == 100.0
    shifted = np.full(len(labels) - 1, 0.9)
    shifted[[0, 3, 6]] = 0.3
    s = evaluate_segmentation(shifted, labels, 0.65)
    assert s.prf[0].tp == 0 and s.prf[1].tp == 3 and s.prf[1].recall == 0.75
    points = [p.points for p in sweep(trace, labels)]
    assert points[6] == 0 and points[7] == 4  # 0.3 < 0.35 but not < 0.3
    assert points[18] == 4 and points[19] == 8 and points[-1] == 8  # 0.9 < 0.95 but not < 0.9
    with pytest.raises(ValueError, match="trace of length"):
        evaluate_segmentation(trace[:-1], labels, 0.65)


def test_sweep_scores_equal_per_row_scores():
    """A sweep scores each distinct boundary set once, for all thresholds together: the numbers of each one alone."""
    rng = np.random.default_rng(7)
    labels = ["a"] * 6 + ["b"] * 9 + ["c"] * 5 + ["a"] * 4  # a phase that comes back: the general algorithm too
    for trial in range(20):
        trace = np.round(rng.uniform(0.2, 1.0, len(labels) - 1), 1)
        if trial % 3 == 0:
            trace[rng.integers(0, len(trace), 3)] = np.nan
        points = sweep(trace, labels, THRESHOLDS)
        truth = truth_of(labels)
        masks = np.stack([trace < thr for thr in THRESHOLDS])
        whole = score_masks(masks, truth)
        for i, sp in enumerate(points):
            alone = score_masks(masks[i : i + 1], truth)
            assert sp.points == int(whole["points"][i]) == int(alone["points"][0])
            for tol, prf in sp.prf.items():
                assert prf.f1 == float(whole[f"f1_tol{tol}"][i]) == float(alone[f"f1_tol{tol}"][0])
            assert sp.edit == float(whole["edit"][i])
            assert sp.segmental["frame_acc"] == float(whole["frame_acc"][i])
            assert sp.segmental["f1_at_50"] == float(whole["f1_at_50"][i])
