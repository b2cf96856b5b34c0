"""Chance baselines of a segmentation: the expected score of random segmentation points with the same count
(``CHANCE_DRAWS`` seeded draws, or every set when there are no more), of evenly spaced points of that count,
and of points at the edges of the pipeline's frame groups."""

from __future__ import annotations

import functools
import itertools
import math
from collections.abc import Sequence

import numpy as np

from vlmproprio.segmentation.metrics import Truth, masks_of, score_masks, score_positions

# metrics that get chance baselines and a lift (score - chance); every one is "higher is better"
CHANCE_METRICS: tuple[str, ...] = ("f1_tol1", "edit", "f1_at_10", "f1_at_25", "f1_at_50", "frame_acc")
CHANCE_DRAWS = 10000
CHANCE_SEED = 20261201


def evenly_spaced(n_frames: int, k: int) -> list[int]:
    """k segmentation points cutting n frames into k + 1 segments as equal as possible (rounded half up)."""
    if not 0 <= k <= n_frames - 1:
        raise ValueError(f"{k} segmentation points do not fit {n_frames} frames")
    return [(2 * i * n_frames + k + 1) // (2 * (k + 1)) - 1 for i in range(1, k + 1)]


def group_edges(n_frames: int, group: int) -> list[int]:
    """Segmentation points at the edges of the pipeline's frame groups (frames 0..group-1, group.., ...)."""
    if group < 1:
        raise ValueError(f"group size must be >= 1, got {group}")
    return [j for j in range(group - 1, n_frames - 1, group)]


@functools.lru_cache(maxsize=16)
def random_orders(n_positions: int, draws: int, seed: int) -> np.ndarray:
    """``draws`` uniformly random orderings of the n positions (seeded); read-only.

    The first k positions of a uniformly random ordering are a uniform k-subset, so one set of orderings
    serves every count k of an episode length (the estimates for different k share their draws)."""
    rng = np.random.Generator(np.random.PCG64([seed, n_positions]))
    order = np.argsort(rng.random((draws, n_positions)), axis=1, kind="stable")
    order.flags.writeable = False
    return order


def random_positions(n_positions: int, k: int, draws: int, seed: int) -> np.ndarray:
    """``draws`` uniform k-subsets of the n positions, ascending per row."""
    return np.sort(random_orders(n_positions, draws, seed)[:, :k], axis=1)


def random_masks(n_positions: int, k: int, draws: int, seed: int) -> np.ndarray:
    """``random_positions`` as boolean masks."""
    out = np.zeros((draws, n_positions), dtype=bool)
    if k:
        np.put_along_axis(out, random_positions(n_positions, k, draws, seed), True, axis=1)
    return out


def chance_random(
    truth: Truth, k: int, metrics: Sequence[str] = CHANCE_METRICS, draws: int = CHANCE_DRAWS, seed: int = CHANCE_SEED
) -> dict[str, float]:
    """Expected score of k segmentation points placed uniformly at random among the n - 1 positions.

    Exact when there are at most ``draws`` possible sets (all of them are scored: every k-subset is equally
    likely); otherwise the mean over ``draws`` seeded draws. Sums are exact (``math.fsum``)."""
    n_pos = truth.n_frames - 1
    if not 0 <= k <= n_pos:
        raise ValueError(f"{k} segmentation points do not fit {truth.n_frames} frames")
    if math.comb(n_pos, k) <= draws:
        combos = itertools.chain.from_iterable(itertools.combinations(range(n_pos), k))
        pos = np.fromiter(combos, np.int64, count=math.comb(n_pos, k) * k).reshape(math.comb(n_pos, k), k)
    else:
        pos = random_positions(n_pos, k, draws, seed)
    tols = sorted({int(m.removeprefix("f1_tol")) for m in metrics if m.startswith("f1_tol")})
    scores = score_positions(pos, np.full(len(pos), k, dtype=np.int64), truth, tols)
    return {m: math.fsum(scores[m].tolist()) / len(pos) for m in metrics}


def chance_is_exact(n_frames: int, k: int, draws: int = CHANCE_DRAWS) -> bool:
    return math.comb(max(n_frames - 1, 0), k) <= draws


def score_points(points: Sequence[int], truth: Truth, metrics: Sequence[str] = CHANCE_METRICS) -> dict[str, float]:
    """The metrics of one set of segmentation points."""
    scores = score_masks(masks_of([points], truth.n_frames), truth)
    return {m: float(scores[m][0]) for m in metrics}
