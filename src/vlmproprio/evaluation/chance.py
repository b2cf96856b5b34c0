"""Chance baselines of segmentation: the same number of points at random (exact or seeded draws: a precomputed
table shipped with the package, then a cache on disk), evenly spaced at one phase and at every phase, the model's
own points at every circular shift, boundaries at the pipeline's frame-group edges; the lift over random chance
(``*_lift``) and over the best of these content-free baselines (``*_lift_cf``, ``CONTENT_FREE_RULE``)."""

from __future__ import annotations

import functools
import json
import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

from vlmproprio.evaluation.cells import CellScores
from vlmproprio.evaluation.inputs import RunInputs, ScoreRunError, frame_group_size
from vlmproprio.evaluation.out_of_sample import add_loo_boundaries, add_out_of_sample
from vlmproprio.segmentation import (
    CHANCE_DRAWS,
    CHANCE_METRICS,
    CHANCE_SEED,
    Truth,
    boundary_prf_gebd,
    chance_groups,
    chance_own_period,
    chance_periodic,
    chance_random,
    chance_shifted,
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


# the content-free baselines a lift is finally read against (CONTENT_FREE_RULE): the best of these per row
CONTENT_FREE = ("chance", "periodic", "shift", "period", "groups")
CONTENT_FREE_RULE = (
    "the best (highest) of five baselines that read nothing, each with as many points as the model placed: at "
    "random, evenly spaced at a random phase offset (the mean over every offset), the model's own points "
    "circularly shifted by a random amount (the mean over every shift), a metronome at the points' own most "
    "common gap at a random phase (where its count is within one of the model's at every phase), and on the "
    "edges of the pipeline's frame groups (every edge first, the rest at random)"
)


@dataclass
class _Shared:
    """What many rows share: the evenly spaced and periodic baselines by (ground truth, count), the group edges'
    scores by episode."""

    group_size: int
    even: dict = field(default_factory=dict)
    periodic: dict = field(default_factory=dict)
    groups: dict = field(default_factory=dict)  # the edges themselves, by episode (seg_groups_*)
    group_chance: dict = field(default_factory=dict)  # as many points as the row's, favouring the edges

    def of(self, table: dict, key, compute) -> dict[str, float]:
        if key not in table:
            table[key] = compute()
        return table[key]


def _chance_columns(
    prefix: str, row: dict, points: Sequence[int], truth: Truth, chance: ChanceTable, shared: _Shared
) -> None:
    k = row.get(f"{prefix}points")
    if k is None:
        return
    k = int(k)
    key = (truth.labels, k)
    rand = chance.random(truth, k)
    even = shared.of(shared.even, key, lambda: score_points(evenly_spaced(truth.n_frames, k), truth))
    periodic = shared.of(shared.periodic, key, lambda: chance_periodic(truth, k))
    shift = chance_shifted(points, truth)
    period = chance_own_period(points, truth)
    groups = shared.of(shared.group_chance, key, lambda: chance_groups(truth, k, shared.group_size))
    for m in CHANCE_METRICS:
        score = row[f"{prefix}{m}"]
        row[f"{prefix}{m}_chance"] = rand[m]
        row[f"{prefix}{m}_lift"] = score - rand[m]
        row[f"{prefix}{m}_even"] = even[m]
        row[f"{prefix}{m}_periodic"] = periodic[m]
        row[f"{prefix}{m}_shift"] = shift[m]
        row[f"{prefix}{m}_groups"] = groups[m]
        row[f"{prefix}{m}_period"] = period[m] if period is not None else None
        best = max(rand[m], periodic[m], shift[m], groups[m], *([period[m]] if period is not None else []))
        row[f"{prefix}{m}_cf"] = best
        row[f"{prefix}{m}_lift_cf"] = score - best


def add_chance(
    rows: list[dict], truths: dict[str, Truth], chance: ChanceTable, group_size: int, traces: dict[str, dict]
) -> None:
    """Chance baselines and lifts for the fixed-threshold (``seg_``) and out-of-sample (``seg_loo_``) scores,
    and the score of boundaries at the frame-group edges (``seg_groups_``). ``traces`` holds each cell's points
    (``predicted_boundaries`` at the fixed threshold, ``loo_boundaries`` out of sample), which the shifted
    baseline moves."""
    from vlmproprio.transcripts import cell_key

    shared = _Shared(group_size)
    for r in rows:
        truth = truths[r["episode_id"]]
        if r["episode_id"] not in shared.groups:
            edges = group_edges(truth.n_frames, group_size)
            shared.groups[r["episode_id"]] = {"points": float(len(edges))} | score_points(edges, truth)
        for m, v in shared.groups[r["episode_id"]].items():
            r[f"seg_groups_{m}"] = v
        tr = traces[cell_key(r["model"], r["episode_id"], r["condition"])]
        _chance_columns("seg_", r, tr["predicted_boundaries"], truth, chance, shared)
        _chance_columns("seg_loo_", r, tr.get("loo_boundaries", []), truth, chance, shared)
        # the same points by GEBD's greedy rule, beside the maximum matching the verdicts use
        r["seg_f1_tol1_gebd"] = boundary_prf_gebd(tr["predicted_boundaries"], truth.boundaries, 1).f1
        if r.get("seg_loo_threshold") is not None:
            r["seg_loo_f1_tol1_gebd"] = boundary_prf_gebd(tr["loo_boundaries"], truth.boundaries, 1).f1


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
    add_loo_boundaries(cells)  # first: the shifted baseline moves the out-of-sample points
    with ChanceTable(chance_dir) as chance:
        add_chance(cells.rows, truths, chance, group_size, cells.traces)
    return Baselines(group_size, chance.exact_share(), chance.computed, chance.cached, chance.precomputed)
