"""The one interface every backend implements.

A backend answers a batch of chat requests, one answer each, in order. It says
who it is through ``identity()``: the fields that, together with the request,
determine an answer and therefore enter the cache key (see vlmproprio.cache).
Device and batch size are deliberately not part of the identity: an answer
recorded on a GPU replays anywhere.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Sequence
from dataclasses import dataclass

from vlmproprio.backends.scheduling import contiguous_batches
from vlmproprio.chat import Answer, ChatRequest
from vlmproprio.errors import VlmproprioError


@dataclass(frozen=True)
class Availability:
    """Whether a model can run here, and why (or why not): what a backend kind's ``live`` check returns."""

    available: bool
    reason: str

    def __bool__(self) -> bool:
        return self.available


class BackendError(VlmproprioError):
    """A backend cannot answer (missing weights, unreachable server, ...). The message says what to do.

    ``partial`` holds, in request order, the answers the backend finished before it gave up (None for
    the others), so the caller can keep them (a server that dies mid-batch loses nothing already answered).
    """

    def __init__(self, message: str, *, partial: Sequence[Answer | None] = ()) -> None:
        super().__init__(message)
        self.partial: list[Answer | None] = list(partial)


class Backend(ABC):
    #: how many requests one ``generate`` call takes at most (the caller splits larger batches)
    max_batch_size: int = 1
    #: False for backends that never run a model (cassette replay, the reference captioner): only these
    #: may answer cache misses in replay mode
    calls_model: bool = True

    @abstractmethod
    def identity(self) -> dict[str, str]:
        """backend, model_id, revision, dtype, attn_implementation: everything model-side in the cache key."""

    @abstractmethod
    def generate(self, requests: Sequence[ChatRequest]) -> list[Answer]:
        """One answer per request, in order. Raises BackendError when it cannot answer at all."""

    def generate_keyed(self, requests: Sequence[ChatRequest], keys: Sequence[str]) -> list[Answer]:
        """``generate`` for a caller that already computed each request's cache key (``keys[i]`` is
        ``cache.request_key(cache.key_identity(self.identity()), requests[i])``, as the Answerer computes it).

        Backends that answer by key (cassette replay) use them instead of hashing every request again."""
        return self.generate(requests)

    def plan_batches(self, requests: Sequence[ChatRequest]) -> list[tuple[int, ...]]:
        """How to split ``requests`` into ``generate`` calls: positions, every one exactly once.

        Arrival order in chunks of ``max_batch_size`` here; a backend whose cost depends on how alike a
        batch is (a local model pads every row to the longest) groups them its own way."""
        return contiguous_batches(len(requests), max(1, int(self.max_batch_size)))

    def close(self) -> None:  # noqa: B027 - optional hook
        """Free what the backend holds (GPU memory, HTTP pools)."""

    def __enter__(self) -> Backend:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
