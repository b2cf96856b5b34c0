"""Content-addressed answers: the request key, the on-disk response cache, cassettes, and cached answering.

The request key
---------------
``request_key(identity, request)`` is the lower-case hex sha256 of the UTF-8
bytes of ``json.dumps(doc, sort_keys=True, separators=(",", ":"), ensure_ascii=False)``
where ``doc`` is (KEY_VERSION = 1)::

    {
      "key_version": 1,
      "model": {                      # from Backend.identity(); a missing field counts as ""
        "backend": ..., "model_id": ..., "revision": ..., "dtype": ..., "attn_implementation": ...
      },
      "generation": {"max_new_tokens": int, "temperature": float, "seed": int | null,
                     "min_new_tokens": int | null},          # GenerationConfig.to_dict()
      "prompt_version": str,                                 # ChatRequest.prompt_version
      "messages": [                                          # in order
        {"role": "system" | "user" | "assistant",
         "parts": [                                          # in order, text and images interleaved
           {"type": "text", "text": str},                    # the exact text, not normalised
           {"type": "image", "sha256": hex of the image bytes, "mime": "image/png"}
         ]}
      ]
    }

Nothing else enters the key: not the RequestTag (episode, condition, stage,
group), not the device, batch size, base URL or API key. Identity fields
other than the five above are ignored, so an answer recorded on a GPU replays
on a CPU. Dict order never matters (keys are sorted); list order does.

Entries, the cache and cassettes
--------------------------------
An answer is stored as a JSON object (never a pickle) with a ``checksum``: the
sha256 of the canonical JSON of all its other fields. A value whose checksum
does not match, or that cannot be decoded, is *corrupt*: in live mode it is
dropped and recomputed, in replay mode it is a fatal error.

* ``ResponseCache``: a ``diskcache`` directory (SQLite + WAL) shared by any
  number of processes. Values are JSON through a disk class that refuses to
  unpickle anything, and the first writer of a key wins (``add``), so an
  answer is stored once.
* Cassettes, ``fixtures/responses/<model slug>.jsonl``: line 1 is a header
  (model name, identity, key version, checksum), then one answer per line
  ``{key, text, meta, tag, status, checksum}`` sorted by key, each line a
  compact JSON object with sorted keys, so re-recording gives small diffs.

Answer statuses: ``ok``, or ``empty`` (the model answered nothing). Empty
answers are kept so that a replay gives exactly what the live run gave, but
they are not successes: live mode asks the model again. Failed requests (an
exception) are never stored.
"""

from __future__ import annotations

import functools
import hashlib
import json
import logging
import sqlite3
import time
import zlib
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Literal

from vlmproprio.chat import Answer, AnswerMeta, ChatRequest, ImagePart, RequestTag
from vlmproprio.errors import UsageError, VlmproprioError
from vlmproprio.io import atomic_write_text, loads_json, write_error, writing
from vlmproprio.secrets import scrub, scrub_obj

if TYPE_CHECKING:  # type only: cache comes before backends in the stage order
    from vlmproprio.backends.base import Backend

log = logging.getLogger(__name__)

KEY_VERSION = 1
CASSETTE_VERSION = 1
IDENTITY_FIELDS: tuple[str, ...] = ("backend", "model_id", "revision", "dtype", "attn_implementation")
STATUSES: tuple[str, ...] = ("ok", "empty")
Mode = Literal["replay", "live", "record"]
MODES: tuple[str, ...] = ("replay", "live", "record")
# The response cache is the cache folder itself (its cache.db); embeddings/ and models/ sit beside that file, so
# `--cache-dir DIR` names one folder for every cache and DIR/cache.db is where a run's answers are.


class CacheError(VlmproprioError):
    """The response cache cannot be used (unreadable directory, corrupt entry in replay mode, ...)."""


class CacheCorruptError(CacheError):
    """A cache entry failed its checksum or could not be decoded."""

    def __init__(self, message: str, key: str = "") -> None:
        super().__init__(message)
        self.key = key


class CassetteError(VlmproprioError):
    """A cassette file that cannot be used; the message names the file and line."""


class ReplayMissError(VlmproprioError):
    """Replay mode met a request that no recording answers."""

    def __init__(self, message: str, key: str, tag: RequestTag) -> None:
        super().__init__(message)
        self.key = key
        self.tag = tag


# ---------------------------------------------------------------------------------------------- canonical JSON


def canonical_json(obj: object) -> str:
    """One text per value: sorted keys, no whitespace, UTF-8 kept as is. NaN and infinities are refused."""
    return json.dumps(obj, sort_keys=True, separators=(",", ":"), ensure_ascii=False, allow_nan=False)


def sha256_text(text: str) -> str:
    return hashlib.sha256(text.encode("utf-8")).hexdigest()


def checksum(record: dict) -> str:
    """sha256 of the canonical JSON of ``record`` without its own ``checksum`` field."""
    return sha256_text(canonical_json({k: v for k, v in record.items() if k != "checksum"}))


# ---------------------------------------------------------------------------------------------- the key


def key_identity(identity: dict) -> dict[str, str]:
    """The model-side part of the key: exactly IDENTITY_FIELDS, as strings."""
    return {f: str(identity.get(f, "") or "") for f in IDENTITY_FIELDS}


def key_document(identity: dict, request: ChatRequest) -> dict:
    """The object whose canonical JSON is hashed into the key (see the module docstring)."""
    messages = []
    for m in request.messages:
        parts = []
        for p in m.parts:
            if isinstance(p, ImagePart):
                parts.append({"type": "image", "sha256": p.sha256, "mime": p.mime})
            else:
                parts.append({"type": "text", "text": p.text})
        messages.append({"role": m.role, "parts": parts})
    return {
        "key_version": KEY_VERSION,
        "model": key_identity(identity),
        "generation": request.config.to_dict(),
        "prompt_version": request.prompt_version,
        "messages": messages,
    }


def request_key(identity: dict, request: ChatRequest) -> str:
    """The cache key of ``request`` answered by the model ``identity`` (hex sha256)."""
    return sha256_text(canonical_json(key_document(identity, request)))


# ---------------------------------------------------------------------------------------------- entries


@dataclass(frozen=True)
class CacheEntry:
    """One stored answer. ``model`` and ``identity`` say who answered (used to export cassettes)."""

    key: str
    text: str
    meta: dict
    tag: dict
    status: str = "ok"
    model: str = ""
    identity: dict = field(default_factory=dict)

    @classmethod
    def from_answer(cls, key: str, answer: Answer, tag: RequestTag, model: str, identity: dict) -> CacheEntry:
        return cls(
            key=key,
            text=answer.text,
            meta=answer.meta.to_dict(),
            tag=asdict(tag),
            status="ok" if answer.text.strip() else "empty",
            model=model,
            identity=key_identity(identity),
        )

    def to_answer(self, *, from_cache: bool = True) -> Answer:
        return Answer(text=self.text, meta=AnswerMeta.from_dict(self.meta), key=self.key, from_cache=from_cache)

    def cache_record(self) -> dict:
        rec = asdict(self)
        rec["checksum"] = checksum(rec)
        return rec

    def cassette_record(self) -> dict:
        rec = {"key": self.key, "text": self.text, "meta": self.meta, "tag": self.tag, "status": self.status}
        rec["checksum"] = checksum(rec)
        return rec


def _entry_from_record(rec: object, *, model: str = "", identity: dict | None = None) -> CacheEntry:
    """Validate a decoded record (cache value or cassette line); raises ValueError saying what is wrong."""
    if not isinstance(rec, dict):
        raise ValueError(f"expected a JSON object, got {type(rec).__name__}")
    if "checksum" not in rec:
        raise ValueError("no checksum")
    if checksum(rec) != rec["checksum"]:
        raise ValueError("checksum mismatch (the entry was changed or damaged)")
    for name, typ in (("key", str), ("text", str), ("meta", dict), ("tag", dict), ("status", str)):
        if not isinstance(rec.get(name), typ):
            raise ValueError(f"field {name!r} missing or not a {typ.__name__}")
    if rec["status"] not in STATUSES:
        raise ValueError(f"unknown status {rec['status']!r}")
    try:
        AnswerMeta.from_dict(rec["meta"])
    except TypeError as exc:
        raise ValueError(f"field 'meta' is not answer metadata ({exc})") from None
    rec_model, rec_identity = rec.get("model", model), rec.get("identity", identity or {})
    return CacheEntry(
        key=rec["key"],
        text=rec["text"],
        meta=rec["meta"],
        tag=rec["tag"],
        status=rec["status"],
        model=rec_model if isinstance(rec_model, str) else model,
        identity=rec_identity if isinstance(rec_identity, dict) else {},
    )


# ---------------------------------------------------------------------------------------------- the runtime cache


def cache_root() -> Path:
    """Where vlmproprio keeps its caches: $VLMPROPRIO_CACHE, else the user cache directory (vlmproprio.locations)."""
    from vlmproprio.locations import cache_root as root

    return root()


def default_cache_dir() -> Path:
    """The response cache: the cache folder itself (see cache_root)."""
    return cache_root()


@functools.cache
def _json_only_disk() -> type:
    """diskcache's JSONDisk, minus its pickle fallbacks: a cache file is data and must never run code."""
    import diskcache
    from diskcache.core import MODE_BINARY, MODE_RAW

    class JSONOnlyDisk(diskcache.JSONDisk):
        def get(self, key, raw):
            if not raw:  # JSONDisk stores keys as raw bytes; anything else was not written by us
                raise CacheCorruptError("cache key is not raw JSON bytes (refusing to unpickle)")
            return super().get(key, raw)

        def fetch(self, mode, filename, value, read):
            if mode not in (MODE_RAW, MODE_BINARY):
                raise CacheCorruptError(f"cache value has storage mode {mode} (refusing to unpickle)")
            return super().fetch(mode, filename, value, read)

    return JSONOnlyDisk


class ResponseCache:
    """Answers by key in a diskcache directory; safe for many processes at once.

    Values are JSON (zlib-compressed), checksummed; never evicted (a cache that
    silently forgets answers would turn a replay into a live run).
    """

    def __init__(self, directory: Path | str, *, timeout_s: float = 120.0) -> None:
        import diskcache

        self.directory = Path(directory)
        try:
            self.directory.mkdir(parents=True, exist_ok=True)
        except OSError as exc:  # a file in the way, a read-only or full disk
            raise write_error(self.directory, exc, "create cache directory") from exc
        self._cache = None
        # Opening runs schema setup (PRAGMAs, CREATE TABLE) that can collide with another process doing the same.
        deadline = time.monotonic() + timeout_s
        while True:
            try:
                self._cache = diskcache.Cache(
                    str(self.directory),
                    timeout=timeout_s,
                    disk=_json_only_disk(),
                    eviction_policy="none",
                    disk_compress_level=6,
                )
                break
            except sqlite3.OperationalError as exc:
                if "locked" not in str(exc) or time.monotonic() > deadline:
                    raise CacheError(f"cannot open cache {self.directory}: {exc}") from exc
                time.sleep(0.05)
            except OSError as exc:  # a read-only or full cache folder
                with writing(self.directory, "open cache"):
                    raise exc from None

    # -------------------------------------------------------------------------------- reading
    def get(self, key: str) -> CacheEntry | None:
        """The entry for ``key``, None when absent; CacheCorruptError when it is damaged."""
        try:
            rec = self._cache.get(key, default=None, retry=True)
        except CacheCorruptError as exc:
            raise CacheCorruptError(f"{self._where(key)}: {exc}", key) from exc
        except (zlib.error, ValueError, UnicodeDecodeError, OSError) as exc:
            raise CacheCorruptError(f"{self._where(key)}: cannot decode ({type(exc).__name__}: {exc})", key) from exc
        if rec is None:
            return None
        try:
            entry = _entry_from_record(rec)
        except ValueError as exc:
            raise CacheCorruptError(f"{self._where(key)}: {exc}", key) from exc
        if entry.key != key:
            raise CacheCorruptError(f"{self._where(key)}: entry is stored under another key ({entry.key})", key)
        return entry

    def __contains__(self, key: str) -> bool:
        return key in self._cache

    def __len__(self) -> int:
        return len(self._cache)

    def keys(self) -> list[str]:
        return sorted(self._cache.iterkeys())

    def __iter__(self) -> Iterator[str]:
        return iter(self.keys())

    def entries(self, model: str | None = None) -> Iterator[CacheEntry]:
        """Every valid entry (for ``model`` when given), sorted by key; corrupt ones are skipped with a warning."""
        for key in self.keys():
            try:
                entry = self.get(key)
            except CacheCorruptError as exc:
                log.warning("skipping corrupt cache entry: %s", exc)
                continue
            if entry is not None and (model is None or entry.model == model):
                yield entry

    def models(self) -> dict[str, int]:
        """How many valid entries each model has."""
        counts: dict[str, int] = {}
        for e in self.entries():
            counts[e.model] = counts.get(e.model, 0) + 1
        return counts

    # -------------------------------------------------------------------------------- writing
    def add(self, entry: CacheEntry) -> bool:
        """Store ``entry`` unless its key is present; True when this call stored it."""
        with writing(self.directory, "store an answer in cache"):  # "database or disk is full", read-only
            return bool(self._cache.add(entry.key, entry.cache_record(), retry=True))

    def put(self, entry: CacheEntry) -> None:
        """Store ``entry``, replacing what is there (used to replace empty or corrupt entries)."""
        with writing(self.directory, "store an answer in cache"):
            self._cache.set(entry.key, entry.cache_record(), retry=True)

    def delete(self, key: str) -> bool:
        with writing(self.directory, "delete an entry of cache"):
            return bool(self._cache.delete(key, retry=True))

    def store(self, entry: CacheEntry) -> bool:
        """Add ``entry``; an ``ok`` answer also replaces an ``empty`` one. True when something was written."""
        if self.add(entry):
            return True
        if entry.status != "ok":
            return False
        try:
            existing = self.get(entry.key)
        except CacheCorruptError:
            existing = None
        if existing is None or existing.status != "ok":
            self.put(entry)
            return True
        return False

    def close(self) -> None:
        if self._cache is not None:
            self._cache.close()

    def __enter__(self) -> ResponseCache:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def _where(self, key: str) -> str:
        return f"cache {self.directory}, entry {key}"


# ---------------------------------------------------------------------------------------------- cassettes


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
        raw = path.read_bytes()
    except OSError as exc:
        raise CassetteError(f"{path}: cannot read cassette ({exc.strerror or exc})") from exc
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
            entry = _entry_from_record(rec, model=model, identity=identity)
        except ValueError as exc:
            raise CassetteError(f"{path}:{i}: bad answer line: {exc}") from exc
        if entry.key <= previous:
            raise CassetteError(f"{path}:{i}: keys not strictly increasing (duplicate or unsorted line)")
        previous = entry.key
        entries[entry.key] = replace(entry, model=model, identity=identity)
    return Cassette(path=path, model=model, identity=identity, entries=entries)


def write_cassette(
    path: Path | str, model: str, identity: dict, entries: Iterable[CacheEntry], *, merge: bool = True
) -> Path:
    """Write (atomically) a cassette with ``entries``; with ``merge``, keep the answers already in ``path``.

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
        if old is None or (old.text, old.status) != (e.text, e.status):
            merged[e.key] = e  # an unchanged answer keeps its old line (and latency): re-recording diffs stay small
    lines = [canonical_json(cassette_header(model, ident))]
    lines += [canonical_json(merged[k].cassette_record()) for k in sorted(merged)]
    atomic_write_text(path, "\n".join(lines) + "\n")
    return path


def _describe(identity: dict) -> str:
    return ", ".join(f"{k} {v}" for k, v in identity.items() if v)


def scrubbed_entry(entry: CacheEntry) -> CacheEntry:
    """``entry`` with secrets masked in its answer text and metadata (unchanged when it holds none)."""
    text, meta = scrub(entry.text), scrub_obj(entry.meta)
    return entry if (text, meta) == (entry.text, entry.meta) else replace(entry, text=text, meta=meta)


def export_cassette(cache: ResponseCache, model: str, path: Path | str, *, merge: bool = True) -> tuple[Path, int]:
    """Write every cached answer of ``model`` (its slug as stored in the cache) to a cassette."""
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
    return write_cassette(path, model, entries[0].identity, entries, merge=merge), len(entries)


def import_cassette(cache: ResponseCache, path: Path | str) -> tuple[str, int]:
    """Copy a cassette's answers into the cache; returns (model, number of entries newly stored)."""
    cas = read_cassette(path)
    stored = sum(cache.store(e) for e in cas.entries.values())
    return cas.model, stored


# ---------------------------------------------------------------------------------------------- cached answering


def replay_miss_message(model: str, key: str, tag: RequestTag, where: str) -> str:
    return (
        f"no recorded answer for {tag} (key {key}) in {where}. Replay mode never calls a model: record it by "
        f"running it in record mode where it can run (`vlmproprio run --model {model} --mode record`, which writes "
        f"<fixtures>/responses/{model}.jsonl; answers already in a response cache: "
        f"`vlmproprio cassette export --model {model}`) and commit the cassette"
    )


class CachedBackend:
    """Answers requests from the cache where it can and from ``backend`` where it must.

    Modes:

    * ``live``: serve hits, send misses to the backend in the batches ``backend.plan_batches`` makes
      (at most ``backend.max_batch_size`` each), store each batch's answers as soon as it returns. A corrupt entry is dropped and recomputed.
    * ``record``: as live, and every answer used is kept in :attr:`used` for
      :meth:`export_cassette`.
    * ``replay``: never call a model: hits from the cache (if one is given; a corrupt entry is
      fatal), misses only from a backend that does not call a model (a cassette, the reference
      captioner); any other miss is a ReplayMissError naming the request.
    """

    def __init__(self, backend: Backend, *, mode: str, cache: ResponseCache | None = None, model: str = "") -> None:
        """``model``: the model's slug (``registry.model_slug(name)``), stored with each answer so that
        ``vlmproprio cassette export --model NAME`` finds them; defaults to the identity's model_id."""
        if mode not in MODES:
            raise UsageError(f"unknown mode {mode!r}; choose from {', '.join(MODES)}")
        self.backend = backend
        self.mode: Mode = mode  # type: ignore[assignment]
        self.cache = cache
        self.identity = key_identity(backend.identity())
        self.model = model or self.identity["model_id"]
        self.used: dict[str, CacheEntry] = {}
        self.stats = {"hits": 0, "misses": 0, "stored": 0, "corrupt": 0}

    # -------------------------------------------------------------------------------- public
    def key(self, request: ChatRequest) -> str:
        return request_key(self.identity, request)

    def answer(self, requests: Sequence[ChatRequest]) -> list[Answer]:
        """One answer per request, in request order, with ``key`` and ``from_cache`` set."""
        keys = [self.key(r) for r in requests]
        results: list[Answer | None] = [None] * len(requests)
        todo: dict[str, int] = {}  # key -> first request index that needs the backend
        for i, key in enumerate(keys):
            if key in todo:
                continue
            entry = self._lookup(key)
            if entry is not None:
                self.stats["hits"] += 1
                self._use(entry)
                results[i] = entry.to_answer(from_cache=True)
            else:
                todo[key] = i
        if todo:
            self._answer_misses(requests, todo, results)
        by_key = {k: a for k, a in zip(keys, results, strict=True) if a is not None}
        out = [a if a is not None else by_key[k] for k, a in zip(keys, results, strict=True)]
        return out

    def export_cassette(self, path: Path | str, *, merge: bool = True) -> Path:
        """Write the answers used in this session (record mode) to a cassette."""
        if not self.used:
            raise CacheError("nothing to export: no answers were used in this session")
        return write_cassette(path, self.model, self.identity, self.used.values(), merge=merge)

    # -------------------------------------------------------------------------------- internals
    def _lookup(self, key: str) -> CacheEntry | None:
        if self.cache is None:
            return None
        try:
            entry = self.cache.get(key)
        except CacheCorruptError as exc:
            self.stats["corrupt"] += 1
            if self.mode == "replay":
                raise CacheCorruptError(
                    f"{exc}. Replay mode cannot recompute it: delete {self.cache.directory} and re-import the "
                    "cassette (`vlmproprio cassette import CASSETTE.jsonl`), or run in live mode (--mode live)",
                    key,
                ) from exc
            log.warning("corrupt cache entry dropped and recomputed: %s", exc)
            self.cache.delete(key)
            return None
        if entry is not None and entry.status != "ok" and self.mode != "replay":
            return None  # an empty answer is not a success: ask again
        return entry

    def _answer_misses(self, requests: Sequence[ChatRequest], todo: dict[str, int], results: list) -> None:
        if self.mode == "replay" and getattr(self.backend, "calls_model", True):
            key, i = next(iter(todo.items()))
            where = f"cache {self.cache.directory}" if self.cache is not None else "the cache (none given)"
            raise ReplayMissError(replay_miss_message(self.model, key, requests[i].tag, where), key, requests[i].tag)
        items = list(todo.items())
        # the backend groups its misses (a local model puts alike shapes together); answers are stored per batch
        for plan in self.backend.plan_batches([requests[i] for _, i in items]):
            batch = [items[j] for j in plan]
            batch_requests = [requests[i] for _, i in batch]
            self.stats["misses"] += len(batch)
            try:
                answers = self.backend.generate(batch_requests)
            except VlmproprioError as exc:  # BackendError and kin
                # keep whatever the backend finished before it gave up (a dead server mid-batch)
                for (key, i), ans in zip(batch, getattr(exc, "partial", ()) or (), strict=False):
                    if ans is not None:
                        results[i] = self._keep(key, requests[i], ans)
                raise
            if len(answers) != len(batch):
                raise CacheError(
                    f"backend {self.identity['backend']} returned {len(answers)} answers for {len(batch)} requests"
                )
            for (key, i), ans in zip(batch, answers, strict=True):
                results[i] = self._keep(key, requests[i], ans)

    def _keep(self, key: str, request: ChatRequest, answer: Answer) -> Answer:
        # a server that echoes the API key in an answer must not get it into the cache, cassette or transcripts
        text = scrub(answer.text)
        if text != answer.text:
            answer = replace(answer, text=text)
        entry = scrubbed_entry(CacheEntry.from_answer(key, answer, request.tag, self.model, self.identity))
        if self.cache is not None and self.mode != "replay" and self.cache.store(entry):
            self.stats["stored"] += 1
        self._use(entry)
        return replace(answer, key=key)

    def _use(self, entry: CacheEntry) -> None:
        if self.mode == "record":
            self.used[entry.key] = entry


def answer(
    requests: Sequence[ChatRequest],
    backend: Backend,
    cache: ResponseCache | None,
    mode: str,
    *,
    model: str = "",
) -> list[Answer]:
    """One-shot form of ``CachedBackend(backend, mode=mode, cache=cache, model=model).answer(requests)``."""
    return CachedBackend(backend, mode=mode, cache=cache, model=model).answer(requests)
