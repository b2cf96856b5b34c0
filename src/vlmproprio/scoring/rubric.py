"""Caption scoring: does a caption name the target object, the action and the trajectory, and correctly?

The rubric of the paper's Fig. 5, made automatic and auditable: a caption's analysis
(:mod:`vlmproprio.scoring.matching`) judged against an episode's :class:`Expectation`.

* A negated *expected* term is wrong ("does not open"), a negated wrong one is ignored ("without closing").
* A direction word binds to the nearest motion verb before it in its clause
  ("turn the handle *down*"); unbound direction words are mentions only.
* A bin phrase led by a source cue ("from the right bin") is where the object came from and is ignored.
  A compartment may also be named without the camera: near/far from the robot and next to / away from
  the source bin.

Items, each ``mentioned`` / ``correct`` / ``wrong`` (mentioned-but-wrong):

* object: correct when the episode's object is named and no other known object is.
* action: correct when every requirement of the task (door: open or pull;
  pick_place: pick or lift, and place) is met by a non-negated term and nothing
  contradicts it (a wrong action such as "close" or "push the door", or a negated required one).
* trajectory: door -- at least one direction bound to its motion is expected and none is the opposite;
  pick_place -- the target compartment is named by its row (near/far, or top/bottom in the image) and its
  column (left/right, or next to / away from the source bin), nothing names another one, and no bound
  direction is the opposite of an expected one (see :mod:`vlmproprio.scoring.expectation`).

Every hit keeps its span, matched text and lexicon entry, so a report can show
why a caption scored as it did. A missing or empty caption scores as an empty
text: nothing mentioned, nothing correct, zero words.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, fields

from vlmproprio.episodes import Episode
from vlmproprio.scoring.expectation import Expectation, expectation_for
from vlmproprio.scoring.lexicon import Lexicon, load_lexicon
from vlmproprio.scoring.matching import TextAnalysis, analyse_text

ITEMS = ("object", "action", "trajectory")

# Verdicts a hit can carry; only the first three count as keyword hits.
CORRECT, WRONG, MENTIONED, IGNORED = "correct", "wrong", "mentioned", "ignored"
KEYWORD_VERDICTS = (CORRECT, WRONG, MENTIONED)


@dataclass(frozen=True)
class Hit:
    """One matched lexicon term in a caption, with the reason for its verdict."""

    item: str  # object | action | trajectory | other
    kind: str  # the tag kind that was used
    value: str  # canonical meaning: "door", "open", "down", "far", ...
    start: int
    end: int
    text: str
    entry: str
    negated: bool
    verdict: str  # correct | wrong | mentioned | ignored
    note: str = ""  # e.g. the motion a direction is bound to

    def to_dict(self) -> dict:
        # the fields are scalars: asdict's recursive deep copy would cost more than scoring the caption
        return {name: getattr(self, name) for name in _HIT_FIELDS}


_HIT_FIELDS = tuple(f.name for f in fields(Hit))


@dataclass(frozen=True)
class ItemScore:
    mentioned: bool
    correct: bool
    wrong: bool


@dataclass(frozen=True)
class CaptionScore:
    text: str
    words: int
    hits: int
    hits_per_word: float
    object: ItemScore
    action: ItemScore
    trajectory: ItemScore
    matches: tuple[Hit, ...] = field(default=())

    @property
    def all_correct(self) -> bool:
        return self.object.correct and self.action.correct and self.trajectory.correct

    def item(self, name: str) -> ItemScore:
        if name not in ITEMS:
            raise KeyError(name)
        return getattr(self, name)

    def to_dict(self) -> dict:
        d = asdict(self)
        d["all_correct"] = self.all_correct
        return d


def score_text(
    text: str, expectation: Expectation, lexicon: Lexicon, analysis: TextAnalysis | None = None
) -> CaptionScore:
    """Score one caption against what the episode says a correct caption contains. ``analysis``:
    ``analyse_text(text, lexicon)`` when the caller already has it (it does not depend on the episode)."""
    text = text or ""
    analysis = analyse_text(text, lexicon) if analysis is None else analysis
    tokens, cands, failed = analysis.tokens, analysis.cands, analysis.failed
    required = {g for alts in lexicon.required for g in alts}
    motion_of_group = {g: m for m in expectation.motions for g in m.groups}
    hits = []
    for c in cands:
        item, verdict, note = "other", IGNORED, ""
        if c.kind == "object":
            item = "object"
            verdict = CORRECT if c.value == expectation.target_object else WRONG
        elif c.kind == "action" and id(c) in failed:
            item, verdict, note = "action", WRONG, "followed by a failure cue"
        elif c.kind == "action" and c.negated and c.value not in required:
            # "the handle is not turned up but down": denying a sub-step the task does not require is no
            # wrong action; its direction words are judged on their own
            item, verdict, note = "action", MENTIONED, "negated, not a required action"
        elif c.kind == "action":
            item, verdict = "action", (WRONG if c.negated else CORRECT)
            note = "negated expected action" if c.negated else ""
        elif c.kind == "wrong_action":
            item, verdict = "action", (IGNORED if c.negated else WRONG)
            note = "negated wrong action" if c.negated else ""
        elif c.kind == "direction":
            item = "trajectory"
            verdict, note = _direction_verdict(c, cands, tokens, motion_of_group, lexicon)
        elif c.kind in ("row", "image_row", "side", "column"):
            item = "trajectory"
            verdict, note = _compartment_verdict(c, cands, tokens, expectation, lexicon)
        else:
            note = c.kind
        t0, t1 = tokens[c.first], tokens[c.last]
        hits.append(
            Hit(item, c.kind, c.value, t0.start, t1.end, text[t0.start : t1.end], c.entry, c.negated, verdict, note)
        )
    return _summarise(text, hits, expectation, lexicon)


def _direction_verdict(c, cands, tokens, motion_of_group, lex) -> tuple[str, str]:
    clause = tokens[c.first].clause
    before = [
        o
        for o in cands
        if o.kind == "action" and o.value in motion_of_group and o.first < c.first and tokens[o.first].clause == clause
    ]
    if not before:
        return (IGNORED if c.negated else MENTIONED), "not bound to a motion verb"
    # the nearest verb before it; a split phrasal verb ("set it down") owns its particle
    verb = max(before, key=lambda o: (o.first, o.last))
    motion = motion_of_group[verb.value]
    note = f"bound to {motion.name!r} ({tokens[verb.first].text}); expected {'/'.join(motion.expected) or 'nothing'}"
    if c.value in motion.expected:
        return (WRONG if c.negated else CORRECT), note
    if c.value in motion.returns and not c.negated:
        cue = any(t.text in motion.return_cues for t in tokens if t.clause == clause)
        said_main = any(
            o.kind == "direction"
            and o.last < c.first
            and o.value in motion.expected
            and not o.negated
            and any(v.value in motion.groups for v in cands if v.kind == "action" and v.last < o.first)
            for o in cands
        )
        if cue or said_main:
            why = "a return cue in its clause" if cue else "after the main direction"
            return CORRECT, f"{note}; the return ({'/'.join(motion.returns)}) with {why}"
    if c.value in motion.opposite:
        return (IGNORED if c.negated else WRONG), note
    return (IGNORED if c.negated else MENTIONED), note


def _compartment_verdict(c, cands, tokens, exp: Expectation, lex) -> tuple[str, str]:
    clause = tokens[c.first].clause
    window = lex.compartment.window
    if any(o.kind == "source" and tokens[o.first].clause == clause and 0 < c.first - o.last <= window for o in cands):
        return IGNORED, "source bin (led by a source cue)"
    value, target = c.value, None
    if c.kind == "row":
        target = exp.target_row
    elif c.kind == "image_row":
        value = dict(exp.image_rows).get(c.value)
        target = exp.target_row
        if value is None:
            return MENTIONED, f"the camera ({exp.camera}) does not say which row is '{c.value}' in its image"
    elif c.kind == "column":
        target = exp.target_column
    elif c.value.startswith("robot_"):
        target = f"robot_{exp.target_side}"
    else:
        target = exp.image_side
        if target is None:
            return MENTIONED, f"the camera ({exp.camera}) does not show the robot's left/right as image sides"
    ok = value == target
    note = f"target {c.kind} {target}" + (f" ('{c.value}' = {value})" if value != c.value else "")
    if c.negated:
        return (WRONG if ok else IGNORED), note
    return (CORRECT if ok else WRONG), note


def _summarise(text: str, hits: list[Hit], exp: Expectation, lex: Lexicon) -> CaptionScore:
    def of(item: str) -> list[Hit]:
        return [h for h in hits if h.item == item and h.verdict != IGNORED]

    obj = of("object")
    obj_wrong = any(h.verdict == WRONG for h in obj)
    object_score = ItemScore(bool(obj), any(h.verdict == CORRECT for h in obj) and not obj_wrong, obj_wrong)

    act = of("action")
    act_wrong = any(h.verdict == WRONG for h in act)
    groups_ok = {h.value for h in act if h.verdict == CORRECT and h.kind == "action"}
    met = all(any(g in groups_ok for g in alts) for alts in lex.required)
    action_score = ItemScore(bool(act), met and not act_wrong, act_wrong)

    traj = of("trajectory")
    traj_wrong = any(h.verdict == WRONG for h in traj)
    if lex.compartment is not None:
        good = {h.kind for h in traj if h.verdict == CORRECT}
        ok = bool(good & {"row", "image_row"}) and bool(good & {"side", "column"})
    else:
        ok = any(h.verdict == CORRECT for h in traj)
    trajectory_score = ItemScore(bool(traj), ok and not traj_wrong, traj_wrong)

    n_words = len(text.split())
    n_hits = sum(1 for h in hits if h.item in ITEMS and h.verdict in KEYWORD_VERDICTS)
    return CaptionScore(
        text=text,
        words=n_words,
        hits=n_hits,
        hits_per_word=(n_hits / n_words) if n_words else 0.0,
        object=object_score,
        action=action_score,
        trajectory=trajectory_score,
        matches=tuple(hits),
    )


def score_caption(text: str, episode: Episode, lexicon: Lexicon | None = None) -> CaptionScore:
    """Score one caption of an episode (final or scene caption) with the episode's task lexicon."""
    lex = lexicon or load_lexicon(episode.task)
    return score_text(text, expectation_for(episode, lex), lex)
