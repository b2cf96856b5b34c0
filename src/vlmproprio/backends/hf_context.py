"""Whether a request fits a transformers model's context, checked before generating.

Past its context a model reads positions it was never trained on, and its answers look like any other answer:
nothing downstream would say they are garbage. So the hf backend refuses such a request with one line that
names it, its tokens, the context and the fix. The context is the model's own: its text config's
``max_position_embeddings`` (a model whose config names none is not checked).
"""

from __future__ import annotations

from collections.abc import Sequence

from vlmproprio.backends.base import BackendError
from vlmproprio.chat import ChatRequest


def context_length(config) -> int | None:
    """The context in tokens of a model with this (transformers) config, None when it names none."""
    text_config = config.get_text_config() if hasattr(config, "get_text_config") else config
    n = getattr(text_config, "max_position_embeddings", None)
    return int(n) if isinstance(n, int) and n > 0 else None


def check_context(
    model_id: str, config, requests: Sequence[ChatRequest], prompt_tokens: Sequence[int], max_new: int
) -> None:
    """BackendError for the first request whose prompt tokens and ``max_new`` answer tokens exceed the context."""
    context = context_length(config)
    if context is None:
        return
    for request, n in zip(requests, prompt_tokens, strict=True):
        if n + max_new > context:
            t = request.tag
            where = f"{t.stage or 'a request'} of {t.episode_id or '?'} / {t.condition or '?'}"
            raise BackendError(
                f"{model_id} ({getattr(config, 'model_type', '?')}): {where} is {n} prompt tokens "
                f"({len(request.images)} images) + {max_new} new, past the model's context of {context} tokens; "
                "cap the images of Process 3 (--max-images-p3 N) or the answer length (--max-new-tokens), or use "
                "a model with a longer context"
            )
