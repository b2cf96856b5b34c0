"""Subtask segmentation from frame captions (the paper's Sec. III-B) and its comparison with ground truth.

* The similarity trace of an episode is the cosine similarity of each frame
  caption's embedding with the next one's: ``trace[j] = cos(e_j, e_{j+1})``, so
  it is indexed like ``Episode.boundaries()``.
* A segmentation point is a ``j`` with ``trace[j] < threshold`` (a new segment
  starts at frame ``j + 1``). Thresholds sweep 0.00 ... 1.00 in steps of 0.05.
* Missing captions (parse status "missing", or an empty text) are kept in place:
  every pair that has a missing side gets NaN in the trace and never makes a
  boundary, so the trace stays aligned with frame indices and a model that lost a
  caption cannot find the boundary next to it.
* The cosine is computed with exact products of float32 values in float64 and
  ``math.fsum`` (an exactly rounded sum), so a trace has the same bits on every
  machine and numpy build, given the cached embeddings.

Against ground truth: boundary precision / recall / F1 with a tolerance of
``tol`` frames (one-to-one matching), and the MS-TCN edit score over segment
sequences, where each predicted segment is labelled with the ground-truth phase
that covers most of its frames (ties: the earliest frame's phase) and adjacent
predicted segments are *not* merged, so over-segmentation costs insertions.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict, dataclass

import numpy as np

DEFAULT_THRESHOLD = 0.65
THRESHOLDS: tuple[float, ...] = tuple(k / 20 for k in range(21))
TOLERANCES: tuple[int, ...] = (0, 1, 2)


# ---------------------------------------------------------------------------------------------- trace


def caption_present(text: str | None, status: str = "ok") -> bool:
    """Whether a frame caption takes part in the trace: not missing and not blank."""
    return status != "missing" and bool(text and text.strip())


def cosine(a: np.ndarray, b: np.ndarray) -> float:
    """Cosine similarity with the same bits everywhere: float32*float32 is exact in float64, fsum is exact."""
    a64 = np.asarray(a, dtype=np.float32).astype(np.float64)
    b64 = np.asarray(b, dtype=np.float32).astype(np.float64)
    dot = math.fsum((a64 * b64).tolist())
    na2 = math.fsum((a64 * a64).tolist())
    nb2 = math.fsum((b64 * b64).tolist())
    if na2 == 0.0 or nb2 == 0.0:
        return float("nan")
    # one sqrt of the product: identical vectors give exactly 1.0 (sqrt(x*x) == x in IEEE double)
    return dot / math.sqrt(na2 * nb2)


def cosine_trace(vectors: Sequence[np.ndarray | None]) -> np.ndarray:
    """trace[j] = cos(v_j, v_{j+1}); NaN where either side is None. Length len(vectors) - 1 (0 if empty)."""
    n = max(len(vectors) - 1, 0)
    out = np.full(n, np.nan, dtype=np.float64)
    for j in range(n):
        a, b = vectors[j], vectors[j + 1]
        if a is not None and b is not None:
            out[j] = cosine(a, b)
    return out


def similarity_trace(
    texts: Sequence[str | None],
    embed: Callable[[list[str]], Mapping[str, np.ndarray]],
    statuses: Sequence[str] | None = None,
) -> np.ndarray:
    """The similarity trace of one episode's frame captions.

    ``embed`` maps a list of texts to {text: vector} (``CachedEmbedder.embed``); ``statuses`` are the frame
    parse statuses (a "missing" caption is a gap even if it has text)."""
    statuses = list(statuses) if statuses is not None else ["ok"] * len(texts)
    if len(statuses) != len(texts):
        raise ValueError(f"{len(texts)} texts but {len(statuses)} statuses")
    present = [caption_present(t, s) for t, s in zip(texts, statuses, strict=True)]
    vecs = embed([t for t, p in zip(texts, present, strict=True) if p]) if any(present) else {}
    return cosine_trace([vecs[t] if p else None for t, p in zip(texts, present, strict=True)])


# ---------------------------------------------------------------------------------------------- thresholds


def boundaries_at(trace: np.ndarray, threshold: float) -> list[int]:
    """Segmentation points: indices j with trace[j] < threshold (NaN never is)."""
    t = np.asarray(trace, dtype=np.float64)
    return [int(j) for j in np.flatnonzero(t < threshold)]


def segment_counts(trace: np.ndarray, thresholds: Sequence[float] = THRESHOLDS) -> list[int]:
    """Number of segmentation points per threshold (the paper's Fig. 6)."""
    t = np.asarray(trace, dtype=np.float64)
    return [int(np.count_nonzero(t < thr)) for thr in thresholds]


# ---------------------------------------------------------------------------------------------- metrics


@dataclass(frozen=True)
class PRF:
    precision: float
    recall: float
    f1: float
    tp: int
    n_pred: int
    n_true: int

    def to_dict(self) -> dict:
        return asdict(self)


def boundary_prf(pred: Sequence[int], truth: Sequence[int], tol: int = 1) -> PRF:
    """Boundary precision/recall/F1; a predicted boundary matches at most one true one within ``tol`` frames.

    Greedy matching over sorted positions (each prediction takes the earliest unmatched truth in reach) is a
    maximum matching for interval tolerances. Empty sets: precision is 1 with no predictions and no truth, 0
    with no predictions but some truth; recall likewise with the roles swapped; F1 is 0 when either is 0."""
    if tol < 0:
        raise ValueError(f"tolerance must be >= 0, got {tol}")
    p = sorted(set(int(x) for x in pred))
    t = sorted(set(int(x) for x in truth))
    used = [False] * len(t)
    tp = 0
    k = 0
    for x in p:
        while k < len(t) and (used[k] or t[k] < x - tol):
            k += 1
        if k < len(t) and abs(t[k] - x) <= tol:
            used[k] = True
            tp += 1
            k += 1
    precision = tp / len(p) if p else (1.0 if not t else 0.0)
    recall = tp / len(t) if t else (1.0 if not p else 0.0)
    f1 = 2 * precision * recall / (precision + recall) if precision + recall > 0 else 0.0
    return PRF(precision, recall, f1, tp, len(p), len(t))


def segments_from_labels(labels: Sequence[str]) -> list[str]:
    """Collapse runs of equal frame labels into the sequence of segments."""
    out: list[str] = []
    for lab in labels:
        if not out or out[-1] != lab:
            out.append(lab)
    return out


def predicted_segment_labels(boundaries: Sequence[int], true_labels: Sequence[str]) -> list[str]:
    """Label each predicted segment with the ground-truth phase covering most of its frames (not merged)."""
    n = len(true_labels)
    cuts = sorted({b + 1 for b in boundaries if 0 <= b < n - 1})
    starts = [0, *cuts]
    ends = [*cuts, n]
    out = []
    for s, e in zip(starts, ends, strict=True):
        seg = list(true_labels[s:e])
        counts: dict[str, int] = {}
        for lab in seg:
            counts[lab] = counts.get(lab, 0) + 1
        best = max(counts.values())
        out.append(next(lab for lab in seg if counts[lab] == best))
    return out


def levenshtein(a: Sequence[str], b: Sequence[str]) -> int:
    prev = list(range(len(b) + 1))
    for i, x in enumerate(a, 1):
        cur = [i] + [0] * len(b)
        for j, y in enumerate(b, 1):
            cur[j] = min(prev[j] + 1, cur[j - 1] + 1, prev[j - 1] + (x != y))
        prev = cur
    return prev[-1]


def edit_score(pred_segments: Sequence[str], true_segments: Sequence[str]) -> float:
    """MS-TCN edit score in [0, 100]: (1 - Levenshtein / max length) * 100 over segment label sequences."""
    m = max(len(pred_segments), len(true_segments))
    if m == 0:
        return 100.0
    return (1.0 - levenshtein(pred_segments, true_segments) / m) * 100.0


# ---------------------------------------------------------------------------------------------- sweep


@dataclass(frozen=True)
class SweepPoint:
    threshold: float
    points: int
    prf: dict[int, PRF]  # by tolerance
    edit: float

    def flat(self) -> dict:
        d: dict = {"threshold": self.threshold, "points": self.points}
        for tol, m in sorted(self.prf.items()):
            d[f"p_tol{tol}"] = m.precision
            d[f"r_tol{tol}"] = m.recall
            d[f"f1_tol{tol}"] = m.f1
        d["edit"] = self.edit
        return d


def evaluate_segmentation(
    trace: np.ndarray,
    true_labels: Sequence[str],
    threshold: float,
    tolerances: Sequence[int] = TOLERANCES,
) -> SweepPoint:
    """Segmentation at one threshold against the ground-truth frame phases."""
    n = len(true_labels)
    if len(trace) != max(n - 1, 0):
        raise ValueError(f"trace of length {len(trace)} for {n} frames (expected {max(n - 1, 0)})")
    truth = [j for j in range(n - 1) if true_labels[j] != true_labels[j + 1]]
    pred = boundaries_at(trace, threshold)
    prf = {tol: boundary_prf(pred, truth, tol) for tol in tolerances}
    edit = edit_score(predicted_segment_labels(pred, true_labels), segments_from_labels(true_labels))
    return SweepPoint(threshold, len(pred), prf, edit)


def sweep(
    trace: np.ndarray,
    true_labels: Sequence[str],
    thresholds: Sequence[float] = THRESHOLDS,
    tolerances: Sequence[int] = TOLERANCES,
) -> list[SweepPoint]:
    return [evaluate_segmentation(trace, true_labels, thr, tolerances) for thr in thresholds]
