"""Answering: one door through which every model answer passes (runs, the benchmark, the judge).

An :class:`Answerer` puts a backend behind the response cache (vlmproprio.cache) in one of three modes;
:func:`open_answerer` builds one for a model reference: it creates the backend, opens the cache (not in
replay) and, in record mode, writes the answers used to the model's cassette (vlmproprio.cassettes) when
it closes. Nothing below this layer imports it.
"""

from __future__ import annotations

import logging
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import replace
from pathlib import Path
from typing import Literal

from vlmproprio.backends.base import Backend
from vlmproprio.backends.registry import create_backend, resolve_mode
from vlmproprio.backends.settings import BackendSettings
from vlmproprio.cache import (
    CacheCorruptError,
    CacheEntry,
    CacheError,
    ResponseCache,
    default_cache_dir,
    key_identity,
    request_key,
)
from vlmproprio.cassettes import (
    ReplayMissError,
    check_recordable,
    replay_miss_message,
    scrubbed_entry,
    write_cassette,
)
from vlmproprio.chat import Answer, ChatRequest
from vlmproprio.errors import UsageError, VlmproprioError
from vlmproprio.models import ModelRef, resolve_model
from vlmproprio.options import ANSWER_MODES
from vlmproprio.secrets import scrub

log = logging.getLogger(__name__)

Mode = Literal["replay", "live", "record"]


class Answerer:
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
        """``model``: the model's slug (``ModelRef.slug``), stored with each answer so that
        ``vlmproprio cassette export --model NAME`` finds them; defaults to the identity's model_id."""
        if mode not in ANSWER_MODES:
            raise UsageError(f"unknown mode {mode!r}; choose from {', '.join(ANSWER_MODES)}")
        self.backend = backend
        self.mode: Mode = mode  # type: ignore[assignment]
        self.cache = cache
        self.identity = key_identity(backend.identity())
        self.model = model or self.identity["model_id"]
        self.used: dict[str, CacheEntry] = {}
        self.cassette: Path | None = None  # the cassette written when a record session closed
        self.stats = {"hits": 0, "misses": 0, "stored": 0, "corrupt": 0}

    # -------------------------------------------------------------------------------- public
    @property
    def pure(self) -> bool:
        """Whether each answer is a function of its request alone: a replay from a backend that calls no model
        (a cassette, a rule-based captioner), with no cache to read or fill. Such answering may be split over
        processes (vlmproprio.runner): every part gets the answers one process would have got."""
        return self.mode == "replay" and not self.backend.calls_model and self.cache is None

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

    def export_cassette(self, path: Path | str, *, merge: bool = True, allow_empty: bool = False) -> Path:
        """Write the answers used in this session (record mode) to a cassette; answers that hold no caption are
        refused unless ``allow_empty`` (cassettes.check_recordable)."""
        if not self.used:
            raise CacheError("nothing to export: no answers were used in this session")
        check_recordable(self.used.values(), self.model, path, allow_empty=allow_empty)
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
        if self.mode == "replay" and self.backend.calls_model:
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
                answers = self.backend.generate_keyed(batch_requests, [key for key, _ in batch])
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
        text, reasoning = scrub(answer.text), scrub(answer.reasoning)
        if (text, reasoning) != (answer.text, answer.reasoning):
            answer = replace(answer, text=text, reasoning=reasoning)
        storing = self.cache is not None and self.mode != "replay"
        if storing or self.mode == "record":  # replay keeps no entry: building and scrubbing one is wasted
            entry = scrubbed_entry(CacheEntry.from_answer(key, answer, request.tag, self.model, self.identity))
            if storing and self.cache.store(entry):
                self.stats["stored"] += 1
            self._use(entry)
        return replace(answer, key=key)

    def _use(self, entry: CacheEntry) -> None:
        if self.mode == "record":
            self.used[entry.key] = entry


@contextmanager
def open_answerer(
    model: str | ModelRef,
    mode: str,
    settings: BackendSettings | None = None,
    cache_dir: Path | str | None = None,
    *,
    allow_empty: bool = False,
) -> Iterator[Answerer]:
    """The answerer for ``model`` in ``mode`` (``auto`` made concrete), as captioning and the judge use it.

    Backend from the registry; the response cache in ``cache_dir`` (none in replay, where answers come only from
    the committed cassette, so a stale local cache cannot mask a missing answer); in record mode, on a clean exit,
    the answers used are merged into the model's cassette (``settings.cassette_dir``/<slug>.jsonl), which is
    registered in the fixture manifest, and :attr:`Answerer.cassette` says where. Answers that hold no caption
    (cassettes.check_recordable) stop the recording with a CassetteError unless ``allow_empty``."""
    settings = settings or BackendSettings()
    ref = resolve_model(model)
    mode = resolve_mode(ref, mode, settings)
    backend = create_backend(ref, mode, settings)
    cache = None
    try:
        cache = None if mode == "replay" else ResponseCache(cache_dir or default_cache_dir())
        answerer = Answerer(backend, mode=mode, cache=cache, model=ref.slug)
        yield answerer
        if mode == "record" and answerer.used:
            # registered in the fixture manifest in the same step (cassettes.write_cassette)
            answerer.cassette = answerer.export_cassette(ref.cassette(settings.cassette_dir), allow_empty=allow_empty)
    finally:
        backend.close()
        if cache is not None:
            cache.close()
