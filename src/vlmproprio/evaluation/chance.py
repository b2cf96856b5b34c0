"""Chance baselines of segmentation: the same number of points at random (exact or seeded draws: a precomputed
table shipped with the package, then a cache on disk), evenly spaced, the lift over random chance, and
boundaries at the pipeline's frame-group edges."""

from __future__ import annotations

import functools
import json
import math
from collections.abc import Iterable, Sequence
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
# every fixture episode's ground truth with every count of points, precomputed (scripts/chance_table.py): a fresh
# cache would otherwise redraw 10 000 sets per (ground truth, count), most of a cold score's time
CHANCE_TABLE_FILE = Path(__file__).with_name("chance_table.json")


def chance_settings() -> list:
    """What random chance depends on besides the ground truth and the count: a table or cache entry made with
    other settings (or by an earlier version of this code) is never read."""
    return [CHANCE_CACHE_VERSION, CHANCE_DRAWS, CHANCE_SEED, list(CHANCE_METRICS)]


def chance_key(labels: Sequence[str], k: int) -> str:
    """The disk cache's key of random chance for one ground truth and count."""
    return json.dumps([CHANCE_CACHE_VERSION, list(labels), k, CHANCE_DRAWS, CHANCE_SEED, list(CHANCE_METRICS)])


def build_chance_table(label_sequences: Iterable[Sequence[str]]) -> dict:
    """Random chance for every count of points (0 .. frames - 1) of each ground truth, as ``ChanceTable`` reads
    it: ``{"settings": chance_settings(), "truths": {json labels: {str(k): {metric: value}}}}`` (JSON floats
    round-trip exactly, so a value read back has the bits ``chance_random`` computed)."""
    truths: dict[str, dict[str, dict[str, float]]] = {}
    for labels in sorted({tuple(seq) for seq in label_sequences}):
        truth = truth_of(labels)
        truths[json.dumps(list(labels))] = {str(k): chance_random(truth, k) for k in range(truth.n_frames)}
    return {"settings": chance_settings(), "truths": truths}


@functools.lru_cache(maxsize=4)
def load_chance_table(path: Path = CHANCE_TABLE_FILE) -> dict[tuple[tuple[str, ...], int], dict[str, float]]:
    """The precomputed table by (labels, k); empty when the file is missing or was made with other settings."""
    from vlmproprio.io import load_json

    try:
        doc = load_json(path, error=ScoreRunError)
    except FileNotFoundError:
        return {}
    if not isinstance(doc, dict) or doc.get("settings") != chance_settings():
        return {}
    return {
        (tuple(json.loads(labels)), int(k)): value
        for labels, by_k in doc["truths"].items()
        for k, value in by_k.items()
    }


class ChanceTable:
    """Random-chance scores by (episode ground truth, number of points).

    They depend on neither the model nor the run: they come from the precomputed table (``table``, by default
    ``chance_table.json`` beside this module), then from disk (``<cache root>/chance``, diskcache, keyed by
    ``chance_key``: the labels, the count, the number of draws, the seed and this code's version), and only
    then are drawn (and kept on disk). The disk cache is opened at the first value the table lacks."""

    def __init__(
        self,
        directory: str | Path | None = None,
        table: dict[tuple[tuple[str, ...], int], dict[str, float]] | None = None,
    ) -> None:
        self._random: dict[tuple, dict[str, float]] = {}
        self._exact: dict[tuple, bool] = {}
        self._dir = Path(directory) if directory is not None else None
        self._table = load_chance_table() if table is None else table
        self._disk = None
        self.computed = 0
        self.cached = 0
        self.precomputed = 0

    def __enter__(self) -> ChanceTable:
        return self

    def __exit__(self, *exc) -> None:
        if self._disk is not None:
            self._disk.close()
            self._disk = None

    def _open_disk(self):
        if self._disk is None and self._dir is not None:
            from vlmproprio.stores import JSON_VALUES, open_store

            try:
                # JSON values only, never diskcache's pickling default: a cache file is data, not code
                self._disk = open_store(self._dir, JSON_VALUES, error=ScoreRunError, what="chance-baseline cache")
            except Exception as exc:  # any failure to open it (a file in the way, a locked or broken database)
                raise ScoreRunError(f"{self._dir}: cannot open the chance-baseline cache ({exc})") from exc
        return self._disk

    def _lookup(self, truth: Truth, k: int) -> dict[str, float]:
        value = self._table.get((truth.labels, k))
        if value is not None:
            self.precomputed += 1
            return value
        disk = self._open_disk()
        disk_key = chance_key(truth.labels, k)
        value = disk.get(disk_key) if disk is not None else None
        if value is not None:
            self.cached += 1
            return value
        value = chance_random(truth, k)
        self.computed += 1
        if disk is not None:
            disk.set(disk_key, value)
        return value

    def random(self, truth: Truth, k: int) -> dict[str, float]:
        key = (truth.labels, k)
        if key not in self._random:
            self._random[key] = self._lookup(truth, k)
            self._exact[key] = math.comb(truth.n_frames - 1, k) <= CHANCE_DRAWS
        return self._random[key]

    def exact_share(self) -> float | None:
        return sum(self._exact.values()) / len(self._exact) if self._exact else None


def _chance_columns(prefix: str, row: dict, truth: Truth, chance: ChanceTable, even_of: dict) -> None:
    k = row.get(f"{prefix}points")
    if k is None:
        return
    rand = chance.random(truth, int(k))
    key = (truth.labels, int(k))
    if key not in even_of:  # many rows share a ground truth and a count
        even_of[key] = score_points(evenly_spaced(truth.n_frames, int(k)), truth)
    even = even_of[key]
    for m in CHANCE_METRICS:
        row[f"{prefix}{m}_chance"] = rand[m]
        row[f"{prefix}{m}_lift"] = row[f"{prefix}{m}"] - rand[m]
        row[f"{prefix}{m}_even"] = even[m]


def add_chance(rows: list[dict], truths: dict[str, Truth], chance: ChanceTable, group_size: int) -> None:
    """Chance baselines and lifts for the fixed-threshold (``seg_``) and out-of-sample (``seg_loo_``) scores,
    and the score of boundaries at the frame-group edges (``seg_groups_``)."""
    groups: dict[str, dict[str, float]] = {}
    even_of: dict[tuple[tuple[str, ...], int], dict[str, float]] = {}
    for r in rows:
        truth = truths[r["episode_id"]]
        _chance_columns("seg_", r, truth, chance, even_of)
        _chance_columns("seg_loo_", r, truth, chance, even_of)
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
    precomputed: int  # read from the table shipped with the package


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
    return Baselines(group_size, chance.exact_share(), chance.computed, chance.cached, chance.precomputed)
