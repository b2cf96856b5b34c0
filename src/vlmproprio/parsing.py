"""Turn model answers into captions, robustly.

Process 1 asks for ``Frame <n>: <caption>`` lines, one per image. Models
drift from that, so parsing goes from strict to lenient and records how each
frame's caption was obtained:

* ``ok``        the exact requested form, each number once;
* ``recovered`` found another way: other numbering (``1.``, ``Image 1 -``,
  markdown bold), a JSON list or object, or unnumbered lines/sentences when
  their count matches the number of frames; or cut to MAX_CAPTION_CHARS;
* ``missing``   nothing usable for this frame (its caption is the empty string).

Parsing never raises on any string and always returns one result per frame.
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass

from vlmproprio.chat import valid_unicode
from vlmproprio.prompts.state import EE_LABEL, JOINT_LABEL
from vlmproprio.transcripts import ParseStatus

MAX_CAPTION_CHARS = 2000
# Answers beyond this are not searched further (a runaway model can emit megabytes).
MAX_ANSWER_CHARS = 200_000

_EXACT = re.compile(r"^Frame (\d{1,4}): (\S.*)$")
_LOOSE = re.compile(
    r"^\s*(?:[-*•]\s*)?(?:\*\*|__)?\s*(?:(?:frame|image|step|caption)\s*#?\s*)?(\d{1,4})\s*(?:\*\*|__)?"
    r"\s*[:.)\-–—]\s*(?:\*\*|__)?\s*(\S.*)$",
    re.IGNORECASE,
)
_LABEL = re.compile(
    r"^\s*(?:\*\*|__)?\s*(?:summary|scene caption|scene|caption|instruction|answer|final instruction)\s*"
    r"(?:\*\*|__)?\s*:\s*(?:\*\*|__)?\s*",
    re.IGNORECASE,
)
_STATE_ECHO = re.compile(rf"^(?:{re.escape(JOINT_LABEL)}|{re.escape(EE_LABEL)}) \[", re.IGNORECASE)
_SENTENCE = re.compile(r"(?<=[.!?])\s+(?=[A-Z])")


@dataclass(frozen=True)
class Parsed:
    text: str
    status: ParseStatus


def _clean(text: str) -> str:
    """One line of text, its markdown emphasis stripped, and valid Unicode: a lone surrogate (a JSON answer's
    ``"\\ud800"`` escape decodes to one) is replaced, since no UTF-8 transcript could hold it."""
    text = re.sub(r"\s+", " ", text).strip().strip("*_").strip()
    return valid_unicode(text)


def _cap(p: Parsed) -> Parsed:
    if len(p.text) > MAX_CAPTION_CHARS:
        return Parsed(p.text[:MAX_CAPTION_CHARS].rstrip() + "…", "recovered")
    return p


def _is_state_echo(text: str) -> bool:
    """A prompt's own state line repeated back (``Frame 2: joint angles [...]``) is not a caption."""
    numbered = _LOOSE.match(text)  # with its "Frame 2:" label, as the unnumbered fallback sees whole lines
    return _STATE_ECHO.match(numbered.group(2) if numbered else text) is not None


def _numbered(lines: list[str], count: int, rx: re.Pattern) -> dict[int, str]:
    found: dict[int, str] = {}
    for line in lines:
        m = rx.match(line)
        if m:
            n = int(m.group(1))
            text = _clean(m.group(2))
            if 1 <= n <= count and n not in found and text and not _is_state_echo(text):
                found[n] = text
    return found


def _from_json(answer: str, count: int) -> dict[int, str]:
    start = min((i for i in (answer.find("["), answer.find("{")) if i >= 0), default=-1)
    if start < 0:
        return {}
    try:
        data, _ = json.JSONDecoder().raw_decode(answer[start:])
    except (ValueError, RecursionError):
        return {}
    items: list = []
    if isinstance(data, dict):
        for key in ("captions", "frames", "answers"):
            if isinstance(data.get(key), list):
                data = data[key]
                break
    if isinstance(data, list):
        items = list(enumerate(data, start=1))
    elif isinstance(data, dict):
        for k, v in data.items():
            m = re.search(r"\d+", str(k))
            if m and len(m.group()) <= 9:  # a longer number is no frame, and past 4300 digits int() raises
                items.append((int(m.group()), v))
    found: dict[int, str] = {}
    for n, v in items:
        if isinstance(v, dict):
            v = v.get("caption", v.get("text", ""))
        if isinstance(v, str) and 1 <= n <= count and n not in found and _clean(v):
            found[n] = _clean(v)
    return found


def _unnumbered(lines: list[str], count: int) -> dict[int, str]:
    candidates = [c for c in (_clean(line) for line in lines) if c and not _is_state_echo(c)]
    if len(candidates) != count:
        joined = " ".join(candidates)
        candidates = [s for s in (_clean(x) for x in _SENTENCE.split(joined)) if s]
    if len(candidates) != count:
        return {}
    return dict(enumerate(candidates, start=1))


def parse_frame_captions(answer: str, count: int) -> list[Parsed]:
    """One Parsed per frame (1..count) from a Process 1 answer."""
    if count <= 0:
        return []
    answer = (answer if isinstance(answer, str) else "")[:MAX_ANSWER_CHARS]
    lines = answer.splitlines()
    exact = _numbered(lines, count, _EXACT)
    if len(exact) == count:
        return [_cap(Parsed(exact[n], "ok")) for n in range(1, count + 1)]
    found = exact
    for extra in (_numbered(lines, count, _LOOSE), _from_json(answer, count)):
        found = {**extra, **found}
    if not found:
        found = _unnumbered(lines, count)
    out = []
    for n in range(1, count + 1):
        if n in found:
            out.append(_cap(Parsed(found[n], "recovered")))
        else:
            out.append(Parsed("", "missing"))
    return out


def parse_single(answer: str) -> Parsed:
    """A Process 2 or 3 answer: one text. Leading labels ("Summary:") are removed and recorded as recovered."""
    answer = (answer if isinstance(answer, str) else "")[:MAX_ANSWER_CHARS]
    text = _clean(answer)
    if not text:
        return Parsed("", "missing")
    stripped = _clean(_LABEL.sub("", answer, count=1))
    if stripped != text:
        return _cap(Parsed(stripped, "recovered" if stripped else "missing"))
    return _cap(Parsed(text, "ok"))
