"""The similarity trace and the segmentation points it gives, on hand-made cases with known answers."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from vlmproprio.segmentation.trace import (
    THRESHOLDS,
    CosineCache,
    boundaries_at,
    cosine,
    cosine_trace,
    segment_counts,
    similarity_trace,
)


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


def test_a_cosine_cache_gives_the_bits_of_cosine():
    rng = np.random.default_rng(3)
    pool = [rng.standard_normal(16).astype(np.float32) for _ in range(4)] + [np.zeros(16, dtype=np.float32)]
    seqs = [[pool[i] if i is not None else None for i in idx] for idx in ([0, 1, 0, 1, 2, None, 3], [4, 0, 0, 4, 1])]
    cache = CosineCache()
    for seq in seqs:
        assert cosine_trace(seq, cache).tobytes() == cosine_trace(seq).tobytes()
    for a in pool:
        for b in pool:
            assert np.array([cache.cosine(a, b)]).tobytes() == np.array([cosine(a, b)]).tobytes()


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
