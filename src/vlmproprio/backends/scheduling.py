"""Which requests share a generate() call: a batching scheduler for local (transformers) inference.

A batch of a local model is padded on the left to its longest prompt, and every
padded position costs prefill compute and, with a static KV cache, decode
bandwidth too. The pipeline hands over a whole wave of requests at once (every
group of every episode under every condition), whose prompts differ a lot:
a Process 1 request has 1 to 5 images (~81 tokens each for a 256x256 frame in
Qwen2-VL), the ``state_only`` control has none, and the state text of
``both`` is several times that of ``none``. So the scheduler:

* keeps requests with different decoding settings apart (one generate() call
  takes one setting);
* orders the rest by prompt length (image tokens included), then by number of
  images, longest first: neighbours have alike shapes, so little padding; the
  longest batch runs first, so a batch size that does not fit in memory fails
  at once rather than after an hour;
* cuts that order into batches of ``max_batch_size``, so every batch but the
  last of each setting is full (on a GPU, decoding is bound by reading the
  weights once per step, whatever the batch size: full batches are what pays);
* optionally caps a batch's padded size, rows x longest prompt, at
  ``max_batch_tokens``: prefill memory grows with it (and the attention mask
  of a padded batch with rows x length squared), so a wave of long Process 3
  prompts gets smaller batches than a wave of short ones. A request longer
  than the cap runs alone.

It only decides the grouping; the caller runs the batches and puts the answers
back in request order (``Batch.indices`` are positions in the list given).
Greedy answers do not depend on the grouping (a test checks it on the tiny
model), so the plan never changes what a model says.

Pure Python: the shapes come from the backend (it knows its tokenizer).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass


@dataclass(frozen=True)
class RequestShape:
    """What the scheduler knows of one request."""

    setting: str  # decoding settings (canonical JSON); only equal settings share a batch
    prompt_tokens: int  # after the processor expands each image into its image tokens
    images: int


@dataclass(frozen=True)
class Batch:
    indices: tuple[int, ...]  # positions in the planned sequence, longest prompt first
    padded_tokens: int  # the longest prompt: every row is left-padded to it

    def __len__(self) -> int:
        return len(self.indices)

    def __iter__(self):
        return iter(self.indices)


def rows_allowed(padded_tokens: int, max_batch_size: int, max_batch_tokens: int | None) -> int:
    """How many rows a batch whose longest prompt is ``padded_tokens`` may have."""
    if max_batch_tokens is None:
        return max_batch_size
    return max(1, min(max_batch_size, max_batch_tokens // max(1, padded_tokens)))


def plan_batches(
    shapes: Sequence[RequestShape], max_batch_size: int, max_batch_tokens: int | None = None
) -> list[Batch]:
    """Batches of alike shapes, at most ``max_batch_size`` rows and (when given) ``max_batch_tokens`` padded
    tokens each; every index appears exactly once."""
    if max_batch_size < 1:
        raise ValueError(f"max_batch_size must be >= 1, got {max_batch_size}")
    if max_batch_tokens is not None and max_batch_tokens < 1:
        raise ValueError(f"max_batch_tokens must be >= 1 or None, got {max_batch_tokens}")
    by_setting: dict[str, list[int]] = {}
    for i, s in enumerate(shapes):
        by_setting.setdefault(s.setting, []).append(i)
    batches: list[Batch] = []
    for members in by_setting.values():  # settings in order of first appearance
        # the index last: ties keep request order, so a plan is the same on every run
        order = sorted(members, key=lambda i: (-shapes[i].prompt_tokens, -shapes[i].images, i))
        start = 0
        while start < len(order):
            longest = shapes[order[start]].prompt_tokens  # longest first: the batch's first row sets its padding
            chunk = tuple(order[start : start + rows_allowed(longest, max_batch_size, max_batch_tokens)])
            batches.append(Batch(chunk, longest))
            start += len(chunk)
    return batches


def contiguous_batches(n: int, max_batch_size: int) -> list[tuple[int, ...]]:
    """Arrival-order batches: what a backend without a scheduler does."""
    if max_batch_size < 1:
        raise ValueError(f"max_batch_size must be >= 1, got {max_batch_size}")
    return [tuple(range(i, min(i + max_batch_size, n))) for i in range(0, n, max_batch_size)]


@dataclass(frozen=True)
class PaddingStats:
    batches: int
    prompt_tokens: int  # real prompt tokens, summed over requests
    padded_tokens: int  # rows x longest prompt, summed over batches

    @property
    def waste(self) -> float:
        """Fraction of the prefill positions that are padding."""
        return 1.0 - self.prompt_tokens / self.padded_tokens if self.padded_tokens else 0.0


def padding_stats(shapes: Sequence[RequestShape], batches: Sequence[Sequence[int]]) -> PaddingStats:
    """How much left padding a grouping costs (for benchmarks and tests)."""
    real = sum(s.prompt_tokens for s in shapes)
    padded = sum(len(b) * max(shapes[i].prompt_tokens for i in b) for b in batches if len(b))
    return PaddingStats(len(batches), real, padded)


def round_up(n: int, multiple: int) -> int:
    """``n`` rounded up to a multiple of ``multiple`` (static-cache lengths come in a few sizes)."""
    if multiple < 1:
        raise ValueError(f"multiple must be >= 1, got {multiple}")
    return -(-n // multiple) * multiple
