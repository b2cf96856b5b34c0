"""Power analysis: what the suite's episodes can detect, with the suite's own paired test.

A claim "A beats B" holds when, paired by episode, the mean difference is positive and the two-sided
sign-flip p-value of ``vlmproprio.stats`` is below the corrected alpha. This module asks the question a
reader asks before trusting a "not supported": *if* a model had an effect of a given size, how often would
the suite see it?

* **Episode structure.** The shipped fixtures: 10 Door and 12 bin episodes, compared per task and pooled
  (22), each episode paired with itself across conditions (``GROUPS``); a named set of
  ``record/named_sets.json`` by its parts' tasks and pooled (``set_groups``: the extended set's 60 Door, 96
  pick-place and 60 Stack episodes, 216 pooled).
* **The test.** Exactly the suite's: the exact distribution over all 2**n sign patterns for
  n <= ``stats.DEFAULT_MAX_EXACT`` episodes (``stats.exact_sign_flip_p`` itself), else
  ``stats.DEFAULT_N_PERM`` random patterns drawn as ``stats.sign_flip_p`` draws them (same seed), and the
  same tie tolerance. ``sign_flip_p_many`` computes it for many simulated data sets at once and is checked
  against ``stats.sign_flip_p`` by tests/test_power.py.
* **Correction.** A family of ``family`` primary hypotheses corrected with Holm at ``alpha``. A hypothesis
  is rejected for sure when its p is below alpha / family (Holm's first step), so the power computed at
  that level is a lower bound on its power under Holm (and equal to it when the other hypotheses are null).
* **Effects.** Two kinds of primary hypothesis:
  - a *rate* (trajectory correctness, ``both > none`` and ``both > both_shuffled``): a captioner right with
    probability p under A and q under B, independently per episode (per-episode differences in {-1, 0, 1});
  - a *continuous* metric (boundary-F1 lift ``both > none``; word counts): per-episode differences drawn
    from a normal distribution with mean d and standard deviation sd; the power depends on d / sd only.
* **Closed form.** For a rate the exact sign-flip test is the two-sided sign test on the non-zero
  differences, so its power has a binomial formula (``exact_rate_power``); the simulation must agree with
  it within Monte-Carlo error (the test that keeps the simulation honest).

Simulations are seeded per (kind, group, effect) from one seed, so a number does not depend on which
other numbers were asked for, and repeated runs give the same bits.
"""

from __future__ import annotations

import contextlib
import functools
import hashlib
import itertools
import json
import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from vlmproprio.errors import UsageError
from vlmproprio.stats import (
    DEFAULT_MAX_EXACT,
    DEFAULT_N_PERM,
    DEFAULT_SEED,
    TIE_RTOL,
    exact_sign_flip_p,
    observed_and_tolerance,
)

GROUPS: dict[str, int] = {"door": 10, "pick_place": 12, "all": 22}
SHIPPED = "shipped"  # the set GROUPS describes; a named set of record/named_sets.json is the other kind


def set_groups(name: str) -> dict[str, int]:
    """The groups of an episode set: the shipped one's (``GROUPS``), or a named set's tasks and all of them,
    each as ``<set>/<task>`` so that two sets can be analysed side by side."""
    if name == SHIPPED:
        return dict(GROUPS)
    from vlmproprio.record.named_sets import named_set

    ns = named_set(name)
    groups: dict[str, int] = {}
    for part in ns.parts:
        groups[f"{name}/{part.task}"] = groups.get(f"{name}/{part.task}", 0) + part.count
    groups[f"{name}/all"] = ns.count
    return groups


TARGET_POWER = 0.8
# The paper's mean final-instruction length without and with state (GPT-4V, Table II): 25.2 -> 35.45 words.
PAPER_WORDS = (25.2, 35.45)
# Per-episode SD of a paired difference, chosen above what the shipped models show (see docs/findings.md):
# words both - none: 2.7-7.2 (reference), 1.5-6.9 (tiny-qwen2-vl); boundary F1 (+-1 frame): 0.06-0.15.
DEFAULT_SD_WORDS = 10.0
DEFAULT_SD_F1 = 0.15
DEFAULT_CORRECTNESS = (0.6, 0.3)  # P(right) with and without state, for the "episodes needed" line
RATE_BASELINES = (0.0, 0.3)  # q: how often the captioner is right without state
_ROWS_PER_CHUNK = 256  # simulated data sets per matrix product (bounds memory: rows x patterns floats)


@dataclass(frozen=True)
class PowerSettings:
    alpha: float = 0.05
    family: int = 4  # primary hypotheses corrected together (Holm): the four of vlmproprio/claims.yml
    n_sims: int = 1000
    seed: int = DEFAULT_SEED
    n_perm: int = DEFAULT_N_PERM  # as the suite's test above max_exact episodes
    max_exact: int = DEFAULT_MAX_EXACT

    def __post_init__(self) -> None:
        if not 0.0 < self.alpha < 1.0:
            raise UsageError(f"alpha must be between 0 and 1, got {self.alpha}")
        if self.family < 1:
            raise UsageError(f"the family of primary hypotheses needs at least 1 member, got {self.family}")
        if self.n_sims < 10:
            raise UsageError(f"at least 10 simulations are needed, got {self.n_sims}")

    @property
    def level(self) -> float:
        """Holm's first-step level alpha / family: below it a hypothesis is rejected whatever the others do."""
        return self.alpha / self.family


# ---------------------------------------------------------------------------------------------- the test


def sign_patterns(n: int, n_perm: int = DEFAULT_N_PERM, seed: int = DEFAULT_SEED) -> np.ndarray:
    """The ``n_perm`` random +-1 sign patterns ``stats.sign_flip_p`` draws for n > max_exact episodes (patterns x
    episodes): one random integer a pattern up to 62 episodes, its bits the signs; above, n draws of 0 or 1."""
    rng = np.random.Generator(np.random.PCG64(seed + 1))
    parts, done = [], 0
    while done < n_perm:  # the same draws, in the same chunks, as stats.sign_flip_p
        m = min(1 << 16, n_perm - done)
        if n <= 62:
            codes = rng.integers(0, 1 << n, size=m, dtype=np.int64)
            parts.append(1.0 - 2.0 * ((codes[:, None] >> np.arange(n, dtype=np.int64)) & 1))
        else:
            parts.append(1.0 - 2.0 * rng.integers(0, 2, size=(m, n)))
        done += m
    return np.concatenate(parts)


def sign_flip_p_many(
    d: np.ndarray, n_perm: int = DEFAULT_N_PERM, seed: int = DEFAULT_SEED, max_exact: int = DEFAULT_MAX_EXACT
) -> np.ndarray:
    """``stats.sign_flip_p`` for every row of ``d`` (data sets x episodes) at once: the p-values."""
    d = np.asarray(d, dtype=np.float64)
    if d.ndim != 2 or d.shape[1] == 0:
        raise UsageError(f"expected data sets x episodes, got shape {d.shape}")
    if d.shape[1] <= max_exact:
        return exact_sign_flip_p(d)  # the suite's own exact test, row by row
    signs = sign_patterns(d.shape[1], n_perm, seed)
    # patterns as columns, contiguous, and |statistics| taken in place: the same products and comparisons as
    # one would write plainly, in under half the time
    columns = np.ascontiguousarray(signs.T)
    out = np.empty(d.shape[0])
    for s in range(0, d.shape[0], _ROWS_PER_CHUNK):
        block = d[s : s + _ROWS_PER_CHUNK]
        obs, tol = observed_and_tolerance(block)
        stats = block @ columns
        np.abs(stats, out=stats)
        hits = np.count_nonzero(stats >= (obs - tol)[:, None], axis=1)
        out[s : s + len(block)] = (hits + 1) / (len(signs) + 1)
    return out


def detected(d: np.ndarray, settings: PowerSettings) -> np.ndarray:
    """Per simulated data set: the claim holds (mean difference > 0 and p below the corrected level)."""
    p = sign_flip_p_many(d, settings.n_perm, settings.seed, settings.max_exact)
    return (d.mean(axis=1) > 0) & (p < settings.level)


# ---------------------------------------------------------------------------------------------- effects


def _rng(settings: PowerSettings, *key: int) -> np.random.Generator:
    return np.random.default_rng([settings.seed, *key])


def simulate_rate_power(n: int, p: float, q: float, settings: PowerSettings, key: Sequence[int] = ()) -> float:
    """Power for a rate: right with probability p under A and q under B, per episode, independently."""
    for name, v in (("p", p), ("q", q)):
        if not 0.0 <= v <= 1.0:
            raise UsageError(f"{name} must be a probability, got {v}")
    rng = _rng(settings, 1, n, round(p * 1e6), round(q * 1e6), *key)
    a = rng.random((settings.n_sims, n)) < p
    b = rng.random((settings.n_sims, n)) < q
    return float(detected(a.astype(np.float64) - b.astype(np.float64), settings).mean())


def simulate_shift_power(n: int, effect_sd: float, settings: PowerSettings, key: Sequence[int] = ()) -> float:
    """Power for a continuous metric: per-episode differences ~ Normal(effect_sd, 1) (effect in SD units)."""
    rng = _rng(settings, 2, n, round(effect_sd * 1e6), *key)
    d = rng.normal(effect_sd, 1.0, size=(settings.n_sims, n))
    return float(detected(d, settings).mean())


@functools.lru_cache(maxsize=1 << 16)  # the closed forms below ask for each (k, j) once per number of episodes
def sign_test_p(k: int, j: int) -> float:
    """Two-sided p of the exact sign-flip test when k differences are +-1 (j of them positive), zeros aside."""
    if k == 0:
        return 1.0
    obs = abs(2 * j - k)
    return math.fsum(math.comb(k, i) for i in range(k + 1) if abs(2 * i - k) >= obs) / 2**k


def exact_rate_power(n: int, p: float, q: float, level: float) -> float:
    """Closed form of ``simulate_rate_power`` with the exact test: a sum over binomial outcomes."""
    up, down = p * (1 - q), q * (1 - p)  # P(difference +1), P(difference -1)
    moved = up + down
    if moved == 0.0:
        return 0.0
    total = []
    for k in range(1, n + 1):
        pk = math.comb(n, k) * moved**k * (1 - moved) ** (n - k)
        for j in range(k // 2 + 1, k + 1):  # more positive than negative: the mean difference is > 0
            if sign_test_p(k, j) < level:
                total.append(pk * math.comb(k, j) * (up / moved) ** j * (down / moved) ** (k - j))
    return math.fsum(total)


def mc_error(power: float, n_sims: int) -> float:
    """Standard error of a simulated power."""
    return math.sqrt(max(power * (1 - power), 1e-12) / n_sims)


# ---------------------------------------------------------------------------------------------- analysis


@dataclass
class PowerAnalysis:
    settings: dict
    groups: dict[str, int]
    rate_curves: dict = field(default_factory=dict)  # q -> group -> [(p, power)]
    shift_curves: dict = field(default_factory=dict)  # group -> [(effect in SD, power)]
    mde_rate: dict = field(default_factory=dict)  # q -> group -> smallest p with power >= target (None: never)
    mde_shift_sd: dict = field(default_factory=dict)  # group -> smallest effect (SD units) with power >= target
    words: dict = field(default_factory=dict)
    correctness: dict = field(default_factory=dict)
    f1: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> PowerAnalysis:
        """The analysis ``to_dict`` gave, its curves' points as tuples again (JSON keeps them as lists)."""
        points = lambda pts: [tuple(pt) for pt in pts]  # noqa: E731
        return cls(
            **{k: d[k] for k in ("settings", "groups", "mde_rate", "mde_shift_sd", "words", "correctness", "f1")},
            rate_curves={q: {g: points(v) for g, v in by_group.items()} for q, by_group in d["rate_curves"].items()},
            shift_curves={g: points(v) for g, v in d["shift_curves"].items()},
        )


def _first_reaching(points: Sequence[tuple[float, float]], target: float) -> float | None:
    """The smallest x where the curve reaches target, linearly interpolated; None when it never does."""
    for (x0, y0), (x1, y1) in itertools.pairwise(points):
        if y0 >= target:
            return x0
        if y1 >= target:
            return x0 + (target - y0) * (x1 - x0) / (y1 - y0)
    return points[-1][0] if points and points[-1][1] >= target else None


def rate_mde(n: int, q: float, level: float, target: float = TARGET_POWER) -> float | None:
    """The smallest p (to 0.01) that the exact test detects with the target power when B is right with q."""
    for i in range(round(q * 100) + 1, 101):
        if exact_rate_power(n, i / 100, q, level) >= target:
            return i / 100
    return None


def episodes_for_rate(p: float, q: float, level: float, target: float = TARGET_POWER, max_n: int = 1000) -> int | None:
    """How many paired episodes the exact test needs to detect p vs q with the target power."""
    for n in range(1, max_n + 1):
        if exact_rate_power(n, p, q, level) >= target:
            return n
    return None


def episodes_for_shift(
    effect_sd: float, settings: PowerSettings, target: float = TARGET_POWER, max_n: int = 62
) -> tuple[int | None, float]:
    """Smallest number of paired episodes with simulated power >= target (and that power)."""
    if effect_sd <= 0:
        return None, 0.0
    for n in range(2, max_n + 1):
        pw = simulate_shift_power(n, effect_sd, settings, key=(9,))
        if pw >= target:
            return n, pw
    return None, 0.0


def analyse(
    settings: PowerSettings = PowerSettings(),
    *,
    groups: dict[str, int] | None = None,
    words: tuple[float, float] = PAPER_WORDS,
    sd_words: float = DEFAULT_SD_WORDS,
    sd_f1: float = DEFAULT_SD_F1,
    correctness: tuple[float, float] = DEFAULT_CORRECTNESS,
    rate_grid: Sequence[float] = tuple(i / 10 for i in range(11)),
    shift_grid: Sequence[float] = tuple(i / 10 for i in range(21)),
) -> PowerAnalysis:
    """Power curves per group, minimal detectable effects, and episodes needed for two named effects."""
    groups = dict(GROUPS if groups is None else groups)
    if sd_words <= 0 or sd_f1 <= 0:
        raise UsageError("the per-episode standard deviations must be positive")
    if not all(0.0 <= v <= 1.0 for v in correctness):
        raise UsageError(f"correctness rates must be probabilities, got {correctness}")
    out = PowerAnalysis(settings={**asdict(settings), "level": settings.level}, groups=groups)
    for q in RATE_BASELINES:
        key = f"{q:g}"
        out.rate_curves[key], out.mde_rate[key] = {}, {}
        for g, n in groups.items():
            ps = [p for p in rate_grid if p >= q]
            out.rate_curves[key][g] = [(p, simulate_rate_power(n, p, q, settings)) for p in ps]
            out.mde_rate[key][g] = rate_mde(n, q, settings.level)
    for g, n in groups.items():
        out.shift_curves[g] = [(e, simulate_shift_power(n, e, settings)) for e in shift_grid]
        out.mde_shift_sd[g] = _first_reaching(out.shift_curves[g], TARGET_POWER)
    out.f1 = {
        "sd": sd_f1,
        "mde": {g: (None if v is None else v * sd_f1) for g, v in out.mde_shift_sd.items()},
    }
    diff = words[1] - words[0]
    n_words, pw = episodes_for_shift(diff / sd_words, settings)
    out.words = {
        "from": words[0],
        "to": words[1],
        "difference": diff,
        "sd": sd_words,
        "effect_sd": diff / sd_words,
        "episodes_needed": n_words,
        "power_at_needed": pw,
        "power": {g: simulate_shift_power(n, diff / sd_words, settings, key=(8,)) for g, n in groups.items()},
    }
    p, q = correctness
    out.correctness = {
        "p": p,
        "q": q,
        "episodes_needed": episodes_for_rate(p, q, settings.level),
        "power": {g: exact_rate_power(n, p, q, settings.level) for g, n in groups.items()},
    }
    return out


# The report analyses every run it shows (~6 s of simulation for the shipped fixtures' 10/12/22 episodes), with
# the same few settings each time: results are kept in a cache folder, keyed by everything they depend on.
POWER_CACHE_DIR = "power"


def analysis_key(settings: PowerSettings, groups: dict[str, int]) -> str:
    """The cache key of ``analyse(settings, groups=groups)`` with its other arguments at their defaults: the
    arguments, the tie tolerance, this module's code (any change to it is a new key) and numpy's version (its
    random streams)."""
    code = hashlib.sha256(Path(__file__).read_bytes()).hexdigest()
    defaults = [PAPER_WORDS, DEFAULT_SD_WORDS, DEFAULT_SD_F1, DEFAULT_CORRECTNESS, TIE_RTOL, TARGET_POWER]
    return json.dumps([code, np.__version__, asdict(settings), sorted(groups.items()), defaults])


def analyse_cached(settings: PowerSettings, groups: dict[str, int], cache_dir: Path | None) -> PowerAnalysis:
    """``analyse(settings, groups=groups)``, read from the JSON store in ``cache_dir`` when an earlier call kept
    it there (bit for bit: JSON keeps every float). A cache that cannot be opened, read or written only means
    computing; it never changes a number."""
    import sqlite3

    from vlmproprio.errors import VlmproprioError
    from vlmproprio.stores import JSON_VALUES, open_store

    if cache_dir is None:
        return analyse(settings, groups=groups)
    try:
        key = analysis_key(settings, groups)
        store = open_store(cache_dir, JSON_VALUES, error=VlmproprioError, what="power-analysis cache", timeout_s=10)
    except (OSError, VlmproprioError):
        return analyse(settings, groups=groups)
    with store:
        try:
            return PowerAnalysis.from_dict(store[key])
        except Exception:  # absent, or damaged in any way (diskcache decodes a value outside its own guard)
            pass
        out = analyse(settings, groups=groups)
        with contextlib.suppress(OSError, sqlite3.Error, VlmproprioError):
            store[key] = out.to_dict()
    return out


# ---------------------------------------------------------------------------------------------- output


def _fmt(v: float | None, spec: str = ".2f") -> str:
    return "never" if v is None else format(v, spec)


def summary_markdown(a: PowerAnalysis) -> str:
    s = a.settings
    lines = [
        "# Power of the suite's paired test",
        "",
        f"Exact sign-flip test as in `vlmproprio.stats` (all sign patterns up to {s['max_exact']} episodes, "
        f"{s['n_perm']} random ones above), claim detected when the mean difference is > 0 and p < "
        f"alpha / family = {s['alpha']:g} / {s['family']} = {s['level']:.4f} (Holm's first step: a lower bound "
        f"on the power under Holm). {s['n_sims']} simulated data sets per point, seed {s['seed']}.",
        "",
        "## Minimal detectable effects at 80 % power",
        "",
        "| group | episodes | rate, q = 0: p >= | rate, q = 0.3: p >= | continuous (SD units) | "
        f"boundary F1 (sd {a.f1['sd']:g}) |",
        "|---|---|---|---|---|---|",
    ]
    for g, n in a.groups.items():
        lines.append(
            f"| {g} | {n} | {_fmt(a.mde_rate['0'][g])} | {_fmt(a.mde_rate['0.3'][g])} | "
            f"{_fmt(a.mde_shift_sd[g])} | {_fmt(a.f1['mde'][g])} |"
        )
    w, c = a.words, a.correctness
    lines += [
        "",
        f"Word count {w['from']:g} -> {w['to']:g} (difference {w['difference']:.2f}, per-episode SD {w['sd']:g}, "
        f"{w['effect_sd']:.2f} SD): power "
        + ", ".join(f"{g} {v:.2f}" for g, v in w["power"].items())
        + f"; {_fmt(w['episodes_needed'], 'd')} paired episodes reach 80 %.",
        "",
        f"Correctness {c['p']:g} with state vs {c['q']:g} without: power "
        + ", ".join(f"{g} {v:.2f}" for g, v in c["power"].items())
        + f" (exact); {_fmt(c['episodes_needed'], 'd')} paired episodes reach 80 %.",
        "",
    ]
    return "\n".join(lines)


def plot_power_curves(a: PowerAnalysis, path: Path) -> Path:
    """One PNG: power vs effect for rates (one panel per q) and for continuous effects, a line per group."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(a.rate_curves) + 1, figsize=(4.2 * (len(a.rate_curves) + 1), 3.6), sharey=True)
    for ax, (q, curves) in zip(axes, a.rate_curves.items(), strict=False):
        for g, pts in curves.items():
            ax.plot([p for p, _ in pts], [y for _, y in pts], marker="o", ms=3, label=f"{g} (n={a.groups[g]})")
        ax.set_xlabel(f"P(right) with state (without: {q})")
        ax.set_title(f"trajectory correctness, q = {q}")
    ax = axes[-1]
    for g, pts in a.shift_curves.items():
        ax.plot([e for e, _ in pts], [y for _, y in pts], marker="o", ms=3, label=f"{g} (n={a.groups[g]})")
    ax.set_xlabel("mean paired difference / per-episode SD")
    ax.set_title("continuous metric (F1 lift, words)")
    for ax in axes:
        ax.axhline(TARGET_POWER, color="grey", lw=0.8, ls="--")
        ax.set_ylim(0, 1.02)
        ax.grid(alpha=0.3)
    axes[0].set_ylabel(f"power at alpha/{a.settings['family']} = {a.settings['level']:.4f}")
    axes[0].legend(fontsize=8, loc="upper left")
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    # fixed metadata: the same analysis gives the same PNG bytes
    fig.savefig(path, dpi=110, metadata={"Software": None})
    plt.close(fig)
    return path


def write_power(a: PowerAnalysis, out_dir: Path) -> list[Path]:
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    j = out_dir / "power.json"
    j.write_text(json.dumps(a.to_dict(), indent=1, sort_keys=True) + "\n")
    m = out_dir / "power.md"
    m.write_text(summary_markdown(a))
    return [j, m, plot_power_curves(a, out_dir / "power_curves.png")]
