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
* Some verbs take their meaning from what follows (door.json ``contextual``): "push the lever down" turns
  the handle, "push the door" is the opposite of the pull that opens it. Phrasal verbs may be split
  (``gapped``: "set it down", "transfers the box from A to B"). A failure cue ("... but fails") negates
  the action before it.
* Row and side words ("far", "left") are compartment words only near a bin noun
  or as a row+side pair ("far left"); a bin phrase led by a source cue ("from the
  right bin") is where the object came from and is ignored. A compartment may also be named without
  the camera: near/far from the robot and next to / away from the source bin.

Items, each ``mentioned`` / ``correct`` / ``wrong`` (mentioned-but-wrong):

* object: correct when the episode's object is named and no other known object is.
* action: correct when every requirement of the task (door: open or pull;
  pick_place: pick or lift, and place) is met by a non-negated term and nothing
  contradicts it (a wrong action such as "close" or "push the door", or a negated required one).
* trajectory: door -- at least one direction bound to its motion is expected and none is the opposite;
  pick_place -- the target compartment is named by its row (near/far, or top/bottom in the image) and its
  column (left/right, or next to / away from the source bin), nothing names another one, and no bound
  direction is the opposite of an expected one. Expected directions come from the episode's ground truth
  (``expectation_for``): the hand's net displacement in the phase a motion names, read from ``steps.npz``,
  and the camera's pose for words that depend on it (image left/right, top/bottom).

Every hit keeps its span, matched text and lexicon entry, so a report can show
why a caption scored as it did. A missing or empty caption scores as an empty
text: nothing mentioned, nothing correct, zero words.
"""

from __future__ import annotations

import hashlib
import json
import re
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field, fields
from functools import cache, lru_cache
from importlib import resources

import numpy as np

from vlmproprio.chat import Answer, ChatRequest
from vlmproprio.episodes import Episode
from vlmproprio.errors import VlmproprioError

ITEMS = ("object", "action", "trajectory")
LEXICON_PACKAGE = "vlmproprio/lexicons"
COMMON_LEXICON = "common.json"
CAMERAS_FILE = "cameras.json"
NOT_TASKS = (COMMON_LEXICON, "judge.json", CAMERAS_FILE)

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
    # object | action | wrong_action | contextual | direction | row | image_row | side | column | noun
    # | negation | failure | neutral | source
    kind: str
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
    expected: tuple[str, ...] = ()  # constant directions (a lexicon without ground-truth motion)
    from_phase: str = ""  # regex of the phase whose hand displacement names the directions
    axes: tuple[str, ...] = ("x", "y", "z")
    min_share: float = 0.5
    return_phase: str = ""  # the motion reverses in this phase (a lever springing back)
    return_cues: tuple[str, ...] = ()


@dataclass(frozen=True)
class Contextual:
    """A verb whose meaning depends on the first object or direction after it (door.json action.contextual)."""

    name: str
    window: int
    as_group: str
    when_next_is: frozenset[str]
    entry: str


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
    keep_together: frozenset[tuple[str, str]] = frozenset()
    contextual: dict[str, Contextual] = field(default_factory=dict)
    gapped_window: int = 0
    gapped: dict[str, tuple[tuple[str, Tag], ...]] = field(default_factory=dict)  # first word -> (second, tag)
    gapped_needs: dict[str, frozenset[str]] = field(default_factory=dict)  # group -> words one of which must be between

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
    return sorted(n[:-5] for n in names if n not in NOT_TASKS)


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


class _Terms:
    """The lexicon's terms and their tags, in the order added (that order is the order of a term's tags)."""

    def __init__(self) -> None:
        self.tags: dict[tuple[str, ...], list[Tag]] = {}

    def add(self, text: str, tag: Tag) -> None:
        toks = tuple(_words(text))
        if not toks:
            raise ValueError(f"empty term {text!r} in {tag.entry}")
        self.tags.setdefault(toks, []).append(tag)

    def add_all(self, words, kind: str, value: str | None, entry: str) -> None:
        """Each word tagged (kind, value, entry); value None: the word itself."""
        for w in words:
            self.add(w, Tag(kind, w if value is None else value, entry))

    def index(self) -> dict[str, tuple[Term, ...]]:
        """Terms by first word, longest first (then alphabetically), each tag once."""
        index: dict[str, list[Term]] = {}
        for toks, tags in self.tags.items():
            index.setdefault(toks[0], []).append(Term(toks, tuple(dict.fromkeys(tags))))
        return {k: tuple(sorted(v, key=lambda t: (-len(t.tokens), t.tokens))) for k, v in index.items()}


def _add_common_terms(terms: _Terms, common: dict) -> None:
    c = "common.json"
    for key, words in common["objects"].items():
        if key == "about":
            continue
        terms.add_all([key, *words], "object", key, f"{c}:objects.{key}")
    for d, words in common["directions"]["terms"].items():
        terms.add_all(words, "direction", d, f"{c}:directions.terms.{d}")
    terms.add_all(common["negation"]["cues"], "negation", None, f"{c}:negation.cues")
    terms.add_all(common["negation"].get("failure_cues", ()), "failure", None, f"{c}:negation.failure_cues")
    terms.add_all(common["neutral"]["terms"], "neutral", None, f"{c}:neutral.terms")


def _contextuals(terms: _Terms, action: dict, fname: str) -> dict[str, Contextual]:
    contextual = {}
    for name, spec_c in action.get("contextual", {}).items():
        if name == "about":
            continue
        entry = f"{fname}:action.contextual.{name}"
        if spec_c["as_group"] not in action["groups"]:
            raise ValueError(f"contextual {name!r}: group {spec_c['as_group']!r} is not in action.groups")
        terms.add_all(spec_c["terms"], "contextual", name, entry)
        contextual[name] = Contextual(
            name,
            int(spec_c["window"]),
            spec_c["as_group"],
            frozenset(" ".join(_words(w)) for w in spec_c["when_next_is"]),
            entry,
        )
    return contextual


def _gapped_terms(action: dict, fname: str) -> dict[str, tuple[tuple[str, Tag], ...]]:
    """Two-word terms that may have words between them: first word -> (second word, tag)."""
    gapped: dict[str, list[tuple[str, Tag]]] = {}
    for group, words in action.get("gapped", {}).get("terms", {}).items():
        if group not in action["groups"]:
            raise ValueError(f"gapped group {group!r} is not in action.groups")
        for w in words:
            toks = _words(w)
            if len(toks) != 2:
                raise ValueError(f"gapped term {w!r} must be two words")
            gapped.setdefault(toks[0], []).append((toks[1], Tag("action", group, f"{fname}:action.gapped.{group}")))
    return {k: tuple(v) for k, v in gapped.items()}


def _required_groups(action: dict) -> tuple[tuple[str, ...], ...]:
    required = tuple(tuple(alts) for alts in action["required"])
    for alts in required:
        for g in alts:
            if g not in action["groups"]:
                raise ValueError(f"required group {g!r} is not in action.groups")
    return required


def _motion(m: dict, groups: dict) -> Motion:
    for g in m["groups"]:
        if g not in groups:
            raise ValueError(f"motion {m['name']!r}: group {g!r} is not in action.groups")
    axes = tuple(m.get("axes", ("x", "y", "z")))
    if not set(axes) <= set(AXES):
        raise ValueError(f"motion {m['name']!r}: axes {axes} not among x, y, z")
    return Motion(
        name=m["name"],
        groups=tuple(m["groups"]),
        expected=tuple(m.get("expected", ())),
        from_phase=m.get("from_phase", m.get("expected_from_phase", "")),
        axes=axes,
        min_share=float(m.get("min_share", 0.5)),
        return_phase=m.get("return_phase", ""),
        return_cues=tuple(m.get("return_cues", ())),
    )


def _compartment(terms: _Terms, traj: dict, fname: str) -> CompartmentRules | None:
    if "compartment" not in traj:
        return None
    comp = traj["compartment"]
    rules = CompartmentRules(window=int(comp["window"]))
    where = f"{fname}:trajectory.compartment"
    terms.add_all(comp["nouns"], "noun", None, f"{where}.nouns")
    for row, words in comp["rows"].items():
        terms.add_all(words, "row", row, f"{where}.rows.{row}")
    for side, words in comp["sides"].items():
        terms.add_all(words, "side", side, f"{where}.sides.{side}")
    for image_row, words in comp.get("image_rows", {}).items():
        terms.add_all(words, "image_row", image_row, f"{where}.image_rows.{image_row}")
    for col, words in comp.get("columns", {}).items():
        terms.add_all(words, "column", col, f"{where}.columns.{col}")
    terms.add_all(comp["source_cues"], "source", None, f"{where}.source_cues")
    return rules


def _build_lexicon(task: str, common: dict, spec: dict, fname: str, raw: bytes) -> Lexicon:
    # The order of the steps below is the order of every term's tags: keep it.
    terms = _Terms()
    _add_common_terms(terms, common)
    action = spec["action"]
    for group, words in action["groups"].items():
        terms.add_all(words, "action", group, f"{fname}:action.groups.{group}")
    terms.add_all(action["wrong"], "wrong_action", None, f"{fname}:action.wrong")
    contextual = _contextuals(terms, action, fname)
    gapped = _gapped_terms(action, fname)
    required = _required_groups(action)
    traj = spec["trajectory"]
    motions = tuple(_motion(m, action["groups"]) for m in traj["motions"])
    compartment = _compartment(terms, traj, fname)
    gap = action.get("gapped", {})
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
        motions=motions,
        compartment=compartment,
        index=terms.index(),
        keep_together=frozenset(tuple(_words(w)) for w in breaks.get("keep_together", ())),
        contextual=contextual,
        gapped_window=int(gap.get("window", 0)),
        gapped=gapped,
        gapped_needs={g: frozenset(w) for g, w in gap.get("needs_between", {}).items()},
    )


# ---------------------------------------------------------------------------------------------- expectation

AXES = ("x", "y", "z")
# Directions whose meaning never depends on the camera: the robot's frame (forward = +x, left = +y, up = +z).
ROBOT_VECTORS: dict[str, tuple[float, float, float]] = {
    "forward": (1.0, 0.0, 0.0),
    "backward": (-1.0, 0.0, 0.0),
    "robot_left": (0.0, 1.0, 0.0),
    "robot_right": (0.0, -1.0, 0.0),
    "up": (0.0, 0.0, 1.0),
    "down": (0.0, 0.0, -1.0),
}
# A hand displacement shorter than this (m) names no direction (as vlmproprio.primitives.MIN_MOVE_M).
MIN_MOVE_M = 0.01
# A camera axis counts as one of the robot's when their cosine is at least this.
AXIS_COS = 0.5


@dataclass(frozen=True)
class CameraAxes:
    """Image right, image up and viewing direction of an episode's camera, unit vectors in the robot's frame."""

    right: tuple[float, float, float]
    up: tuple[float, float, float]
    view: tuple[float, float, float]
    source: str


@lru_cache(maxsize=1)
def _camera_table() -> dict:
    data, _ = _read_lexicon_file(CAMERAS_FILE)
    if not isinstance(data.get("envs"), dict):
        raise ScoringError(f"lexicon {LEXICON_PACKAGE}/{CAMERAS_FILE}: missing 'envs'")
    return data["envs"]


def _axes(d: dict, where: str) -> CameraAxes:
    try:
        vecs = [np.asarray(d[k], dtype=float) for k in ("right", "up", "view")]
    except (KeyError, TypeError, ValueError) as exc:
        raise ScoringError(f"{where}: camera axes need right, up and view as 3-vectors ({exc})") from exc
    if any(v.shape != (3,) or not np.isfinite(v).all() or np.linalg.norm(v) < 1e-6 for v in vecs):
        raise ScoringError(f"{where}: camera axes need right, up and view as non-zero 3-vectors")
    r, u, v = (tuple(float(x) for x in vec / np.linalg.norm(vec)) for vec in vecs)
    return CameraAxes(r, u, v, where)


def camera_axes(episode: Episode) -> CameraAxes | None:
    """The pose of the episode's camera: its own (episode.json extra.camera_axes, written by the demo importer),
    else the shipped table (lexicons/cameras.json by env and camera name), else None (unknown camera)."""
    own = episode.extra.get("camera_axes") if isinstance(episode.extra, dict) else None
    if own is not None:
        return _axes(own, f"episode {episode.episode_id}: episode.json extra.camera_axes")
    for env_prefix, cams in _camera_table().items():
        if episode.env_name.startswith(env_prefix) and episode.camera in cams:
            return _axes(cams[episode.camera], f"{CAMERAS_FILE}: {env_prefix}/{episode.camera}")
    return None


def direction_vectors(camera: CameraAxes | None) -> dict[str, np.ndarray]:
    """Unit vector of every direction value in the robot's frame; plain left/right are the image's when the
    camera is known, else the robot's (the shipped bin camera's convention: image left = robot left)."""
    out = {k: np.asarray(v) for k, v in ROBOT_VECTORS.items()}
    if camera is None:
        out["left"], out["right"] = out["robot_left"], out["robot_right"]
    else:
        out["right"] = np.asarray(camera.right)
        out["left"] = -np.asarray(camera.right)
    return out


@dataclass(frozen=True)
class MotionExpectation:
    name: str
    groups: tuple[str, ...]
    expected: tuple[str, ...]
    source: str  # where ``expected`` comes from, for the audit
    opposite: tuple[str, ...] = ()
    returns: tuple[str, ...] = ()  # directions of the motion's return phase (the lever springing back up)
    return_cues: tuple[str, ...] = ()


@dataclass(frozen=True)
class Expectation:
    """What a correct caption of one episode says: from the episode's ground truth and the lexicon."""

    task: str
    target_object: str
    target_row: str | None
    target_side: str | None  # the robot's side of the target compartment (left | right)
    motions: tuple[MotionExpectation, ...]
    image_side: str | None = None  # the side word in the camera's image; None when the camera does not tell
    image_rows: tuple[tuple[str, str], ...] = ()  # (image word top|bottom, row near|far) for this camera
    target_column: str | None = None  # next_to_source | away_from_source
    camera: str = ""  # where the camera pose came from

    def to_dict(self) -> dict:
        return asdict(self)


def _consistent_steps(episode: Episode):
    """The full-rate states when they belong to this episode (one row per sim step), else None."""
    path = episode.root / "steps.npz"
    if not path.is_file():
        return None
    try:
        st = episode.step_states
    except VlmproprioError:
        return None
    if len(st.step) != episode.steps + 1 or (len(st.phase) and int(st.phase.max()) >= len(episode.phase_names)):
        return None
    return st


def phase_displacement(episode: Episode, phase_pattern: str) -> tuple[np.ndarray | None, str]:
    """The hand's net displacement (m, robot frame) over the steps of the phases matching the pattern.

    From ``steps.npz`` when the episode has one; else (an episode without full-rate states) a pseudo
    displacement from the sampled frames' direction labels, one unit vector per moving frame."""
    pat = re.compile(phase_pattern, re.IGNORECASE)
    st = _consistent_steps(episode)
    if st is not None:
        names = [i for i, n in enumerate(episode.phase_names) if pat.search(n)]
        idx = np.flatnonzero(np.isin(st.phase, names))
        if not len(idx):
            return None, f"steps.npz: no step in a phase matching {phase_pattern!r}"
        first, last = int(idx[0]), int(idx[-1])
        delta = st.ee[last, :3] - st.ee[first, :3]
        where = ", ".join(repr(episode.phase_names[i]) for i in names)
        d = "(" + ", ".join(f"{x:+.3f}" for x in delta) + ")"
        return (
            delta,
            f"steps.npz: hand displacement {d} m over steps {int(st.step[first])}..{int(st.step[last])} ({where})",
        )
    moving = [f for f in episode.frames if pat.search(f.phase) and f.direction not in ("still", "")]
    if not moving:
        return None, f"ground truth: no moving frame in a phase matching {phase_pattern!r}"
    total = np.zeros(3)
    for f in moving:
        v = sum(
            (np.asarray(ROBOT_VECTORS["robot_" + w if w in ("left", "right") else w]) for w in f.direction.split("+")),
            np.zeros(3),
        )
        total += v / np.linalg.norm(v)
    idx = [f.index for f in moving]
    return (
        total,
        f"ground truth: direction labels of {len(moving)} moving frames {idx[0]}..{idx[-1]} in phase {moving[0].phase!r}",
    )


def directions_of(delta: np.ndarray | None, axes: Sequence[str], min_share: float, vectors: dict[str, np.ndarray]):
    """(expected, opposite) direction values for a displacement restricted to ``axes``: a value is expected
    when its unit vector carries at least ``min_share`` of the displacement, opposite when it carries that
    much against it."""
    if delta is None:
        return (), ()
    d = np.array([delta[i] if a in axes else 0.0 for i, a in enumerate(AXES)])
    norm = float(np.linalg.norm(d))
    if norm < MIN_MOVE_M:
        return (), ()
    share = {k: float(d @ v) / norm for k, v in vectors.items()}
    return tuple(sorted(k for k, c in share.items() if c >= min_share)), tuple(
        sorted(k for k, c in share.items() if c <= -min_share)
    )


def _image_words(cam: CameraAxes | None) -> tuple[str | None, tuple[tuple[str, str], ...]]:
    """(the image side of the robot's left, image row words -> near/far) for a camera; None/() where it does not tell."""
    if cam is None:  # the shipped convention: image left = robot left, top of the image = far from the robot
        return "left", (("top", "far"), ("bottom", "near"))
    left_in_image = -float(np.asarray(ROBOT_VECTORS["robot_left"]) @ np.asarray(cam.right))
    side = "left" if left_in_image >= AXIS_COS else "right" if left_in_image <= -AXIS_COS else None
    far_up = float(np.asarray(ROBOT_VECTORS["forward"]) @ np.asarray(cam.up))
    rows: tuple[tuple[str, str], ...] = ()
    if far_up >= AXIS_COS:
        rows = (("top", "far"), ("bottom", "near"))
    elif far_up <= -AXIS_COS:
        rows = (("top", "near"), ("bottom", "far"))
    return side, rows


def expectation_for(episode: Episode, lexicon: Lexicon | None = None) -> Expectation:
    lex = lexicon or load_lexicon(episode.task)
    cam = camera_axes(episode)
    vectors = direction_vectors(cam)
    motions = []
    for m in lex.motions:
        opposite: tuple[str, ...] = ()
        returns: tuple[str, ...] = ()
        if m.from_phase:
            delta, source = phase_displacement(episode, m.from_phase)
            expected, opposite = directions_of(delta, m.axes, m.min_share, vectors)
            if m.return_phase:
                back, back_source = phase_displacement(episode, m.return_phase)
                returns, _ = directions_of(back, m.axes, m.min_share, vectors)
                source += f"; returns {'/'.join(returns) or 'nowhere'} from {back_source}"
        else:
            expected, source = m.expected, f"lexicon {lex.task}.json"
            opposite = tuple(sorted({lex.opposite[d] for d in expected if d in lex.opposite}))
        unknown = [d for d in expected if d not in lex.opposite]
        if unknown:
            raise ScoringError(f"episode {episode.episode_id}: unknown direction words {unknown} for motion {m.name!r}")
        returns = tuple(d for d in returns if d not in expected)
        motions.append(MotionExpectation(m.name, m.groups, expected, source, opposite, returns, tuple(m.return_cues)))
    row = side = column = image_side = None
    image_rows: tuple[tuple[str, str], ...] = ()
    if lex.compartment is not None:
        if episode.target_bin is None:
            raise ScoringError(f"episode {episode.episode_id}: task {episode.task} needs a target_bin in episode.json")
        row, side = episode.target_bin.row, episode.target_bin.side
        if row not in ("near", "far") or side not in ("left", "right"):
            raise ScoringError(
                f"episode {episode.episode_id}: target_bin row/side {row!r}/{side!r} not near|far, left|right"
            )
        # robosuite's PickPlace.not_in_bin index: bit 1 set = the column away from the source bin
        column = "away_from_source" if episode.target_bin.index & 2 else "next_to_source"
        left_word, image_rows = _image_words(cam)
        if left_word is not None:
            image_side = side if left_word == "left" else lex.opposite[side]
    return Expectation(
        task=episode.task,
        target_object=lex.object_key(episode.target_object),
        target_row=row,
        target_side=side,
        motions=tuple(motions),
        image_side=image_side,
        image_rows=image_rows,
        target_column=column,
        camera=cam.source if cam else "unknown camera: image words read in the robot's frame",
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
        # asdict's deep copy of ten scalars costs more than scoring the caption (an audit holds ~12 000 hits)
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


def tokenize(text: str, lexicon: Lexicon) -> list[Token]:
    out = []
    clause = 0
    matches = list(_TOKEN_RE.finditer(text))
    words = [m.group(0).lower().replace("’", "'") for m in matches]
    for i, m in enumerate(matches):
        tok = words[i]
        is_word = tok not in lexicon.clause_punct
        kept = i + 1 < len(words) and (tok, words[i + 1]) in lexicon.keep_together
        if not is_word or (tok in lexicon.clause_words and not kept):
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
    return cands + _match_gapped(tokens, lex, cands)


def _match_gapped(tokens: list[Token], lex: Lexicon, cands: list[_Cand]) -> list[_Cand]:
    """Split phrasal verbs ("set it down"): extra candidates spanning verb..particle; words between keep theirs."""
    spans = {(c.first, c.last) for c in cands}
    objects = {c.first for c in cands if _tag(c, ("object",))}
    owned: dict[int, set[tuple[str, str]]] = {}  # the tags of the matches starting at each token
    for c in cands:
        owned.setdefault(c.first, set()).update((t.kind, t.value) for t in c.term.tags)
    out = []
    for i, tok in enumerate(tokens):
        gapped = lex.gapped.get(tok.text, ()) if tok.is_word else ()
        own = owned.get(i, set()) if gapped else set()
        for second, tag in gapped:
            for j in range(i + 1, min(len(tokens), i + lex.gapped_window + 2)):
                if not tokens[j].is_word or tokens[j].clause != tok.clause:
                    break
                if tokens[j].text == second:
                    needs = lex.gapped_needs.get(tag.value)
                    between = set(range(i + 1, j))
                    has_needed = needs is None or any(
                        tokens[k].text in needs or ("<object>" in needs and k in objects) for k in between
                    )
                    # skip when the unsplit phrase already matched, or the verb alone means the same
                    if (i, j) not in spans and (tag.kind, tag.value) not in own and has_needed:
                        term = Term((tok.text, second), (tag,))
                        out.append(_Cand(i, j, term, tag.kind, tag.value, tag.entry))
                    break
            else:
                continue
            break
    return out


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
        others = ("side",) if kind in ("row", "image_row") else ("row", "image_row")
        return any(o is not c and _tag(o, others) and (o.first == c.last + 1 or c.first == o.last + 1) for o in cands)

    for c in cands:
        if c.kind:  # split phrasal verbs come tagged
            continue
        column = _tag(c, ("column",)) if lex.compartment else None
        comp = _tag(c, ("row", "image_row", "side")) if lex.compartment else None
        if column is not None:
            chosen = column
        elif comp is not None and (near_noun(c) or pair(c, comp.kind)):
            chosen = comp
        else:
            order = (
                "neutral",
                "negation",
                "failure",
                "source",
                "noun",
                "object",
                "wrong_action",
                "contextual",
                "action",
                "direction",
            )
            chosen = next((t for k in order for t in c.term.tags if t.kind == k), None)
        if chosen is not None:
            c.kind, c.value, c.entry = chosen.kind, chosen.value, chosen.entry
    out = sorted((c for c in cands if c.kind), key=lambda c: (c.first, c.last))
    _resolve_contextual(out, tokens, lex)
    return out


def _resolve_contextual(cands: list[_Cand], tokens: list[Token], lex: Lexicon) -> None:
    """'push the lever down' turns the handle; 'push the door' is a wrong action (door.json action.contextual)."""
    for c in cands:
        if c.kind != "contextual":
            continue
        rule = lex.contextual[c.value]
        clause = tokens[c.first].clause
        nxt = next(
            (
                o
                for o in cands
                if o.first > c.last
                and o.kind in ("object", "direction", "noun")
                and tokens[o.first].clause == clause
                and o.first - c.last <= rule.window
            ),
            None,
        )
        said = " ".join(t.text for t in tokens[nxt.first : nxt.last + 1]) if nxt else ""
        if nxt is not None and (said in rule.when_next_is or said.split()[-1] in rule.when_next_is):
            c.kind, c.value = "action", rule.as_group
        else:
            c.kind, c.value = "wrong_action", rule.name
        c.entry = rule.entry


def _negated(c: _Cand, cands: list[_Cand], tokens: list[Token], lex: Lexicon) -> bool:
    clause = tokens[c.first].clause
    for j in range(max(0, c.first - lex.negation_window), c.first):
        if tokens[j].clause == clause and tokens[j].text.endswith(lex.negation_suffixes):
            return True
    return any(
        o.kind == "negation" and tokens[o.first].clause == clause and 0 < c.first - o.last <= lex.negation_window
        for o in cands
    )


@dataclass(frozen=True)
class TextAnalysis:
    """What a caption says in a lexicon's terms, before any episode judges it: its tokens, its matches (each
    with one meaning and whether it is negated) and the actions a failure cue takes back. The same text and
    lexicon give the same analysis; nothing downstream changes it, so cells with the same caption share it."""

    tokens: list[Token]
    cands: list[_Cand]
    failed: set[int]  # ids of the action candidates a later failure cue negates


def analyse_text(text: str, lexicon: Lexicon) -> TextAnalysis:
    """Tokenize ``text`` and match, resolve and negate its terms (the expectation-free half of ``score_text``)."""
    tokens = tokenize(text or "", lexicon)
    cands = _resolve(_match_terms(tokens, lexicon), tokens, lexicon)
    for c in cands:
        if c.kind in ("action", "wrong_action", "direction", "row", "image_row", "side", "column"):
            c.negated = _negated(c, cands, tokens, lexicon)
    return TextAnalysis(tokens, cands, _failed_actions(cands, tokens))


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


def _failed_actions(cands: list[_Cand], tokens: list[Token]) -> set[int]:
    """ids of the action candidates that a later failure cue ("... but fails") negates: the nearest action
    before each cue in the same sentence."""
    out = set()
    for f in cands:
        if f.kind != "failure":
            continue
        for c in sorted((c for c in cands if c.kind == "action" and c.last < f.first), key=lambda c: -c.last):
            if any(t.text in (".", "!", "?") for t in tokens[c.last : f.first]):
                break
            out.add(id(c))
            break
    return out


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


_JUDGE_WORDS = {
    "robot_left": "to the robot's left",
    "robot_right": "to the robot's right",
    "left": "left in the image",
    "right": "right in the image",
    "forward": "forward (away from the robot)",
    "backward": "backward (toward the robot)",
}


def _trajectory_truth(exp: Expectation) -> str:
    """The ground truth a judge grades the trajectory against, in words (as expectation_for derives it)."""

    def words(ds: Sequence[str]) -> str:
        return " and ".join(_JUDGE_WORDS.get(d, d) for d in ds)

    parts = []
    for m in exp.motions:
        if m.expected:
            text = f"{m.name}: {words(m.expected)}"
            if m.returns:
                text += f" (afterwards it returns {words(m.returns)})"
            parts.append(text)
    if exp.target_row:
        column = (exp.target_column or "").replace("_", " ")
        side = f", {exp.image_side} in the image" if exp.image_side else ""
        parts.insert(
            0,
            f"the object goes to the {exp.target_row} compartment of the target bin on the robot's "
            f"{exp.target_side}{side} ({column} bin; near/far = from the robot)",
        )
    return "; ".join(parts) or "none"


def judge_request(text: str, episode: Episode, condition: str = ""):
    """The chat request asking a judge model to grade one caption of an episode."""
    from string import Template

    from vlmproprio.chat import GenerationConfig, Message, RequestTag, TextPart

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


def judge_captions(
    answer: Callable[[Sequence[ChatRequest]], list[Answer]], captions: Sequence[tuple[str, Episode, str]]
) -> list[JudgeVerdict]:
    """Grade (text, episode, condition) triples, in order, with ``answer`` (a judge's ``Answerer.answer``, see
    vlmproprio.answering: its requests go through the same content-addressed response cache and cassettes as
    captioning, so a judge's verdicts replay bit-identically)."""
    requests = [judge_request(text, ep, cond) for text, ep, cond in captions]
    answers = answer(requests) if requests else []
    if len(answers) != len(requests):
        raise ScoringError(f"judge answered {len(answers)} of {len(requests)} requests")
    return [parse_judge_answer(a.text) for a in answers]


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
