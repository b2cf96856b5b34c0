"""Sanity checks of a model's outputs: warnings that say when a model's differences between conditions cannot be
read as "the model used the state".

Per model: near-constant frame captions, missing captions, answers with no caption in them, gibberish (many
non-words), captions made of numbers (the state echoed), off-task final captions (nothing the task's lexicon
knows), heavy recovery by the parser, segmentation points that fall on the edges of the pipeline's frame groups
or keep time at any other fixed period, and leaks (scores a model cannot reach from what it was shown). Every
threshold is documented in docs/metrics.md. ``vlmproprio.verdicts`` puts these beside the verdicts.
"""

from __future__ import annotations

import math
import re
from collections import Counter
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field, fields

# sanity thresholds (docs/metrics.md explains each)
# distinct frame captions / frames of a cell (episode x condition), averaged over cells, below this: near-constant.
# Per cell, not over the run: a templated captioner repeats its sentences across 22 episodes yet changes them
# within every episode (reference: 0.43, reference-state: 0.30), while a model that ignores its input writes one
# or two texts per episode (tiny-qwen2-vl: 0.07); a real VLM's captions are nearly all distinct (~1).
MIN_DISTINCT_PER_CELL = 0.15
MAX_MISSING_FRAME_SHARE = 0.20  # frame captions missing (unparsed or empty), above this: warn
MAX_NON_WORD_SHARE = 0.20  # caption tokens that are no word or number, above this: gibberish
MAX_NO_HIT_FINAL_SHARE = 0.80  # final captions without a single lexicon hit, above this: off-task
_NUMBER_RE = re.compile(r"[+-]?\d+(?:[.,]\d+)*%?")
# present frame captions found by position rather than read from a label (parsing.HEAVY_CLASSES), at least
# this share: the captions may sit on the wrong frames, so the segmentation reads the parser's guess
MIN_HEAVY_RECOVERY_SHARE = 0.20
# frame captions missing because the server's answers held none (refusals, tool calls, filters, ...), at least
# this share of all frame captions: most of the model's captions were never written
MIN_NO_ANSWER_SHARE = 0.50
# leaks and ceilings: scores a model cannot reach from what it is shown. Without state ("none", images only) the
# varying part of the trajectory (the target compartment among four) right in at least this share of a task's
# episodes; boundaries at +-1 frame with at least this mean F1; final captions that are the ground-truth
# instruction word for word (of at least MIN_LEAK_WORDS words) in at least this share of cells
LEAK_TRAJECTORY_SHARE = 0.9
LEAK_MIN_EPISODES = 4
LEAK_BOUNDARY_F1 = 0.9
LEAK_INSTRUCTION_SHARE = 0.25
MIN_LEAK_WORDS = 6
NO_STATE_CONDITIONS = ("none",)
# frame captions made mostly of numbers: the model copies the state instead of describing the motion
STATE_ECHO_SHARE = 0.5
GROUP_EDGE_RATIO = 1.5  # points on group edges / expected under uniform placement, at least this ...
GROUP_EDGE_P = 0.001  # ... and a one-sided binomial p-value below this
# every fixed schedule up to this period (and every offset) is checked the same way ('periodic'), at a ratio of
# at least PERIODIC_RATIO and the p-value corrected for the number of schedules: a metronome is caught at any
# period; real boundaries (phases of 3-15 frames, different in every episode) are not periodic
MAX_PERIOD = 12
PERIODIC_RATIO = 2.0
# ... and most points on that one schedule: episodes of a task share their phase structure, so a model whose points
# follow the episodes puts some of them at the same frames, and a lattice through those frames holds a few of them
PERIODIC_MIN_SHARE = 0.6
WORD_RE = re.compile(r"^(?:[A-Za-z]+(?:['-][A-Za-z]+)*|[+-]?\d+(?:[.,]\d+)*%?)$")
STRIP = ".,;:!?()[]{}\"'`*"


@dataclass(frozen=True)
class FinalCell:
    """What the leak checks read of one cell (episode x condition)."""

    task: str
    condition: str
    truth: str  # the episode's trajectory ground truth that varies within its task (a compartment), or ""
    trajectory_correct: bool
    is_instruction: bool  # the final caption is the episode's ground-truth instruction, word for word
    boundary_f1: float | None  # boundary F1 (+-1 frame) at the fixed threshold


def _words(text: str) -> list[str]:
    return re.findall(r"[a-z0-9]+", (text or "").lower())


def same_sentence(caption: str, instruction: str) -> bool:
    """``caption`` says ``instruction`` word for word (case and punctuation aside), for an instruction long enough
    (``MIN_LEAK_WORDS``) that a model does not write it by chance."""
    words = _words(instruction)
    return len(words) >= MIN_LEAK_WORDS and _words(caption) == words


@dataclass
class ModelOutputs:
    """What the sanity checks read about one model's run."""

    frame_captions: list[str] = field(default_factory=list)  # every present frame caption, all cells
    cell_distinct: list[float] = field(default_factory=list)  # per cell: distinct present frame captions / frames
    frames_missing: int = 0
    frames_heavy: int = 0  # present frame captions that needed a heavy recovery
    # missing frame captions whose Process 1 answer came back without a plain answer (chat.ANSWER_PROBLEMS)
    frames_missing_problem: int = 0
    answer_problems: list[str] = field(default_factory=list)  # the class of each request that had one
    all_captions: list[str] = field(default_factory=list)  # frame, scene and final captions
    final_hits: list[int] = field(default_factory=list)  # lexicon hits of each final caption
    # per cell: (number of frames, segmentation points at the reported threshold)
    cells: list[tuple[int, list[int]]] = field(default_factory=list)
    finals: list[FinalCell] = field(default_factory=list)

    def extend(self, later: ModelOutputs) -> None:
        """Add what ``later`` read from the cells after these (lists in order, counts summed)."""
        for f in fields(self):
            mine, theirs = getattr(self, f.name), getattr(later, f.name)
            if isinstance(mine, list):
                mine += theirs
            elif type(mine) is int:
                setattr(self, f.name, mine + theirs)
            else:
                raise TypeError(f"ModelOutputs.{f.name}: no rule to add a {type(mine).__name__}")


def _token_share(texts: Iterable[str], counts) -> tuple[float, int]:
    """Share of whitespace tokens (punctuation stripped) for which ``counts`` holds, and the number of tokens;
    a model repeats its captions across conditions, so each distinct text is split once."""
    total = hits = 0
    for t, n in Counter(texts).items():
        for tok in (t or "").split():
            w = tok.strip(STRIP)
            if w:
                total += n
                hits += n * bool(counts(w))
    return (hits / total if total else 0.0), total


def non_word_share(texts: Iterable[str]) -> tuple[float, int]:
    """Share of whitespace tokens (punctuation stripped) that are neither a word of letters nor a number."""
    return _token_share(texts, lambda w: not WORD_RE.match(w))


def number_share(texts: Iterable[str]) -> float:
    """Share of whitespace tokens (punctuation stripped) that are numbers: captions that echo the state."""
    return _token_share(texts, _NUMBER_RE.fullmatch)[0]


def binomial_tail(k: int, n: int, p: float) -> float:
    """P(X >= k) for X ~ Binomial(n, p): the one-sided binomial test's p-value (summed in log space, no scipy)."""
    if k <= 0:
        return 1.0
    if p <= 0.0:
        return 0.0
    if p >= 1.0:
        return 1.0
    logs = [
        math.lgamma(n + 1) - math.lgamma(i + 1) - math.lgamma(n - i + 1) + i * math.log(p) + (n - i) * math.log1p(-p)
        for i in range(k, n + 1)
    ]
    top = max(logs)
    return min(1.0, math.exp(top) * math.fsum(math.exp(x - top) for x in logs))


def group_edge_excess(cells: Sequence[tuple[int, Sequence[int]]], group_size: int) -> dict:
    """Points on frame-group edges (after frames k - 1, 2k - 1, ...: the lattice of period k at offset k - 1)
    against their expectation if the same points fell uniformly at random."""
    e = lattice_excess(cells, group_size, group_size - 1)
    return {
        "points": e["points"],
        "on_edges": e["on_lattice"],
        "expected": e["expected"],
        "ratio": e["ratio"],
        "p_value": e["p_value"],
    }


def lattice_excess(cells: Sequence[tuple[int, Sequence[int]]], period: int, offset: int) -> dict:
    """Points at positions j with j mod ``period`` = ``offset``, against their expectation if the same points
    fell uniformly at random (per cell: its points times the lattice's share of its positions)."""
    observed = total = 0
    expected = 0.0
    for n_frames, points in cells:
        if n_frames < 2:
            continue
        n_pos = n_frames - 1
        on = len(range(offset, n_pos, period))
        observed += sum(1 for j in points if j % period == offset)
        total += len(points)
        expected += len(points) * on / n_pos
    p = binomial_tail(observed, total, expected / total) if total and expected else 1.0
    return {
        "points": total,
        "on_lattice": observed,
        "expected": expected,
        "p_value": float(p),
        "ratio": observed / expected if expected else None,
    }


def periodic_excess(cells: Sequence[tuple[int, Sequence[int]]], group_size: int) -> dict | None:
    """The fixed schedule (period 2 .. ``MAX_PERIOD``, every offset) that the points follow most, beyond
    chance, with its p-value corrected for the number of schedules tried (Bonferroni); None when no points.
    The frame groups' own lattice (period a multiple of k at offset k - 1) is the group-edges check's."""
    best = None
    tried = 0
    for period in range(2, MAX_PERIOD + 1):
        for offset in range(period):
            if period % group_size == 0 and offset % group_size == group_size - 1:
                continue
            tried += 1
            e = lattice_excess(cells, period, offset)
            if e["ratio"] is None:
                continue
            if best is None or e["p_value"] < best["p_value"]:
                best = {**e, "period": period, "offset": offset}
    if best is not None:
        best["p_corrected"] = min(1.0, best["p_value"] * tried)
        best["schedules"] = tried
    return best


def _warning(model: str, kind: str, message: str, value, **extra) -> dict:
    return {"model": model, "kind": kind, "message": message, "value": value, **extra}


def sanity_warnings(outputs: Mapping[str, ModelOutputs], group_size: int) -> list[dict]:
    """Warnings per model (see the module docstring); each has model, kind, message and the measured values."""
    out = []
    for model, o in outputs.items():
        out += _caption_warnings(model, o)
        out += _text_warnings(model, o)
        out += _segmentation_warnings(model, o, group_size)
        out += leak_warnings(model, o.finals)
    return out


def _caption_warnings(model: str, o: ModelOutputs) -> list[dict]:
    """near-constant, missing-captions, no-answers and heavy-recovery: how many frame captions there are to read."""
    out = []
    n_frames = len(o.frame_captions)
    distinct = sum(o.cell_distinct) / len(o.cell_distinct) if o.cell_distinct else 1.0
    if distinct < MIN_DISTINCT_PER_CELL:
        msg = (
            f"near-constant captions: per episode and condition, {100 * distinct:.1f}% of the frames have a caption "
            f"of their own on average (< {100 * MIN_DISTINCT_PER_CELL:g}%; {len(set(o.frame_captions))} distinct "
            f"texts among {n_frames} frame captions)"
        )
        out.append(_warning(model, "near-constant", msg, distinct))
    missing = o.frames_missing / (n_frames + o.frames_missing) if n_frames + o.frames_missing else 0.0
    if missing > MAX_MISSING_FRAME_SHARE:
        msg = (
            f"{o.frames_missing} of {n_frames + o.frames_missing} frame captions are missing "
            f"({100 * missing:.0f}% > {100 * MAX_MISSING_FRAME_SHARE:g}%): the parser found no caption"
        )
        out.append(_warning(model, "missing-captions", msg, missing))
    out += _no_answer_warning(model, o, n_frames + o.frames_missing)
    heavy = o.frames_heavy / n_frames if n_frames else 0.0
    if heavy >= MIN_HEAVY_RECOVERY_SHARE:
        msg = (
            f"{o.frames_heavy} of {n_frames} present frame captions needed heavy recovery ({100 * heavy:.0f}% >= "
            f"{100 * MIN_HEAVY_RECOVERY_SHARE:g}%): placed by position, not read from a frame label, so they may "
            "describe other frames"
        )
        out.append(_warning(model, "heavy-recovery", msg, heavy))
    return out


def _text_warnings(model: str, o: ModelOutputs) -> list[dict]:
    """gibberish, state-echo and off-task: whether the captions are words about the task."""
    out = []
    share, tokens = non_word_share(o.all_captions)
    if tokens and share > MAX_NON_WORD_SHARE:
        msg = (
            f"gibberish: {100 * share:.0f}% of {tokens} caption tokens are neither words nor numbers "
            f"(limit {100 * MAX_NON_WORD_SHARE:g}%)"
        )
        out.append(_warning(model, "gibberish", msg, share))
    numbers = number_share(o.all_captions) if o.all_captions else 0.0
    no_hit = sum(1 for h in o.final_hits if h == 0) / len(o.final_hits) if o.final_hits else 0.0
    if numbers >= STATE_ECHO_SHARE:  # its own label: such captions are neither gibberish nor merely off-task
        msg = (
            f"captions made of numbers: {100 * numbers:.0f}% of caption tokens are numbers (limit "
            f"{100 * STATE_ECHO_SHARE:g}%): the model copies the state instead of describing the motion"
        )
        out.append(_warning(model, "state-echo", msg, numbers, number_share=numbers))
    elif no_hit > MAX_NO_HIT_FINAL_SHARE:
        msg = (
            f"off-task: {100 * no_hit:.0f}% of final captions name nothing in the task lexicon "
            f"(limit {100 * MAX_NO_HIT_FINAL_SHARE:g}%); {100 * numbers:.0f}% of caption tokens are numbers"
        )
        out.append(_warning(model, "off-task", msg, no_hit, number_share=numbers))
    return out


def _segmentation_warnings(model: str, o: ModelOutputs, group_size: int) -> list[dict]:
    """group-edges and periodic: segmentation points that keep to a schedule instead of the episode."""
    out = []
    g = group_edge_excess(o.cells, group_size)
    if g["ratio"] is not None and g["ratio"] >= GROUP_EDGE_RATIO and g["p_value"] < GROUP_EDGE_P:
        msg = (
            f"segmentation follows the frame groups: {g['on_edges']} of {g['points']} points fall on the edges of "
            f"the k = {group_size} groups, {g['ratio']:.1f}x the {g['expected']:.1f} expected by chance "
            f"(binomial p = {g['p_value']:.1g})"
        )
        out.append(_warning(model, "group-edges", msg, g["ratio"], **{k: v for k, v in g.items() if k != "ratio"}))
    return out + _periodic_warning(model, o, group_size)


def leak_warnings(model: str, finals: Sequence[FinalCell]) -> list[dict]:
    """'leak': scores the model cannot reach from what it was shown (the thresholds above), one warning each."""
    out = []
    found: list[str] = []
    for task in sorted({f.task for f in finals}):
        for cond in NO_STATE_CONDITIONS:
            cells = [f for f in finals if f.task == task and f.condition == cond]
            if len(cells) < LEAK_MIN_EPISODES or len({f.truth for f in cells}) < 2:
                continue  # a trajectory shared by every episode is the ceiling a constant caption reaches
            share = sum(f.trajectory_correct for f in cells) / len(cells)
            if share >= LEAK_TRAJECTORY_SHARE:
                found.append(
                    f"the trajectory (target compartment) is right in {sum(f.trajectory_correct for f in cells)} of "
                    f"{len(cells)} {task} episodes under {cond}, which shows no state"
                )
            f1s = [f.boundary_f1 for f in cells if f.boundary_f1 is not None]
            if f1s and sum(f1s) / len(f1s) >= LEAK_BOUNDARY_F1:
                found.append(f"boundary F1 is {sum(f1s) / len(f1s):.2f} on {task} under {cond}")
    same = sum(f.is_instruction for f in finals)
    if finals and same / len(finals) >= LEAK_INSTRUCTION_SHARE:
        found.append(f"{same} of {len(finals)} final captions are the episode's ground-truth instruction word for word")
    for what in found:
        out.append(
            {
                "model": model,
                "kind": "leak",
                "message": f"possible ground-truth leak: {what}; the model may be given the answer (check the "
                "prompt, the images and the backend): its scores cannot be read as what it saw",
                "value": None,
            }
        )
    return out


def _periodic_warning(model: str, o: ModelOutputs, group_size: int) -> list[dict]:
    """'periodic': the segmentation points follow a fixed schedule (every period, every offset), not the episode."""
    e = periodic_excess(o.cells, group_size)
    if e is None or e["ratio"] is None or e["ratio"] < PERIODIC_RATIO or e["p_corrected"] >= GROUP_EDGE_P:
        return []
    if e["on_lattice"] < PERIODIC_MIN_SHARE * e["points"]:
        return []
    return [
        {
            "model": model,
            "kind": "periodic",
            "message": f"segmentation follows a fixed schedule: {e['on_lattice']} of {e['points']} points fall every "
            f"{e['period']} frames (position mod {e['period']} = {e['offset']}), {e['ratio']:.1f}x the "
            f"{e['expected']:.1f} expected by chance (binomial p = {e['p_corrected']:.1g}, corrected for "
            f"{e['schedules']} schedules): the points keep time, they do not follow the episode",
            "value": e["ratio"],
            **{k: v for k, v in e.items() if k != "ratio"},
        }
    ]


def _no_answer_warning(model: str, o: ModelOutputs, n_frames: int) -> list[dict]:
    """'no-answers': most frame captions are missing because the answers held none, with the classes counted."""
    share = o.frames_missing_problem / n_frames if n_frames else 0.0
    if share < MIN_NO_ANSWER_SHARE:
        return []
    counts = Counter(o.answer_problems)
    classes = ", ".join(f"{name} {n}" for name, n in counts.most_common())
    return [
        {
            "model": model,
            "kind": "no-answers",
            "message": f"{o.frames_missing_problem} of {n_frames} frame captions are missing because the server's "
            f"answers held none ({100 * share:.0f}% >= {100 * MIN_NO_ANSWER_SHARE:g}%; requests: {classes}): "
            "the model's conditions cannot be compared",
            "value": share,
            "answer_problems": dict(counts.most_common()),
        }
    ]
