"""Similarity traces, thresholds, boundary P/R/F1 and the edit score on hand-made cases with known answers."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from scoring_helpers import door_episode
from vlmproprio.segmentation import (
    THRESHOLDS,
    boundaries_at,
    boundary_prf,
    cosine,
    cosine_trace,
    edit_score,
    evaluate_segmentation,
    predicted_segment_labels,
    segment_counts,
    segments_from_labels,
    similarity_trace,
    sweep,
)

# (pred, truth, tol, precision, recall, f1)
PRF_CASES = [
    ([3], [3], 0, 1.0, 1.0, 1.0),
    ([2], [3], 0, 0.0, 0.0, 0.0),
    ([2], [3], 1, 1.0, 1.0, 1.0),
    ([1], [3], 1, 0.0, 0.0, 0.0),
    ([1], [3], 2, 1.0, 1.0, 1.0),
    ([2, 3, 4], [3], 1, 1 / 3, 1.0, 0.5),  # one-to-one: a true boundary is found once
    ([3], [2, 4], 1, 1.0, 0.5, 2 / 3),
    ([2, 3], [1, 3], 1, 1.0, 1.0, 1.0),  # greedy must not let 2 steal 3 from prediction 3
    ([1, 5], [2, 6], 0, 0.0, 0.0, 0.0),
    ([1, 5], [2, 6], 1, 1.0, 1.0, 1.0),
    ([1, 4, 9], [1, 5, 7], 1, 2 / 3, 2 / 3, 2 / 3),
    ([], [], 1, 1.0, 1.0, 1.0),
    ([], [4], 1, 0.0, 0.0, 0.0),
    ([4], [], 1, 0.0, 0.0, 0.0),
]


@pytest.mark.parametrize(("pred", "truth", "tol", "p", "r", "f1"), PRF_CASES)
def test_boundary_prf_known_answers(pred, truth, tol, p, r, f1):
    m = boundary_prf(pred, truth, tol)
    assert (m.precision, m.recall, m.f1) == pytest.approx((p, r, f1))


@given(
    st.lists(st.integers(0, 40), max_size=12),
    st.lists(st.integers(0, 40), max_size=12),
    st.integers(0, 3),
)
def test_boundary_prf_matches_brute_force(pred, truth, tol):
    """Greedy matching equals a maximum one-to-one matching (brute force by augmenting paths)."""
    p, t = sorted(set(pred)), sorted(set(truth))
    match: dict[int, int] = {}

    def augment(i: int, seen: set) -> bool:
        for j, y in enumerate(t):
            if abs(p[i] - y) <= tol and j not in seen:
                seen.add(j)
                if j not in match or augment(match[j], seen):
                    match[j] = i
                    return True
        return False

    best = sum(augment(i, set()) for i in range(len(p)))
    assert boundary_prf(pred, truth, tol).tp == best


# (pred segments, true segments, edit score)
EDIT_CASES = [
    (["a", "b", "c"], ["a", "b", "c"], 100.0),
    (["a", "a", "b", "c"], ["a", "b", "c"], 75.0),
    (["a", "c"], ["a", "b", "c"], 100 * (1 - 1 / 3)),
    (["c", "b", "a"], ["a", "b", "c"], 100 * (1 - 2 / 3)),
    ([], [], 100.0),
    ([], ["a", "b"], 0.0),
]


@pytest.mark.parametrize(("pred", "truth", "score"), EDIT_CASES)
def test_edit_score_known_answers(pred, truth, score):
    assert edit_score(pred, truth) == pytest.approx(score)


LABELS = ["a", "a", "a", "b", "b", "c"]


@pytest.mark.parametrize(
    ("boundaries", "segments", "edit"),
    [
        ([2, 4], ["a", "b", "c"], 100.0),
        ([], ["a"], 100 * (1 - 2 / 3)),
        ([0, 2, 4], ["a", "a", "b", "c"], 75.0),  # over-segmentation costs an insertion
        ([3], ["a", "b"], 100 * (1 - 1 / 3)),  # frames 0..3 mostly a; 4..5 tie b/c -> earliest (b)
    ],
)
def test_predicted_segments_and_edit(boundaries, segments, edit):
    got = predicted_segment_labels(boundaries, LABELS)
    assert got == segments
    assert edit_score(got, segments_from_labels(LABELS)) == pytest.approx(edit)


def test_cosine_trace_known_values_and_missing_gaps():
    e = [np.array([1, 0], np.float32), np.array([1, 0], np.float32), np.array([0, 1], np.float32)]
    assert cosine_trace(e).tolist() == [1.0, 0.0]
    gap = cosine_trace([e[0], None, e[2], e[2]])
    assert len(gap) == 3 and math.isnan(gap[0]) and math.isnan(gap[1]) and gap[2] == 1.0
    assert cosine_trace([]).shape == (0,)
    assert cosine(np.array([3, 4], np.float32), np.array([4, 3], np.float32)) == pytest.approx(24 / 25)


def test_similarity_trace_keeps_frame_alignment_for_missing_captions():
    vec = {"open": np.array([1, 0, 0], np.float32), "turn": np.array([0.6, 0.8, 0], np.float32)}
    asked = []

    def embed(texts):
        asked.append(list(texts))
        return {t: vec[t] for t in texts}

    trace = similarity_trace(["open", "open", "", "turn", "turn"], embed, ["ok", "ok", "missing", "ok", "recovered"])
    assert len(trace) == 4
    assert trace[0] == 1.0 and math.isnan(trace[1]) and math.isnan(trace[2]) and trace[3] == 1.0
    assert asked == [["open", "open", "turn", "turn"]]
    # a caption marked missing is a gap even when it carries text
    t2 = similarity_trace(["open", "turn", "open"], embed, ["ok", "missing", "ok"])
    assert np.isnan(t2).all()
    assert boundaries_at(t2, 1.01) == []


@settings(max_examples=200)
@given(st.lists(st.one_of(st.floats(-1, 1), st.just(float("nan"))), max_size=40))
def test_sweep_counts_grow_with_threshold(values):
    trace = np.array(values, dtype=np.float64)
    counts = segment_counts(trace)
    assert counts == sorted(counts)
    assert counts[-1] == int(np.count_nonzero(trace < 1.0))
    assert all(c == len(boundaries_at(trace, t)) for c, t in zip(counts, THRESHOLDS, strict=True))


def test_thresholds_are_the_exact_grid():
    assert len(THRESHOLDS) == 21 and THRESHOLDS[0] == 0.0 and THRESHOLDS[-1] == 1.0
    assert THRESHOLDS[13] == 0.65


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


def test_a_cosine_cache_gives_the_bits_of_cosine():
    from vlmproprio.segmentation import CosineCache, cosine, cosine_trace

    rng = np.random.default_rng(3)
    pool = [rng.standard_normal(16).astype(np.float32) for _ in range(4)] + [np.zeros(16, dtype=np.float32)]
    seqs = [[pool[i] if i is not None else None for i in idx] for idx in ([0, 1, 0, 1, 2, None, 3], [4, 0, 0, 4, 1])]
    cache = CosineCache()
    for seq in seqs:
        assert cosine_trace(seq, cache).tobytes() == cosine_trace(seq).tobytes()
    for a in pool:
        for b in pool:
            assert np.array([cache.cosine(a, b)]).tobytes() == np.array([cosine(a, b)]).tobytes()
