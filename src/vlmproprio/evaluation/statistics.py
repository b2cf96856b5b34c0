"""Paired statistics of a run: condition differences paired by episode, marked primary or exploratory, and the
verdicts on the pre-registered hypotheses with the sanity warnings (vlmproprio.verdicts)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

from vlmproprio.conditions import BASELINE, PAPER_CONDITIONS
from vlmproprio.evaluation.definitions import PAIRED_METRICS, ScoreSettings
from vlmproprio.evaluation.inputs import condition_order
from vlmproprio.sanity import ModelOutputs, sanity_warnings
from vlmproprio.stats import DEFAULT_N_BOOT, DEFAULT_N_PERM, DEFAULT_SEED, paired_difference
from vlmproprio.verdicts import Claims, combined_verdicts, mark_families, verdicts

# the final caption's rubric items, right (1) or not (0) per episode: their differences get exact bounds
BINARY_METRICS = tuple(m for m in PAIRED_METRICS if m.endswith(("_correct", "_mentioned")))


def default_comparisons(conditions: Sequence[str]) -> list[tuple[str, str]]:
    """Every condition against the no-state baseline, and the full-state condition against each control."""
    conds = condition_order(conditions)
    out = [(c, BASELINE) for c in conds if c != BASELINE and BASELINE in conds]
    if "both" in conds:
        out += [("both", c) for c in conds if c not in PAPER_CONDITIONS]
    return out


def paired_table(
    rows: list[dict],
    comparisons: Sequence[tuple[str, str]],
    metrics: Sequence[str] = PAIRED_METRICS,
    *,
    n_boot: int = DEFAULT_N_BOOT,
    n_perm: int = DEFAULT_N_PERM,
    seed: int = DEFAULT_SEED,
) -> list[dict]:
    index = {(r["model"], r["task"], r["condition"], r["episode_id"]): r for r in rows}
    out = []
    models = sorted({r["model"] for r in rows})
    tasks = sorted({r["task"] for r in rows})
    for model in models:
        for task in [*tasks, "all"]:
            for a, b in comparisons:
                ta = [task] if task != "all" else tasks
                pairs = [
                    (index[(model, t, a, e)], index[(model, t, b, e)])
                    for (m, t, c, e) in index
                    if m == model and c == a and t in ta and (model, t, b, e) in index
                ]
                if not pairs:
                    continue
                pairs.sort(key=lambda p: p[0]["episode_id"])
                for metric in metrics:
                    va = [p[0].get(metric) for p in pairs]
                    vb = [p[1].get(metric) for p in pairs]
                    keep = [(x, y) for x, y in zip(va, vb, strict=True) if x is not None and y is not None]
                    res = paired_difference(
                        [x for x, _ in keep],
                        [y for _, y in keep],
                        n_boot=n_boot,
                        n_perm=n_perm,
                        seed=seed,
                        binary=metric in BINARY_METRICS,
                    )
                    out.append({"model": model, "task": task, "metric": metric, "a": a, "b": b, **res.to_dict()})
    return out


@dataclass
class Statistics:
    comparisons: list[tuple[str, str]]
    paired: list[dict]  # already in a meaningful order: model, task, comparison (as listed), metric (as listed)
    verdicts: dict  # scores/verdicts.json: claims, verdicts per model and hypothesis, sanity warnings


def paired_statistics(
    rows: list[dict],
    conditions: list[str],
    outputs: dict[str, ModelOutputs],
    settings: ScoreSettings,
    claims: Claims,
    group_size: int,
) -> Statistics:
    comps = list(settings.comparisons) if settings.comparisons is not None else default_comparisons(conditions)
    paired = paired_table(rows, comps, n_boot=settings.n_boot, n_perm=settings.n_perm, seed=settings.seed)
    mark_families(paired, claims)
    models = sorted({r["model"] for r in rows})
    hypotheses = verdicts(paired, claims, models)
    verdict_doc = {
        "claims": claims.to_dict(),
        "combined": combined_verdicts(hypotheses, claims, models),
        "verdicts": hypotheses,
        "warnings": sanity_warnings({m: outputs[m] for m in models}, group_size),
        "group_size": group_size,
    }
    return Statistics(comps, paired, verdict_doc)
