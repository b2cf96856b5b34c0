"""Content-addressed answers: the request key and the on-disk response cache.

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

Entries and the cache
---------------------
An answer is stored as a JSON object (never a pickle) with a ``checksum``: the
sha256 of the canonical JSON of all its other fields. A value whose checksum
does not match, or that cannot be decoded, is *corrupt*: in live mode it is
dropped and recomputed, in replay mode it is a fatal error (vlmproprio.answering).

``ResponseCache`` is a ``diskcache`` directory (SQLite + WAL) shared by any
number of processes. Values are JSON through a disk class that refuses to
unpickle anything, and the first writer of a key wins (``add``), so an
answer is stored once. The cassette file format is vlmproprio.cassettes;
answering from cache, cassette or model is vlmproprio.answering.

An entry's optional ``reasoning`` field holds the reasoning a server returned beside the answer
(``Answer.reasoning``); it is written only when not empty, so the record of an answer without one, and its
checksum, are what they always were.

Answer statuses: ``ok``, or ``empty`` (the model answered nothing). Empty
answers are kept so that a replay gives exactly what the live run gave, but
they are not successes: live mode asks the model again. Failed requests (an
exception) are never stored.
"""

from __future__ import annotations

import hashlib
import json
import logging
import zlib
from collections.abc import Iterator
from dataclasses import asdict, dataclass, field
from json.encoder import encode_basestring
from pathlib import Path

from vlmproprio.chat import Answer, AnswerMeta, ChatRequest, ImagePart, RequestTag
from vlmproprio.errors import VlmproprioError
from vlmproprio.io import writing
from vlmproprio.stores import JSON_VALUES, open_store

log = logging.getLogger(__name__)

KEY_VERSION = 1
IDENTITY_FIELDS: tuple[str, ...] = ("backend", "model_id", "revision", "dtype", "attn_implementation")
STATUSES: tuple[str, ...] = ("ok", "empty")
# The response cache is the cache folder itself (its cache.db); embeddings/ and models/ sit beside that file, so
# `--cache-dir DIR` names one folder for every cache and DIR/cache.db is where a run's answers are.


class CacheError(VlmproprioError):
    """The response cache cannot be used (unreadable directory, corrupt entry in replay mode, ...)."""


class CacheCorruptError(CacheError):
    """A cache entry failed its checksum or could not be decoded."""

    def __init__(self, message: str, key: str = "") -> None:
        super().__init__(message)
        self.key = key


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
    return sha256_text(key_text(identity, request))


_PART_TEXT: dict[str, str] = {}  # a text part's canonical JSON by its text: prompts repeat their sections
_MAX_PART_TEXTS = 1 << 14


def _part_json(part) -> str:
    if isinstance(part, ImagePart):
        mime, digest = part.mime, part.sha256
        if type(mime) is str and type(digest) is str:  # (encode_basestring is json.dumps of a str, as below)
            return '{"mime":' + encode_basestring(mime) + ',"sha256":' + encode_basestring(digest) + ',"type":"image"}'
        return canonical_json({"type": "image", "sha256": digest, "mime": mime})
    text = part.text
    if type(text) is not str:
        return canonical_json({"type": "text", "text": text})
    out = _PART_TEXT.get(text)
    if out is None:
        # json.dumps of a str with ensure_ascii=False is exactly encode_basestring (JSONEncoder.encode)
        out = '{"text":' + encode_basestring(text) + ',"type":"text"}'
        if len(_PART_TEXT) < _MAX_PART_TEXTS:
            _PART_TEXT[text] = out
    return out


def key_text(identity: dict, request: ChatRequest) -> str:
    """``canonical_json(key_document(identity, request))``, laid out here in its sorted key order with each
    prompt section encoded once: the same text, without building and sorting every request's document."""
    messages = ",".join(
        '{"parts":[' + ",".join(_part_json(p) for p in m.parts) + '],"role":' + canonical_json(m.role) + "}"
        for m in request.messages
    )
    return (
        f'{{"generation":{canonical_json(request.config.to_dict())},"key_version":{canonical_json(KEY_VERSION)},'
        f'"messages":[{messages}],"model":{canonical_json(key_identity(identity))},'
        f'"prompt_version":{canonical_json(request.prompt_version)}}}'
    )


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
    reasoning: str = ""  # the server's reasoning beside the answer (Answer.reasoning); never part of ``text``

    @classmethod
    def from_answer(cls, key: str, answer: Answer, tag: RequestTag, model: str, identity: dict) -> CacheEntry:
        return cls(
            key=key,
            text=answer.text,
            meta=answer.meta.to_dict(),
            tag=tag.to_dict(),
            status="ok" if answer.text.strip() else "empty",
            model=model,
            identity=key_identity(identity),
            reasoning=answer.reasoning,
        )

    def to_answer(self, *, from_cache: bool = True) -> Answer:
        meta = AnswerMeta.from_dict(self.meta)
        return Answer(text=self.text, meta=meta, key=self.key, from_cache=from_cache, reasoning=self.reasoning)

    def cache_record(self) -> dict:
        rec = asdict(self)
        if not self.reasoning:  # an answer without reasoning is the record (and checksum) it always was
            del rec["reasoning"]
        rec["checksum"] = checksum(rec)
        return rec

    def cassette_record(self) -> dict:
        rec = {"key": self.key, "text": self.text, "meta": self.meta, "tag": self.tag, "status": self.status}
        if self.reasoning:
            rec["reasoning"] = self.reasoning
        rec["checksum"] = checksum(rec)
        return rec


def entry_from_record(rec: object, *, model: str = "", identity: dict | None = None) -> CacheEntry:
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
    if not isinstance(rec.get("reasoning", ""), str):
        raise ValueError("field 'reasoning' is not a str")
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
        reasoning=rec.get("reasoning", ""),
    )


# ---------------------------------------------------------------------------------------------- the runtime cache


def cache_root() -> Path:
    """Where vlmproprio keeps its caches: $VLMPROPRIO_CACHE, else the user cache directory (vlmproprio.locations)."""
    from vlmproprio.locations import cache_root as root

    return root()


def default_cache_dir() -> Path:
    """The response cache: the cache folder itself (see cache_root)."""
    return cache_root()


class ResponseCache:
    """Answers by key in a diskcache directory; safe for many processes at once.

    Values are JSON (zlib-compressed), checksummed; never evicted (a cache that
    silently forgets answers would turn a replay into a live run).
    """

    def __init__(self, directory: Path | str, *, timeout_s: float = 120.0) -> None:
        self.directory = Path(directory)
        self._cache = open_store(
            self.directory,
            JSON_VALUES,
            error=CacheError,
            corrupt=CacheCorruptError,
            what="cache",
            timeout_s=timeout_s,
            disk_compress_level=6,
        )

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
            entry = entry_from_record(rec)
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
