"""Segmentation points against ground truth (every definition, with its reference, is in docs/metrics.md).

* boundary precision / recall / F1 with a tolerance of ``tol`` frames and a maximum one-to-one matching
  (``boundary_prf``), and by the greedy rule of generic event boundary detection's evaluation code
  (``boundary_prf_gebd``; GEBD, Shou et al., ICCV 2021), both with an absolute tolerance in frames instead of
  GEBD's relative distance;
* frame-wise labels from the predicted segments: each predicted segment takes the ground-truth phase that
  covers most of its frames (ties: the phase that comes first in the episode) -- an oracle labelling, since
  the captions carry no phase names;
* on those frame-wise labels, the standard metrics of temporal action segmentation exactly as MS-TCN's
  evaluation computes them (Farha & Gall, CVPR 2019; ``eval.py`` of the MS-TCN and ASFormer code): the
  segmental edit score (adjacent equal labels merged, ``(1 - Levenshtein / max length) * 100``) and the
  segmental F1@{10, 25, 50} (a predicted segment is a true positive when its IoU with the not yet matched
  ground-truth segment of the same label that overlaps it most is >= the threshold), per episode; and
  frame accuracy;
* ``edit_score_unmerged``: majority-labelled predicted segments *not* merged, so over-segmentation costs
  insertions (MS-TCN's edit score forgives it under oracle labels).

``score_masks`` computes every metric for many boundary sets at once (numpy, no Python loop over the sets);
the sweep, the chance baselines and single predictions all go through it, and tests/segmentation/test_metrics.py
checks it against a straightforward implementation on thousands of random cases.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict, dataclass

import numpy as np

TOLERANCES: tuple[int, ...] = (0, 1, 2)
IOU_THRESHOLDS: tuple[float, ...] = (0.10, 0.25, 0.50)


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

    A maximum one-to-one matching (the most pairs any matching can make), computed greedily over sorted positions
    (each prediction takes the earliest unmatched truth in reach), which is maximum for interval tolerances. GEBD's
    own rule is another greedy matching that can make fewer pairs: ``boundary_prf_gebd``. Empty sets: precision is 1 with no predictions and no truth, 0
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


def boundary_prf_gebd(pred: Sequence[int], truth: Sequence[int], tol: int = 1) -> PRF:
    """Boundary precision/recall/F1 by GEBD's rule (Kinetics-GEBD's evaluation code): each true boundary, in
    order, takes its nearest remaining prediction (ties: the earliest), a hit when at most ``tol`` frames away,
    and a hit removes that prediction. Greedy, so it can pair fewer than a maximum matching (``boundary_prf``)
    does: a truth may take the prediction a later truth needed. Empty sets as in ``boundary_prf``."""
    if tol < 0:
        raise ValueError(f"tolerance must be >= 0, got {tol}")
    p = sorted(set(int(x) for x in pred))
    t = sorted(set(int(x) for x in truth))
    left = list(p)
    tp = 0
    for x in t:
        if not left:
            break
        j = min(range(len(left)), key=lambda i: (abs(left[i] - x), i))
        if abs(left[j] - x) <= tol:
            tp += 1
            del left[j]
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
    """Label each predicted segment with the ground-truth phase covering most of its frames (ties: the
    earliest frame's phase), one label per predicted segment, *not* merged (for ``edit_score_unmerged``)."""
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
    """Edit score in [0, 100] of two segment label sequences: (1 - Levenshtein / max length) * 100 (MS-TCN's
    ``edit_score``, Farha & Gall 2019, given sequences that are already merged)."""
    m = max(len(pred_segments), len(true_segments))
    if m == 0:
        return 100.0
    return (1.0 - levenshtein(pred_segments, true_segments) / m) * 100.0


def edit_score_unmerged(boundaries: Sequence[int], true_labels: Sequence[str]) -> float:
    """An edit score that is not MS-TCN's: majority-labelled predicted segments, *not* merged, against the true
    segment sequence, so every extra boundary inside a phase costs an insertion."""
    return edit_score(predicted_segment_labels(boundaries, true_labels), segments_from_labels(true_labels))


def iou_key(tau: float) -> str:
    """'f1_at_10' for IoU threshold 0.10 (MS-TCN's F1@10)."""
    return f"f1_at_{round(tau * 100):02d}"


@dataclass(frozen=True)
class Truth:
    """One episode's ground truth as ``score_masks`` needs it.

    ``codes`` numbers the phases by first appearance in the episode; the merged ground-truth segments are
    ``(seg_label[s], seg_start[s], seg_end[s])`` with exclusive ends, as MS-TCN's
    ``get_labels_start_end_time`` returns them."""

    labels: tuple[str, ...]
    codes: np.ndarray
    n_labels: int
    boundaries: np.ndarray
    seg_label: np.ndarray
    seg_start: np.ndarray
    seg_end: np.ndarray

    @property
    def n_frames(self) -> int:
        return len(self.labels)

    @property
    def ordered(self) -> bool:
        """Every phase is one run (as in the fixtures): then majority labels of consecutive predicted
        segments never go back, which allows the closed forms in ``score_masks``."""
        return len(self.seg_label) == self.n_labels


def truth_of(labels: Sequence[str]) -> Truth:
    if not labels:
        raise ValueError("an episode without frames has no segmentation")
    order: dict[str, int] = {}
    for lab in labels:
        order.setdefault(lab, len(order))
    codes = np.array([order[lab] for lab in labels], dtype=np.int64)
    n = len(labels)
    bounds = np.array([j for j in range(n - 1) if codes[j] != codes[j + 1]], dtype=np.int64)
    starts = np.array([0, *(bounds + 1)], dtype=np.int64)
    ends = np.array([*(bounds + 1), n], dtype=np.int64)
    return Truth(tuple(labels), codes, len(order), bounds, codes[starts], starts, ends)


def _matched_boundaries(pos: np.ndarray, k: np.ndarray, truth: np.ndarray, tol: int) -> np.ndarray:
    """Per row, the size of the one-to-one matching of predicted and true boundaries within ``tol``: predicted
    positions in ascending order, each takes the earliest unmatched true boundary in reach (as
    ``boundary_prf``, a maximum matching). ``pos`` is sorted per row; entries from column ``k[d]`` on are
    padding."""
    d = pos.shape[0]
    used = np.zeros((d, len(truth)), dtype=bool)
    if len(truth) == 0:
        return np.zeros(d, dtype=np.int64)
    rows = np.arange(d)
    for c in range(pos.shape[1]):
        cand = ~used & (np.abs(truth[None, :] - pos[:, c : c + 1]) <= tol) & (c < k)[:, None]
        has = cand.any(axis=1)
        first = cand.argmax(axis=1)
        used[rows[has], first[has]] = True
    return used.sum(axis=1)


def _prf_arrays(tp: np.ndarray, k: np.ndarray, m: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Precision, recall, F1 with ``boundary_prf``'s conventions for empty sets, elementwise."""
    precision = np.where(k > 0, tp / np.maximum(k, 1), 1.0 if m == 0 else 0.0)
    recall = tp / m if m else np.where(k == 0, 1.0, 0.0)
    denom = precision + recall
    f1 = np.where(denom > 0, 2 * precision * recall / np.where(denom > 0, denom, 1.0), 0.0)
    return precision, recall, f1


def score_masks(
    masks: np.ndarray,
    truth: Truth,
    tolerances: Sequence[int] = TOLERANCES,
    ious: Sequence[float] = IOU_THRESHOLDS,
) -> dict[str, np.ndarray]:
    """Every segmentation metric for D boundary sets at once.

    ``masks`` is boolean (D, n - 1): ``masks[d, j]`` says a segment ends after frame j. Returns arrays of
    length D: ``points``, ``tp_tol{t}`` (matched boundaries), ``p_tol{t}`` / ``r_tol{t}`` / ``f1_tol{t}``
    (boundary P/R/F1, ``boundary_prf``), ``frame_acc`` (share of frames whose label is right), ``edit``
    (MS-TCN segmental edit score, 0-100, on the frame-wise labels with adjacent equal labels merged) and
    ``f1_at_{10,25,50}`` (MS-TCN segmental F1 at IoU 0.10 / 0.25 / 0.50, one episode, 0-1).

    Frame-wise labels: each predicted segment takes the phase covering most of its frames; ties go to the
    phase that comes first in the episode. The work is done per predicted segment (prefix counts of the
    phases), not per frame, so the cost grows with the number of boundaries, not of frames. See
    docs/metrics.md."""
    masks = np.asarray(masks, dtype=bool)
    n = truth.n_frames
    if masks.ndim != 2 or masks.shape[1] != n - 1:
        raise ValueError(f"boundary masks of shape {masks.shape} for {n} frames (expected (D, {n - 1}))")
    d = masks.shape[0]
    k = masks.sum(axis=1)
    kmax = int(k.max()) if d else 0
    pos = np.full((d, kmax), n - 1, dtype=np.int64)
    di, jj = np.nonzero(masks)  # row-major: ascending positions within a row
    pos[di, np.cumsum(masks, axis=1)[di, jj] - 1] = jj
    return score_positions(pos, k, truth, tolerances, ious)


def score_positions(
    pos: np.ndarray,
    k: np.ndarray,
    truth: Truth,
    tolerances: Sequence[int] = TOLERANCES,
    ious: Sequence[float] = IOU_THRESHOLDS,
) -> dict[str, np.ndarray]:
    """``score_masks`` for boundary sets given as positions: ``pos`` (D, K) ascending per row, row d using
    its first ``k[d]`` entries; the rest must be ``n - 1`` (padding)."""
    n = truth.n_frames
    d = pos.shape[0]
    out: dict[str, np.ndarray] = {"points": k}
    m = len(truth.boundaries)
    for tol in tolerances:
        tp = _matched_boundaries(pos, k, truth.boundaries, tol)
        p, r, f = _prf_arrays(tp, k, m)
        out[f"tp_tol{tol}"] = tp
        out[f"p_tol{tol}"], out[f"r_tol{tol}"], out[f"f1_tol{tol}"] = p, r, f

    # predicted segments: starts 0, pos + 1; ends pos + 1, n (padding gives start = end = n)
    n_raw = pos.shape[1] + 1
    rstart = np.concatenate([np.zeros((d, 1), dtype=np.int64), pos + 1], axis=1)
    rend = np.concatenate([pos + 1, np.full((d, 1), n, dtype=np.int64)], axis=1)
    valid = np.arange(n_raw)[None, :] <= k[:, None]
    # phase counts per segment from prefix counts; the first maximum is the lowest code, the earliest phase
    prefix = np.zeros((n + 1, truth.n_labels), dtype=np.int64)
    prefix[np.arange(1, n + 1), truth.codes] = 1
    prefix = np.cumsum(prefix, axis=0)
    counts = prefix[rend] - prefix[rstart]
    major = counts.argmax(axis=2)
    right = np.take_along_axis(counts, major[:, :, None], axis=2)[:, :, 0]
    out["frame_acc"] = np.where(valid, right, 0).sum(axis=1) / n

    # merged segments: runs of equal labels among consecutive predicted segments
    new = np.ones((d, n_raw), dtype=bool)
    new[:, 1:] = major[:, 1:] != major[:, :-1]
    new &= valid
    merged = np.cumsum(new, axis=1) - 1
    nseg = new.sum(axis=1)
    nmax = int(nseg.max()) if d else 0
    plab = np.full((d, max(nmax, 1)), -1, dtype=np.int64)
    pstart = np.full((d, max(nmax, 1)), n, dtype=np.int64)
    pend = np.full((d, max(nmax, 1)), n, dtype=np.int64)
    di, si = np.nonzero(new)
    plab[di, merged[di, si]] = major[di, si]
    pstart[di, merged[di, si]] = rstart[di, si]
    # a predicted segment closes its merged run when it is the last one or the next one starts a new run
    next_new = np.zeros((d, n_raw), dtype=bool)
    next_new[:, :-1] = new[:, 1:]
    closes = valid & (next_new | (np.arange(n_raw)[None, :] == k[:, None]))
    di, si = np.nonzero(closes)
    pend[di, merged[di, si]] = rend[di, si]

    if truth.ordered:
        _segmental_ordered(out, plab, pstart, pend, nseg, truth, ious)
    else:
        _segmental_general(out, plab, pstart, pend, nseg, nmax, truth, ious)
    return out


def _f1(tp: np.ndarray, fp: np.ndarray, fn: np.ndarray) -> np.ndarray:
    precision = tp / (tp + fp)
    recall = tp / (tp + fn)
    denom = precision + recall
    return np.where(denom > 0, 2 * precision * recall / np.where(denom > 0, denom, 1.0), 0.0)


def _segmental_ordered(out, plab, pstart, pend, nseg, truth: Truth, ious) -> None:
    """Edit and F1@IoU when every phase is one run (``Truth.ordered``). The merged predicted labels are then
    a strictly increasing subsequence of the true segment sequence 0..M-1, so the Levenshtein distance is
    M - nseg (deletions only) and each predicted segment can only match the true segment of its own label,
    never one hit before: the same numbers as the general algorithm, without its loops."""
    mm = len(truth.seg_label)
    out["edit"] = (1.0 - (mm - nseg) / np.maximum(nseg, mm)) * 100.0
    valid = np.arange(plab.shape[1])[None, :] < nseg[:, None]
    lab = np.where(valid, plab, 0)
    ys, ye = truth.seg_start[lab], truth.seg_end[lab]
    iou = (1.0 * (np.minimum(pend, ye) - np.maximum(pstart, ys))) / (np.maximum(pend, ye) - np.minimum(pstart, ys))
    for tau in ious:
        tp = (valid & (iou >= tau)).sum(axis=1)
        out[iou_key(tau)] = _f1(tp, nseg - tp, mm - tp)


def _segmental_general(out, plab, pstart, pend, nseg, nmax, truth: Truth, ious) -> None:
    """Edit and F1@IoU for any ground truth, following MS-TCN's ``levenstein`` and ``f_score`` row-wise."""
    d = plab.shape[0]
    rows = np.arange(d)
    # segmental edit score: Levenshtein distance between the merged label sequences, row by row
    ylab = truth.seg_label
    mm = len(ylab)
    prev = np.tile(np.arange(mm + 1, dtype=np.int64), (d, 1))
    dist = np.zeros(d, dtype=np.int64)
    for i in range(1, nmax + 1):
        cur = np.empty_like(prev)
        cur[:, 0] = i
        lab = plab[:, i - 1]
        for j in range(1, mm + 1):
            cur[:, j] = np.minimum(np.minimum(prev[:, j] + 1, cur[:, j - 1] + 1), prev[:, j - 1] + (lab != ylab[j - 1]))
        done = nseg == i
        dist[done] = cur[done, mm]
        prev = cur
    out["edit"] = (1.0 - dist / np.maximum(nseg, mm)) * 100.0

    # segmental F1@IoU, MS-TCN's f_score: predicted segments in order, each against the ground-truth segment
    # (same label) it overlaps most; a hit needs IoU >= tau and that segment not hit before
    hits = {tau: np.zeros((d, mm), dtype=bool) for tau in ious}
    tps = {tau: np.zeros(d, dtype=np.int64) for tau in ious}
    fps = {tau: np.zeros(d, dtype=np.int64) for tau in ious}
    for j in range(nmax):
        valid = j < nseg
        ps, pe, pl = pstart[:, j : j + 1], pend[:, j : j + 1], plab[:, j : j + 1]
        inter = np.minimum(pe, truth.seg_end[None, :]) - np.maximum(ps, truth.seg_start[None, :])
        union = np.maximum(pe, truth.seg_end[None, :]) - np.minimum(ps, truth.seg_start[None, :])
        iou = (1.0 * inter / union) * (pl == ylab[None, :])
        idx = iou.argmax(axis=1)
        best = iou[rows, idx]
        for tau in ious:
            h = hits[tau]
            ok = valid & (best >= tau) & ~h[rows, idx]
            tps[tau] += ok
            fps[tau] += valid & ~ok
            h[rows[ok], idx[ok]] = True
    for tau in ious:
        tp = tps[tau]
        fn = mm - hits[tau].sum(axis=1)
        out[iou_key(tau)] = _f1(tp, fps[tau], fn)


def masks_of(boundary_sets: Sequence[Sequence[int]], n_frames: int) -> np.ndarray:
    """Boolean (D, n_frames - 1) masks from lists of segmentation points."""
    out = np.zeros((len(boundary_sets), max(n_frames - 1, 0)), dtype=bool)
    for i, b in enumerate(boundary_sets):
        for j in b:
            if not 0 <= j < n_frames - 1:
                raise ValueError(f"segmentation point {j} outside 0..{n_frames - 2}")
            out[i, j] = True
    return out
