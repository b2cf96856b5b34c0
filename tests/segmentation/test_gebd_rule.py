"""Boundary F1 by GEBD's greedy rule, cross-checked against the matching loop of Kinetics-GEBD's published
evaluation code (``Challenge_eval_Code/eval.py``: for each true boundary in order, the nearest remaining
detection by ``np.argmin`` over an offset matrix, a hit within the threshold, and the hit's column deleted),
re-typed below with frames for seconds and an absolute tolerance for ``threshold * duration``."""

from __future__ import annotations

import numpy as np
import pytest

from vlmproprio.segmentation import boundary_prf, boundary_prf_gebd


def gebd_eval_tp(gt: list[int], det: list[int], tol: float) -> int:
    """True positives of one video, as GEBD's ``do_eval`` counts them."""
    tp = 0
    offset_arr = np.zeros((len(gt), len(det)))
    for ann1_idx in range(len(gt)):
        for ann2_idx in range(len(det)):
            offset_arr[ann1_idx, ann2_idx] = abs(gt[ann1_idx] - det[ann2_idx])
    for ann1_idx in range(len(gt)):
        if offset_arr.shape[1] == 0:
            break
        min_idx = np.argmin(offset_arr[ann1_idx, :])
        if offset_arr[ann1_idx, min_idx] <= tol:
            tp += 1
            offset_arr = np.delete(offset_arr, min_idx, 1)
    return tp


@pytest.mark.parametrize("seed", range(300))
def test_the_gebd_rule_counts_what_gebds_code_counts(seed):
    rng = np.random.default_rng(seed)
    n = int(rng.integers(5, 40))
    gt = sorted({int(x) for x in rng.integers(0, n, int(rng.integers(0, 8)))})
    det = sorted({int(x) for x in rng.integers(0, n, int(rng.integers(0, 10)))})
    tol = int(rng.integers(0, 4))
    got = boundary_prf_gebd(det, gt, tol)
    assert got.tp == gebd_eval_tp(gt, det, tol)
    assert got.tp <= boundary_prf(det, gt, tol).tp  # a maximum matching never pairs fewer


def test_the_two_rules_differ_where_a_truth_takes_a_later_truths_prediction():
    # truth 3 takes prediction 4 (1 away, nearer than 1), leaving truth 6 with 1 (5 away): GEBD pairs 1; a
    # maximum matching pairs 3 with 1 and 6 with 4 (2 away each)
    gebd, maximum = boundary_prf_gebd([1, 4], [3, 6], 2), boundary_prf([1, 4], [3, 6], 2)
    assert (gebd.tp, maximum.tp) == (1, 2)
    assert gebd.f1 == pytest.approx(0.5) and maximum.f1 == pytest.approx(1.0)
