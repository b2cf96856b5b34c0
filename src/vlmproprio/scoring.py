"""Caption scoring: does a caption name the target object, the action and the trajectory, and correctly?

The rubric of the paper's Fig. 5, made automatic and auditable. Words and rules
live in versioned lexicon files (``vlmproprio/lexicons/*.json``); this module
only applies them:

* A caption is tokenised (words, numbers, punctuation) and split into clauses at
  punctuation and at connectives such as "then" / "before" / "while".
* Lexicon terms (word sequences, longest match first, never overlapping) are
  matched; articles and possessives may sit between a term's words.
* A negation cue ("not", "without", "doesn't", ...) negates an action, direction
  or compartment term that follows within a few words in the same clause. A
  negated *expected* term is wrong ("does not open"), a negated wrong one is
  ignored ("without closing"). Objects are never negated.
* A direction word binds to the nearest motion verb before it in its clause
  ("turn the handle *down*"); unbound direction words are mentions only.
* Row and side words ("far", "left") are compartment words only near a bin noun
  or as a row+side pair ("far left"); a bin phrase led by a source cue ("from the
  right bin") is where the object came from and is ignored.

Items, each ``mentioned`` / ``correct`` / ``wrong`` (mentioned-but-wrong):

* object: correct when the episode's object is named and no other known object is.
* action: correct when every requirement of the task (door: open or pull;
  pick_place: pick or lift, and place) is met by a non-negated term and nothing
  contradicts it (a wrong action such as "close", or a negated expected one).
* trajectory: door -- at least one direction bound to its motion is the expected
  one (turn: down; pull: backward / toward the robot) and none is the opposite.
  pick_place -- the target compartment is named with both its row (near/far) and
  its side (left/right), no other row or side is named, and no bound direction
  is the opposite of the expected one (lift: up; place/transport: the direction
  words of the ground-truth transport phase).

Every hit keeps its span, matched text and lexicon entry, so a report can show
why a caption scored as it did. A missing or empty caption scores as an empty
text: nothing mentioned, nothing correct, zero words.
"""

from __future__ import annotations

import hashlib
import json
import re
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from functools import cache, lru_cache
from importlib import resources

from vlmproprio.episodes import Episode
from vlmproprio.errors import VlmproprioError

ITEMS = ("object", "action", "trajectory")
LEXICON_PACKAGE = "vlmproprio/lexicons"
COMMON_LEXICON = "common.json"

# Verdicts a hit can carry; only the first three count as keyword hits.
CORRECT, WRONG, MENTIONED, IGNORED = "correct", "wrong", "mentioned", "ignored"
KEYWORD_VERDICTS = (CORRECT, WRONG, MENTIONED)

# Numbers (with a decimal point) are one token so "0.4" never splits a clause; words may carry an apostrophe.
_TOKEN_RE = re.compile(r"\d+(?:\.\d+)?|[^\W_]+(?:['’][^\W_]+)*|[,;.:!?()]")


class ScoringError(VlmproprioError):
    """A lexicon or an episode that the scorer cannot use; the message says which file or field."""


# ---------------------------------------------------------------------------------------------- lexicon


@dataclass(frozen=True)
class Tag:
    kind: str  # object | action | wrong_action | direction | row | side | noun | negation | neutral | source
    value: str
    entry: str  # where in the lexicon: "door.json:action.groups.open"


@dataclass(frozen=True)
class Term:
    tokens: tuple[str, ...]
    tags: tuple[Tag, ...]


@dataclass(frozen=True)
class Motion:
    name: str
    groups: tuple[str, ...]
    expected: tuple[str, ...] = ()
    expected_from_phase: str = ""
    min_share: float = 0.5


@dataclass(frozen=True)
class CompartmentRules:
    window: int


@dataclass(frozen=True)
class Lexicon:
    task: str
    version: str
    sha256: str
    skippable: frozenset[str]
    clause_punct: frozenset[str]
    clause_words: frozenset[str]
    negation_window: int
    negation_suffixes: tuple[str, ...]
    objects: dict[str, tuple[str, ...]]
    opposite: dict[str, str]
    required: tuple[tuple[str, ...], ...]
    motions: tuple[Motion, ...]
    compartment: CompartmentRules | None
    index: dict[str, tuple[Term, ...]]

    def object_key(self, name: str) -> str:
        """The lexicon entry of an episode's target_object ("door", "cereal", "cereal box" -> "cereal")."""
        wanted = " ".join(_words(name))
        for key, terms in self.objects.items():
            if wanted == key or wanted in terms:
                return key
        raise ScoringError(
            f"target object {name!r} is not in the object lexicon ({LEXICON_PACKAGE}/{COMMON_LEXICON}, "
            f"known: {', '.join(self.objects)}); add an entry for it"
        )


def _words(text: str) -> list[str]:
    return [m.group(0).lower().replace("’", "'") for m in _TOKEN_RE.finditer(text)]


def _lexicon_dir():
    # package data of vlmproprio (pyproject: lexicons/*.json), not a package of its own
    return resources.files("vlmproprio").joinpath("lexicons")


def _read_lexicon_file(name: str) -> tuple[dict, bytes]:
    try:
        raw = _lexicon_dir().joinpath(name).read_bytes()
    except (FileNotFoundError, OSError) as exc:
        raise ScoringError(f"lexicon {LEXICON_PACKAGE}/{name} not found ({exc})") from exc
    try:
        data = json.loads(raw)
    except ValueError as exc:
        raise ScoringError(f"lexicon {LEXICON_PACKAGE}/{name}: not valid JSON ({exc})") from exc
    if not isinstance(data, dict) or not isinstance(data.get("version"), int):
        raise ScoringError(f"lexicon {LEXICON_PACKAGE}/{name}: must be an object with an integer 'version'")
    return data, raw


def available_tasks() -> list[str]:
    names = [p.name for p in _lexicon_dir().iterdir() if p.name.endswith(".json")]
    return sorted(n[:-5] for n in names if n not in (COMMON_LEXICON, "judge.json"))


@cache
def load_lexicon(task: str) -> Lexicon:
    """The merged common + task lexicon. Cached: lexicons are package data and do not change in a process."""
    if not re.fullmatch(r"[a-z_]+", task):
        raise ScoringError(f"no lexicon for task {task!r} (known: {', '.join(available_tasks())})")
    if task not in available_tasks():
        raise ScoringError(f"no lexicon for task {task!r} (known: {', '.join(available_tasks())})")
    common, raw_common = _read_lexicon_file(COMMON_LEXICON)
    spec, raw_task = _read_lexicon_file(f"{task}.json")
    fname = f"{task}.json"
    try:
        return _build_lexicon(task, common, spec, fname, raw_common + b"\0" + raw_task)
    except (KeyError, TypeError, ValueError) as exc:
        raise ScoringError(f"lexicon {LEXICON_PACKAGE}/{fname} or {COMMON_LEXICON}: malformed ({exc!r})") from exc


def _build_lexicon(task: str, common: dict, spec: dict, fname: str, raw: bytes) -> Lexicon:
    terms: dict[tuple[str, ...], list[Tag]] = {}

    def add(text: str, tag: Tag) -> None:
        toks = tuple(_words(text))
        if not toks:
            raise ValueError(f"empty term {text!r} in {tag.entry}")
        terms.setdefault(toks, []).append(tag)

    c = "common.json"
    for key, words in common["objects"].items():
        if key == "about":
            continue
        add(key, Tag("object", key, f"{c}:objects.{key}"))
        for w in words:
            add(w, Tag("object", key, f"{c}:objects.{key}"))
    for d, words in common["directions"]["terms"].items():
        for w in words:
            add(w, Tag("direction", d, f"{c}:directions.terms.{d}"))
    for w in common["negation"]["cues"]:
        add(w, Tag("negation", w, f"{c}:negation.cues"))
    for w in common["neutral"]["terms"]:
        add(w, Tag("neutral", w, f"{c}:neutral.terms"))

    action = spec["action"]
    for group, words in action["groups"].items():
        for w in words:
            add(w, Tag("action", group, f"{fname}:action.groups.{group}"))
    for w in action["wrong"]:
        add(w, Tag("wrong_action", w, f"{fname}:action.wrong"))
    required = tuple(tuple(alts) for alts in action["required"])
    for alts in required:
        for g in alts:
            if g not in action["groups"]:
                raise ValueError(f"required group {g!r} is not in action.groups")

    traj = spec["trajectory"]
    motions = []
    for m in traj["motions"]:
        for g in m["groups"]:
            if g not in action["groups"]:
                raise ValueError(f"motion {m['name']!r}: group {g!r} is not in action.groups")
        motions.append(
            Motion(
                name=m["name"],
                groups=tuple(m["groups"]),
                expected=tuple(m.get("expected", ())),
                expected_from_phase=m.get("expected_from_phase", ""),
                min_share=float(m.get("min_share", 0.5)),
            )
        )
    compartment = None
    if "compartment" in traj:
        comp = traj["compartment"]
        compartment = CompartmentRules(window=int(comp["window"]))
        for w in comp["nouns"]:
            add(w, Tag("noun", w, f"{fname}:trajectory.compartment.nouns"))
        for row, words in comp["rows"].items():
            for w in words:
                add(w, Tag("row", row, f"{fname}:trajectory.compartment.rows.{row}"))
        for side, words in comp["sides"].items():
            for w in words:
                add(w, Tag("side", side, f"{fname}:trajectory.compartment.sides.{side}"))
        for w in comp["source_cues"]:
            add(w, Tag("source", w, f"{fname}:trajectory.compartment.source_cues"))

    index: dict[str, list[Term]] = {}
    for toks, tags in terms.items():
        index.setdefault(toks[0], []).append(Term(toks, tuple(dict.fromkeys(tags))))
    frozen_index = {k: tuple(sorted(v, key=lambda t: (-len(t.tokens), t.tokens))) for k, v in index.items()}
    breaks = common["clause_breaks"]
    neg = common["negation"]
    return Lexicon(
        task=task,
        version=f"common-v{common['version']}+{task}-v{spec['version']}",
        sha256=hashlib.sha256(raw).hexdigest(),
        skippable=frozenset(common["skippable_inside"]),
        clause_punct=frozenset(breaks["punctuation"]),
        clause_words=frozenset(breaks["words"]),
        negation_window=int(neg["window"]),
        negation_suffixes=tuple(neg["suffixes"]),
        objects={k: tuple(" ".join(_words(w)) for w in v) for k, v in common["objects"].items() if k != "about"},
        opposite=dict(common["directions"]["opposite"]),
        required=required,
        motions=tuple(motions),
        compartment=compartment,
        index=frozen_index,
    )


# ---------------------------------------------------------------------------------------------- expectation


@dataclass(frozen=True)
class MotionExpectation:
    name: str
    groups: tuple[str, ...]
    expected: tuple[str, ...]
    source: str  # where ``expected`` comes from, for the audit


@dataclass(frozen=True)
class Expectation:
    """What a correct caption of one episode says: from the episode's ground truth and the lexicon."""

    task: str
    target_object: str
    target_row: str | None
    target_side: str | None
    motions: tuple[MotionExpectation, ...]

    def to_dict(self) -> dict:
        return asdict(self)


def phase_directions(episode: Episode, phase_pattern: str, min_share: float) -> tuple[tuple[str, ...], str]:
    """Direction words named by at least ``min_share`` of the moving frames in the phases matching the pattern."""
    pat = re.compile(phase_pattern, re.IGNORECASE)
    moving = [f for f in episode.frames if pat.search(f.phase) and f.direction not in ("still", "")]
    if not moving:
        return (), f"ground truth: no moving frame in a phase matching {phase_pattern!r}"
    counts: dict[str, int] = {}
    for f in moving:
        for w in f.direction.split("+"):
            counts[w] = counts.get(w, 0) + 1
    words = tuple(sorted(w for w, n in counts.items() if n >= min_share * len(moving)))
    idx = [f.index for f in moving]
    return words, f"ground truth: {len(moving)} moving frames {idx[0]}..{idx[-1]} in phase {moving[0].phase!r}"


def expectation_for(episode: Episode, lexicon: Lexicon | None = None) -> Expectation:
    lex = lexicon or load_lexicon(episode.task)
    motions = []
    for m in lex.motions:
        if m.expected_from_phase:
            expected, source = phase_directions(episode, m.expected_from_phase, m.min_share)
        else:
            expected, source = m.expected, f"lexicon {lex.task}.json"
        unknown = [d for d in expected if d not in lex.opposite]
        if unknown:
            raise ScoringError(f"episode {episode.episode_id}: unknown direction words {unknown} for motion {m.name!r}")
        motions.append(MotionExpectation(m.name, m.groups, expected, source))
    row = side = None
    if lex.compartment is not None:
        if episode.target_bin is None:
            raise ScoringError(f"episode {episode.episode_id}: task {episode.task} needs a target_bin in episode.json")
        row, side = episode.target_bin.row, episode.target_bin.side
        if row not in ("near", "far") or side not in ("left", "right"):
            raise ScoringError(
                f"episode {episode.episode_id}: target_bin row/side {row!r}/{side!r} not near|far, left|right"
            )
    return Expectation(
        task=episode.task,
        target_object=lex.object_key(episode.target_object),
        target_row=row,
        target_side=side,
        motions=tuple(motions),
    )


# ---------------------------------------------------------------------------------------------- matching


@dataclass(frozen=True)
class Token:
    text: str  # lower case
    start: int
    end: int
    clause: int
    is_word: bool


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
        return asdict(self)


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


def tokenize(text: str, lexicon: Lexicon) -> list[Token]:
    out = []
    clause = 0
    for m in _TOKEN_RE.finditer(text):
        tok = m.group(0).lower().replace("’", "'")
        is_word = tok not in lexicon.clause_punct
        if not is_word or tok in lexicon.clause_words:
            clause += 1
        out.append(Token(tok, m.start(), m.end(), clause, is_word))
    return out


@dataclass
class _Cand:
    first: int  # token index of the first and last matched token
    last: int
    term: Term
    kind: str = ""
    value: str = ""
    entry: str = ""
    negated: bool = False


def _match_terms(tokens: list[Token], lex: Lexicon) -> list[_Cand]:
    cands = []
    i = 0
    n = len(tokens)
    while i < n:
        tok = tokens[i]
        if not tok.is_word:
            i += 1
            continue
        found = None
        for term in lex.index.get(tok.text, ()):
            j, k = i + 1, 1
            while k < len(term.tokens) and j < n and tokens[j].is_word and tokens[j].clause == tok.clause:
                if tokens[j].text == term.tokens[k]:
                    k += 1
                elif tokens[j].text not in lex.skippable:
                    break
                j += 1
            if k == len(term.tokens):
                found = _Cand(i, j - 1, term)
                break
        if found is None:
            i += 1
        else:
            cands.append(found)
            i = found.last + 1
    return cands


def _tag(cand: _Cand, kinds: Sequence[str]) -> Tag | None:
    for t in cand.term.tags:
        if t.kind in kinds:
            return t
    return None


def _resolve(cands: list[_Cand], tokens: list[Token], lex: Lexicon) -> list[_Cand]:
    """Give each match one meaning; compartment words need a bin noun nearby or a row+side pair."""
    nouns = [c for c in cands if _tag(c, ("noun",))]
    window = lex.compartment.window if lex.compartment else 0

    def near_noun(c: _Cand) -> bool:
        return any(
            tokens[n.first].clause == tokens[c.first].clause
            and min(abs(n.first - c.last), abs(c.first - n.last)) <= window
            for n in nouns
        )

    def pair(c: _Cand, kind: str) -> bool:
        other = "side" if kind == "row" else "row"
        return any(o is not c and _tag(o, (other,)) and (o.first == c.last + 1 or c.first == o.last + 1) for o in cands)

    for c in cands:
        comp = _tag(c, ("row", "side")) if lex.compartment else None
        if comp is not None and (near_noun(c) or pair(c, comp.kind)):
            chosen = comp
        else:
            order = ("neutral", "negation", "source", "noun", "object", "wrong_action", "action", "direction")
            chosen = next((t for k in order for t in c.term.tags if t.kind == k), None)
        if chosen is not None:
            c.kind, c.value, c.entry = chosen.kind, chosen.value, chosen.entry
    return [c for c in cands if c.kind]


def _negated(c: _Cand, cands: list[_Cand], tokens: list[Token], lex: Lexicon) -> bool:
    clause = tokens[c.first].clause
    for j in range(max(0, c.first - lex.negation_window), c.first):
        if tokens[j].clause == clause and tokens[j].text.endswith(lex.negation_suffixes):
            return True
    return any(
        o.kind == "negation" and tokens[o.first].clause == clause and 0 < c.first - o.last <= lex.negation_window
        for o in cands
    )


def score_text(text: str, expectation: Expectation, lexicon: Lexicon) -> CaptionScore:
    """Score one caption against what the episode says a correct caption contains."""
    text = text or ""
    tokens = tokenize(text, lexicon)
    cands = _resolve(_match_terms(tokens, lexicon), tokens, lexicon)
    for c in cands:
        if c.kind in ("action", "wrong_action", "direction", "row", "side"):
            c.negated = _negated(c, cands, tokens, lexicon)
    motion_of_group = {g: m for m in expectation.motions for g in m.groups}
    hits = []
    for c in cands:
        item, verdict, note = "other", IGNORED, ""
        if c.kind == "object":
            item = "object"
            verdict = CORRECT if c.value == expectation.target_object else WRONG
        elif c.kind == "action":
            item, verdict = "action", (WRONG if c.negated else CORRECT)
            note = "negated expected action" if c.negated else ""
        elif c.kind == "wrong_action":
            item, verdict = "action", (IGNORED if c.negated else WRONG)
            note = "negated wrong action" if c.negated else ""
        elif c.kind == "direction":
            item = "trajectory"
            verdict, note = _direction_verdict(c, cands, tokens, motion_of_group, lexicon)
        elif c.kind in ("row", "side"):
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
        if o.kind == "action" and o.value in motion_of_group and o.last < c.first and tokens[o.first].clause == clause
    ]
    if not before:
        return (IGNORED if c.negated else MENTIONED), "not bound to a motion verb"
    verb = max(before, key=lambda o: o.last)
    motion = motion_of_group[verb.value]
    note = f"bound to {motion.name!r} ({tokens[verb.first].text}); expected {'/'.join(motion.expected) or 'nothing'}"
    opposites = {lex.opposite[d] for d in motion.expected}
    if c.value in motion.expected:
        return (WRONG if c.negated else CORRECT), note
    if c.value in opposites:
        return (IGNORED if c.negated else WRONG), note
    return (IGNORED if c.negated else MENTIONED), note


def _compartment_verdict(c, cands, tokens, exp: Expectation, lex) -> tuple[str, str]:
    clause = tokens[c.first].clause
    window = lex.compartment.window
    if any(o.kind == "source" and tokens[o.first].clause == clause and 0 < c.first - o.last <= window for o in cands):
        return IGNORED, "source bin (led by a source cue)"
    target = exp.target_row if c.kind == "row" else exp.target_side
    ok = c.value == target
    note = f"target {c.kind} {target}"
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
        good = {(h.kind, h.value) for h in traj if h.verdict == CORRECT and h.kind in ("row", "side")}
        ok = ("row", exp.target_row) in good and ("side", exp.target_side) in good
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


# ---------------------------------------------------------------------------------------------- judge model
# Optional and off by default: a backend grades captions; the rubric above stays the reference and the
# agreement between the two is reported, so a judge never silently replaces auditable scores.


@dataclass(frozen=True)
class JudgeVerdict:
    items: dict[str, ItemScore] | None  # None when the answer could not be parsed
    raw: str
    error: str = ""

    def to_dict(self) -> dict:
        items = None if self.items is None else {k: asdict(v) for k, v in self.items.items()}
        return {"items": items, "raw": self.raw, "error": self.error}


@lru_cache(maxsize=1)
def judge_prompt() -> dict:
    data, _ = _read_lexicon_file("judge.json")
    for k in ("system", "user", "actions", "max_new_tokens"):
        if k not in data:
            raise ScoringError(f"lexicon {LEXICON_PACKAGE}/judge.json: missing {k!r}")
    return data


def _trajectory_truth(exp: Expectation) -> str:
    parts = [f"{m.name}: {' and '.join(m.expected)}" for m in exp.motions if m.expected]
    if exp.target_row:
        parts.insert(
            0,
            f"the object goes to the {exp.target_row} {exp.target_side} compartment of the target bin "
            "(near/far from the robot, the robot's left/right)",
        )
    return "; ".join(parts) or "none"


def judge_request(text: str, episode: Episode, condition: str = ""):
    """The chat request asking a judge model to grade one caption of an episode."""
    from string import Template

    from vlmproprio.chat import ChatRequest, GenerationConfig, Message, RequestTag, TextPart

    prompt = judge_prompt()
    exp = expectation_for(episode)
    user = Template(prompt["user"]).safe_substitute(
        task=episode.task,
        instruction=episode.instruction,
        object=episode.target_object,
        action=prompt["actions"].get(episode.task, episode.action),
        trajectory=_trajectory_truth(exp),
        caption=text,
    )
    return ChatRequest(
        messages=(Message("system", (TextPart(prompt["system"]),)), Message("user", (TextPart(user),))),
        config=GenerationConfig(max_new_tokens=int(prompt["max_new_tokens"]), temperature=0.0),
        prompt_version=f"judge-v{prompt['version']}",
        tag=RequestTag(episode_id=episode.episode_id, condition=condition, stage="judge"),
    )


def parse_judge_answer(raw: str) -> JudgeVerdict:
    """Read the first JSON object in a judge's answer; anything unusable is a verdict with an error."""
    start = raw.find("{")
    if start < 0:
        return JudgeVerdict(None, raw, "no JSON object in the answer")
    try:
        data, _ = json.JSONDecoder().raw_decode(raw[start:])
        items = {}
        for item in ITEMS:
            d = data[item]
            mentioned, correct = d["mentioned"], d["correct"]
            if not isinstance(mentioned, bool) or not isinstance(correct, bool):
                raise TypeError(f"{item}: mentioned/correct must be true or false")
            items[item] = ItemScore(mentioned, correct and mentioned, mentioned and not correct)
    except (ValueError, KeyError, TypeError) as exc:
        return JudgeVerdict(None, raw, f"unusable answer ({type(exc).__name__}: {exc})")
    return JudgeVerdict(items, raw)


def judge_captions(backend, captions: Sequence[tuple[str, Episode, str]]) -> list[JudgeVerdict]:
    """Grade (text, episode, condition) triples with any vlmproprio Backend, in its batch size, in order."""
    from vlmproprio.backends.base import BackendError

    requests = [judge_request(text, ep, cond) for text, ep, cond in captions]
    out: list[JudgeVerdict] = []
    step = max(1, int(getattr(backend, "max_batch_size", 1)))
    for s in range(0, len(requests), step):
        batch = requests[s : s + step]
        answers = backend.generate(batch)
        if len(answers) != len(batch):
            raise BackendError(f"judge backend answered {len(answers)} of {len(batch)} requests")
        out.extend(parse_judge_answer(a.text) for a in answers)
    return out


def _kappa(pairs: list[tuple[bool, bool]]) -> float | None:
    n = len(pairs)
    if not n:
        return None
    po = sum(1 for a, b in pairs if a == b) / n
    pa = sum(1 for a, _ in pairs if a) / n
    pb = sum(1 for _, b in pairs if b) / n
    pe = pa * pb + (1 - pa) * (1 - pb)
    return None if pe >= 1.0 else (po - pe) / (1 - pe)


def judge_agreement(rubric: Sequence[CaptionScore], verdicts: Sequence[JudgeVerdict]) -> dict:
    """Per item and field: how often judge and rubric agree, and Cohen's kappa; unparsed answers are counted."""
    if len(rubric) != len(verdicts):
        raise ValueError(f"{len(rubric)} rubric scores but {len(verdicts)} judge verdicts")
    usable = [(r, v) for r, v in zip(rubric, verdicts, strict=True) if v.items is not None]
    out: dict = {"n": len(rubric), "unparsed": len(rubric) - len(usable), "items": {}}
    for item in ITEMS:
        for what in ("mentioned", "correct"):
            pairs = [(getattr(r.item(item), what), getattr(v.items[item], what)) for r, v in usable]
            agree = sum(1 for a, b in pairs if a == b)
            out["items"][f"{item}_{what}"] = {
                "n": len(pairs),
                "agreement": agree / len(pairs) if pairs else None,
                "kappa": _kappa(pairs),
            }
    return out
