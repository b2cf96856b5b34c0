"""Verdicts a reviewer accepts: pre-registered primary hypotheses, corrected tests, sanity warnings.

* **Primary hypotheses** are read from a claims file (default: the packaged ``vlmproprio/claims.yml``, the
  pre-registration; ``vlmproprio score RUN_DIR --claims FILE`` for another one). Each names a metric, two conditions
  A and B and a task group; it predicts A > B. Per model, the family of primary tests is corrected with
  Holm's step-down procedure (family-wise error rate ``alpha``).
* **Every other paired test is exploratory** and carries a Benjamini-Hochberg q-value, computed per model
  over all of that model's exploratory tests.
* **Verdict** per model and hypothesis, in the words of ``VERDICT_RULES`` (docs/metrics.md and the report use
  them): *supported*, *not supported*, *inconclusive*, *not tested*. A "not supported" or "inconclusive"
  states the largest effect still compatible with the data (``BOUND_RULE``, ``effect_bound``): a
  rubric item right or wrong per episode gets an exact bound from its discordant pairs, because with none of
  them among 22 episodes a bootstrap CI is [0, 0] while effects up to +15.4 pp are not excluded.
* **Sanity warnings** (per model): near-constant frame captions, gibberish (many non-words), off-task (final
  captions that name nothing the task's lexicon knows), and segmentation points that fall on the edges of
  the pipeline's frame groups more often than chance, and frame captions the parser had to place by
  position rather than read from a label (heavy recovery) -- each means the model's differences cannot be read
  as "the model used the state".

The format of the claims file and every threshold here are documented in docs/metrics.md.
"""

from __future__ import annotations

import hashlib
import math
import re
from collections import Counter
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path

from vlmproprio.errors import VlmproprioError
from vlmproprio.io import read_limited
from vlmproprio.stats import benjamini_hochberg, holm

CLAIMS_FILE = Path(__file__).with_name("claims.yml")
PRIMARY = "primary"
EXPLORATORY = "exploratory"
VERDICTS = ("supported", "not supported", "inconclusive", "not tested")
VERDICT_RULES = {
    "supported": "the mean difference A − B is positive and its Holm-adjusted p ≤ alpha",
    "not supported": "no positive effect detected: the bootstrap 95 % CI of the difference lies at or below 0, "
    "or the corrected test finds A < B; it excludes only effects above the stated bound",
    "inconclusive": "anything else: a positive effect is neither established nor excluded below the stated bound",
    "not tested": "the run lacks condition A or B",
}
BOUND_RULE = (
    "the largest effect still compatible with the data: for a rubric item right or wrong per episode, the exact "
    "one-sided 95 % upper bound of the difference from its discordant pairs (Clopper–Pearson bounds of both "
    "discordant shares at 97.5 %, combined by Bonferroni); for any other metric, the upper end of the "
    "bootstrap 95 % CI"
)

# sanity thresholds (docs/metrics.md explains each)
# distinct frame captions / frames of a cell (episode x condition), averaged over cells, below this: near-constant.
# Per cell, not over the run: a templated captioner repeats its sentences across 22 episodes yet changes them
# within every episode (reference: 0.43, reference-state: 0.30), while a model that ignores its input writes one
# or two texts per episode (tiny-qwen2-vl: 0.07); a real VLM's captions are nearly all distinct (~1).
MIN_DISTINCT_PER_CELL = 0.15
MAX_MISSING_FRAME_SHARE = 0.20  # frame captions missing (unparsed or empty), above this: warn
MAX_NON_WORD_SHARE = 0.20  # caption tokens that are no word or number, above this: gibberish
MAX_NO_HIT_FINAL_SHARE = 0.80  # final captions without a single lexicon hit, above this: off-task
_NUMBER_RE = re.compile(r"[+-]?\d+(?:[.,]\d+)*%?")
# present frame captions found by position rather than read from a label (parsing.HEAVY_CLASSES), at least
# this share: the captions may sit on the wrong frames, so the segmentation reads the parser's guess
MIN_HEAVY_RECOVERY_SHARE = 0.20
# frame captions missing because the server's answers held none (refusals, tool calls, filters, ...), at least
# this share of all frame captions: most of the model's captions were never written
MIN_NO_ANSWER_SHARE = 0.50
GROUP_EDGE_RATIO = 1.5  # points on group edges / expected under uniform placement, at least this ...
GROUP_EDGE_P = 0.001  # ... and a one-sided binomial p-value below this
WORD_RE = re.compile(r"^(?:[A-Za-z]+(?:['-][A-Za-z]+)*|[+-]?\d+(?:[.,]\d+)*%?)$")
STRIP = ".,;:!?()[]{}\"'`*"


class ClaimsError(VlmproprioError):
    """A claims file that cannot be used; the message names the file and the entry."""


@dataclass(frozen=True)
class Hypothesis:
    id: str
    description: str
    metric: str
    a: str
    b: str
    task: str = "all"

    def matches(self, row: Mapping) -> bool:
        return (row.get("task"), row.get("metric"), row.get("a"), row.get("b")) == (
            self.task,
            self.metric,
            self.a,
            self.b,
        )


@dataclass(frozen=True)
class Claims:
    """The pre-registered primary hypotheses of a claims file, where they come from (source, version, sha256), alpha."""

    alpha: float
    hypotheses: tuple[Hypothesis, ...]
    source: str
    sha256: str
    version: int | str | None = None

    def to_dict(self) -> dict:
        return {
            "source": self.source,
            "version": self.version,
            "sha256": self.sha256,
            "alpha": self.alpha,
            "correction": "Holm (family-wise, per model, over the primary hypotheses)",
            "exploratory": "Benjamini-Hochberg q-values (per model, over every other paired test)",
            "primary": [asdict(h) for h in self.hypotheses],
        }


def load_claims(path: str | Path | None = None) -> Claims:
    """Read a claims file (YAML): ``alpha`` and a ``primary`` mapping of hypothesis id -> description, metric,
    a, b, task (default "all")."""
    import yaml

    p = Path(path) if path is not None else CLAIMS_FILE
    try:
        raw = read_limited(p, error=ClaimsError)
        data = yaml.safe_load(raw)
    except FileNotFoundError as exc:
        raise ClaimsError(f"{p}: cannot read the claims file (missing)") from exc
    except (OSError, yaml.YAMLError) as exc:
        raise ClaimsError(f"{p}: cannot read the claims file ({exc})") from exc
    if not isinstance(data, dict) or not isinstance(data.get("primary"), dict) or not data["primary"]:
        raise ClaimsError(f"{p}: expected a mapping with 'alpha' and a non-empty 'primary' mapping")
    alpha = data.get("alpha", 0.05)
    if not isinstance(alpha, (int, float)) or not 0 < alpha < 1:
        raise ClaimsError(f"{p}: alpha must be a number between 0 and 1, got {alpha!r}")
    hyps = []
    for hid, spec in data["primary"].items():
        if not isinstance(spec, dict):
            raise ClaimsError(f"{p}: primary.{hid} must be a mapping")
        missing = [k for k in ("description", "metric", "a", "b") if not isinstance(spec.get(k), str)]
        unknown = set(spec) - {"description", "metric", "a", "b", "task"}
        if missing or unknown:
            what = f"missing {', '.join(missing)}" if missing else f"unknown key(s) {', '.join(sorted(unknown))}"
            raise ClaimsError(f"{p}: primary.{hid}: {what}")
        hyps.append(
            Hypothesis(str(hid), spec["description"], spec["metric"], spec["a"], spec["b"], spec.get("task", "all"))
        )
    source = f"vlmproprio/{p.name}" if path is None else str(p)
    return Claims(float(alpha), tuple(hyps), source, hashlib.sha256(raw).hexdigest(), data.get("version"))


# ---------------------------------------------------------------------------------------------- families


def mark_families(paired: list[dict], claims: Claims) -> None:
    """Mark every paired row primary or exploratory and add ``p_holm`` / ``q_bh`` (in place)."""
    for model in sorted({r["model"] for r in paired}):
        mine = [r for r in paired if r["model"] == model]
        primary, exploratory = [], []
        for r in mine:
            h = next((h for h in claims.hypotheses if h.matches(r)), None)
            r["family"] = PRIMARY if h else EXPLORATORY
            r["hypothesis"] = h.id if h else None
            r["p_holm"] = None
            r["q_bh"] = None
            (primary if h else exploratory).append(r)
        for r, adj in zip(primary, holm([_p(r) for r in primary]), strict=True):
            r["p_holm"] = _finite(adj)
        for r, q in zip(exploratory, benjamini_hochberg([_p(r) for r in exploratory]), strict=True):
            r["q_bh"] = _finite(q)


def _p(r: Mapping) -> float:
    p = r.get("p_value")
    return float(p) if isinstance(p, (int, float)) and math.isfinite(p) else float("nan")


def _finite(x: float) -> float | None:
    return x if math.isfinite(x) else None


def verdict_of(row: Mapping | None, alpha: float) -> str:
    if row is None or row.get("p_holm") is None or row.get("mean_diff") is None:
        return "not tested"
    d, p, hi = row["mean_diff"], row["p_holm"], row.get("ci_high")
    if d > 0 and p <= alpha:
        return "supported"
    if (hi is not None and hi <= 0) or (d < 0 and p <= alpha):
        return "not supported"
    return "inconclusive"


def effect_bound(row: Mapping | None) -> tuple[float | None, str | None]:
    """The largest effect still compatible with the data (``BOUND_RULE``) and the words that state it."""
    if row is None or row.get("mean_diff") is None:
        return None, None
    if row.get("exact_high") is not None:
        hi = row["exact_high"]
        return hi, (
            f"no effect above {100 * hi:+.1f} pp detected (exact 95 % bound; {row['n_ab']} vs {row['n_ba']} "
            f"discordant of {row['n']} episodes)"
        )
    hi = row.get("ci_high")
    if hi is None:
        return None, None
    return hi, f"no effect above {hi:+.3f} detected (bootstrap 95 % CI)"


def verdicts(paired: Sequence[Mapping], claims: Claims, models: Iterable[str]) -> list[dict]:
    """One verdict per model and primary hypothesis (rows must be marked by ``mark_families``)."""
    out = []
    for model in models:
        for h in claims.hypotheses:
            row = next((r for r in paired if r["model"] == model and h.matches(r)), None)
            verdict = verdict_of(row, claims.alpha)
            bound, bound_text = effect_bound(row) if verdict in ("not supported", "inconclusive") else (None, None)
            out.append(
                {
                    "model": model,
                    "hypothesis": h.id,
                    "description": h.description,
                    "metric": h.metric,
                    "a": h.a,
                    "b": h.b,
                    "task": h.task,
                    "verdict": verdict,
                    "n": row.get("n") if row else None,
                    "mean_diff": row.get("mean_diff") if row else None,
                    "ci_low": row.get("ci_low") if row else None,
                    "ci_high": row.get("ci_high") if row else None,
                    "p_value": row.get("p_value") if row else None,
                    "p_holm": row.get("p_holm") if row else None,
                    "p_method": row.get("method") if row else None,
                    "exact_low": row.get("exact_low") if row else None,
                    "exact_high": row.get("exact_high") if row else None,
                    "bound": bound,
                    "bound_text": bound_text,
                    "alpha": claims.alpha,
                }
            )
    return out


# ---------------------------------------------------------------------------------------------- sanity


@dataclass
class ModelOutputs:
    """What the sanity checks read about one model's run."""

    frame_captions: list[str] = field(default_factory=list)  # every present frame caption, all cells
    cell_distinct: list[float] = field(default_factory=list)  # per cell: distinct present frame captions / frames
    frames_missing: int = 0
    frames_heavy: int = 0  # present frame captions that needed a heavy recovery
    # missing frame captions whose Process 1 answer came back without a plain answer (chat.ANSWER_PROBLEMS)
    frames_missing_problem: int = 0
    answer_problems: list[str] = field(default_factory=list)  # the class of each request that had one
    all_captions: list[str] = field(default_factory=list)  # frame, scene and final captions
    final_hits: list[int] = field(default_factory=list)  # lexicon hits of each final caption
    # per cell: (number of frames, segmentation points at the reported threshold)
    cells: list[tuple[int, list[int]]] = field(default_factory=list)

    def extend(self, later: ModelOutputs) -> None:
        """Add what ``later`` read from the cells after these (lists in order, counts summed)."""
        for f in fields(self):
            mine, theirs = getattr(self, f.name), getattr(later, f.name)
            if isinstance(mine, list):
                mine += theirs
            elif type(mine) is int:
                setattr(self, f.name, mine + theirs)
            else:
                raise TypeError(f"ModelOutputs.{f.name}: no rule to add a {type(mine).__name__}")


def _token_share(texts: Iterable[str], counts) -> tuple[float, int]:
    """Share of whitespace tokens (punctuation stripped) for which ``counts`` holds, and the number of tokens;
    a model repeats its captions across conditions, so each distinct text is split once."""
    total = hits = 0
    for t, n in Counter(texts).items():
        for tok in (t or "").split():
            w = tok.strip(STRIP)
            if w:
                total += n
                hits += n * bool(counts(w))
    return (hits / total if total else 0.0), total


def non_word_share(texts: Iterable[str]) -> tuple[float, int]:
    """Share of whitespace tokens (punctuation stripped) that are neither a word of letters nor a number."""
    return _token_share(texts, lambda w: not WORD_RE.match(w))


def number_share(texts: Iterable[str]) -> float:
    """Share of whitespace tokens (punctuation stripped) that are numbers: captions that echo the state."""
    return _token_share(texts, _NUMBER_RE.fullmatch)[0]


def binomial_tail(k: int, n: int, p: float) -> float:
    """P(X >= k) for X ~ Binomial(n, p): the one-sided binomial test's p-value (summed in log space, no scipy)."""
    if k <= 0:
        return 1.0
    if p <= 0.0:
        return 0.0
    if p >= 1.0:
        return 1.0
    logs = [
        math.lgamma(n + 1) - math.lgamma(i + 1) - math.lgamma(n - i + 1) + i * math.log(p) + (n - i) * math.log1p(-p)
        for i in range(k, n + 1)
    ]
    top = max(logs)
    return min(1.0, math.exp(top) * math.fsum(math.exp(x - top) for x in logs))


def group_edge_excess(cells: Sequence[tuple[int, Sequence[int]]], group_size: int) -> dict:
    """Points on frame-group edges against their expectation if the same points fell uniformly at random."""
    observed = total = 0
    expected = 0.0
    for n_frames, points in cells:
        if n_frames < 2:
            continue
        edges = set(range(group_size - 1, n_frames - 1, group_size))
        observed += sum(1 for j in points if j in edges)
        total += len(points)
        expected += len(points) * len(edges) / (n_frames - 1)
    p = binomial_tail(observed, total, expected / total) if total and expected else 1.0
    return {
        "points": total,
        "on_edges": observed,
        "expected": expected,
        "ratio": observed / expected if expected else None,
        "p_value": float(p),
    }


def sanity_warnings(outputs: Mapping[str, ModelOutputs], group_size: int) -> list[dict]:
    """Warnings per model (see the module docstring); each has model, kind, message and the measured values."""
    out = []
    for model, o in outputs.items():
        n_frames = len(o.frame_captions)
        distinct = sum(o.cell_distinct) / len(o.cell_distinct) if o.cell_distinct else 1.0
        if distinct < MIN_DISTINCT_PER_CELL:
            out.append(
                {
                    "model": model,
                    "kind": "near-constant",
                    "message": f"near-constant captions: per episode and condition, {100 * distinct:.1f}% of the frames "
                    f"have a caption of their own on average (< {100 * MIN_DISTINCT_PER_CELL:g}%; "
                    f"{len(set(o.frame_captions))} distinct texts among {n_frames} frame captions)",
                    "value": distinct,
                }
            )
        missing = o.frames_missing / (n_frames + o.frames_missing) if n_frames + o.frames_missing else 0.0
        if missing > MAX_MISSING_FRAME_SHARE:
            out.append(
                {
                    "model": model,
                    "kind": "missing-captions",
                    "message": f"{o.frames_missing} of {n_frames + o.frames_missing} frame captions are missing "
                    f"({100 * missing:.0f}% > {100 * MAX_MISSING_FRAME_SHARE:g}%): the parser found no caption",
                    "value": missing,
                }
            )
        out += _no_answer_warning(model, o, n_frames + o.frames_missing)
        heavy = o.frames_heavy / n_frames if n_frames else 0.0
        if heavy >= MIN_HEAVY_RECOVERY_SHARE:
            out.append(
                {
                    "model": model,
                    "kind": "heavy-recovery",
                    "message": f"{o.frames_heavy} of {n_frames} present frame captions needed heavy recovery "
                    f"({100 * heavy:.0f}% >= {100 * MIN_HEAVY_RECOVERY_SHARE:g}%): placed by position, not read "
                    "from a frame label, so they may describe other frames",
                    "value": heavy,
                }
            )
        share, tokens = non_word_share(o.all_captions)
        no_hit = sum(1 for h in o.final_hits if h == 0) / len(o.final_hits) if o.final_hits else 0.0
        if tokens and share > MAX_NON_WORD_SHARE:
            out.append(
                {
                    "model": model,
                    "kind": "gibberish",
                    "message": f"gibberish: {100 * share:.0f}% of {tokens} caption tokens are neither words nor "
                    f"numbers (limit {100 * MAX_NON_WORD_SHARE:g}%)",
                    "value": share,
                }
            )
        if no_hit > MAX_NO_HIT_FINAL_SHARE:
            numbers = number_share(o.all_captions)
            out.append(
                {
                    "model": model,
                    "kind": "off-task",
                    "message": f"off-task: {100 * no_hit:.0f}% of final captions name nothing in the task lexicon "
                    f"(limit {100 * MAX_NO_HIT_FINAL_SHARE:g}%); {100 * numbers:.0f}% of caption tokens are numbers",
                    "value": no_hit,
                    "number_share": numbers,
                }
            )
        g = group_edge_excess(o.cells, group_size)
        if g["ratio"] is not None and g["ratio"] >= GROUP_EDGE_RATIO and g["p_value"] < GROUP_EDGE_P:
            out.append(
                {
                    "model": model,
                    "kind": "group-edges",
                    "message": f"segmentation follows the frame groups: {g['on_edges']} of {g['points']} points "
                    f"fall on the edges of the k = {group_size} groups, {g['ratio']:.1f}x the "
                    f"{g['expected']:.1f} expected by chance (binomial p = {g['p_value']:.1g})",
                    "value": g["ratio"],
                    **{k: v for k, v in g.items() if k != "ratio"},
                }
            )
    return out


def _no_answer_warning(model: str, o: ModelOutputs, n_frames: int) -> list[dict]:
    """'no-answers': most frame captions are missing because the answers held none, with the classes counted."""
    share = o.frames_missing_problem / n_frames if n_frames else 0.0
    if share < MIN_NO_ANSWER_SHARE:
        return []
    counts = Counter(o.answer_problems)
    classes = ", ".join(f"{name} {n}" for name, n in counts.most_common())
    return [
        {
            "model": model,
            "kind": "no-answers",
            "message": f"{o.frames_missing_problem} of {n_frames} frame captions are missing because the server's "
            f"answers held none ({100 * share:.0f}% >= {100 * MIN_NO_ANSWER_SHARE:g}%; requests: {classes}): "
            "the model's conditions cannot be compared",
            "value": share,
            "answer_problems": dict(counts.most_common()),
        }
    ]


def format_verdict(v: Mapping) -> str:
    """'h: both > none on final_trajectory_correct (all): inconclusive, diff +0.045 [+0.000, +0.136], Holm p = 0.310;
    no effect above +22.8 pp detected (exact 95 % bound; 1 vs 0 discordant of 22 episodes)'."""
    head = f"{v['hypothesis']}: {v['a']} > {v['b']} on {v['metric']} ({v['task']}): {v['verdict']}"
    if v.get("mean_diff") is None:
        return head
    p = v.get("p_holm")
    ptxt = "–" if p is None else ("<0.001" if p < 0.001 else f"{p:.3f}")
    out = f"{head}, diff {v['mean_diff']:+.3f} [{v['ci_low']:+.3f}, {v['ci_high']:+.3f}], Holm p = {ptxt}"
    return f"{out}; {v['bound_text']}" if v.get("bound_text") else out
