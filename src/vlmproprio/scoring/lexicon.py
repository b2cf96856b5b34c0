"""The scoring lexicons: versioned word lists and rules read from package data, merged per task.

Words and rules live in ``vlmproprio/lexicons/*.json`` (``common.json`` plus one file per task); a
:class:`Lexicon` is their merged, indexed form. Terms are lower-case word sequences, indexed by their first
word, longest first. A lexicon records its version and the sha256 of the files it was built from, so a
score names the words that produced it.
"""

from __future__ import annotations

import hashlib
import json
import re
from dataclasses import dataclass, field
from functools import cache
from importlib import resources

from vlmproprio.errors import VlmproprioError

LEXICON_PACKAGE = "vlmproprio/lexicons"
COMMON_LEXICON = "common.json"
CAMERAS_FILE = "cameras.json"
NOT_TASKS = (COMMON_LEXICON, "judge.json", CAMERAS_FILE)
# The robot frame's axes, the names a motion's ``axes`` may use.
AXES = ("x", "y", "z")

# Numbers (with a decimal point) are one token so "0.4" never splits a clause; words may carry an apostrophe.
_TOKEN_RE = re.compile(r"\d+(?:\.\d+)?|[^\W_]+(?:['’][^\W_]+)*|[,;.:!?()]")


class ScoringError(VlmproprioError):
    """A lexicon or an episode that the scorer cannot use; the message says which file or field."""


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
    # package data of vlmproprio (pyproject.toml's package-data), not a package of its own
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
