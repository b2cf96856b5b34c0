"""Verdicts a reviewer accepts: pre-registered primary hypotheses, corrected tests, combined claims.

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
* **Combined claims** answer one question with several hypotheses (``COMBINED_RULE``): "the state's content
  helps" is supported only when both > none and both > both_shuffled are; a captioner that only notices that
  numbers are present can win the first, never the second.
* **Sanity warnings** (``vlmproprio.sanity``) say when a model's differences cannot be read as "the model used
  the state"; the score puts them beside the verdicts.

The format of the claims file and every threshold here are documented in docs/metrics.md.
"""

from __future__ import annotations

import hashlib
import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import asdict, dataclass
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
    "not tested": "the run lacks condition A or B, or no episode has a value under both (the verdict says which)",
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


def _number(x) -> bool:
    return isinstance(x, (int, float)) and math.isfinite(x)


def untested_why(row: Mapping | None, h: Hypothesis) -> str:
    """Why a hypothesis could not be tested, in words a user can act on."""
    if row is None:
        return (
            f"the run has no paired comparison of {h.a} with {h.b} on {h.task} episodes: run both conditions "
            f"(--conditions {h.a},{h.b},...) on episodes of that task"
        )
    n = row.get("n") or 0
    if not n:
        return f"no episode has a value of {h.metric} under both {h.a} and {h.b} (every one is undefined)"
    return f"the paired test gave no p-value on {n} episodes (every difference is undefined or the test failed)"


def verdict_of(row: Mapping | None, alpha: float) -> str:
    if row is None or row.get("p_holm") is None or not _number(row.get("mean_diff")):
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
                    "why": untested_why(row, h) if verdict == "not tested" else None,
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


def format_verdict(v: Mapping) -> str:
    """'h: both > none on final_trajectory_correct (all): inconclusive, diff +0.045 [+0.000, +0.136], Holm p = 0.310;
    no effect above +22.8 pp detected (exact 95 % bound; 1 vs 0 discordant of 22 episodes)'."""
    head = f"{v['hypothesis']}: {v['a']} > {v['b']} on {v['metric']} ({v['task']}): {v['verdict']}"
    if v["verdict"] == "not tested":
        return f"{head} ({v.get('why') or VERDICT_RULES['not tested']})"
    if not _number(v.get("mean_diff")):
        return head
    p = v.get("p_holm")
    ptxt = "–" if p is None else ("<0.001" if p < 0.001 else f"{p:.3f}")
    out = f"{head}, diff {v['mean_diff']:+.3f} [{v['ci_low']:+.3f}, {v['ci_high']:+.3f}], Holm p = {ptxt}"
    return f"{out}; {v['bound_text']}" if v.get("bound_text") else out
