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
COMBINED_RULE = (
    "an intersection-union test: the combined claim is supported only when every hypothesis under it is supported "
    "(each at its Holm-corrected level, so the combined error rate stays at most alpha); not supported when any is "
    "not supported; not tested when any is not tested; else inconclusive. Its p is the largest Holm p under it"
)
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
# leaks and ceilings: scores a model cannot reach from what it is shown. Without state ("none", images only) the
# varying part of the trajectory (the target compartment among four) right in at least this share of a task's
# episodes; boundaries at +-1 frame with at least this mean F1; final captions that are the ground-truth
# instruction word for word (of at least MIN_LEAK_WORDS words) in at least this share of cells
LEAK_TRAJECTORY_SHARE = 0.9
LEAK_MIN_EPISODES = 4
LEAK_BOUNDARY_F1 = 0.9
LEAK_INSTRUCTION_SHARE = 0.25
MIN_LEAK_WORDS = 6
NO_STATE_CONDITIONS = ("none",)
# frame captions made mostly of numbers: the model copies the state instead of describing the motion
STATE_ECHO_SHARE = 0.5
GROUP_EDGE_RATIO = 1.5  # points on group edges / expected under uniform placement, at least this ...
GROUP_EDGE_P = 0.001  # ... and a one-sided binomial p-value below this
# every fixed schedule up to this period (and every offset) is checked the same way ('periodic'), at a ratio of
# at least PERIODIC_RATIO and the p-value corrected for the number of schedules: a metronome is caught at any
# period; real boundaries (phases of 3-15 frames, different in every episode) are not periodic
MAX_PERIOD = 12
PERIODIC_RATIO = 2.0
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
class CombinedClaim:
    """One question answered by several primary hypotheses at once: supported only when every one of them is
    (an intersection-union test, ``COMBINED_RULE``)."""

    id: str
    description: str
    all_of: tuple[str, ...]


@dataclass(frozen=True)
class Claims:
    """The pre-registered primary hypotheses of a claims file, where they come from (source, version, sha256), alpha,
    and the combined claims read from them."""

    alpha: float
    hypotheses: tuple[Hypothesis, ...]
    source: str
    sha256: str
    version: int | str | None = None
    combined: tuple[CombinedClaim, ...] = ()

    def to_dict(self) -> dict:
        return {
            "source": self.source,
            "version": self.version,
            "sha256": self.sha256,
            "alpha": self.alpha,
            "correction": "Holm (family-wise, per model, over the primary hypotheses)",
            "exploratory": "Benjamini-Hochberg q-values (per model, over every other paired test)",
            "primary": [asdict(h) for h in self.hypotheses],
            "combined": [{**asdict(c), "all_of": list(c.all_of)} for c in self.combined],
            "combined_rule": COMBINED_RULE,
        }


def load_claims(path: str | Path | None = None) -> Claims:
    """Read a claims file (YAML): ``alpha`` and a ``primary`` mapping of hypothesis id -> description, metric,
    a, b, task (default "all")."""
    import yaml

    p = Path(path) if path is not None else CLAIMS_FILE
    try:
        raw = p.read_bytes()
        data = yaml.safe_load(raw)
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
    combined = _combined_claims(p, data.get("combined"), {h.id for h in hyps})
    return Claims(float(alpha), tuple(hyps), source, hashlib.sha256(raw).hexdigest(), data.get("version"), combined)


def _combined_claims(p: Path, spec, ids: set[str]) -> tuple[CombinedClaim, ...]:
    """The ``combined`` mapping of a claims file: id -> description and ``all_of`` (primary hypothesis ids)."""
    if spec is None:
        return ()
    if not isinstance(spec, dict):
        raise ClaimsError(f"{p}: 'combined' must be a mapping of claim id -> description, all_of")
    out = []
    for cid, c in spec.items():
        if not isinstance(c, dict) or set(c) != {"description", "all_of"} or not isinstance(c["description"], str):
            raise ClaimsError(f"{p}: combined.{cid}: expected exactly 'description' (text) and 'all_of' (a list)")
        parts = c["all_of"]
        if not isinstance(parts, list) or len(parts) < 2 or not all(isinstance(x, str) for x in parts):
            raise ClaimsError(f"{p}: combined.{cid}: all_of must list at least two primary hypothesis ids")
        unknown = [x for x in parts if x not in ids]
        if unknown:
            raise ClaimsError(f"{p}: combined.{cid}: all_of names unknown hypotheses {', '.join(unknown)}")
        if str(cid) in ids:
            raise ClaimsError(f"{p}: combined.{cid}: the id is a primary hypothesis's too")
        out.append(CombinedClaim(str(cid), c["description"], tuple(parts)))
    return tuple(out)


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


def combined_verdict(parts: Sequence[Mapping]) -> str:
    """``COMBINED_RULE`` over the verdicts of the hypotheses under one combined claim."""
    got = [v["verdict"] for v in parts]
    if all(v == "supported" for v in got):
        return "supported"
    for verdict in ("not supported", "not tested"):
        if verdict in got:
            return verdict
    return "inconclusive"


def combined_verdicts(hypotheses: Sequence[Mapping], claims: Claims, models: Iterable[str]) -> list[dict]:
    """One verdict per model and combined claim, from the hypotheses' verdicts (``verdicts``), with the reason."""
    out = []
    for model in models:
        mine = {v["hypothesis"]: v for v in hypotheses if v["model"] == model}
        for c in claims.combined:
            parts = [mine[h] for h in c.all_of]
            verdict = combined_verdict(parts)
            ps = [v.get("p_holm") for v in parts]
            failing = [v["hypothesis"] for v in parts if v["verdict"] != "supported"]
            out.append(
                {
                    "model": model,
                    "claim": c.id,
                    "description": c.description,
                    "all_of": list(c.all_of),
                    "verdict": verdict,
                    "p": max(ps) if None not in ps else None,  # the intersection-union test's p
                    "parts": {v["hypothesis"]: v["verdict"] for v in parts},
                    "because": "every hypothesis under it is supported"
                    if not failing
                    else "; ".join(f"{h} is {mine[h]['verdict']}" for h in failing),
                    "alpha": claims.alpha,
                }
            )
    return out


def format_combined(c: Mapping) -> str:
    """'state_content_helps_trajectory: not supported (trajectory_both_vs_shuffled is not supported)'."""
    p = c.get("p")
    ptxt = "" if p is None else f", p = {'<0.001' if p < 0.001 else f'{p:.3f}'}"
    return f"{c['claim']}: {c['verdict']}{ptxt} ({c['because']})"


def verdict_doc_lines(doc: Mapping) -> list[str]:
    """What a score's verdicts say, one line each, most important first: the sanity warnings, the combined claims,
    then the hypotheses under them (``score``, ``report`` and report.md print these)."""
    out = [f"⚠ {w['model']}: {w['message']}" for w in doc.get("warnings", [])]
    out += [f"{c['model']} — CLAIM {format_combined(c)}" for c in doc.get("combined", [])]
    out += [f"{v['model']} — {format_verdict(v)}" for v in doc.get("verdicts", [])]
    return out


# ---------------------------------------------------------------------------------------------- sanity


@dataclass(frozen=True)
class FinalCell:
    """What the leak checks read of one cell (episode x condition)."""

    task: str
    condition: str
    truth: str  # the episode's trajectory ground truth that varies within its task (a compartment), or ""
    trajectory_correct: bool
    is_instruction: bool  # the final caption is the episode's ground-truth instruction, word for word
    boundary_f1: float | None  # boundary F1 (+-1 frame) at the fixed threshold


def _words(text: str) -> list[str]:
    return re.findall(r"[a-z0-9]+", (text or "").lower())


def same_sentence(caption: str, instruction: str) -> bool:
    """``caption`` says ``instruction`` word for word (case and punctuation aside), for an instruction long enough
    (``MIN_LEAK_WORDS``) that a model does not write it by chance."""
    words = _words(instruction)
    return len(words) >= MIN_LEAK_WORDS and _words(caption) == words


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
    finals: list[FinalCell] = field(default_factory=list)

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


def lattice_excess(cells: Sequence[tuple[int, Sequence[int]]], period: int, offset: int) -> dict:
    """Points at positions j with j mod ``period`` = ``offset``, against their expectation if the same points
    fell uniformly at random (per cell: its points times the lattice's share of its positions)."""
    observed = total = 0
    expected = 0.0
    for n_frames, points in cells:
        if n_frames < 2:
            continue
        n_pos = n_frames - 1
        on = len(range(offset, n_pos, period))
        observed += sum(1 for j in points if j % period == offset)
        total += len(points)
        expected += len(points) * on / n_pos
    p = binomial_tail(observed, total, expected / total) if total and expected else 1.0
    return {
        "points": total,
        "on_lattice": observed,
        "expected": expected,
        "p_value": float(p),
        "ratio": observed / expected if expected else None,
    }


def periodic_excess(cells: Sequence[tuple[int, Sequence[int]]], group_size: int) -> dict | None:
    """The fixed schedule (period 2 .. ``MAX_PERIOD``, every offset) that the points follow most, beyond
    chance, with its p-value corrected for the number of schedules tried (Bonferroni); None when no points.
    The frame groups' own lattice (period a multiple of k at offset k - 1) is the group-edges check's."""
    best = None
    tried = 0
    for period in range(2, MAX_PERIOD + 1):
        for offset in range(period):
            if period % group_size == 0 and offset % group_size == group_size - 1:
                continue
            tried += 1
            e = lattice_excess(cells, period, offset)
            if e["ratio"] is None:
                continue
            if best is None or e["p_value"] < best["p_value"]:
                best = {**e, "period": period, "offset": offset}
    if best is not None:
        best["p_corrected"] = min(1.0, best["p_value"] * tried)
        best["schedules"] = tried
    return best


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
        numbers = number_share(o.all_captions) if o.all_captions else 0.0
        if numbers >= STATE_ECHO_SHARE:
            out.append(
                {
                    "model": model,
                    "kind": "state-echo",
                    "message": f"captions made of numbers: {100 * numbers:.0f}% of caption tokens are numbers "
                    f"(limit {100 * STATE_ECHO_SHARE:g}%): the model copies the state instead of describing the motion",
                    "value": numbers,
                }
            )
        elif no_hit > MAX_NO_HIT_FINAL_SHARE:
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
        out += _periodic_warning(model, o, group_size)
        out += leak_warnings(model, o.finals)
    return out


def leak_warnings(model: str, finals: Sequence[FinalCell]) -> list[dict]:
    """'leak': scores the model cannot reach from what it was shown (the thresholds above), one warning each."""
    out = []
    found: list[str] = []
    for task in sorted({f.task for f in finals}):
        for cond in NO_STATE_CONDITIONS:
            cells = [f for f in finals if f.task == task and f.condition == cond]
            if len(cells) < LEAK_MIN_EPISODES or len({f.truth for f in cells}) < 2:
                continue  # a trajectory shared by every episode is the ceiling a constant caption reaches
            share = sum(f.trajectory_correct for f in cells) / len(cells)
            if share >= LEAK_TRAJECTORY_SHARE:
                found.append(
                    f"the trajectory (target compartment) is right in {sum(f.trajectory_correct for f in cells)} of "
                    f"{len(cells)} {task} episodes under {cond}, which shows no state"
                )
            f1s = [f.boundary_f1 for f in cells if f.boundary_f1 is not None]
            if f1s and sum(f1s) / len(f1s) >= LEAK_BOUNDARY_F1:
                found.append(f"boundary F1 is {sum(f1s) / len(f1s):.2f} on {task} under {cond}")
    same = sum(f.is_instruction for f in finals)
    if finals and same / len(finals) >= LEAK_INSTRUCTION_SHARE:
        found.append(f"{same} of {len(finals)} final captions are the episode's ground-truth instruction word for word")
    for what in found:
        out.append(
            {
                "model": model,
                "kind": "leak",
                "message": f"possible ground-truth leak: {what}; the model may be given the answer (check the "
                "prompt, the images and the backend): its scores cannot be read as what it saw",
                "value": None,
            }
        )
    return out


def _periodic_warning(model: str, o: ModelOutputs, group_size: int) -> list[dict]:
    """'periodic': the segmentation points follow a fixed schedule (every period, every offset), not the episode."""
    e = periodic_excess(o.cells, group_size)
    if e is None or e["ratio"] is None or e["ratio"] < PERIODIC_RATIO or e["p_corrected"] >= GROUP_EDGE_P:
        return []
    return [
        {
            "model": model,
            "kind": "periodic",
            "message": f"segmentation follows a fixed schedule: {e['on_lattice']} of {e['points']} points fall every "
            f"{e['period']} frames (position mod {e['period']} = {e['offset']}), {e['ratio']:.1f}x the "
            f"{e['expected']:.1f} expected by chance (binomial p = {e['p_corrected']:.1g}, corrected for "
            f"{e['schedules']} schedules): the points keep time, they do not follow the episode",
            "value": e["ratio"],
            **{k: v for k, v in e.items() if k != "ratio"},
        }
    ]


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
