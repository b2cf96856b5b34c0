"""Score each (model, episode, condition) cell: the rubric on its final and scene captions, segmentation of its
frame captions at the fixed threshold and over the sweep, its audit and its similarity trace."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field, fields
from typing import NamedTuple

import numpy as np

from vlmproprio.episodes import Episode
from vlmproprio.evaluation import metrics
from vlmproprio.evaluation.captions import Cell, EmbeddedCaptions
from vlmproprio.evaluation.inputs import RunInputs
from vlmproprio.evaluation.metrics import CellView, computed_columns
from vlmproprio.parallel import map_groups
from vlmproprio.parsing import HEAVY_CLASSES
from vlmproprio.sanity import FinalCell, ModelOutputs, same_sentence
from vlmproprio.scoring import (
    ITEMS,
    CaptionScore,
    Expectation,
    Lexicon,
    TextAnalysis,
    analyse_text,
    expectation_for,
    load_lexicon,
    score_text,
)
from vlmproprio.segmentation import CosineCache, SweepPoint, boundaries_at, cosine_trace, sweep
from vlmproprio.transcripts import Transcript, cell_key, frames_missing_by_problem


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


class FinalCaption(NamedTuple):
    """A cell's final caption as the judge grades it (evaluation.judge.judge_table)."""

    key: str  # transcripts.cell_key
    score: CaptionScore
    text: str
    episode: Episode
    condition: str


@dataclass
class CellScores:
    """Every cell's row, sweep and trace, the audit of its captions, and what the sanity checks and the judge
    read, in the transcripts' order."""

    rows: list[dict] = field(default_factory=list)
    sweep_rows: list[dict] = field(default_factory=list)
    cell_sweeps: dict[Cell, list[dict]] = field(default_factory=dict)  # the sweep of each cell (out-of-sample)
    audit: dict[str, dict] = field(default_factory=dict)
    traces: dict[str, dict] = field(default_factory=dict)
    outputs: dict[str, ModelOutputs] = field(default_factory=dict)
    lexicons: dict[str, Lexicon] = field(default_factory=dict)
    finals: list[FinalCaption] = field(default_factory=list)


@dataclass
class _Captions:
    """One cell's captions as scored: a missing final or scene caption is an empty text."""

    final_text: str
    final: CaptionScore
    scene_texts: list[str]
    scenes: list[CaptionScore]


@dataclass
class _Shared:
    """What cells share, computed once per run: a model repeats its captions and its traces (the same text
    scores the same against the same episode; the same trace segments the same), and every cell of an
    episode has the same expectation. Each memo holds exactly what the computation would return again."""

    expectations: dict[str, Expectation] = field(default_factory=dict)  # by episode
    captions: dict[tuple[str, str], CaptionScore] = field(default_factory=dict)  # by (text, episode)
    analyses: dict[tuple[str, str], TextAnalysis] = field(default_factory=dict)  # by (text, task): its lexicon
    sweeps: dict[tuple[bytes, str], list[SweepPoint]] = field(default_factory=dict)  # by (trace bits, episode)
    cosines: CosineCache = field(default_factory=CosineCache)

    def expectation(self, ep: Episode, lex: Lexicon) -> Expectation:
        if ep.episode_id not in self.expectations:
            self.expectations[ep.episode_id] = expectation_for(ep, lex)
        return self.expectations[ep.episode_id]

    def score(self, text: str, ep: Episode, exp: Expectation, lex: Lexicon) -> CaptionScore:
        key = (text, ep.episode_id)
        if key not in self.captions:
            # the text's tokens and matches depend on the lexicon alone: shared by every episode of the task
            analysis = self.analyses.get((text, ep.task))
            if analysis is None:
                analysis = self.analyses[(text, ep.task)] = analyse_text(text, lex)
            self.captions[key] = score_text(text, exp, lex, analysis)
        return self.captions[key]

    def sweep(self, trace: np.ndarray, ep: Episode, thresholds: Sequence[float]) -> list[SweepPoint]:
        key = (trace.tobytes(), ep.episode_id)  # the exact bits: NaN gaps and -0.0 included
        if key not in self.sweeps:
            self.sweeps[key] = sweep(trace, ep.frame_phases, thresholds)
        return self.sweeps[key]


def _score_captions(t: Transcript, ep: Episode, exp: Expectation, lex: Lexicon, shared: _Shared) -> _Captions:
    final_text = t.final if t.final_status != "missing" else ""
    scene_texts = [(s.text if s.status != "missing" else "") for s in t.scenes]
    return _Captions(
        final_text,
        shared.score(final_text, ep, exp, lex),
        scene_texts,
        [shared.score(x, ep, exp, lex) for x in scene_texts],
    )


def _row(
    t: Transcript, ep: Episode, c: _Captions, statuses: list[str], at: SweepPoint, trace: np.ndarray, threshold: float
) -> dict:
    return {
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
        "final_words": c.final.words,
        "final_hits": c.final.hits,
        "final_hits_per_word": c.final.hits_per_word,
        **_caption_columns("final", c.final),
        **_scene_columns(c.scenes),
        "seg_threshold": threshold,
        "seg_gt_boundaries": len(ep.boundaries()),
        **{f"seg_{k}": v for k, v in at.flat().items() if k != "threshold"},
        **_trace_stats(trace),
        **_computed(CellView(t, ep, c.final, c.scenes, statuses, at, trace, threshold)),
    }


def _computed(view: CellView) -> dict:
    """The columns of the metric table's metrics that bring their own function (read at call time, so a table
    extended at run time counts too)."""
    table = metrics.METRICS
    return computed_columns(view, table) if any(m.compute is not None for m in table) else {}


def _add_outputs(
    o: ModelOutputs, t: Transcript, ep: Episode, texts: list[str], statuses: list[str], c: _Captions, at: SweepPoint
) -> None:
    o.frames_missing += statuses.count("missing")
    o.frames_heavy += sum(
        1
        for f in t.frames
        if 0 <= f.frame_index < len(statuses)
        and statuses[f.frame_index] != "missing"
        and HEAVY_CLASSES.intersection(f.removed)
    )
    o.answer_problems += [r.problem for r in t.requests if r.problem]
    o.frames_missing_problem += frames_missing_by_problem(t)
    present = [x for x, st in zip(texts, statuses, strict=True) if st != "missing"]
    o.frame_captions.extend(present)
    o.cell_distinct.append(len(set(present)) / len(ep.frames))
    o.all_captions.extend([*present, *c.scene_texts, c.final_text])
    o.final_hits.append(c.final.hits)
    o.finals.append(
        FinalCell(
            task=ep.task,
            condition=t.condition,
            truth=str(ep.target_bin.index) if ep.target_bin is not None else "",
            trajectory_correct=bool(c.final.item("trajectory").correct),
            is_instruction=same_sentence(c.final_text, ep.instruction),
            boundary_f1=at.prf[1].f1 if 1 in at.prf else None,
        )
    )


def _audit(t: Transcript, exp: Expectation, c: _Captions) -> dict:
    return {
        "expectation": exp.to_dict(),
        "final": _caption_audit(t.final, t.final_status, c.final),
        "scenes": [
            {"group": s.group, "frame_indices": list(s.frame_indices), **_caption_audit(s.text, s.status, sc)}
            for s, sc in zip(t.scenes, c.scenes, strict=True)
        ],
    }


def _trace(trace: np.ndarray, statuses: list[str], ep: Episode, threshold: float) -> dict:
    return {
        "trace": [_finite_or_none(float(x)) for x in trace.tolist()],
        "frame_status": statuses,
        "predicted_boundaries": boundaries_at(trace, threshold),
        "true_boundaries": ep.boundaries(),
        "true_phases": ep.frame_phases,
    }


def _score_each(
    transcripts: Sequence[Transcript],
    inputs: RunInputs,
    captions: EmbeddedCaptions,
    thresholds: Sequence[float],
    threshold: float,
) -> list[CellScores]:
    """Each transcript's cell scores on its own (one CellScores each), with what cells share computed once."""
    shared = _Shared()
    lexicons: dict[str, Lexicon] = {}
    scored = []
    for t in transcripts:
        out = CellScores()
        ep = inputs.episodes[t.episode_id]
        cell = (t.model, t.episode_id, t.condition)
        key = cell_key(*cell)
        lex = lexicons.setdefault(ep.task, load_lexicon(ep.task))
        out.lexicons[ep.task] = lex
        exp = shared.expectation(ep, lex)
        c = _score_captions(t, ep, exp, lex, shared)
        out.finals.append(FinalCaption(key, c.final, c.final_text, ep, t.condition))
        texts, statuses = captions.frames[cell]
        vectors = [captions.vectors[x] if s != "missing" else None for x, s in zip(texts, statuses, strict=True)]
        trace = cosine_trace(vectors, shared.cosines)
        points = shared.sweep(trace, ep, (*thresholds, threshold))
        out.cell_sweeps[cell] = [sp.flat() for sp in points[:-1]]
        out.rows.append(_row(t, ep, c, statuses, points[-1], trace, threshold))
        for sp in out.cell_sweeps[cell]:
            out.sweep_rows.append(
                {"model": t.model, "episode_id": t.episode_id, "task": ep.task, "condition": t.condition} | sp
            )
        _add_outputs(out.outputs.setdefault(t.model, ModelOutputs()), t, ep, texts, statuses, c, points[-1])
        out.audit[key] = _audit(t, exp, c)
        out.traces[key] = _trace(trace, statuses, ep, threshold)
        scored.append(out)
    return scored


def _merge(parts: Sequence[CellScores], episodes: dict[str, Episode]) -> CellScores:
    """The scores of consecutive transcripts as one CellScores, as a single loop over all of them builds it."""
    out = CellScores()
    for part in parts:
        for f in fields(CellScores):
            mine, theirs = getattr(out, f.name), getattr(part, f.name)
            if f.name == "finals":  # a worker's came back with copies of the episodes: this process's own again
                mine += [final._replace(episode=episodes[final.episode.episode_id]) for final in theirs]
            elif f.name == "outputs":
                for model, o in theirs.items():
                    mine.setdefault(model, ModelOutputs()).extend(o)
            elif isinstance(mine, list):
                mine += theirs
            elif isinstance(mine, dict):  # by cell (one per transcript), or lexicons by task: the first one kept
                for k, v in theirs.items():
                    mine.setdefault(k, v)
            else:
                raise TypeError(f"CellScores.{f.name}: no rule to merge a {type(mine).__name__}")
    return out


# below this many transcripts per worker a forked worker costs more than it saves (one cell: ~4 ms)
MIN_CELLS_PER_WORKER = 24


def score_cells(
    inputs: RunInputs, captions: EmbeddedCaptions, thresholds: Sequence[float], threshold: float, workers: int = 1
) -> CellScores:
    """Score every transcript of the run (the rubric, the trace, the sweep and the fixed threshold); with
    ``workers`` > 1, the episodes dealt out to forked processes (vlmproprio.parallel), the same result."""
    each = map_groups(
        lambda chunk: _score_each(chunk, inputs, captions, thresholds, threshold),
        inputs.transcripts,
        workers,
        lambda t: t.episode_id,  # an episode's cells share their expectation and many texts and traces
        min_chunk=MIN_CELLS_PER_WORKER,
        what="transcripts",
    )
    return _merge(each, inputs.episodes)
