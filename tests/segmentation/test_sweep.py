"""The sweep: segmentation at each threshold, its columns from ``score_masks``, and one threshold on a door episode."""

from __future__ import annotations

import numpy as np
import pytest

from scoring_helpers import door_episode
from vlmproprio.segmentation.sweep import evaluate_segmentation, sweep


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
