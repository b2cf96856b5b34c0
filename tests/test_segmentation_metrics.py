"""The segmentation metrics against a straightforward implementation written here, on thousands of random cases.

The reference functions below do not call vlmproprio: they follow the published definitions literally --
MS-TCN's evaluation (Farha & Gall, CVPR 2019, ``eval.py``: ``get_labels_start_end_time``, ``levenstein``,
``edit_score``, ``f_score``; ASFormer uses the same file), a maximum one-to-one matching for boundary F1
(GEBD-style, Shou et al. 2021, absolute tolerance in frames), and majority labelling of predicted segments.
"""

from __future__ import annotations

import itertools
import math
import random

import numpy as np
import pytest

from vlmproprio.segmentation import (
    CHANCE_METRICS,
    chance_random,
    evenly_spaced,
    group_edges,
    masks_of,
    random_masks,
    score_masks,
    sweep,
    truth_of,
)

N_CASES = 1500
TOL = 1e-9


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


def test_sweep_columns_come_from_score_masks():
    labels = ["a"] * 4 + ["b"] * 4 + ["c"] * 4
    trace = np.array([0.9, 0.9, 0.9, 0.2, 0.9, 0.9, 0.5, 0.3, 0.9, 0.9, 0.9])
    pts = sweep(trace, labels, (0.0, 0.25, 0.4, 1.0))
    assert [p.points for p in pts] == [0, 1, 2, 11]
    assert pts[2].prf[0].f1 == 1.0 and pts[2].edit == 100.0
    assert pts[3].edit_unmerged < 100.0 and pts[3].edit == 100.0  # the honest name: over-segmentation costs


# ---------------------------------------------------------------------------------------------- chance


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
