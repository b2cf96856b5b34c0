"""The similarity trace of an episode's frame captions (the paper's Sec. III-B) and the points where it cuts.

* The trace is the cosine similarity of each frame caption's embedding with the next one's:
  ``trace[j] = cos(e_j, e_{j+1})``, so it is indexed like ``Episode.boundaries()``.
* A segmentation point is a ``j`` with ``trace[j] < threshold`` (a new segment starts at frame ``j + 1``).
  Thresholds sweep 0.00 ... 1.00 in steps of 0.05.
* Missing captions (parse status "missing", or an empty text) are kept in place: every pair that has a missing
  side gets NaN in the trace and never makes a boundary, so the trace stays aligned with frame indices and a
  model that lost a caption cannot find the boundary next to it.
* The cosine is computed with exact products of float32 values in float64 and ``math.fsum`` (an exactly
  rounded sum), so a trace has the same bits on every machine and numpy build, given the cached embeddings.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence

import numpy as np

DEFAULT_THRESHOLD = 0.65
THRESHOLDS: tuple[float, ...] = tuple(k / 20 for k in range(21))


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


class CosineCache:
    """``cosine`` of many pairs among few vectors (a model repeats its captions): each vector's float64 copy and
    squared norm once, each distinct pair's cosine once. The same ``fsum`` inputs, so the same bits as ``cosine``.

    Vectors are known by identity; the cache holds a reference to each, so an id is never reused while cached."""

    def __init__(self) -> None:
        self._vectors: dict[int, tuple[np.ndarray, np.ndarray, float]] = {}
        self._pairs: dict[tuple[int, int], float] = {}

    def _prepared(self, v: np.ndarray) -> tuple[np.ndarray, float]:
        hit = self._vectors.get(id(v))
        if hit is None:
            v64 = np.asarray(v, dtype=np.float32).astype(np.float64)
            hit = self._vectors[id(v)] = (v, v64, math.fsum((v64 * v64).tolist()))
        return hit[1], hit[2]

    def cosine(self, a: np.ndarray, b: np.ndarray) -> float:
        key = (id(a), id(b))
        c = self._pairs.get(key)
        if c is None:
            (a64, na2), (b64, nb2) = self._prepared(a), self._prepared(b)
            dot = math.fsum((a64 * b64).tolist())
            c = float("nan") if na2 == 0.0 or nb2 == 0.0 else dot / math.sqrt(na2 * nb2)
            self._pairs[key] = c
        return c


def cosine_trace(vectors: Sequence[np.ndarray | None], cache: CosineCache | None = None) -> np.ndarray:
    """trace[j] = cos(v_j, v_{j+1}); NaN where either side is None. Length len(vectors) - 1 (0 if empty).

    ``cache`` (a ``CosineCache``) shares the work between the traces of a run."""
    n = max(len(vectors) - 1, 0)
    out = np.full(n, np.nan, dtype=np.float64)
    cos = cache.cosine if cache is not None else cosine
    for j in range(n):
        a, b = vectors[j], vectors[j + 1]
        if a is not None and b is not None:
            out[j] = cos(a, b)
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


def boundaries_at(trace: np.ndarray, threshold: float) -> list[int]:
    """Segmentation points: indices j with trace[j] < threshold (NaN never is)."""
    t = np.asarray(trace, dtype=np.float64)
    return [int(j) for j in np.flatnonzero(t < threshold)]


def segment_counts(trace: np.ndarray, thresholds: Sequence[float] = THRESHOLDS) -> list[int]:
    """Number of segmentation points per threshold (the paper's Fig. 6)."""
    t = np.asarray(trace, dtype=np.float64)
    return [int(np.count_nonzero(t < thr)) for thr in thresholds]
