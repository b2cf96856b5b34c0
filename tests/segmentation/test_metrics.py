"""The segmentation metrics: hand-made cases with known answers, then a straightforward implementation written
here, on thousands of random cases.

The reference functions below do not call vlmproprio: they follow the published definitions literally --
MS-TCN's evaluation (Farha & Gall, CVPR 2019, ``eval.py``: ``get_labels_start_end_time``, ``levenstein``,
``edit_score``, ``f_score``; ASFormer uses the same file), a maximum one-to-one matching for boundary F1
(GEBD-style, Shou et al. 2021, absolute tolerance in frames), and majority labelling of predicted segments.
"""

from __future__ import annotations

import itertools
import random

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from vlmproprio.segmentation.metrics import (
    boundary_prf,
    edit_score,
    masks_of,
    predicted_segment_labels,
    score_masks,
    segments_from_labels,
    truth_of,
)

N_CASES = 1500
TOL = 1e-9


# ---------------------------------------------------------------------------------------------- known answers


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


def test_known_answers_msts_edit_merges_and_f1_at_iou():
    labels = ["a"] * 5 + ["b"] * 5
    truth = truth_of(labels)
    # over-segmentation inside phase a: merged away by MS-TCN's edit score (100), F1@50 perfect
    s = score_masks(masks_of([[1, 4]], 10), truth)
    assert s["edit"][0] == 100.0 and s["f1_at_50"][0] == 1.0 and s["frame_acc"][0] == 1.0
    # no boundary: one segment labelled a (tie 5/5 -> the earlier phase): edit 50, F1@10 = 2*(1*0.5)/1.5
    s = score_masks(masks_of([[]], 10), truth)
    assert s["edit"][0] == 50.0
    assert s["f1_at_10"][0] == pytest.approx(2 / 3)
    assert s["frame_acc"][0] == 0.5
    # boundary one frame late: IoU of a is 5/6, of b 4/5: both hit at 50
    s = score_masks(masks_of([[5]], 10), truth)
    assert s["f1_at_50"][0] == 1.0 and s["f1_tol0"][0] == 0.0 and s["f1_tol1"][0] == 1.0


# ---------------------------------------------------------------------------------------------- reference


def ref_max_matching(pred: list[int], truth: list[int], tol: int) -> int:
    """Maximum bipartite matching by augmenting paths (Kuhn's algorithm)."""
    match_of_truth: dict[int, int] = {}

    def augment(p: int, seen: set[int]) -> bool:
        for t in range(len(truth)):
            if abs(pred[p] - truth[t]) <= tol and t not in seen:
                seen.add(t)
                if t not in match_of_truth or augment(match_of_truth[t], seen):
                    match_of_truth[t] = p
                    return True
        return False

    return sum(augment(p, set()) for p in range(len(pred)))


def ref_boundary_f1(pred: list[int], truth: list[int], tol: int) -> tuple[float, float, float]:
    tp = ref_max_matching(pred, truth, tol)
    precision = tp / len(pred) if pred else (1.0 if not truth else 0.0)
    recall = tp / len(truth) if truth else (1.0 if not pred else 0.0)
    f1 = 2 * precision * recall / (precision + recall) if precision + recall > 0 else 0.0
    return precision, recall, f1


def ref_frame_labels(pred: list[int], labels: list[str]) -> list[str]:
    """Each predicted segment gets the label covering most of its frames; ties: the label seen first in the
    whole episode."""
    first_seen: list[str] = []
    for lab in labels:
        if lab not in first_seen:
            first_seen.append(lab)
    cuts = [0] + [b + 1 for b in sorted(pred)] + [len(labels)]
    out: list[str] = []
    for s, e in itertools.pairwise(cuts):
        seg = labels[s:e]
        best = max(seg.count(lab) for lab in seg)
        winner = next(lab for lab in first_seen if seg.count(lab) == best)
        out += [winner] * (e - s)
    return out


def get_labels_start_end_time(frame_wise_labels: list[str]):
    """MS-TCN eval.py (no background class here)."""
    labels, starts, ends = [], [], []
    last_label = frame_wise_labels[0]
    labels.append(frame_wise_labels[0])
    starts.append(0)
    for i in range(len(frame_wise_labels)):
        if frame_wise_labels[i] != last_label:
            labels.append(frame_wise_labels[i])
            starts.append(i)
            ends.append(i)
            last_label = frame_wise_labels[i]
    ends.append(i + 1)
    return labels, starts, ends


def levenstein(p: list[str], y: list[str], norm: bool = False) -> float:
    """MS-TCN eval.py."""
    m_row, n_col = len(p), len(y)
    d = np.zeros([m_row + 1, n_col + 1], float)
    for i in range(m_row + 1):
        d[i, 0] = i
    for i in range(n_col + 1):
        d[0, i] = i
    for j in range(1, n_col + 1):
        for i in range(1, m_row + 1):
            if y[j - 1] == p[i - 1]:
                d[i, j] = d[i - 1, j - 1]
            else:
                d[i, j] = min(d[i - 1, j] + 1, d[i, j - 1] + 1, d[i - 1, j - 1] + 1)
    if norm:
        return (1 - d[-1, -1] / max(m_row, n_col)) * 100
    return d[-1, -1]


def ref_edit(recognized: list[str], ground_truth: list[str]) -> float:
    p, _, _ = get_labels_start_end_time(recognized)
    y, _, _ = get_labels_start_end_time(ground_truth)
    return levenstein(p, y, True)


def ref_f_score(recognized: list[str], ground_truth: list[str], overlap: float) -> float:
    """MS-TCN eval.py f_score, turned into one episode's F1 (0-1)."""
    p_label, p_start, p_end = get_labels_start_end_time(recognized)
    y_label, y_start, y_end = get_labels_start_end_time(ground_truth)
    tp = fp = 0
    hits = np.zeros(len(y_label))
    for j in range(len(p_label)):
        intersection = np.minimum(p_end[j], y_end) - np.maximum(p_start[j], y_start)
        union = np.maximum(p_end[j], y_end) - np.minimum(p_start[j], y_start)
        iou = (1.0 * intersection / union) * np.array([p_label[j] == y_label[x] for x in range(len(y_label))])
        idx = np.array(iou).argmax()
        if iou[idx] >= overlap and not hits[idx]:
            tp += 1
            hits[idx] = 1
        else:
            fp += 1
    fn = len(y_label) - sum(hits)
    precision = tp / float(tp + fp)
    recall = tp / float(tp + fn)
    f1 = 2.0 * (precision * recall) / (precision + recall) if precision + recall > 0 else 0.0
    return float(f1)


def reference_scores(pred: list[int], labels: list[str]) -> dict[str, float]:
    truth = [j for j in range(len(labels) - 1) if labels[j] != labels[j + 1]]
    out: dict[str, float] = {"points": len(pred)}
    for tol in (0, 1, 2):
        out[f"p_tol{tol}"], out[f"r_tol{tol}"], out[f"f1_tol{tol}"] = ref_boundary_f1(pred, truth, tol)
    framewise = ref_frame_labels(pred, labels)
    out["frame_acc"] = sum(a == b for a, b in zip(framewise, labels, strict=True)) / len(labels)
    out["edit"] = ref_edit(framewise, labels)
    for tau, key in ((0.10, "f1_at_10"), (0.25, "f1_at_25"), (0.50, "f1_at_50")):
        out[key] = ref_f_score(framewise, labels, tau)
    return out


# ---------------------------------------------------------------------------------------------- cases


def random_case(rng: random.Random) -> tuple[list[str], list[int]]:
    n = rng.randint(1, 40)
    if rng.random() < 0.5:  # phases in order, each one run (like the fixtures)
        n_phases = rng.randint(1, min(n, 8))
        cuts = sorted(rng.sample(range(1, n), n_phases - 1)) if n_phases > 1 else []
        labels = []
        for p, (s, e) in enumerate(zip([0, *cuts], [*cuts, n], strict=True)):
            labels += [f"phase{p}"] * (e - s)
    else:  # any labels, phases may recur (harder for ties and matching)
        alphabet = [f"l{i}" for i in range(rng.randint(1, 5))]
        labels = [rng.choice(alphabet) for _ in range(n)]
    k = rng.randint(0, n - 1)
    pred = sorted(rng.sample(range(n - 1), k)) if n > 1 else []
    return labels, pred


def test_score_masks_matches_the_reference_on_random_cases():
    rng = random.Random(12)
    worst: dict[str, float] = {}
    for case in range(N_CASES):
        labels, pred = random_case(rng)
        truth = truth_of(labels)
        got = score_masks(masks_of([pred], len(labels)), truth)
        want = reference_scores(pred, labels)
        for key, value in want.items():
            diff = abs(float(got[key][0]) - value)
            worst[key] = max(worst.get(key, 0.0), diff)
            assert diff <= TOL, f"case {case}: {key} {got[key][0]} != {value} (labels {labels}, pred {pred})"
    assert set(worst) >= {"f1_tol1", "edit", "f1_at_10", "f1_at_25", "f1_at_50", "frame_acc"}


def test_many_sets_at_once_equal_one_at_a_time():
    """Rows of one batch do not influence each other (the chance baselines score 10 000 sets in one call)."""
    rng = random.Random(7)
    labels = ["a"] * 4 + ["b"] * 3 + ["c"] * 6 + ["a"] * 2 + ["d"] * 5
    sets = [sorted(rng.sample(range(len(labels) - 1), rng.randint(0, len(labels) - 1))) for _ in range(200)]
    truth = truth_of(labels)
    batch = score_masks(masks_of(sets, len(labels)), truth)
    for i, s in enumerate(sets):
        one = score_masks(masks_of([s], len(labels)), truth)
        for key in batch:
            assert batch[key][i] == one[key][0]
