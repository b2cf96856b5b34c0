"""The chance baselines: uniform random sets (seeded), exact enumeration, evenly spaced points, group edges."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from vlmproprio.segmentation.chance import CHANCE_METRICS, chance_random, evenly_spaced, group_edges, random_masks
from vlmproprio.segmentation.metrics import masks_of, score_masks, truth_of


def test_random_masks_are_uniform_k_subsets():
    masks = random_masks(6, 2, 30000, seed=1)
    assert (masks.sum(axis=1) == 2).all()
    counts: dict[tuple, int] = {}
    for row in masks:
        key = tuple(np.flatnonzero(row))
        counts[key] = counts.get(key, 0) + 1
    assert len(counts) == math.comb(6, 2)
    expected = 30000 / 15
    chi2 = sum((c - expected) ** 2 / expected for c in counts.values())
    assert chi2 < 36.1  # chi-square, 14 degrees of freedom, p = 0.001
    assert (random_masks(6, 2, 50, seed=1) == masks[:50]).all()  # seeded


@pytest.mark.parametrize(("labels", "k"), [(["a"] * 3 + ["b"] * 4 + ["c"] * 3, 2), (["x"] * 6 + ["y"] * 6, 4)])
def test_chance_random_agrees_with_exact_enumeration(labels, k):
    truth = truth_of(labels)
    n_pos = len(labels) - 1
    subsets = [list(c) for c in itertools.combinations(range(n_pos), k)]
    every = score_masks(masks_of(subsets, len(labels)), truth)
    got = chance_random(truth, k)
    for m in CHANCE_METRICS:
        exact = float(np.mean(every[m]))
        se = float(np.std(every[m])) / math.sqrt(10000)
        assert abs(got[m] - exact) <= 5 * se + 1e-12, (m, got[m], exact)


def test_evenly_spaced_and_group_edges():
    assert evenly_spaced(10, 1) == [4]
    assert evenly_spaced(10, 4) == [1, 3, 5, 7]
    assert evenly_spaced(10, 9) == list(range(9))
    assert evenly_spaced(10, 0) == []
    assert group_edges(12, 5) == [4, 9]
    assert group_edges(10, 5) == [4]
    with pytest.raises(ValueError):
        evenly_spaced(5, 5)
