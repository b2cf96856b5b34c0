"""Answers from a cassette only: the way a model that is not here (GPT-4V, a GPU-only VLM) is run.

The backend's identity is the one in the cassette header, so request keys are
computed exactly as when the answers were recorded. It never imports torch,
transformers or openai, and a request the cassette does not hold is a
ReplayMissError naming the episode, stage, group and key, and how to record it.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path

from vlmproprio.backends.base import Backend
from vlmproprio.cache import request_key
from vlmproprio.cassettes import Cassette, ReplayMissError, read_cassette, replay_miss_message
from vlmproprio.chat import Answer, ChatRequest


class ReplayBackend(Backend):
    max_batch_size = 4096
    calls_model = False

    def __init__(self, cassette: Path | str | Cassette, *, model: str | None = None) -> None:
        self.cassette = cassette if isinstance(cassette, Cassette) else read_cassette(cassette)
        self.model = model or self.cassette.model

    @property
    def path(self) -> Path:
        return self.cassette.path

    def identity(self) -> dict[str, str]:
        return dict(self.cassette.identity)

    def generate(self, requests: Sequence[ChatRequest]) -> list[Answer]:
        return self.generate_keyed(requests, [request_key(self.cassette.identity, req) for req in requests])

    def generate_keyed(self, requests: Sequence[ChatRequest], keys: Sequence[str]) -> list[Answer]:
        # the Answerer's keys (computed from this backend's identity, the cassette's): hashing each request's
        # key document again cost as much as the first time
        out = []
        for req, key in zip(requests, keys, strict=True):
            entry = self.cassette.entries.get(key)
            if entry is None:
                raise ReplayMissError(
                    replay_miss_message(self.model, key, req.tag, f"cassette {self.cassette.path}"), key, req.tag
                )
            out.append(replace(entry.to_answer(from_cache=True), key=key))
        return out
