"""Chance baselines of a segmentation, each the score of points placed without reading anything:

* random: the same number of points uniformly at random (``CHANCE_DRAWS`` seeded draws, or every set when there
  are no more);
* evenly spaced: that many points evenly spaced, at one phase (``evenly_spaced``) and averaged over every phase
  offset (``chance_periodic``: what a caption stream that changes at a fixed period scores at a random phase);
* shifted: the segmentation's own points circularly shifted, averaged over every shift (``chance_shifted``:
  their spacing kept, their alignment with the episode lost);
* own period: a metronome at the points' most common gap, averaged over every phase (``chance_own_period``);
* the edges of the pipeline's frame groups, as many of them as the segmentation has points (``chance_groups``).

Each places as many points as the segmentation it is read against: a baseline with more points would make a
condition with few points (no state: often none) look worse than it is, and the difference between conditions
would then reward merely placing points.

Evenly spaced points beat random ones (ground-truth phases are never shorter than a few frames, and random points
bunch up), so a lift over random chance alone can be won by a metronome; the best of these content-free
baselines cannot."""

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


def _mean_scores(pos: np.ndarray, truth: Truth, metrics: Sequence[str]) -> dict[str, float]:
    tols = sorted({int(m.removeprefix("f1_tol")) for m in metrics if m.startswith("f1_tol")})
    scores = score_positions(pos, np.full(len(pos), pos.shape[1], dtype=np.int64), truth, tols)
    return {m: math.fsum(scores[m].tolist()) / len(pos) for m in metrics}


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
    return _mean_scores(pos, truth, metrics)


def chance_is_exact(n_frames: int, k: int, draws: int = CHANCE_DRAWS) -> bool:
    return math.comb(max(n_frames - 1, 0), k) <= draws


def shifted_positions(points: Sequence[int], n_positions: int) -> np.ndarray:
    """Every circular shift of ``points`` among ``n_positions`` positions: row s holds (p + s) mod n, ascending."""
    pts = np.asarray(sorted(set(points)), dtype=np.int64)
    if pts.size and not (pts[0] >= 0 and pts[-1] < n_positions):
        raise ValueError(f"segmentation points {points} do not fit {n_positions} positions")
    return np.sort((pts[None, :] + np.arange(n_positions, dtype=np.int64)[:, None]) % n_positions, axis=1)


def chance_shifted(points: Sequence[int], truth: Truth, metrics: Sequence[str] = CHANCE_METRICS) -> dict[str, float]:
    """Expected score of ``points`` at a uniformly random phase: the exact mean over all circular shifts."""
    n_pos = truth.n_frames - 1
    if n_pos < 1 or not points:
        return score_points(sorted(set(points)), truth, metrics)
    return _mean_scores(shifted_positions(points, n_pos), truth, metrics)


def own_period(points: Sequence[int]) -> int | None:
    """The most common gap between consecutive points (the smallest of equally common ones); None below 2 points."""
    pts = sorted(set(points))
    gaps = [b - a for a, b in itertools.pairwise(pts)]
    if not gaps:
        return None
    counts = {g: gaps.count(g) for g in gaps}
    return min(counts, key=lambda g: (-counts[g], g))


def chance_own_period(
    points: Sequence[int], truth: Truth, metrics: Sequence[str] = CHANCE_METRICS
) -> dict[str, float] | None:
    """Expected score of a metronome at the points' own period (``own_period``) and a random phase: the mean over
    every offset o of the points o, o + period, ... across the whole episode. A segmentation that keeps time at one
    period scores this on average over its phases, so its lift over it is at most 0 in expectation (the circular
    shift only approaches that: its wrap breaks the period once). None when such a metronome would place more
    than one point more or fewer than the segmentation does at some offset: then the points do not keep time
    (they cluster), and a baseline with another count would not be comparable."""
    period = own_period(points)
    if period is None:
        return None
    n_pos, k = truth.n_frames - 1, len(set(points))
    lattices = [list(range(o, n_pos, period)) for o in range(period)]
    if any(abs(len(lat) - k) > 1 for lat in lattices):
        return None
    rows = [score_points(lat, truth, metrics) for lat in lattices]
    return {m: math.fsum(r[m] for r in rows) / len(rows) for m in metrics}


def chance_periodic(truth: Truth, k: int, metrics: Sequence[str] = CHANCE_METRICS) -> dict[str, float]:
    """Expected score of k evenly spaced points at a uniformly random phase offset (every offset, exactly)."""
    return chance_shifted(evenly_spaced(truth.n_frames, k), truth, metrics)


GROUP_DRAWS = 2000  # the group-edge baseline's seeded draws of the points beyond the edges, when more sets exist


def chance_groups(
    truth: Truth, k: int, group: int, metrics: Sequence[str] = CHANCE_METRICS, seed: int = CHANCE_SEED
) -> dict[str, float]:
    """Expected score of k points that favour the edges of the frame groups: k of the edges (every choice
    equally likely) when there are at least k, else every edge and the rest at random. Same count as the model's,
    so a model is never compared with a baseline that places more points than it does."""
    n_pos = truth.n_frames - 1
    if not 0 <= k <= n_pos:
        raise ValueError(f"{k} segmentation points do not fit {truth.n_frames} frames")
    edges = group_edges(truth.n_frames, group)
    if k == 0:
        return score_points([], truth, metrics)
    if k <= len(edges):
        pos = np.array(list(itertools.combinations(edges, k)), dtype=np.int64)
    else:
        rest = np.array([j for j in range(n_pos) if j not in set(edges)], dtype=np.int64)
        extra = k - len(edges)
        if math.comb(len(rest), extra) <= GROUP_DRAWS:
            picks = np.array(list(itertools.combinations(range(len(rest)), extra)), dtype=np.int64)
        else:
            picks = random_positions(len(rest), extra, GROUP_DRAWS, seed)
        fixed = np.broadcast_to(np.asarray(edges, dtype=np.int64), (len(picks), len(edges)))
        pos = np.sort(np.concatenate([fixed, rest[picks]], axis=1), axis=1)
    return _mean_scores(pos, truth, metrics)


def score_points(points: Sequence[int], truth: Truth, metrics: Sequence[str] = CHANCE_METRICS) -> dict[str, float]:
    """The metrics of one set of segmentation points."""
    scores = score_masks(masks_of([points], truth.n_frames), truth)
    return {m: float(scores[m][0]) for m in metrics}
