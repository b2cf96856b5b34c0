"""Process 2 and 3 answers: one text (a scene caption, the final instruction).

The reasoning block is split off first; then fences, a JSON wrapper, headings, a preamble, a trailer and
the caption's own wrappers (emphasis, a label, quotes) come off, in rounds until none is left. Whatever
came off is recorded; an answer with nothing left is ``missing`` and keeps its raw text in the audit.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

from vlmproprio.parsing.common import MAX_ANSWER_CHARS, Parsed, finish, missing, squash
from vlmproprio.parsing.reasoning import split_reasoning
from vlmproprio.parsing.wrappers import (
    TEXT_KEYS,
    clean_fragment,
    decode_json,
    first_json,
    strip_fences,
    strip_headings,
    strip_preamble,
    strip_trailer,
    text_of,
)

_KEYED = re.compile(r'"(' + "|".join(TEXT_KEYS) + r')"\s*:\s*"', re.IGNORECASE)


@dataclass(frozen=True)
class SingleAnswer:
    caption: Parsed
    reasoning: str


def parse_single_answer(answer: str) -> SingleAnswer:
    raw = (answer if isinstance(answer, str) else "")[:MAX_ANSWER_CHARS]
    split = split_reasoning(raw)
    removed = list(split.removed)
    text, got = strip_fences(split.body)
    removed += got
    text, got = _from_json(text)
    removed += got
    for _ in range(4):
        before = text
        for step in (strip_headings, strip_preamble, strip_trailer, clean_fragment):
            text, got = step(text)
            removed += got
        if text == before:
            break
    text = squash(text)
    if not text:
        return SingleAnswer(missing(raw, tuple(dict.fromkeys(removed))), split.reasoning)
    return SingleAnswer(finish(text, raw, tuple(removed), exact=True), split.reasoning)


def _from_json(text: str) -> tuple[str, tuple[str, ...]]:
    """The caption of an answer that is a JSON value, or that holds a ``"instruction": "…"`` field."""
    stripped = text.strip()
    if stripped[:1] in ("{", "["):  # a quoted answer is not read as a JSON string: unquote keeps what follows
        value = first_json(stripped)
        found = text_of(value) if value is not None else None
        if isinstance(found, str) and found.strip():
            return found, ("json",)
    m = _KEYED.search(text)
    if m:
        value = decode_json(text, m.end() - 1)
        if isinstance(value, str) and value.strip():
            return value, ("json",)
    return text, ()


def parse_single(answer: str) -> Parsed:
    """A Process 2 or 3 answer: one text, its wrappers removed and recorded (``recovered``)."""
    return parse_single_answer(answer).caption
