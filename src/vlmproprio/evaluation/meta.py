"""scores/meta.json: what a score was computed with (encoder, lexicons, segmentation and statistics settings) and
how each of its numbers is defined, so the scores can be read without the code."""

from __future__ import annotations

from collections import Counter

from vlmproprio.evaluation.captions import EmbeddedCaptions
from vlmproprio.evaluation.chance import Baselines
from vlmproprio.evaluation.definitions import PAIRED_METRICS, SCORES_VERSION, ScoreSettings
from vlmproprio.evaluation.inputs import RunInputs
from vlmproprio.evaluation.out_of_sample import LOO_RULE
from vlmproprio.evaluation.statistics import Statistics
from vlmproprio.parsing import HEAVY_CLASSES, RECOVERY_CLASSES
from vlmproprio.scoring import Lexicon
from vlmproprio.segmentation import CHANCE_DRAWS, CHANCE_METRICS, CHANCE_SEED, IOU_THRESHOLDS, TOLERANCES
from vlmproprio.stats import DEFAULT_MAX_EXACT
from vlmproprio.transcripts import Transcript, answer_problems

MISSING_POLICY = (
    "A frame caption with status 'missing', an empty text, or no entry in the transcript is a gap: the trace "
    "keeps its place and every pair touching it is NaN, which never makes a boundary. A missing final or scene "
    "caption scores as an empty text (nothing mentioned, zero words). 'recovered' captions are used as they are."
)


def _encoder(captions: EmbeddedCaptions) -> dict:
    # path and threads are left out: neither changes a vector, and a path differs between machines
    vectors = captions.vectors
    return {k: v for k, v in captions.encoder.items() if k not in ("path", "threads")} | {
        "dim": int(next(iter(vectors.values())).shape[0]) if vectors else None
    }


def _segmentation(settings: ScoreSettings, baselines: Baselines) -> dict:
    group_size = baselines.group_size
    return {
        "default_threshold": settings.threshold,
        "thresholds": list(settings.thresholds),
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
            "exact_share": baselines.exact_share,
        },
        "boundary": "segmentation point j where cos(caption j, caption j+1) < threshold",
        "missing_frames": MISSING_POLICY,
    }


def _stats(settings: ScoreSettings, stats: Statistics) -> dict:
    return {
        "comparisons": [list(c) for c in stats.comparisons],
        "metrics": list(PAIRED_METRICS),
        "n_boot": settings.n_boot,
        "n_perm": settings.n_perm,
        "seed": settings.seed,
        "ci": "percentile bootstrap 95%",
        "p_value": f"two-sided sign-flip permutation, exact over every sign pattern up to {DEFAULT_MAX_EXACT} "
        f"pairs, above that Monte Carlo, {settings.n_perm} patterns, p >= 1/{settings.n_perm + 1}",
        "p_methods": dict(sorted(Counter(r["method"] for r in stats.paired).items())),
        "multiplicity": "primary hypotheses (scores/verdicts.json): Holm per model; every other paired test: "
        "exploratory, Benjamini-Hochberg q-value per model",
    }


CAPTION_KINDS = ("frames", "scenes", "final")


def _model_parsing(transcripts: list[Transcript]) -> dict:
    """One model's parse audit: its answers, their reasoning (the server's field and the text's blocks) and the
    answers that came back without a plain answer, by class (chat.ANSWER_PROBLEMS), its frame captions by status (``heavy``: found
    by position, not read from a label), and per recovery class the present captions of each kind it took."""
    captions: dict[str, list[tuple[str, tuple[str, ...]]]] = {kind: [] for kind in CAPTION_KINDS}
    requests = [r for t in transcripts for r in t.requests]
    for t in transcripts:
        captions["frames"] += [(f.status, f.removed) for f in t.frames]
        captions["scenes"] += [(s.status, s.removed) for s in t.scenes]
        captions["final"].append((t.final_status, t.final_removed))
    frames = captions["frames"]
    present = {kind: [removed for status, removed in got if status != "missing"] for kind, got in captions.items()}
    recoveries = {
        cls: {kind: sum(cls in removed for removed in present[kind]) for kind in CAPTION_KINDS}
        for cls in RECOVERY_CLASSES
    }
    return {
        "answers": len(requests),
        "answers_with_reasoning": sum(1 for r in requests if r.reasoning),
        "reasoning_chars": sum(len(r.reasoning) for r in requests),
        "answer_problems": answer_problems(transcripts),
        "frames": {
            "captions": len(frames),
            "recovered": sum(1 for status, _ in frames if status == "recovered"),
            "missing": sum(1 for status, _ in frames if status == "missing"),
            "heavy": sum(1 for removed in present["frames"] if HEAVY_CLASSES.intersection(removed)),
        },
        "recoveries": {cls: n for cls, n in recoveries.items() if any(n.values())},
    }


def parsing_meta(transcripts: list[Transcript]) -> dict:
    """What meta.json records of how the answers were parsed, per model (recoveries: only classes met)."""
    models = sorted({t.model for t in transcripts})
    return {
        "heavy_classes": sorted(HEAVY_CLASSES),
        "models": {m: _model_parsing([t for t in transcripts if t.model == m]) for m in models},
    }


def score_meta(
    inputs: RunInputs,
    captions: EmbeddedCaptions,
    lexicons: dict[str, Lexicon],
    baselines: Baselines,
    controls: dict,
    stats: Statistics,
    settings: ScoreSettings,
) -> dict:
    return {
        "scores_version": SCORES_VERSION,
        "models": inputs.models,
        "conditions": inputs.conditions,
        "episodes": sorted(inputs.episode_ids, key=lambda e: inputs.episode_order[e]),
        "n_transcripts": len(inputs.transcripts),
        "encoder": _encoder(captions),
        "lexicons": {task: {"version": lx.version, "sha256": lx.sha256} for task, lx in sorted(lexicons.items())},
        "segmentation": _segmentation(settings, baselines),
        "controls": controls,
        "stats": _stats(settings, stats),
        "parsing": parsing_meta(inputs.transcripts),
    }
