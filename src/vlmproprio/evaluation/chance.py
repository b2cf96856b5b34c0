"""Chance baselines of segmentation: the same number of points at random (exact or seeded draws, cached on disk)
and evenly spaced, the lift over random chance, and boundaries at the pipeline's frame-group edges."""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from vlmproprio.evaluation.cells import CellScores
from vlmproprio.evaluation.inputs import RunInputs, ScoreRunError, frame_group_size
from vlmproprio.evaluation.out_of_sample import add_loo_boundaries, add_out_of_sample
from vlmproprio.segmentation import (
    CHANCE_DRAWS,
    CHANCE_METRICS,
    CHANCE_SEED,
    Truth,
    chance_random,
    evenly_spaced,
    group_edges,
    score_points,
    truth_of,
)

CHANCE_CACHE_VERSION = 2  # 2: JSON values (1 was pickled)


class ChanceTable:
    """Random-chance scores by (episode ground truth, number of points).

    They depend on neither the model nor the run, so they are kept on disk (``<cache root>/chance``, diskcache,
    keyed by the labels, the count, the number of draws, the seed and this code's version) as well as in
    memory: a second scoring of any run reads them instead of drawing 10 000 sets again."""

    def __init__(self, directory: str | Path | None = None) -> None:
        self._random: dict[tuple, dict[str, float]] = {}
        self._exact: dict[tuple, bool] = {}
        self._dir = Path(directory) if directory is not None else None
        self._disk = None
        self.computed = 0
        self.cached = 0

    def __enter__(self) -> ChanceTable:
        if self._dir is not None:
            from vlmproprio.stores import JSON_VALUES, open_store

            try:
                # JSON values only, never diskcache's pickling default: a cache file is data, not code
                self._disk = open_store(self._dir, JSON_VALUES, error=ScoreRunError, what="chance-baseline cache")
            except Exception as exc:  # any failure to open it (a file in the way, a locked or broken database)
                raise ScoreRunError(f"{self._dir}: cannot open the chance-baseline cache ({exc})") from exc
        return self

    def __exit__(self, *exc) -> None:
        if self._disk is not None:
            self._disk.close()
            self._disk = None

    def random(self, truth: Truth, k: int) -> dict[str, float]:
        key = (truth.labels, k)
        if key not in self._random:
            disk_key = json.dumps(
                [CHANCE_CACHE_VERSION, list(truth.labels), k, CHANCE_DRAWS, CHANCE_SEED, list(CHANCE_METRICS)]
            )
            value = self._disk.get(disk_key) if self._disk is not None else None
            if value is None:
                value = chance_random(truth, k)
                self.computed += 1
                if self._disk is not None:
                    self._disk.set(disk_key, value)
            else:
                self.cached += 1
            self._random[key] = value
            self._exact[key] = math.comb(truth.n_frames - 1, k) <= CHANCE_DRAWS
        return self._random[key]

    def exact_share(self) -> float | None:
        return sum(self._exact.values()) / len(self._exact) if self._exact else None


def _chance_columns(prefix: str, row: dict, truth: Truth, chance: ChanceTable) -> None:
    k = row.get(f"{prefix}points")
    if k is None:
        return
    rand = chance.random(truth, int(k))
    even = score_points(evenly_spaced(truth.n_frames, int(k)), truth)
    for m in CHANCE_METRICS:
        row[f"{prefix}{m}_chance"] = rand[m]
        row[f"{prefix}{m}_lift"] = row[f"{prefix}{m}"] - rand[m]
        row[f"{prefix}{m}_even"] = even[m]


def add_chance(rows: list[dict], truths: dict[str, Truth], chance: ChanceTable, group_size: int) -> None:
    """Chance baselines and lifts for the fixed-threshold (``seg_``) and out-of-sample (``seg_loo_``) scores,
    and the score of boundaries at the frame-group edges (``seg_groups_``)."""
    groups: dict[str, dict[str, float]] = {}
    for r in rows:
        truth = truths[r["episode_id"]]
        _chance_columns("seg_", r, truth, chance)
        _chance_columns("seg_loo_", r, truth, chance)
        if r["episode_id"] not in groups:
            edges = group_edges(truth.n_frames, group_size)
            groups[r["episode_id"]] = {"points": float(len(edges))} | score_points(edges, truth)
        for m, v in groups[r["episode_id"]].items():
            r[f"seg_groups_{m}"] = v


@dataclass(frozen=True)
class Baselines:
    """What meta.json and timing.json record of the chance baselines of a score."""

    group_size: int  # the pipeline's frame-group size k (group-edge baseline, sanity checks)
    exact_share: float | None  # share of (ground truth, points) whose random chance is exact, not drawn
    computed: int
    cached: int


def add_segmentation_baselines(
    inputs: RunInputs, cells: CellScores, thresholds: Sequence[float], chance_dir: Path
) -> Baselines:
    """Out-of-sample thresholds, chance baselines and lifts, and group-edge scores, added to every row."""
    group_size = frame_group_size(inputs.manifest)
    truths = {e: truth_of(ep.frame_phases) for e, ep in inputs.episodes.items()}
    add_out_of_sample(cells.rows, cells.cell_sweeps, thresholds)
    with ChanceTable(chance_dir) as chance:
        add_chance(cells.rows, truths, chance, group_size)
    add_loo_boundaries(cells)
    return Baselines(group_size, chance.exact_share(), chance.computed, chance.cached)
