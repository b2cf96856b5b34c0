"""Reasoning blocks, split off before any caption is looked for.

Reasoning models write their draft before the answer, in a block of their chat template's own markers:
``<think>…</think>`` (Qwen3, QwQ, DeepSeek-R1), ``<thinking>``, ``<reasoning>``, ``<thought>``,
``◁think▷…◁/think▷`` (Kimi-VL), ``[THINK]…[/THINK]`` (Magistral), ``<|begin_of_thought|>…<|end_of_thought|>``,
and the analysis channel of gpt-oss's harmony format. Templates that open the block in the prompt leave
only its closing marker in the answer, so everything before a lone closing marker is reasoning too; a block
opened and never closed (the model ran out of tokens while thinking) takes the rest of the answer with it.
None of that text may become a caption: it goes to ``reasoning``, apart from the answer.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

_NAMES = r"think|thinking|reasoning|thought|seed:think"
# (opening, closing) marker patterns; a pair's group names the block kind for nothing but readability
_MARKERS: tuple[tuple[str, str], ...] = (
    (rf"<(?:{_NAMES})>", rf"</(?:{_NAMES})>"),
    (r"◁think▷", r"◁/think▷"),
    (r"\[THINK\]", r"\[/THINK\]"),
    (r"<\|begin_of_thought\|>", r"<\|end_of_thought\|>"),
    (r"<\|channel\|>analysis<\|message\|>", r"<\|end\|>"),
)
_CLOSED = [re.compile(f"{o}(.*?){c}", re.IGNORECASE | re.DOTALL) for o, c in _MARKERS]
_OPEN = [re.compile(o, re.IGNORECASE) for o, _ in _MARKERS]
_CLOSE = [re.compile(c, re.IGNORECASE) for _, c in _MARKERS]
# What harmony puts between the analysis and the final message, and the answer markers of other formats.
_LEFTOVER = re.compile(
    r"<\|start\|>assistant|<\|channel\|>final<\|message\|>|<\|return\|>|<\|end\|>|"
    r"<\|begin_of_solution\|>|<\|end_of_solution\|>|</?answer>|</?response>",
    re.IGNORECASE,
)


@dataclass(frozen=True)
class Split:
    """An answer taken apart: ``body`` is what may hold captions, ``reasoning`` the drafts (blocks joined by
    blank lines, stripped), ``removed`` the recovery classes this took ("reasoning", "unclosed_reasoning")."""

    body: str
    reasoning: str
    removed: tuple[str, ...]


def split_reasoning(answer: str) -> Split:
    drafts: list[str] = []
    removed: list[str] = []
    body = answer
    for rx in _CLOSED:
        found = [m.group(1) for m in rx.finditer(body)]
        if found:
            drafts += found
            body = rx.sub("\n", body)
            removed.append("reasoning")
    body, before = _lone_closer(body)
    if before is not None:
        drafts.insert(0, before)
        removed.append("unclosed_reasoning")
    body, after = _never_closed(body)
    if after is not None:
        drafts.append(after)
        removed.append("unclosed_reasoning")
    if removed:
        body = _LEFTOVER.sub("\n", body)
    text = "\n\n".join(d.strip() for d in drafts if d.strip())
    return Split(body, text, tuple(dict.fromkeys(removed)))


def _lone_closer(body: str) -> tuple[str, str | None]:
    """Everything up to the last closing marker left once closed blocks are gone, as reasoning."""
    last = None
    for rx in _CLOSE:
        for m in rx.finditer(body):
            if last is None or m.end() > last.end():
                last = m
    if last is None:
        return body, None
    return body[last.end() :], body[: last.start()]


def _never_closed(body: str) -> tuple[str, str | None]:
    """An opening marker with no close: the rest of the answer from it is reasoning."""
    first = None
    for rx in _OPEN:
        m = rx.search(body)
        if m and (first is None or m.start() < first.start()):
            first = m
    if first is None:
        return body, None
    return body[: first.start()], body[first.end() :]


def has_reasoning_marker(text: str) -> bool:
    """Whether any reasoning marker is left in ``text`` (a caption must never hold one)."""
    return any(rx.search(text) for rx in (*_OPEN, *_CLOSE))
