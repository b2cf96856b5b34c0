"""Paired statistics between conditions: mean difference, bootstrap CI and a sign-flip permutation p-value.

Conditions are compared on the same episodes (10 Door, 12 bin episodes), so
differences are paired by episode and no normal approximation is used:

* the mean difference, summed exactly (``math.fsum``);
* a percentile bootstrap 95 % CI of the mean difference: episodes resampled with
  replacement, ``n_boot`` times, from a numpy PCG64 generator with a fixed seed;
* a two-sided sign-flip permutation p-value: under "no effect" each episode's
  difference is as likely positive as negative, and p = P(|S| >= |s_obs|) over the 2**n equally likely
  sums S = sum(s_i d_i). With n <= ``max_exact`` (40) that distribution is enumerated exactly, by meet in
  the middle: the 2**(n/2) signed sums of each half of the differences, one half sorted, and for every sum
  of the other half the count of partners that make |S| large enough (``np.searchsorted``): O(2**(n/2) n),
  exact for the 10, 12 and 22 pooled episodes of the fixtures and for any run up to 40 pairs. Above that
  ``n_perm`` random patterns are drawn with the fixed seed and p = (hits + 1) / (n_perm + 1) >= 1/(n_perm + 1)
  (Monte Carlo; standard error about sqrt(p (1 - p) / n_perm)); the method is recorded with each p.

Every sum is taken left to right with element-wise IEEE additions (no BLAS, no
SIMD reassociation), so results have the same bits on any machine. Ties
``|S| >= |s_obs|`` are compared with a tolerance of 1e-9 times max(|s_obs|, max |d_i|): a signed sum of
n float64 values is off its exact value by at most about n**2 2**-53 max |d_i| (below 1e-13 max |d_i| for
n <= 40), so every pattern whose exact |S| ties |s_obs| counts, for real-valued data as for 0/1 rates,
without rescaling the data to integers.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Iterable, Sequence

import numpy as np

DEFAULT_SEED = 20250101
DEFAULT_N_BOOT = 10000
DEFAULT_N_PERM = 20000
DEFAULT_MAX_EXACT = 40  # meet in the middle: two halves of 2**20 sums at most, ~0.5 s
TIE_RTOL = 1e-9


@dataclasses.dataclass(frozen=True)
class PairedResult:
    n: int
    mean_a: float
    mean_b: float
    mean_diff: float  # mean of a - b
    ci_low: float
    ci_high: float
    p_value: float
    method: str  # "exact sign-flip" | "monte-carlo sign-flip (N patterns, p >= 1/(N+1))" | "none (n=0)"
    n_boot: int
    seed: int
    # binary metrics only (``paired_difference(binary=True)``): the discordant pairs and the exact bounds
    n_ab: int | None = None  # episodes with A = 1, B = 0
    n_ba: int | None = None  # episodes with A = 0, B = 1
    exact_low: float | None = None  # exact one-sided lower bound of the difference at ``level``
    exact_high: float | None = None  # exact one-sided upper bound: the largest effect compatible with the data

    def to_dict(self) -> dict:
        # asdict's deep copy of ten scalars cost more than the statistics of small tables; the same dict
        return dict(vars(self))


def exact_mean(x: Sequence[float]) -> float:
    return math.fsum(float(v) for v in x) / len(x) if len(x) else float("nan")


def _sum_columns(columns: Iterable[np.ndarray]) -> np.ndarray:
    """Add columns left to right with element-wise IEEE adds: the same bits on any machine and BLAS."""
    total = None
    for col in columns:
        total = col.copy() if total is None else total + col
    return total


@functools.lru_cache(maxsize=64)
def _bootstrap_columns(n: int, n_boot: int, seed: int) -> np.ndarray:
    """The bootstrap's resampled episode indices, one contiguous row per draw position (read-only).

    They depend only on (n, n_boot, seed), so a run's hundreds of comparisons share one draw."""
    rng = np.random.Generator(np.random.PCG64(seed))
    cols = np.ascontiguousarray(rng.integers(0, n, size=(n_boot, n)).T)
    cols.flags.writeable = False
    return cols


def bootstrap_ci(
    d: np.ndarray, n_boot: int = DEFAULT_N_BOOT, seed: int = DEFAULT_SEED, level: float = 0.95
) -> tuple[float, float]:
    """Percentile bootstrap CI of the mean of ``d`` (episodes resampled with replacement)."""
    n = len(d)
    cols = _bootstrap_columns(n, n_boot, seed)
    means = _sum_columns(d[cols[j]] for j in range(n)) / n
    alpha = (1.0 - level) / 2.0
    lo, hi = np.quantile(means, [alpha, 1.0 - alpha], method="linear")
    return float(lo), float(hi)


def _signs_of(codes: np.ndarray, n: int) -> np.ndarray:
    """The sign patterns whose bits are ``codes`` (bit j set: episode j flipped), one contiguous row per episode."""
    signs = 1.0 - 2.0 * ((codes[:, None] >> np.arange(n, dtype=np.int64)) & 1)
    return np.ascontiguousarray(signs.T)


@functools.lru_cache(maxsize=16)
def _sign_patterns(n: int, n_perm: int, seed: int) -> tuple[np.ndarray, ...]:
    """The Monte Carlo test's ``n_perm`` seeded sign patterns in chunks of at most 65 536, each (n, patterns),
    read-only. They depend only on these arguments, not on the data."""
    chunks = []
    rng = np.random.Generator(np.random.PCG64(seed + 1))
    done = 0
    while done < n_perm:
        m = min(1 << 16, n_perm - done)
        if n <= 62:  # one random integer per pattern, its bits are the signs
            chunks.append(_signs_of(rng.integers(0, 1 << n, size=m, dtype=np.int64), n))
        else:
            chunks.append(np.ascontiguousarray((1.0 - 2.0 * rng.integers(0, 2, size=(m, n))).T))
        done += m
    for c in chunks:
        c.flags.writeable = False
    return tuple(chunks)


def signed_sums(d: np.ndarray) -> np.ndarray:
    """Every sum sum(s_i d_i), s_i = +-1, of each row of ``d`` (rows x k): rows x 2**k, taken left to right
    with IEEE adds. Rounding is symmetric, so each row's sums are exactly symmetric about 0."""
    rows, k = d.shape
    sums = np.zeros((rows, 1 << k))
    for j in range(k):
        m, x = 1 << j, d[:, j : j + 1]
        np.subtract(sums[:, :m], x, out=sums[:, m : 2 * m])
        sums[:, :m] += x
    return sums


def _exact_tail_counts(d: np.ndarray, thresholds: np.ndarray) -> np.ndarray:
    """Per row of ``d``: how many of the 2**n sign patterns give |sum(s_i d_i)| >= its threshold.

    Meet in the middle: |A + B| >= t splits into A + B >= t and A + B <= -t (disjoint when t > 0), A a
    signed sum of the row's first half, B one of its second half. Both halves' sums are exactly symmetric, so
    the second part counts as many patterns as the first: twice #(B >= t - A), from one sorted B per row
    (the A sorted too, descending, so that the searches walk B in order)."""
    n = d.shape[1]
    left = np.sort(signed_sums(d[:, : n // 2]), axis=1)[:, ::-1]
    right = np.sort(signed_sums(d[:, n // 2 :]), axis=1)
    counts = np.full(len(d), 1 << n, dtype=np.int64)  # a threshold <= 0: every pattern is as extreme
    for r in np.flatnonzero(thresholds > 0.0):
        below = np.searchsorted(right[r], thresholds[r] - left[r], side="left")
        counts[r] = 2 * (left.shape[1] * right.shape[1] - int(below.sum()))
    return counts


def observed_and_tolerance(d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per row of ``d`` (rows x n): |s_obs| summed left to right, and its tie tolerance (module docstring)."""
    obs = np.abs(_sum_columns(d[:, j] for j in range(d.shape[1])))
    tol = TIE_RTOL * np.maximum(np.maximum(obs, np.abs(d).max(axis=1)), 1e-300)
    return obs, tol


def exact_sign_flip_p(d: np.ndarray) -> np.ndarray:
    """The exact two-sided sign-flip p-value of every row of ``d`` (rows x n, n >= 1): the share of all 2**n
    sign patterns whose |sum| reaches the row's own, within the tie tolerance."""
    rows, n = d.shape
    obs, tol = observed_and_tolerance(d)
    # rows at a time whose half-sums fit in about 2**22 floats (32 MiB), whatever n
    step = max(1, (1 << 22) >> (n - n // 2))
    counts = np.concatenate(
        [_exact_tail_counts(d[s : s + step], (obs - tol)[s : s + step]) for s in range(0, rows, step)]
    )
    return counts / float(1 << n)


def monte_carlo_method(n_perm: int) -> str:
    return f"monte-carlo sign-flip ({n_perm} patterns, p >= 1/{n_perm + 1})"


def sign_flip_p(
    d: np.ndarray, n_perm: int = DEFAULT_N_PERM, seed: int = DEFAULT_SEED, max_exact: int = DEFAULT_MAX_EXACT
) -> tuple[float, str]:
    """Two-sided sign-flip p-value of the mean of ``d``; returns (p, method).

    Exact (every sign pattern) for n <= ``max_exact``; else ``n_perm`` seeded patterns (module docstring)."""
    n = len(d)
    if n <= max_exact:
        return float(exact_sign_flip_p(np.asarray(d, dtype=np.float64)[None, :])[0]), "exact sign-flip"
    obs, tol = (float(v[0]) for v in observed_and_tolerance(np.asarray(d, dtype=np.float64)[None, :]))
    hits = 0
    for signs in _sign_patterns(n, n_perm, seed):
        stats = np.abs(_sum_columns(signs[j] * d[j] for j in range(n)))
        hits += int(np.count_nonzero(stats >= obs - tol))
    return (hits + 1) / (n_perm + 1), monte_carlo_method(n_perm)


# ---------------------------------------------------------------------------------------------- exact bounds


def _binomial_cdf(k: int, n: int, p: float) -> float:
    """P(X <= k) for X ~ Binomial(n, p), its terms summed in log space (no overflow for large n)."""
    if k >= n or p <= 0.0:
        return 1.0
    if k < 0 or p >= 1.0:
        return 0.0
    logs = [
        math.lgamma(n + 1) - math.lgamma(i + 1) - math.lgamma(n - i + 1) + i * math.log(p) + (n - i) * math.log1p(-p)
        for i in range(k + 1)
    ]
    top = max(logs)
    return min(1.0, math.exp(top) * math.fsum(math.exp(x - top) for x in logs))


def _bisect_decreasing(f, target: float) -> float:
    """The p in [0, 1] where the decreasing f(p) crosses target, to the last bit (bisection)."""
    lo, hi = 0.0, 1.0
    while True:
        mid = 0.5 * (lo + hi)
        if mid in (lo, hi):
            return hi
        if f(mid) > target:
            lo = mid
        else:
            hi = mid


@functools.lru_cache(maxsize=4096)
def clopper_pearson(k: int, n: int, tail: float) -> tuple[float, float]:
    """Exact one-sided bounds (L, U) of a binomial proportion from k successes in n trials, each missing with
    probability at most ``tail`` (Clopper & Pearson 1934): P(X >= k | L) = tail and P(X <= k | U) = tail, L = 0
    for k = 0 and U = 1 for k = n. They are the beta quantiles Beta(tail; k, n - k + 1) and
    Beta(1 - tail; k + 1, n - k), found by bisection on the binomial tail (no scipy in the core install)."""
    if not 0 <= k <= n or n == 0:
        raise ValueError(f"need 0 <= k <= n and n > 0, got k = {k}, n = {n}")
    lower = 0.0 if k == 0 else _bisect_decreasing(lambda p: _binomial_cdf(k - 1, n, p), 1.0 - tail)
    upper = 1.0 if k == n else _bisect_decreasing(lambda p: _binomial_cdf(k, n, p), tail)
    return lower, upper


def binary_difference_bounds(n_ab: int, n_ba: int, n: int, level: float = 0.95) -> tuple[float, float]:
    """Exact bounds of the paired difference P(A = 1) - P(B = 1) = P(A=1, B=0) - P(A=0, B=1) of 0/1 outcomes
    from the discordant pairs: with (L, U) the Clopper-Pearson bounds of each discordant share at tail
    (1 - level) / 2, high = U(n_ab) - L(n_ba) and low = L(n_ab) - U(n_ba). The difference exceeds high only when
    one of two bounds fails, so by Bonferroni each end is a one-sided bound at ``level`` (together, an interval
    covering with probability at least 2 level - 1), whatever the dependence between A and B."""
    tail = (1.0 - level) / 2.0
    lab, uab = clopper_pearson(n_ab, n, tail)
    lba, uba = clopper_pearson(n_ba, n, tail)
    return max(-1.0, lab - uba), min(1.0, uab - lba)


# ---------------------------------------------------------------------------------------------- tests


@functools.lru_cache(maxsize=4096)
def _difference_tests(
    d_bits: bytes, n_boot: int, n_perm: int, seed: int, max_exact: int, level: float
) -> tuple[float, float, float, str]:
    """Bootstrap CI and sign-flip p of one vector of differences, given as its exact bits: many comparisons
    of a run have the same differences (all zero, or a metric repeated), and they are tested once."""
    d = np.frombuffer(d_bits, dtype=np.float64)
    lo, hi = bootstrap_ci(d, n_boot, seed, level)
    p, method = sign_flip_p(d, n_perm, seed, max_exact)
    return lo, hi, p, method


def paired_difference(
    a: Sequence[float],
    b: Sequence[float],
    *,
    n_boot: int = DEFAULT_N_BOOT,
    n_perm: int = DEFAULT_N_PERM,
    seed: int = DEFAULT_SEED,
    max_exact: int = DEFAULT_MAX_EXACT,
    level: float = 0.95,
    binary: bool = False,
) -> PairedResult:
    """Compare condition A with condition B on the same episodes (a[i] and b[i] belong to episode i).

    ``binary``: the outcomes are 0/1 (a rubric item right or not); the result then also carries the discordant
    pairs and the exact bounds of the difference (``binary_difference_bounds``)."""
    if len(a) != len(b):
        raise ValueError(f"paired samples differ in length: {len(a)} vs {len(b)}")
    av = np.asarray(a, dtype=np.float64)
    bv = np.asarray(b, dtype=np.float64)
    if not (np.isfinite(av).all() and np.isfinite(bv).all()):
        raise ValueError("paired samples must be finite")
    n = len(av)
    if n == 0:
        nan = float("nan")
        return PairedResult(0, nan, nan, nan, nan, nan, nan, "none (n=0)", n_boot, seed)
    if binary and not (np.isin(av, (0.0, 1.0)).all() and np.isin(bv, (0.0, 1.0)).all()):
        raise ValueError("binary paired samples must be 0 or 1")
    d = av - bv
    lo, hi, p, method = _difference_tests(d.tobytes(), n_boot, n_perm, seed, max_exact, level)
    res = PairedResult(n, exact_mean(av), exact_mean(bv), exact_mean(d), lo, hi, p, method, n_boot, seed)
    if not binary:
        return res
    n_ab, n_ba = int(np.count_nonzero(d > 0)), int(np.count_nonzero(d < 0))
    exact_low, exact_high = binary_difference_bounds(n_ab, n_ba, n, level)
    return dataclasses.replace(res, n_ab=n_ab, n_ba=n_ba, exact_low=exact_low, exact_high=exact_high)


# ---------------------------------------------------------------------------------------------- multiplicity


def holm(p_values: Sequence[float]) -> list[float]:
    """Holm's step-down adjusted p-values (Holm 1979), controlling the family-wise error rate.

    Sorted ascending p_(1) <= ... <= p_(m): adjusted p_(i) = max over j <= i of min(1, (m - j + 1) p_(j)).
    A hypothesis is rejected at level alpha exactly when its adjusted p-value is <= alpha. NaN stays NaN and
    does not count towards m."""
    return _adjust(p_values, _holm_sorted)


def benjamini_hochberg(p_values: Sequence[float]) -> list[float]:
    """Benjamini-Hochberg q-values (Benjamini & Hochberg 1995), controlling the false discovery rate.

    Sorted ascending: q_(i) = min over j >= i of min(1, m p_(j) / j). NaN stays NaN and does not count."""
    return _adjust(p_values, _bh_sorted)


def _holm_sorted(p: list[float]) -> list[float]:
    m = len(p)
    out, running = [], 0.0
    for i, x in enumerate(p):
        running = max(running, min(1.0, (m - i) * x))
        out.append(running)
    return out


def _bh_sorted(p: list[float]) -> list[float]:
    m = len(p)
    out = [0.0] * m
    running = 1.0
    for i in range(m - 1, -1, -1):
        running = min(running, min(1.0, m * p[i] / (i + 1)))
        out[i] = running
    return out


def _adjust(p_values: Sequence[float], method) -> list[float]:
    vals = [float(p) for p in p_values]
    finite = [i for i, p in enumerate(vals) if math.isfinite(p)]
    if any(not 0.0 <= vals[i] <= 1.0 for i in finite):
        raise ValueError("p-values must lie in [0, 1]")
    order = sorted(finite, key=lambda i: (vals[i], i))
    adjusted = method([vals[i] for i in order])
    out = [float("nan")] * len(vals)
    for i, a in zip(order, adjusted, strict=True):
        out[i] = a
    return out
