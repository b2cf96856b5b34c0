"""The data a backend is asked and answers with: chat requests, generation settings, answers.

These types are the boundary between the pipeline (which builds requests from
episodes and prompts) and the backends (which answer them). They carry no
behaviour beyond serialisation, so every stage can import them.
"""

from __future__ import annotations

import hashlib
import re
from dataclasses import dataclass, field
from functools import cached_property
from typing import Literal

_LONE_SURROGATE = re.compile("[\ud800-\udfff]")


def valid_unicode(text: str) -> str:
    """``text`` with every lone surrogate replaced by U+FFFD. JSON escapes can carry them (``"\\ud800"``), in a
    server's response or inside a model's answer, and no UTF-8 file can hold one: answers and the captions parsed
    from them go through here before anything stores them."""
    return _LONE_SURROGATE.sub("\ufffd", text)


Role = Literal["system", "user", "assistant"]


@dataclass(frozen=True)
class TextPart:
    text: str


@dataclass(frozen=True)
class ImagePart:
    """An image as the exact bytes of its file (PNG). The cache key uses their sha256."""

    data: bytes
    mime: str = "image/png"

    @cached_property
    def sha256(self) -> str:
        # cached: one frame's image is shared by many requests, and every cache key needs its hash
        return hashlib.sha256(self.data).hexdigest()

    def __repr__(self) -> str:  # keep logs and tracebacks free of megabytes of bytes
        return f"ImagePart(sha256={self.sha256[:12]}…, {len(self.data)} bytes)"


Part = TextPart | ImagePart


@dataclass(frozen=True)
class Message:
    role: Role
    parts: tuple[Part, ...]

    @property
    def text(self) -> str:
        return "".join(p.text for p in self.parts if isinstance(p, TextPart))

    @property
    def images(self) -> list[ImagePart]:
        return [p for p in self.parts if isinstance(p, ImagePart)]


@dataclass(frozen=True)
class GenerationConfig:
    """Decoding settings. Greedy (temperature 0) is the paper's setting and the default."""

    max_new_tokens: int = 512
    temperature: float = 0.0
    seed: int | None = 0
    # Forces exactly this many new tokens when set (benchmarks use it so the work is comparable).
    min_new_tokens: int | None = None
    # A reasoning model's thinking switch (the chat template's ``enable_thinking``, Qwen3's and others'): None
    # leaves the template's default; False asks for the answer without a reasoning block.
    thinking: bool | None = None

    def to_dict(self) -> dict:
        # explicit, in field order (as dataclasses.asdict gave): every cache key builds this dict
        d = {
            "max_new_tokens": self.max_new_tokens,
            "temperature": self.temperature,
            "seed": self.seed,
            "min_new_tokens": self.min_new_tokens,
        }
        if self.thinking is not None:  # only when set: every key made without the switch stays what it was
            d["thinking"] = self.thinking
        return d


@dataclass(frozen=True)
class RequestTag:
    """Where a request comes from. Used in messages and transcripts; never part of the cache key."""

    episode_id: str = ""
    condition: str = ""
    stage: str = ""  # "p1" | "p2" | "p3"
    group: int = -1

    def to_dict(self) -> dict:
        return {"episode_id": self.episode_id, "condition": self.condition, "stage": self.stage, "group": self.group}

    def __str__(self) -> str:
        g = f" group {self.group}" if self.group >= 0 else ""
        return f"episode {self.episode_id}, condition {self.condition}, stage {self.stage}{g}"


@dataclass(frozen=True)
class ChatRequest:
    messages: tuple[Message, ...]
    config: GenerationConfig = GenerationConfig()
    # Version of the prompt templates that produced the messages; part of the cache key.
    prompt_version: str = ""
    tag: RequestTag = field(default=RequestTag(), compare=False)

    @property
    def images(self) -> list[ImagePart]:
        return [img for m in self.messages for img in m.images]


@dataclass(frozen=True)
class AnswerMeta:
    """What produced an answer. ``identity`` fields also enter the cache key (see vlmproprio.cache)."""

    backend: str
    model_id: str
    revision: str = ""
    dtype: str = ""
    device: str = ""
    attn_implementation: str = ""
    prompt_tokens: int = 0
    completion_tokens: int = 0
    latency_s: float = 0.0
    extra: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        # explicit, in field order, ``extra`` copied as deep as dataclasses.asdict copied it
        return {
            "backend": self.backend,
            "model_id": self.model_id,
            "revision": self.revision,
            "dtype": self.dtype,
            "device": self.device,
            "attn_implementation": self.attn_implementation,
            "prompt_tokens": self.prompt_tokens,
            "completion_tokens": self.completion_tokens,
            "latency_s": self.latency_s,
            "extra": _copy_data(self.extra),
        }

    @classmethod
    def from_dict(cls, d: dict) -> AnswerMeta:
        known = {k: d[k] for k in cls.__dataclass_fields__ if k in d}
        return cls(**known)


def _copy_data(obj):
    """A copy of nested dicts, lists and tuples (the containers dataclasses.asdict rebuilds); leaves shared."""
    if isinstance(obj, dict):
        return type(obj)((_copy_data(k), _copy_data(v)) for k, v in obj.items())
    if isinstance(obj, list | tuple):
        return type(obj)(_copy_data(v) for v in obj)
    return obj


@dataclass(frozen=True)
class Answer:
    """What a model answered. ``reasoning``: the reasoning a server returned beside the answer (the
    ``reasoning`` / ``reasoning_content`` field of vLLM, SGLang, OpenRouter), never part of ``text`` and never
    parsed for a caption."""

    text: str
    meta: AnswerMeta
    key: str = ""
    from_cache: bool = False
    reasoning: str = ""


# Why an answer holds no caption (or may not be the asked model's), as the backend saw it in the response; kept
# as ``AnswerMeta.extra["answer_problem"]``, only on answers that have one. Each is named in the run's warnings,
# the transcript and the score meta, and an answer with one is refused in a cassette unless asked for.
ANSWER_PROBLEMS: dict[str, str] = {
    "refusal": "the model refused (message.refusal)",
    "content_filter": "the server's content filter stopped the answer (finish_reason content_filter)",
    "tool_calls": "the model called a tool instead of answering (message.tool_calls)",
    "length": "the answer was cut off at the token limit (finish_reason length); raise --max-new-tokens",
    "reasoning_only": "the server put everything in the reasoning field and left the answer empty (a reasoning "
    "parser applied to a model that does not think, e.g. vLLM --reasoning-parser)",
    "empty": "the first choice held no text and gave no reason",
    "other_model": "the response names another model than the one asked for",
}


def answer_problem(meta: AnswerMeta | dict) -> str:
    """The ANSWER_PROBLEMS class the backend recorded on an answer ("" when none); ``meta`` as an
    AnswerMeta or its dict (a cache entry's)."""
    extra = meta.extra if isinstance(meta, AnswerMeta) else meta.get("extra")
    value = extra.get("answer_problem", "") if isinstance(extra, dict) else ""
    return value if isinstance(value, str) and value in ANSWER_PROBLEMS else ""
