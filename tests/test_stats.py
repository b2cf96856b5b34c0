"""Paired statistics: mean difference, bootstrap CI, sign-flip p-values on cases with known answers."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from vlmproprio.stats import (
    DEFAULT_MAX_EXACT,
    TIE_RTOL,
    binary_difference_bounds,
    bootstrap_ci,
    clopper_pearson,
    paired_difference,
    sign_flip_p,
)


def test_all_episodes_improve_by_one():
    r = paired_difference([1.0] * 10, [0.0] * 10)
    assert (r.n, r.mean_a, r.mean_b, r.mean_diff) == (10, 1.0, 0.0, 1.0)
    assert (r.ci_low, r.ci_high) == (1.0, 1.0)
    assert r.p_value == 2 / 2**10  # only all-plus and all-minus are as extreme
    assert r.method == "exact sign-flip"


# (differences, exact two-sided p worked out by hand)
P_CASES = [
    ([1, 2, 3], 2 / 8),
    ([3, 1, 1, 1], 2 / 16),  # flipping any 1 gives |4| < 6
    ([1, 1, 1, 1], 2 / 16),
    ([2, 1, 1], 2 / 8),  # other patterns give |2|, |0|
    ([1, -1, 1, -1], 1.0),
    ([0, 0, 0], 1.0),
]


def _brute_p(d):
    obs = abs(sum(d))
    pats = list(itertools.product([1, -1], repeat=len(d)))
    return sum(abs(sum(s * x for s, x in zip(p, d, strict=True))) >= obs - 1e-12 for p in pats) / len(pats)


@pytest.mark.parametrize(("d", "p"), P_CASES)
def test_exact_sign_flip_p(d, p):
    assert _brute_p(d) == pytest.approx(p)
    got, method = sign_flip_p(np.array(d, dtype=float))
    assert got == pytest.approx(p) and method == "exact sign-flip"


def test_exact_p_matches_scipy_permutation_test():
    stats = pytest.importorskip("scipy.stats")  # a cross-check with an independent implementation
    rng = np.random.default_rng(3)
    a, b = rng.normal(0.3, 1, 11), rng.normal(0, 1, 11)
    ours = paired_difference(a, b)
    ref = stats.permutation_test(
        (a, b),
        lambda x, y: np.mean(x - y),
        permutation_type="samples",
        alternative="two-sided",
        n_resamples=np.inf,
    )
    assert ours.p_value == pytest.approx(ref.pvalue, abs=1e-12)


def test_monte_carlo_p_is_close_to_exact_and_seeded():
    rng = np.random.default_rng(5)
    d = rng.normal(0.4, 1, 14)
    exact, _ = sign_flip_p(d, max_exact=16)
    mc, method = sign_flip_p(d, n_perm=20000, seed=1, max_exact=8)
    assert method.startswith("monte-carlo")
    assert abs(mc - exact) < 0.015
    assert sign_flip_p(d, n_perm=20000, seed=1, max_exact=8) == (mc, method)


def _enumerated_p(d: np.ndarray) -> float:
    """The exact branch the suite had before meet in the middle: every one of the 2**n sign patterns as a
    column, summed left to right, compared with the same tolerance (n <= 16)."""
    n = len(d)
    codes = np.arange(1 << n, dtype=np.int64)
    signs = 1.0 - 2.0 * ((codes[:, None] >> np.arange(n, dtype=np.int64)) & 1)
    stats = np.zeros(1 << n)
    obs = 0.0
    for j in range(n):
        stats = stats + signs[:, j] * d[j]
        obs = obs + d[j]
    obs = abs(obs)
    tol = TIE_RTOL * max(obs, float(np.abs(d).max()), 1e-300)
    return int(np.count_nonzero(np.abs(stats) >= obs - tol)) / (1 << n)


@pytest.mark.parametrize("n", [1, 2, 5, 9, 10, 12, 15, 16])
def test_exact_p_equals_the_enumeration_of_every_pattern(n):
    rng = np.random.default_rng(100 + n)
    cases = [
        rng.normal(0.3, 1.0, n),
        np.round(rng.normal(0.2, 0.5, n), 2),  # many exact ties between patterns
        rng.integers(-1, 2, n).astype(float),  # a rate: differences in {-1, 0, 1}
        np.full(n, 0.25),
    ]
    for d in cases:
        got, method = sign_flip_p(d)
        assert method == "exact sign-flip"
        assert got == _enumerated_p(d), d.tolist()


def _sign_test_p(k: int, j: int) -> float:
    """Two-sided sign test: k differences of +-1, j of them positive (zeros carry no sign information)."""
    obs = abs(2 * j - k)
    return sum(math.comb(k, i) for i in range(k + 1) if abs(2 * i - k) >= obs) / 2**k


@pytest.mark.parametrize(("plus", "minus", "zeros"), [(22, 0, 0), (15, 5, 2), (11, 11, 0), (18, 1, 3), (6, 0, 16)])
def test_pooled_rates_are_exact_below_any_monte_carlo_floor(plus, minus, zeros):
    """22 pooled episodes: the sign-flip test of a rate is the sign test, exactly (1 / 20 001 was the floor)."""
    d = np.array([1.0] * plus + [-1.0] * minus + [0.0] * zeros)
    np.random.default_rng(plus).shuffle(d)
    p, method = sign_flip_p(d)
    assert method == "exact sign-flip"
    assert p == pytest.approx(_sign_test_p(plus + minus, plus), rel=1e-12)
    if plus == 22:
        assert p == 2 / 2**22 < 1 / 20001


def test_exact_up_to_forty_pairs_then_monte_carlo_with_its_floor():
    rng = np.random.default_rng(8)
    d40 = rng.normal(0.0, 1.0, 40)
    p40, method = sign_flip_p(d40)
    assert DEFAULT_MAX_EXACT == 40 and method == "exact sign-flip" and 0.0 < p40 <= 1.0
    d = np.ones(41)
    p, method = sign_flip_p(d, n_perm=1000)
    assert method == "monte-carlo sign-flip (1000 patterns, p >= 1/1001)"
    assert p == 1 / 1001  # no random pattern reaches all-plus: the floor, not the exact 2 / 2**41


finite = st.floats(-5.0, 5.0, allow_nan=False, allow_infinity=False, width=32)


@settings(max_examples=150, deadline=None)
@given(st.lists(st.one_of(finite, st.sampled_from([0.0, 0.5, -0.5, 1.0, -1.0])), min_size=1, max_size=14))
def test_exact_p_properties(values):
    """Against the enumeration; and what the null distribution guarantees whatever the data: p in (0, 1],
    p >= 2 / 2**n unless everything is zero, unchanged by negating, reordering or doubling the differences."""
    d = np.array(values, dtype=np.float64)
    p, _ = sign_flip_p(d)
    assert p == _enumerated_p(d)
    assert 0.0 < p <= 1.0
    if np.any(d != 0.0):
        assert p >= 2 / 2 ** len(d)
    assert sign_flip_p(-d)[0] == p
    assert sign_flip_p(d[::-1].copy())[0] == pytest.approx(p, abs=1e-12)
    assert sign_flip_p(2.0 * d)[0] == p


# ---------------------------------------------------------------------------------------------- exact bounds


@pytest.mark.parametrize("n", [1, 5, 10, 12, 22, 60, 1500])
def test_clopper_pearson_equals_the_beta_quantiles(n):
    beta = pytest.importorskip("scipy.stats").beta  # an independent implementation of the same quantiles
    for k in sorted({0, 1, n // 3, n // 2, n - 1, n}):
        for tail in (0.025, 0.005, 0.2):
            lo, hi = clopper_pearson(k, n, tail)
            assert lo == (0.0 if k == 0 else pytest.approx(beta.ppf(tail, k, n - k + 1), rel=1e-9, abs=1e-15))
            assert hi == (1.0 if k == n else pytest.approx(beta.ppf(1 - tail, k + 1, n - k), rel=1e-9))


def test_no_discordant_pair_among_22_leaves_15_points():
    lo, hi = binary_difference_bounds(0, 0, 22)
    assert hi == pytest.approx(1 - 0.025 ** (1 / 22), rel=1e-12)  # U(0 of 22) - L(0 of 22) = U - 0
    assert 0.15 < hi < 0.16 and lo == -hi
    r = paired_difference([1.0] * 11 + [0.0] * 11, [1.0] * 11 + [0.0] * 11, binary=True)
    assert (r.ci_low, r.ci_high, r.n_ab, r.n_ba) == (0.0, 0.0, 0, 0)
    assert (r.exact_low, r.exact_high) == (lo, hi)
    assert paired_difference([1.0], [0.0]).exact_high is None  # only binary metrics get them
    with pytest.raises(ValueError, match="0 or 1"):
        paired_difference([0.5], [0.0], binary=True)


def test_exact_bounds_combine_the_beta_quantiles_of_both_discordant_shares():
    beta = pytest.importorskip("scipy.stats").beta
    lo, hi = binary_difference_bounds(5, 2, 22)  # 5 episodes right only under A, 2 only under B
    assert hi == pytest.approx(beta.ppf(0.975, 6, 17) - beta.ppf(0.025, 2, 21), rel=1e-9)
    assert lo == pytest.approx(beta.ppf(0.025, 5, 18) - beta.ppf(0.975, 3, 20), rel=1e-9)
    # right under A in all 22, never under B: low = L(22 of 22) - U(0 of 22) = 2 * 0.025**(1/22) - 1
    assert binary_difference_bounds(22, 0, 22) == pytest.approx((2 * 0.025 ** (1 / 22) - 1, 1.0), rel=1e-12)


def _miss_probability(n: int, p_ab: float, p_ba: float, level: float) -> tuple[float, float]:
    """P(difference > high) and P(difference < low) over every outcome of n pairs (multinomial, exact)."""
    diff, over, under = p_ab - p_ba, 0.0, 0.0
    p_same = 1.0 - p_ab - p_ba
    for i in range(n + 1):
        for j in range(n + 1 - i):
            prob = math.comb(n, i) * math.comb(n - i, j) * p_ab**i * p_ba**j * p_same ** (n - i - j)
            lo, hi = binary_difference_bounds(i, j, n, level)
            over += prob * (diff > hi)
            under += prob * (diff < lo)
    return over, under


@pytest.mark.parametrize("n", [6, 13, 22])
def test_each_exact_bound_misses_at_most_one_minus_level(n):
    """Each end is a one-sided bound at the level, for every pair of discordant shares (enumerated exactly)."""
    for p_ab, p_ba in [(0.0, 0.0), (0.05, 0.0), (0.3, 0.1), (0.02, 0.4), (0.5, 0.5), (0.9, 0.05), (0.15, 0.15)]:
        over, under = _miss_probability(n, p_ab, p_ba, 0.95)
        assert over <= 0.05 + 1e-12 and under <= 0.05 + 1e-12, (p_ab, p_ba, over, under)


def test_bootstrap_ci_is_seeded_and_brackets_the_mean():
    d = np.random.default_rng(11).normal(0.3, 1.0, 10)
    lo, hi = bootstrap_ci(d, seed=7)
    assert (lo, hi) == bootstrap_ci(d, seed=7)
    assert lo < d.mean() < hi
    assert bootstrap_ci(d, seed=8) != (lo, hi)
    # a constant difference has a zero-width interval
    assert bootstrap_ci(np.full(12, 0.25)) == (0.25, 0.25)


def test_paired_difference_direction_and_errors():
    r = paired_difference([0.0, 0.5, 1.0], [1.0, 1.0, 1.0])
    assert r.mean_diff == pytest.approx(-0.5) and r.ci_high <= 0.0
    with pytest.raises(ValueError, match="differ in length"):
        paired_difference([1.0], [1.0, 2.0])
    with pytest.raises(ValueError, match="finite"):
        paired_difference([float("nan")], [1.0])
    assert paired_difference([], []).n == 0


# ---------------------------------------------------------------------------------------------- multiplicity


def _holm_by_definition(p: list[float], alpha: float) -> list[bool]:
    """Holm's procedure as a sequence of decisions: reject while p_(i) <= alpha / (m - i + 1)."""
    order = sorted(range(len(p)), key=lambda i: p[i])
    reject = [False] * len(p)
    for rank, i in enumerate(order):
        if p[i] <= alpha / (len(p) - rank):
            reject[i] = True
        else:
            break
    return reject


def _bh_by_definition(p: list[float], alpha: float) -> list[bool]:
    """BH step-up: find the largest i with p_(i) <= i alpha / m, reject the i smallest."""
    order = sorted(range(len(p)), key=lambda i: p[i])
    m = len(p)
    cut = max((r + 1 for r, i in enumerate(order) if p[i] <= (r + 1) * alpha / m), default=0)
    reject = [False] * m
    for i in order[:cut]:
        reject[i] = True
    return reject


def test_holm_and_bh_decisions_match_their_definitions():
    from vlmproprio.stats import benjamini_hochberg, holm

    rng = np.random.default_rng(5)
    for _ in range(300):
        m = int(rng.integers(1, 30))
        p = [float(x) for x in rng.uniform(0, 0.2, m) ** rng.uniform(0.5, 3)]
        for alpha in (0.01, 0.05, 0.1):
            assert [h <= alpha for h in holm(p)] == _holm_by_definition(p, alpha)
            assert [q <= alpha for q in benjamini_hochberg(p)] == _bh_by_definition(p, alpha)


def test_bh_equals_scipy_and_holm_known_values():
    from scipy.stats import false_discovery_control

    from vlmproprio.stats import benjamini_hochberg, holm

    p = [0.01, 0.04, 0.03, 0.005, 0.2]
    assert benjamini_hochberg(p) == pytest.approx(list(false_discovery_control(p, method="bh")), abs=1e-12)
    # sorted 0.005, 0.01, 0.03, 0.04, 0.2 -> 5*0.005, 4*0.01, 3*0.03, 2*0.04 (running max), 0.2
    assert holm(p) == pytest.approx([0.04, 0.09, 0.09, 0.025, 0.2])
    assert holm([float("nan"), 0.01])[1] == 0.01 and math.isnan(holm([float("nan"), 0.01])[0])
    with pytest.raises(ValueError):
        holm([1.5])
