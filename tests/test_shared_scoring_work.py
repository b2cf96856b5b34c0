"""Work shared between cells gives the numbers computed alone: a sweep scoring each distinct boundary set once."""

from __future__ import annotations

import numpy as np

from vlmproprio.segmentation import THRESHOLDS, score_masks, sweep, truth_of


def test_sweep_scores_equal_per_row_scores():
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
