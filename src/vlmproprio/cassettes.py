"""Cassettes: a model's answers frozen in one file, committed beside the fixtures.

``fixtures/responses/<model slug>.jsonl``: line 1 is a header (model name,
identity, key version, checksum), then one answer per line
``{key, text, meta, tag, status, checksum}`` sorted by key (and ``reasoning``
when the server returned some beside the answer), each line a
compact JSON object with sorted keys, so re-recording gives small diffs. Keys
and entries are those of vlmproprio.cache; a line whose checksum does not
match is an error naming the file and line.

A cassette is committed as what the model answers, so answers that hold no caption (empty, a refusal, a tool
call, a content filter, an answer cut off before any text) or that another model gave are refused in it
(``check_recordable``) unless the recording says it wants them (``--allow-empty-answers``).
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, replace
from pathlib import Path

from vlmproprio.cache import (
    KEY_VERSION,
    CacheEntry,
    CacheError,
    ResponseCache,
    canonical_json,
    checksum,
    entry_from_record,
    key_identity,
)
from vlmproprio.chat import ANSWER_PROBLEMS, RequestTag, answer_problem
from vlmproprio.episodes.manifest import write_fixture_file
from vlmproprio.errors import VlmproprioError
from vlmproprio.io import loads_json, read_limited
from vlmproprio.secrets import scrub, scrub_obj

CASSETTE_VERSION = 1


class CassetteError(VlmproprioError):
    """A cassette file that cannot be used; the message names the file and line."""


class ReplayMissError(VlmproprioError):
    """Replay mode met a request that no recording answers."""

    def __init__(self, message: str, key: str, tag: RequestTag) -> None:
        super().__init__(message)
        self.key = key
        self.tag = tag


def replay_miss_message(model: str, key: str, tag: RequestTag, where: str) -> str:
    return (
        f"no recorded answer for {tag} (key {key}) in {where}. Replay mode never calls a model: record it by "
        f"running it in record mode where it can run (`vlmproprio run --model {model} --mode record`, which writes "
        f"<fixtures>/responses/{model}.jsonl; answers already in a response cache: "
        f"`vlmproprio cassette export --model {model}`) and commit the cassette"
    )


@dataclass(frozen=True)
class Cassette:
    """A frozen set of answers for one model identity."""

    path: Path
    model: str
    identity: dict[str, str]
    entries: dict[str, CacheEntry]


def cassette_header(model: str, identity: dict) -> dict:
    head = {
        "cassette": CASSETTE_VERSION,
        "key_version": KEY_VERSION,
        "model": model,
        "identity": key_identity(identity),
    }
    head["checksum"] = checksum(head)
    return head


def read_cassette(path: Path | str) -> Cassette:
    """Load and verify a cassette; any bad line is a CassetteError naming the file and line number."""
    path = Path(path)
    try:
        raw = read_limited(path, error=CassetteError)
    except FileNotFoundError as exc:
        raise CassetteError(f"{path}: cannot read cassette (missing)") from exc
    lines = raw.split(b"\n")
    if lines and lines[-1] == b"":
        lines.pop()
    if not lines:
        raise CassetteError(f"{path}:1: empty cassette (no header line)")

    def parse(lineno: int, data: bytes) -> dict:
        obj = loads_json(data, f"{path}:{lineno}", error=CassetteError)
        if not isinstance(obj, dict):
            raise CassetteError(f"{path}:{lineno}: expected a JSON object")
        return obj

    head = parse(1, lines[0])
    if head.get("cassette") != CASSETTE_VERSION or head.get("key_version") != KEY_VERSION:
        raise CassetteError(
            f"{path}:1: not a version-{CASSETTE_VERSION} cassette header "
            f"(cassette={head.get('cassette')!r}, key_version={head.get('key_version')!r})"
        )
    if checksum(head) != head.get("checksum"):
        raise CassetteError(f"{path}:1: header checksum mismatch (the header was changed or damaged)")
    if not isinstance(head.get("identity"), dict) or not isinstance(head.get("model"), str):
        raise CassetteError(f"{path}:1: header lacks 'model' or 'identity'")
    model, identity = head["model"], key_identity(head["identity"])
    entries: dict[str, CacheEntry] = {}
    previous = ""
    for i, data in enumerate(lines[1:], start=2):
        rec = parse(i, data)
        try:
            entry = entry_from_record(rec, model=model, identity=identity)
        except ValueError as exc:
            raise CassetteError(f"{path}:{i}: bad answer line: {exc}") from exc
        if entry.key <= previous:
            raise CassetteError(f"{path}:{i}: keys not strictly increasing (duplicate or unsorted line)")
        previous = entry.key
        if entry.model != model or entry.identity is not identity:  # a line that names its own model
            entry = replace(entry, model=model, identity=identity)
        entries[entry.key] = entry
    return Cassette(path=path, model=model, identity=identity, entries=entries)


def write_cassette(
    path: Path | str, model: str, identity: dict, entries: Iterable[CacheEntry], *, merge: bool = True
) -> Path:
    """Write (atomically) a cassette with ``entries``; with ``merge``, keep the answers already in ``path``.
    In a fixture set's ``responses/``, its manifest entry is written with it (episodes.write_fixture_file).

    Merging into a cassette recorded from another identity is refused: one file, one model identity.
    """
    path = Path(path)
    ident = key_identity(identity)
    merged: dict[str, CacheEntry] = {}
    old = None
    if path.exists():
        try:
            old = read_cassette(path)
        except CassetteError:
            if merge:
                raise
            # --replace over a damaged file: nothing readable to protect
    if old is not None:
        if old.model != model:
            # never advise deleting it: that file holds another model's answers
            raise CassetteError(
                f"{path} holds the answers of another model ({old.model}), not of {model}; refusing to overwrite "
                "it: write this cassette to another file (`vlmproprio cassette export --model MODEL --out FILE`)"
            )
        if merge and old.identity != ident:
            raise CassetteError(
                f"{path}: recorded from {_describe(old.identity)}, not {_describe(ident)} ({len(old.entries)} answers "
                f"of {model}); one cassette holds one identity: write this one to another file "
                "(`vlmproprio cassette export --model MODEL --out FILE`)"
            )
        if merge:
            merged.update(old.entries)
    for e in map(scrubbed_entry, entries):
        old = merged.get(e.key)
        if old is None or (old.text, old.status, old.reasoning) != (e.text, e.status, e.reasoning):
            merged[e.key] = e  # an unchanged answer keeps its old line (and latency): re-recording diffs stay small
    lines = [canonical_json(cassette_header(model, ident))]
    lines += [canonical_json(merged[k].cassette_record()) for k in sorted(merged)]
    # with its manifest entry when it lies in a fixture set: a full disk leaves both as they were
    write_fixture_file(path, scrub("\n".join(lines) + "\n").encode("utf-8"))
    return path


def _describe(identity: dict) -> str:
    return ", ".join(f"{k} {v}" for k, v in identity.items() if v)


def scrubbed_entry(entry: CacheEntry) -> CacheEntry:
    """``entry`` with secrets masked in its answer text, reasoning and metadata (unchanged when it holds none)."""
    text, meta, reasoning = scrub(entry.text), scrub_obj(entry.meta), scrub(entry.reasoning)
    if (text, meta, reasoning) == (entry.text, entry.meta, entry.reasoning):
        return entry
    return replace(entry, text=text, meta=meta, reasoning=reasoning)


ALLOW_EMPTY_FLAG = "--allow-empty-answers"


def unrecordable(entries: Iterable[CacheEntry]) -> dict[str, int]:
    """How many answers of each kind a cassette should not hold: by chat.ANSWER_PROBLEMS class, "empty" for an
    empty answer with none, and "other_model" even with text (it is another model's answer); a text cut off at
    the token limit still holds captions and is kept."""
    counts: dict[str, int] = {}
    for e in entries:
        problem = answer_problem(e.meta)
        if e.status != "ok" or problem == "other_model":
            name = problem or "empty"
            counts[name] = counts.get(name, 0) + 1
    return dict(sorted(counts.items(), key=lambda kv: (-kv[1], kv[0])))


def problem_counts_text(counts: dict[str, int]) -> str:
    """'refusal 12 (the model refused (message.refusal)), empty 1 (...)'."""
    return ", ".join(f"{name} {n} ({ANSWER_PROBLEMS.get(name, 'no text')})" for name, n in counts.items())


def check_recordable(entries: Iterable[CacheEntry], model: str, path: Path | str, *, allow_empty: bool) -> None:
    """Refuse to write answers that hold no caption into ``path`` unless ``allow_empty``: a committed cassette
    of refusals or empty answers would replay as a model that said nothing."""
    entries = list(entries)
    bad = unrecordable(entries)
    if bad and not allow_empty:
        raise CassetteError(
            f"not writing {path}: {sum(bad.values())} of {len(entries)} answers of {model} hold no caption or are "
            f"another model's: {problem_counts_text(bad)}. Fix the server or the request and record again (live "
            f"and record mode ask for empty answers again), or pass {ALLOW_EMPTY_FLAG} to write them anyway; the "
            "answers stay in the response cache"
        )


def export_cassette(
    cache: ResponseCache, model: str, path: Path | str, *, merge: bool = True, allow_empty: bool = False
) -> tuple[Path, int]:
    """Write every cached answer of ``model`` (its slug as stored in the cache) to a cassette; answers that
    hold no caption are refused unless ``allow_empty`` (check_recordable)."""
    entries = list(cache.entries(model=model))
    if not entries:
        present = cache.models()
        listed = ", ".join(f"{m} ({n})" for m, n in sorted(present.items())) or "nothing"
        raise CacheError(
            f"cache {cache.directory} holds no answers for model {model!r} (it holds: {listed}); "
            "run the model in live or record mode first"
        )
    identities = {canonical_json(e.identity) for e in entries}
    if len(identities) > 1:
        listed = "; ".join(sorted(identities))
        raise CacheError(
            f"cache {cache.directory} holds answers of {model!r} from {len(identities)} different identities "
            f"({listed}); a cassette holds one: use a fresh cache directory per model revision"
        )
    check_recordable(entries, model, path, allow_empty=allow_empty)
    return write_cassette(path, model, entries[0].identity, entries, merge=merge), len(entries)


def import_cassette(cache: ResponseCache, path: Path | str) -> tuple[str, int]:
    """Copy a cassette's answers into the cache; returns (model, number of entries newly stored)."""
    cas = read_cassette(path)
    stored = sum(cache.store(e) for e in cas.entries.values())
    return cas.model, stored
