"""Segmentation at a threshold chosen out of sample: for each episode, the best threshold on the other episodes of its
task (same model and condition), so the reported score never saw the episode it scores."""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from vlmproprio.evaluation.cells import CellScores
from vlmproprio.segmentation import boundaries_at
from vlmproprio.transcripts import cell_key

LOO_RULE = (
    "leave one episode out: for each episode, the threshold with the highest mean boundary F1 (+-1 frame) over "
    "the other episodes of the same task, model and condition (ties: the lowest threshold), applied to it"
)


def loo_thresholds(cell_sweeps: dict[tuple[str, str, str], list[dict]], tasks: dict[str, str]) -> dict:
    """(model, episode, condition) -> the threshold chosen on the other episodes of its task (LOO_RULE); None
    when the task has no other episode."""
    groups: dict[tuple[str, str, str], list[str]] = {}
    for model, episode, condition in cell_sweeps:
        groups.setdefault((model, tasks[episode], condition), []).append(episode)
    out = {}
    for (model, _task, condition), members in groups.items():
        for held_out in members:
            others = [cell_sweeps[(model, e, condition)] for e in members if e != held_out]
            if not others:
                out[(model, held_out, condition)] = None
                continue
            best_thr, best_f1 = None, -1.0
            for i, point in enumerate(others[0]):
                f1 = math.fsum(o[i]["f1_tol1"] for o in others) / len(others)
                if f1 > best_f1:
                    best_thr, best_f1 = point["threshold"], f1
            out[(model, held_out, condition)] = best_thr
    return out


SEG_COLUMNS = ("points", "p_tol0", "r_tol0", "f1_tol0", "p_tol1", "r_tol1", "f1_tol1", "p_tol2", "r_tol2", "f1_tol2")


def add_out_of_sample(rows: list[dict], cell_sweeps: dict, thresholds: Sequence[float]) -> None:
    """Add ``seg_loo_threshold`` and every sweep metric at it as ``seg_loo_*`` to each row."""
    chosen = loo_thresholds(cell_sweeps, {r["episode_id"]: r["task"] for r in rows})
    for r in rows:
        cell = (r["model"], r["episode_id"], r["condition"])
        thr = chosen[cell]
        r["seg_loo_threshold"] = thr
        point = next((p for p in cell_sweeps[cell] if p["threshold"] == thr), None)
        for k, v in (point or {}).items():
            if k != "threshold":
                r[f"seg_loo_{k}"] = v


def add_loo_boundaries(cells: CellScores) -> None:
    """Each cell's trace gets its out-of-sample threshold and the boundaries at it, which the sanity checks read."""
    for r in cells.rows:
        tr = cells.traces[cell_key(r["model"], r["episode_id"], r["condition"])]
        tr["loo_threshold"] = r["seg_loo_threshold"]
        thr = r["seg_loo_threshold"]
        tr["loo_boundaries"] = boundaries_at(np.array(tr["trace"], dtype=np.float64), thr) if thr is not None else []
        cells.outputs[r["model"]].cells.append((r["n_frames"], tr["loo_boundaries"]))
