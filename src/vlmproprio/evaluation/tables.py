"""The score tables of a run: rows and sweep rows in the run's order, and their means per (model, task, condition)."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

from vlmproprio.evaluation.cells import CellScores
from vlmproprio.evaluation.inputs import RunInputs

ID_COLUMNS = ("model", "episode_id", "task", "condition")


@dataclass
class ScoreTables:
    rows: list[dict]
    aggregate: list[dict]
    sweep: list[dict]
    sweep_aggregate: list[dict]
    paired: list[dict]
    audit: dict
    traces: dict
    meta: dict
    timing: dict = field(default_factory=dict)
    judge: dict | None = None  # only when a judge backend was given
    verdicts: dict = field(default_factory=dict)  # claims, verdicts per model and hypothesis, sanity warnings


def _mean(values: list) -> float | None:
    vals = [float(v) for v in values if v is not None]
    return math.fsum(vals) / len(vals) if vals else None


def _numeric_columns(rows: list[dict], skip: Sequence[str]) -> list[str]:
    cols: list[str] = []
    for r in rows:
        for k, v in r.items():
            if k in skip or k in cols:
                continue
            if (isinstance(v, (int, float)) and not isinstance(v, bool)) or v is None:
                cols.append(k)
    return [c for c in cols if any(isinstance(r.get(c), (int, float)) for r in rows)]


def _group_means(rows: list[dict], keys: Sequence[str], skip: Sequence[str], add_all_task: bool) -> list[dict]:
    cols = _numeric_columns(rows, skip)
    groups: dict[tuple, list[dict]] = {}
    for r in rows:
        groups.setdefault(tuple(r[k] for k in keys), []).append(r)
        if add_all_task:
            groups.setdefault(tuple("all" if k == "task" else r[k] for k in keys), []).append(r)
    out = []
    for key, members in groups.items():
        d = dict(zip(keys, key, strict=True))
        d["n_episodes"] = len(members)
        for c in cols:
            d[c] = _mean([m.get(c) for m in members])
        out.append(d)
    return out


def _sort_rows(rows: list[dict], episode_order: dict[str, int], conds: list[str]) -> list[dict]:
    tasks = {"door": 0, "pick_place": 1, "all": 9}

    def key(r: dict):
        return (
            r["model"],
            tasks.get(r.get("task"), 5),
            r.get("task", ""),
            episode_order.get(r.get("episode_id", ""), -1),
            conds.index(r.get("condition", "")) if r.get("condition") in conds else len(conds),
            r.get("threshold", 0.0),
        )

    return sorted(rows, key=key)


@dataclass
class Aggregates:
    """Rows and sweep rows sorted (model, task, episode in run order, condition, threshold), and their means; the
    fields of ScoreTables of the same names."""

    rows: list[dict]
    aggregate: list[dict]
    sweep: list[dict]
    sweep_aggregate: list[dict]


def aggregate_tables(inputs: RunInputs, cells: CellScores) -> Aggregates:
    order, conds = inputs.episode_order, inputs.conditions
    rows = _sort_rows(cells.rows, order, conds)
    sweep_rows = _sort_rows(cells.sweep_rows, order, conds)
    skip = (*ID_COLUMNS, "seg_threshold", "threshold")
    aggregate = _group_means(rows, ("model", "task", "condition"), skip, add_all_task=True)
    sweep_aggregate = _group_means(sweep_rows, ("model", "task", "condition", "threshold"), skip, add_all_task=True)
    return Aggregates(rows, _sort_rows(aggregate, order, conds), sweep_rows, _sort_rows(sweep_aggregate, order, conds))
