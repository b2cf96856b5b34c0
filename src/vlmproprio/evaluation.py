"""Score a whole run: caption rubric, segmentation sweep and paired statistics into RUN_DIR/scores/.

Reads ``RUN_DIR/run.json`` (for the fixture root) and every transcript under
``RUN_DIR/transcripts/``, loads the ground truth of each episode, and writes:

* ``rows.json`` / ``rows.csv``: one row per (model, episode, condition) with every metric;
* ``aggregate.json`` / ``aggregate.csv``: means per (model, task, condition), task "all" included;
* ``sweep.json`` / ``sweep.csv``: per (model, episode, condition, threshold 0.00..1.00): number of
  segmentation points, boundary P/R/F1 at tolerance 0/1/2 frames, MS-TCN edit score, F1@{10,25,50},
  frame accuracy and the unmerged edit score;
  ``sweep_aggregate.json`` / ``.csv``: their means per (model, task, condition, threshold);
* ``paired.json`` / ``paired.csv``: condition differences paired by episode (bootstrap CI, sign-flip p), each
  marked primary (a pre-registered hypothesis, Holm-corrected) or exploratory (Benjamini-Hochberg q);
* ``verdicts.json``: per model and primary hypothesis supported / not supported / inconclusive, and the
  sanity warnings (vlmproprio.verdicts);

Segmentation is scored at the paper's fixed threshold (columns ``seg_*``) and at a threshold chosen out of
sample (``seg_loo_*``): for each episode, the threshold with the best mean boundary F1 (+-1 frame) on the
*other* episodes of its task, same model and condition (ties: the lowest). Every segmentation metric has
chance baselines for the same number of points (``*_chance``: random positions, exact or 10 000 seeded
draws; ``*_even``: evenly spaced) and its lift over random chance (``*_lift``); ``seg_groups_*`` scores
boundaries at the edges of the pipeline's frame groups. The in-sample best threshold is not a score: it
exists only in the sweep tables (and the report's sweep plot, marked optimistic).
* ``audit.json``: per caption, every matched span with its verdict, and what was expected;
* ``traces.json``: every similarity trace with its predicted and true boundaries;
* ``meta.json``: encoder name, revision and key, lexicon versions and hashes, settings;
* ``timing.json``: wall times and cache counts -- the only file that differs between repeated runs;
* ``stamp.json``: the digest of exactly the transcripts, run configuration, ground truth, settings and code
  version these scores come from, and the sha256 of every other file (one generation: see below).

Given the same transcripts, fixtures and cached embeddings, every file but
timing.json is byte-identical across runs, processes and machines.
"""

from __future__ import annotations

import csv
import io
import json
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from vlmproprio.embeddings import default_embedding_dir
from vlmproprio.episodes import Episode, load_episodes
from vlmproprio.errors import VlmproprioError
from vlmproprio.io import atomic_write_text, load_json
from vlmproprio.scoring import ITEMS, CaptionScore, expectation_for, load_lexicon, score_text
from vlmproprio.segmentation import (
    CHANCE_DRAWS,
    CHANCE_METRICS,
    CHANCE_SEED,
    DEFAULT_THRESHOLD,
    IOU_THRESHOLDS,
    THRESHOLDS,
    TOLERANCES,
    Truth,
    boundaries_at,
    caption_present,
    chance_random,
    cosine_trace,
    evenly_spaced,
    group_edges,
    score_points,
    sweep,
    truth_of,
)
from vlmproprio.stats import DEFAULT_N_BOOT, DEFAULT_N_PERM, DEFAULT_SEED, paired_difference
from vlmproprio.transcripts import Transcript, read_transcript
from vlmproprio.verdicts import ModelOutputs, load_claims, mark_families, sanity_warnings, verdicts

SCORES_VERSION = 2
BASELINE = "none"
STATE_CONDITIONS = ("none", "ee", "joint", "both")
CONTROL_CONDITIONS = ("both_shuffled", "both_permuted", "both_noisy", "state_only", "primitives")
PAIRED_METRICS = (
    "final_object_correct",
    "final_action_correct",
    "final_trajectory_mentioned",
    "final_trajectory_correct",
    "final_all_correct",
    "final_words",
    "final_hits_per_word",
    # segmentation at the out-of-sample (leave-one-episode-out) threshold; lifts are over random chance
    "seg_loo_points",
    "seg_loo_f1_tol1",
    "seg_loo_f1_tol1_lift",
    "seg_loo_edit_lift",
    "seg_loo_f1_at_25_lift",
)
DEFAULT_GROUP_SIZE = 5
MISSING_POLICY = (
    "A frame caption with status 'missing', an empty text, or no entry in the transcript is a gap: the trace "
    "keeps its place and every pair touching it is NaN, which never makes a boundary. A missing final or scene "
    "caption scores as an empty text (nothing mentioned, zero words). 'recovered' captions are used as they are."
)
ID_COLUMNS = ("model", "episode_id", "task", "condition")


class ScoreRunError(VlmproprioError):
    """A run directory that cannot be scored; the message names the file and what to do."""


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


# ---------------------------------------------------------------------------------------------- inputs


def read_run_manifest(run_dir: Path) -> dict:
    path = run_dir / "run.json"
    if not path.is_file():
        return {}
    data = load_json(path, error=ScoreRunError)
    if not isinstance(data, dict):
        raise ScoreRunError(f"{path}: run manifest must be a JSON object")
    return data


def resolve_fixtures(run_dir: Path, manifest: dict, fixtures: str | Path | None) -> Path:
    if fixtures is not None:
        root = Path(fixtures)
    elif manifest.get("fixtures"):
        root = Path(manifest["fixtures"])
        if not root.is_absolute() and not root.is_dir() and (run_dir / root).is_dir():
            root = run_dir / root
    else:
        raise ScoreRunError(f"{run_dir / 'run.json'}: no 'fixtures' entry; pass the fixture folder (--fixtures)")
    if not root.is_dir():
        raise ScoreRunError(f"fixture folder {root} not found (from {run_dir / 'run.json'}); pass --fixtures")
    return root


def condition_order(conditions: Sequence[str]) -> list[str]:
    known = [*STATE_CONDITIONS, *CONTROL_CONDITIONS]
    return sorted(set(conditions), key=lambda c: (known.index(c) if c in known else len(known), c))


def frame_texts(t: Transcript, n_frames: int, where: str) -> tuple[list[str], list[str]]:
    """Texts and statuses aligned with frame indices 0..n-1; absent frames are 'missing'."""
    texts = [""] * n_frames
    statuses = ["missing"] * n_frames
    for f in t.frames:
        if not 0 <= f.frame_index < n_frames:
            raise ScoreRunError(f"{where}: frame_index {f.frame_index} outside the episode's {n_frames} frames")
        texts[f.frame_index] = f.text or ""
        statuses[f.frame_index] = f.status if caption_present(f.text, f.status) else "missing"
    return texts, statuses


# ---------------------------------------------------------------------------------------------- per transcript


def _flag(b: bool) -> int:
    return 1 if b else 0


def _caption_columns(prefix: str, s: CaptionScore) -> dict:
    d = {}
    for item in ITEMS:
        it = s.item(item)
        d[f"{prefix}_{item}_mentioned"] = _flag(it.mentioned)
        d[f"{prefix}_{item}_correct"] = _flag(it.correct)
        d[f"{prefix}_{item}_wrong"] = _flag(it.wrong)
    d[f"{prefix}_all_correct"] = _flag(s.all_correct)
    return d


def _scene_columns(scores: list[CaptionScore]) -> dict:
    """Fractions of the scene captions that mention / get right each item (None without scene captions)."""
    d: dict = {}
    n = len(scores)
    for item in ITEMS:
        for what in ("mentioned", "correct", "wrong"):
            k = sum(1 for s in scores if getattr(s.item(item), what))
            d[f"scene_{item}_{what}"] = k / n if n else None
    d["scene_all_correct"] = sum(1 for s in scores if s.all_correct) / n if n else None
    d["scene_words"] = math.fsum(s.words for s in scores) / n if n else None
    return d


def _caption_audit(text: str, status: str, s: CaptionScore) -> dict:
    return {
        "text": text,
        "status": status,
        "words": s.words,
        "hits": s.hits,
        "items": {item: vars(s.item(item)).copy() for item in ITEMS} | {"all_correct": s.all_correct},
        "matches": [h.to_dict() for h in s.matches],
    }


def _finite_or_none(x: float) -> float | None:
    return None if x is None or (isinstance(x, float) and not math.isfinite(x)) else x


def _trace_stats(trace: np.ndarray) -> dict:
    fin = [float(x) for x in trace.tolist() if math.isfinite(x)]
    return {
        "sim_mean": _finite_or_none(math.fsum(fin) / len(fin)) if fin else None,
        "sim_min": min(fin) if fin else None,
    }


# ---------------------------------------------------------------------------------------------- tables


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


def default_comparisons(conditions: Sequence[str]) -> list[tuple[str, str]]:
    """Every condition against the no-state baseline, and the full-state condition against each control."""
    conds = condition_order(conditions)
    out = [(c, BASELINE) for c in conds if c != BASELINE and BASELINE in conds]
    if "both" in conds:
        out += [("both", c) for c in conds if c not in STATE_CONDITIONS]
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
                        [x for x, _ in keep], [y for _, y in keep], n_boot=n_boot, n_perm=n_perm, seed=seed
                    )
                    out.append({"model": model, "task": task, "metric": metric, "a": a, "b": b, **res.to_dict()})
    return out


# ---------------------------------------------------------------------------------------------- main entry


def score_run(
    run_dir: str | Path,
    fixtures: str | Path | None = None,
    encoder=None,
    *,
    embedding_cache: str | Path | None = None,
    chance_cache: str | Path | None = None,
    threshold: float = DEFAULT_THRESHOLD,
    thresholds: Sequence[float] = THRESHOLDS,
    comparisons: Sequence[tuple[str, str]] | None = None,
    n_boot: int = DEFAULT_N_BOOT,
    n_perm: int = DEFAULT_N_PERM,
    seed: int = DEFAULT_SEED,
    verify: bool = True,
    write: bool = True,
    judge=None,
    sidecars: Sequence[str | Path] | None = None,
    progress: bool = False,
    claims: str | Path | None = None,
) -> ScoreTables:
    """Score every transcript of a run and (by default) write RUN_DIR/scores/.

    ``encoder`` is an ``embeddings.EncoderSpec`` (default: the packaged all-MiniLM-L6-v2); embeddings are cached
    in ``embedding_cache`` (default <cache root>/embeddings, shared by every run: its entries are keyed
    by encoder and text), so re-scoring a run needs no torch. Chance baselines are cached in ``chance_cache``
    (default: next to the embedding cache, ``<cache root>/chance``). ``judge`` (off by
    default) is any vlmproprio Backend that also grades the final captions; its agreement with the rubric
    goes to scores/judge.json. Frame-caption vectors are read first from ``sidecars`` (default: the
    ``<fixtures>/responses/<model>.embeddings.npz`` of the run's models; ``()``: none), so a replayed
    cassette is scored without loading the encoder. ``progress`` shows a bar over the stages (load, embed,
    score, statistics, write). ``claims`` is the file of pre-registered primary hypotheses (default: the
    packaged vlmproprio/claims.yml); their verdicts and the sanity warnings go to scores/verdicts.json."""
    from tqdm import tqdm

    from vlmproprio.embeddings import (
        CachedEmbedder,
        EmbeddingStore,
        load_sidecars,
        read_sidecar,
        resolve_encoder,
        sidecar_vectors,
    )

    bar = tqdm(total=5, desc="score: loading", unit="stage", disable=not progress or None, leave=False)
    t_start = time.perf_counter()
    claim_set = load_claims(claims)
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise ScoreRunError(f"{run_dir}: run directory not found")
    manifest = read_run_manifest(run_dir)
    transcript_files = run_transcript_files(run_dir, manifest)
    transcripts = [read_transcript(p) for p in transcript_files]
    if not transcripts:
        raise ScoreRunError(
            f"{run_dir / 'transcripts'}: no transcripts (run `vlmproprio run --model NAME --out {run_dir}` first)"
        )
    root = resolve_fixtures(run_dir, manifest, fixtures)
    ids = sorted({t.episode_id for t in transcripts})
    episodes: dict[str, Episode] = {e.episode_id: e for e in load_episodes(root, ids, verify=verify)}
    run_order = [e for e in manifest.get("episodes", []) if isinstance(e, str)]
    episode_order = {e: i for i, e in enumerate([*run_order, *[i for i in ids if i not in run_order]])}
    conds = condition_order([t.condition for t in transcripts])
    t_loaded = time.perf_counter()
    bar.update()
    bar.set_description("score: embedding captions")

    if sidecars is None:
        stored = load_sidecars(root / "responses", {t.model for t in transcripts})
    else:
        stored = [read_sidecar(p) for p in sidecars]
    spec = encoder if encoder is not None else resolve_encoder(stored)
    cache_dir = Path(embedding_cache) if embedding_cache is not None else default_embedding_dir()
    from vlmproprio.runner import refuse_nesting

    refuse_nesting(root, {"RUN_DIR": run_dir, "--embedding-cache": cache_dir})
    aligned = {}
    for t in transcripts:
        where = f"{run_dir}/transcripts/{t.model}/{t.episode_id}__{t.condition}.json"
        ep = episodes[t.episode_id]
        if t.task != ep.task:
            raise ScoreRunError(f"{where}: task {t.task!r} but episode {ep.episode_id} is {ep.task!r}")
        aligned[(t.model, t.episode_id, t.condition)] = frame_texts(t, len(ep.frames), where)
    all_texts = sorted({x for texts, st in aligned.values() for x, s in zip(texts, st, strict=True) if s != "missing"})
    with EmbeddingStore(cache_dir) as store:
        embedder = CachedEmbedder(spec, store, sidecar=sidecar_vectors(stored, spec.key))
        vectors = embedder.embed(all_texts)
    t_embedded = time.perf_counter()
    bar.update()
    bar.set_description("score: rubric and segmentation")

    rows, sweep_rows, audit, traces = [], [], {}, {}
    cell_sweeps: dict[tuple[str, str, str], list[dict]] = {}
    outputs: dict[str, ModelOutputs] = {}
    lexicons = {}
    finals: list[tuple[str, CaptionScore, str, Episode, str]] = []
    for t in transcripts:
        ep = episodes[t.episode_id]
        lex = lexicons.setdefault(ep.task, load_lexicon(ep.task))
        exp = expectation_for(ep, lex)
        key = f"{t.model}/{t.episode_id}__{t.condition}"
        final_text = t.final if t.final_status != "missing" else ""
        final = score_text(final_text, exp, lex)
        finals.append((key, final, final_text, ep, t.condition))
        scene_texts = [(s.text if s.status != "missing" else "") for s in t.scenes]
        scenes = [score_text(x, exp, lex) for x in scene_texts]
        texts, statuses = aligned[(t.model, t.episode_id, t.condition)]
        trace = cosine_trace([vectors[x] if s != "missing" else None for x, s in zip(texts, statuses, strict=True)])
        labels = ep.frame_phases
        points = sweep(trace, labels, (*thresholds, threshold))
        at = points[-1]
        cell_sweeps[(t.model, t.episode_id, t.condition)] = [sp.flat() for sp in points[:-1]]
        row = {
            "model": t.model,
            "episode_id": t.episode_id,
            "task": ep.task,
            "condition": t.condition,
            "n_frames": len(ep.frames),
            "frames_missing": statuses.count("missing"),
            "frames_recovered": statuses.count("recovered"),
            "n_scenes": len(t.scenes),
            "scenes_missing": sum(1 for s in t.scenes if s.status == "missing"),
            "final_missing": _flag(t.final_status == "missing"),
            "final_words": final.words,
            "final_hits": final.hits,
            "final_hits_per_word": final.hits_per_word,
            **_caption_columns("final", final),
            **_scene_columns(scenes),
            "seg_threshold": threshold,
            "seg_gt_boundaries": len(ep.boundaries()),
            **{f"seg_{k}": v for k, v in at.flat().items() if k != "threshold"},
            **_trace_stats(trace),
        }
        rows.append(row)
        for sp in cell_sweeps[(t.model, t.episode_id, t.condition)]:
            sweep_rows.append(
                {"model": t.model, "episode_id": t.episode_id, "task": ep.task, "condition": t.condition} | sp
            )
        o = outputs.setdefault(t.model, ModelOutputs())
        o.frames_missing += statuses.count("missing")
        present = [x for x, st in zip(texts, statuses, strict=True) if st != "missing"]
        o.frame_captions.extend(present)
        o.cell_distinct.append(len(set(present)) / len(ep.frames))
        o.all_captions.extend([*present, *scene_texts, final_text])
        o.final_hits.append(final.hits)
        audit[key] = {
            "expectation": exp.to_dict(),
            "final": _caption_audit(t.final, t.final_status, final),
            "scenes": [
                {"group": s.group, "frame_indices": list(s.frame_indices), **_caption_audit(s.text, s.status, sc)}
                for s, sc in zip(t.scenes, scenes, strict=True)
            ],
        }
        traces[key] = {
            "trace": [_finite_or_none(float(x)) for x in trace.tolist()],
            "frame_status": statuses,
            "predicted_boundaries": boundaries_at(trace, threshold),
            "true_boundaries": ep.boundaries(),
            "true_phases": labels,
        }
    t_scored = time.perf_counter()
    group_size = _group_size(manifest)
    truths = {e: truth_of(ep.frame_phases) for e, ep in episodes.items()}
    add_out_of_sample(rows, cell_sweeps, thresholds)
    chance_dir = Path(chance_cache) if chance_cache is not None else cache_dir.parent / "chance"
    with ChanceTable(chance_dir) as chance:
        add_chance(rows, truths, chance, group_size)
    for r in rows:
        tr = traces[f"{r['model']}/{r['episode_id']}__{r['condition']}"]
        tr["loo_threshold"] = r["seg_loo_threshold"]
        thr = r["seg_loo_threshold"]
        tr["loo_boundaries"] = boundaries_at(np.array(tr["trace"], dtype=np.float64), thr) if thr is not None else []
        outputs[r["model"]].cells.append((r["n_frames"], tr["loo_boundaries"]))
    t_chance = time.perf_counter()
    bar.update()
    bar.set_description("score: paired statistics")

    rows = _sort_rows(rows, episode_order, conds)
    sweep_rows = _sort_rows(sweep_rows, episode_order, conds)
    skip = (*ID_COLUMNS, "seg_threshold", "threshold")
    aggregate = _group_means(rows, ("model", "task", "condition"), skip, add_all_task=True)
    sweep_aggregate = _group_means(sweep_rows, ("model", "task", "condition", "threshold"), skip, add_all_task=True)
    aggregate = _sort_rows(aggregate, episode_order, conds)
    sweep_aggregate = _sort_rows(sweep_aggregate, episode_order, conds)
    controls = control_correlations(root, episodes, conds)
    comps = list(comparisons) if comparisons is not None else default_comparisons(conds)
    # already in a meaningful order: model, task, comparison (as listed), metric (as listed)
    paired = paired_table(rows, comps, n_boot=n_boot, n_perm=n_perm, seed=seed)
    mark_families(paired, claim_set)
    models = sorted({t.model for t in transcripts})
    verdict_doc = {
        "claims": claim_set.to_dict(),
        "verdicts": verdicts(paired, claim_set, models),
        "warnings": sanity_warnings({m: outputs[m] for m in models}, group_size),
        "group_size": group_size,
    }
    t_stats = time.perf_counter()
    bar.update()
    bar.set_description("score: writing")

    meta = {
        "scores_version": SCORES_VERSION,
        "models": sorted({t.model for t in transcripts}),
        "conditions": conds,
        "episodes": sorted(ids, key=lambda e: episode_order[e]),
        "n_transcripts": len(transcripts),
        # path and threads are left out: neither changes a vector, and a path differs between machines
        "encoder": {k: v for k, v in spec.to_dict().items() if k not in ("path", "threads")}
        | {"dim": int(next(iter(vectors.values())).shape[0]) if vectors else None},
        "lexicons": {task: {"version": lx.version, "sha256": lx.sha256} for task, lx in sorted(lexicons.items())},
        "segmentation": {
            "default_threshold": threshold,
            "thresholds": list(thresholds),
            "tolerances": list(TOLERANCES),
            "iou_thresholds": list(IOU_THRESHOLDS),
            "out_of_sample": LOO_RULE,
            "chance": {
                "metrics": list(CHANCE_METRICS),
                "random": "same number of points at uniformly random positions: exact when at most "
                f"{CHANCE_DRAWS} sets are possible, else the mean of {CHANCE_DRAWS} draws (seed {CHANCE_SEED})",
                "even": "the same number of points evenly spaced",
                "groups": f"points at the edges of the pipeline's frame groups (k = {group_size})",
                "lift": "score - random chance",
                "group_size": group_size,
                "exact_share": chance.exact_share(),
            },
            "boundary": "segmentation point j where cos(caption j, caption j+1) < threshold",
            "missing_frames": MISSING_POLICY,
        },
        "controls": controls,
        "stats": {
            "comparisons": [list(c) for c in comps],
            "metrics": list(PAIRED_METRICS),
            "n_boot": n_boot,
            "n_perm": n_perm,
            "seed": seed,
            "ci": "percentile bootstrap 95%",
            "p_value": "two-sided sign-flip permutation (exact up to 16 pairs)",
            "multiplicity": "primary hypotheses (scores/verdicts.json): Holm per model; every other paired test: "
            "exploratory, Benjamini-Hochberg q-value per model",
        },
    }
    timing = {
        "load_s": t_loaded - t_start,
        "embed_s": t_embedded - t_loaded,
        "score_segment_s": t_scored - t_embedded,
        "chance_s": t_chance - t_scored,
        "chance": {"computed": chance.computed, "cached": chance.cached},
        "stats_s": t_stats - t_chance,
        "embeddings": embedder.stats.to_dict(),
    }
    judged = None
    if judge is not None:
        judged = judge_table(judge, finals)
        timing["judge_s"] = time.perf_counter() - t_stats
    tables = ScoreTables(
        rows, aggregate, sweep_rows, sweep_aggregate, paired, audit, traces, meta, timing, judged, verdict_doc
    )
    if write:
        score_settings = {k: meta[k] for k in ("encoder", "segmentation", "stats")} | {
            "judge": judged["backend"] if judged else None
        }
        inputs = score_inputs(run_dir, manifest, transcript_files, root, ids, score_settings, meta["lexicons"])
        write_score_tables(run_dir, tables, inputs)
    bar.update()
    bar.close()
    tables.timing["total_s"] = time.perf_counter() - t_start
    return tables


def judge_table(backend, finals: list[tuple[str, CaptionScore, str, Episode, str]]) -> dict:
    """Grade the final captions with a judge (a CachedBackend, or a Backend) and compare with the rubric."""
    from vlmproprio.scoring import judge_agreement, judge_captions

    verdicts = judge_captions(backend, [(text, ep, cond) for _, _, text, ep, cond in finals])
    identity = backend.identity if isinstance(getattr(backend, "identity", None), dict) else backend.identity()
    return {
        "backend": dict(identity),
        "agreement": judge_agreement([s for _, s, _, _, _ in finals], verdicts),
        "verdicts": {key: v.to_dict() for (key, _, _, _, _), v in zip(finals, verdicts, strict=True)},
    }


def control_correlations(root: Path, episodes: dict[str, Episode], conditions: Sequence[str]) -> dict:
    """Per condition with numeric state (controls and the paper's own-state conditions alike), per task and
    state dimension: the mean, min and max over episodes of the Pearson r between the numbers the prompts
    showed and the episode's true states (conditions.state_correlations) -- how much a control still tells."""
    from vlmproprio.conditions import STATE_DIMENSIONS, get_condition, state_correlations

    known = [c for c in conditions if c in (*STATE_CONDITIONS, *CONTROL_CONDITIONS)]
    numeric = [get_condition(c) for c in known if get_condition(c).numeric_state]
    if not numeric:
        return {}
    peers = list(episodes.values())
    if any(c.source in ("shuffled", "permuted") for c in numeric):
        # partners come from every episode of the fixtures, as in the run (runner.run)
        loaded = set(episodes)
        peers += [e for e in load_episodes(root, verify=False) if e.episode_id not in loaded]
    out: dict = {}
    for cond in numeric:
        per_task: dict[str, dict[str, list[float]]] = {}
        for ep in sorted(episodes.values(), key=lambda e: e.episode_id):
            rs = state_correlations(ep, cond, peers)
            for task in (ep.task, "all"):
                for dim, r in rs.items():
                    if r is not None:
                        per_task.setdefault(task, {}).setdefault(dim, []).append(r)
        out[cond.name] = {
            task: {
                dim: {"mean_r": math.fsum(v) / len(v), "min_r": min(v), "max_r": max(v), "n": len(v)}
                for dim in STATE_DIMENSIONS
                if (v := dims.get(dim))
            }
            for task, dims in per_task.items()
        }
    return out


LOO_RULE = (
    "leave one episode out: for each episode, the threshold with the highest mean boundary F1 (+-1 frame) over "
    "the other episodes of the same task, model and condition (ties: the lowest threshold), applied to it"
)


def _group_size(manifest: dict) -> int:
    """The pipeline's frame-group size k from run.json (every model of a run must agree; default 5)."""
    sizes = {
        m.get("pipeline", {}).get("k")
        for m in manifest.get("models", [])
        if isinstance(m, dict) and isinstance(m.get("pipeline"), dict)
    }
    sizes.discard(None)
    if len(sizes) > 1:
        raise ScoreRunError(f"run.json: models use different frame-group sizes {sorted(sizes)}; score them apart")
    return int(next(iter(sizes))) if sizes else DEFAULT_GROUP_SIZE


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


# ---------------------------------------------------------------------------------------------- writing


def _json_safe(obj):
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: _json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_json_safe(v) for v in obj]
    return obj


def dumps_json(obj) -> str:
    return json.dumps(_json_safe(obj), indent=1, ensure_ascii=False, allow_nan=False) + "\n"


def dumps_csv(rows: list[dict]) -> str:
    cols: list[str] = []
    for r in rows:
        cols += [k for k in r if k not in cols]
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(cols)
    for r in rows:
        w.writerow(["" if r.get(c) is None else repr(r[c]) if isinstance(r[c], float) else r[c] for c in cols])
    return buf.getvalue()


def write_score_tables(run_dir: str | Path, tables: ScoreTables, inputs: dict | None = None) -> list[Path]:
    """Write the tables as one generation of RUN_DIR/scores/ (see ``swap_in_generation``), stamped with
    ``inputs`` (``score_inputs``: what they were computed from)."""
    files = {
        "rows.json": dumps_json(tables.rows),
        "rows.csv": dumps_csv(tables.rows),
        "aggregate.json": dumps_json(tables.aggregate),
        "aggregate.csv": dumps_csv(tables.aggregate),
        "sweep.json": dumps_json(tables.sweep),
        "sweep.csv": dumps_csv(tables.sweep),
        "sweep_aggregate.json": dumps_json(tables.sweep_aggregate),
        "sweep_aggregate.csv": dumps_csv(tables.sweep_aggregate),
        "paired.json": dumps_json(tables.paired),
        "paired.csv": dumps_csv(tables.paired),
        "audit.json": dumps_json(tables.audit),
        "traces.json": dumps_json(tables.traces),
        "meta.json": dumps_json(tables.meta),
        "verdicts.json": dumps_json(tables.verdicts),
        "timing.json": dumps_json(tables.timing),
    }
    if tables.judge is not None:
        files["judge.json"] = dumps_json(tables.judge)
    return swap_in_generation(Path(run_dir), files, inputs or {})


# ---------------------------------------------------------------------------------------------- score generations
#
# RUN_DIR/scores/ is written as one generation: every file goes into a new hidden folder beside it, with
# stamp.json (the digest of exactly the transcripts, run configuration, fixtures' ground truth, settings and
# code version the scores come from, and the sha256 of each score file); the folder then replaces scores/ by
# rename. A reader sees the old generation, the new one, or none -- never a mix -- and the report refuses
# scores whose stamp no longer matches the run (``check_scores``).

STAMP_FILE = "stamp.json"
GENERATION_PREFIX = ".scores-"  # .scores-new-*, .scores-old-*: removed by the next score of the run


class StaleScoresError(ScoreRunError):
    """Scores that do not match the run they sit in; the message says how to re-score."""


def _digest(obj) -> str:
    import hashlib

    return hashlib.sha256(json.dumps(obj, sort_keys=True, separators=(",", ":")).encode("utf-8")).hexdigest()


def run_transcript_files(run_dir: Path, manifest: dict) -> list[Path]:
    """Exactly the transcripts of the configuration recorded in run.json; a one-line error when some are
    missing (an unfinished run) or when others lie there (left by an older run). Without run.json, or with one
    that lists no models: every transcript in the folder."""
    from vlmproprio.runner import recorded_transcripts

    root = run_dir / "transcripts"
    on_disk = sorted(root.glob("*/*.json"))
    expected = recorded_transcripts(run_dir, manifest)
    if expected is None:
        return on_disk
    missing = [p for p in expected if not p.is_file()]
    if missing:
        raise ScoreRunError(
            f"{run_dir}: the run recorded in run.json is not finished ({len(missing)} of {len(expected)} "
            f"transcripts missing, e.g. {missing[0].relative_to(run_dir)}); finish it by running the same "
            "`vlmproprio run --model MODEL --out RUN_DIR` command again (answers already made are cached)"
        )
    extra = sorted(set(on_disk) - set(expected))
    if extra:
        raise ScoreRunError(
            f"{extra[0]}: not part of the run recorded in {run_dir / 'run.json'} ({len(extra)} such transcript(s), "
            "left by another run); move them out of the run folder, or run into a new --out"
        )
    return expected


def run_configuration(manifest: dict) -> dict:
    """The part of run.json that decides what the transcripts are (not status, times, counts or versions)."""
    models = [
        {k: m.get(k) for k in ("name", "slug", "pipeline")} for m in manifest.get("models", []) if isinstance(m, dict)
    ]
    return {"episodes": manifest.get("episodes"), "conditions": manifest.get("conditions"), "models": models}


def code_version() -> dict:
    from vlmproprio import __version__

    return {"vlmproprio": __version__, "scores_version": SCORES_VERSION}


def transcripts_digest(run_dir: Path, files: Sequence[Path]) -> str:
    """The digest of what the transcripts say, leaving out how it was obtained (``requests``: cache hits and
    latencies; ``timing``), which a resumed or repeated run changes without changing a word."""
    from vlmproprio.io import load_json

    said = {}
    for p in files:
        d = load_json(p, error=ScoreRunError)
        said[p.relative_to(run_dir).as_posix()] = (
            {k: v for k, v in d.items() if k not in ("requests", "timing")} if isinstance(d, dict) else d
        )
    return _digest(said)


def score_inputs(
    run_dir: Path, manifest: dict, files: Sequence[Path], fixtures: Path, episode_ids, settings: dict, lexicons: dict
) -> dict:
    """What a generation of scores is computed from, each part as a digest, and their digest (the stamp)."""
    from vlmproprio.episodes import read_manifest

    try:
        fixture_files = read_manifest(fixtures)
        truth = {e: fixture_files.get(f"episodes/{e}/episode.json") for e in episode_ids}
    except VlmproprioError:  # scored with verify=False on fixtures without a manifest
        truth = {}
    parts = {
        "transcripts": transcripts_digest(run_dir, files),
        "run_configuration": _digest(run_configuration(manifest)),
        "ground_truth": _digest(truth),
        "settings": _digest(settings),
        "lexicons": _digest(lexicons),
        "code": code_version(),
    }
    return {"stamp": _digest(parts), "inputs": parts}


def _remove_leftovers(run_dir: Path) -> None:
    import shutil

    for p in run_dir.glob(GENERATION_PREFIX + "*"):
        shutil.rmtree(p, ignore_errors=True)


def swap_in_generation(run_dir: Path, files: dict[str, str], inputs: dict) -> list[Path]:
    """Write ``files`` (name -> text) and stamp.json into a new folder and swap it in for RUN_DIR/scores/."""
    import os
    import shutil
    import uuid

    from vlmproprio.io import WriteError, writing

    _remove_leftovers(run_dir)  # a score killed before its swap left these
    tag = f"{os.getpid()}-{uuid.uuid4().hex[:8]}"
    new, old, out = (
        run_dir / f"{GENERATION_PREFIX}new-{tag}",
        run_dir / f"{GENERATION_PREFIX}old-{tag}",
        run_dir / "scores",
    )
    try:
        with writing(out, "write scores into"):
            new.mkdir(parents=True)
        try:
            written = {name: atomic_write_text(new / name, text) for name, text in files.items()}
        except WriteError as exc:  # name the folder the user knows, not the hidden one
            raise WriteError(str(exc).replace(str(new), str(out))) from exc.__cause__
        # timing.json differs between runs by nature: leaving it out keeps stamp.json byte-identical too
        stamp = {**inputs, "files": {k: v for k, v in sorted(written.items()) if k != "timing.json"}}
        atomic_write_text(new / STAMP_FILE, dumps_json(stamp))
        with writing(out, "replace"):
            if out.exists():
                out.rename(old)
            new.rename(out)
    except BaseException:
        shutil.rmtree(new, ignore_errors=True)
        if old.exists() and not out.exists():
            old.rename(out)  # put the previous generation back
        raise
    shutil.rmtree(old, ignore_errors=True)
    return [out / name for name in files]


def check_scores(run_dir: str | Path, names: Sequence[str] = ()) -> dict:
    """The stamp of RUN_DIR/scores/ after checking it still matches the run: the same transcripts, run
    configuration and code version, and score files ``names`` (default: all) as they were written.
    StaleScoresError, naming the command that fixes it, otherwise."""
    from vlmproprio.io import load_json, sha256_file

    run_dir = Path(run_dir)
    out = run_dir / "scores"
    fix = f"re-score the run: `vlmproprio score {run_dir}`"
    try:
        stamp = load_json(out / STAMP_FILE, error=StaleScoresError)
    except FileNotFoundError:
        raise StaleScoresError(
            f"{out}: scores are out of date: no {STAMP_FILE} (scores from an older version or incomplete); {fix}"
        ) from None
    if not isinstance(stamp, dict) or not isinstance(stamp.get("inputs"), dict):
        raise StaleScoresError(f"{out / STAMP_FILE}: scores are out of date: not a score stamp; {fix}")
    recorded, files = stamp["inputs"], stamp.get("files", {})
    if recorded.get("code") != code_version():
        raise StaleScoresError(
            f"{out}: scores are out of date: scored by {recorded.get('code')}, this is {code_version()}; {fix}"
        )
    manifest = read_run_manifest(run_dir)
    try:
        current = run_transcript_files(run_dir, manifest)
    except ScoreRunError as exc:
        raise StaleScoresError(f"{out}: scores are out of date: the run no longer matches them ({exc})") from None
    if recorded.get("run_configuration") != _digest(run_configuration(manifest)):
        raise StaleScoresError(
            f"{out}: scores are out of date: run.json records another configuration than the one scored; {fix}"
        )
    if recorded.get("transcripts") != transcripts_digest(run_dir, current):
        raise StaleScoresError(f"{out}: scores are out of date: transcripts changed since the run was scored; {fix}")
    for name in names or list(files):
        path = out / name
        if name not in files or not path.is_file() or sha256_file(path) != files[name]:
            raise StaleScoresError(
                f"{path}: scores are out of date: not the file of this generation of scores (changed or mixed); {fix}"
            )
    return stamp
