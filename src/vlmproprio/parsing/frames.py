"""Process 1 answers: one caption per frame of a group of k images.

The reasoning block and code fences come off first. Then the answer is read from strict to lenient, each
reading filling only frames the ones before left open: labelled lines (``frame_lines``: the exact
``Frame <n>: <caption>`` form and the others models write, per-frame headings, a label alone on its line),
Markdown table rows, a JSON value, ordinal phrases; only when none of them found anything, unnumbered lines
or sentences in order, and only when their count matches the frames. Within each reading, the numbers the
model wrote are mapped to frames: 1-based (as asked), zero-based, or continued from the previous group
(the caller passes the number of frames before the group as ``offset``).

Every frame is ``ok`` only when all of them came in the exact form with nothing removed; any frame nothing
was found for is ``missing`` and keeps the raw answer in its audit. Parsing never raises on any string.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, replace

from vlmproprio.parsing.common import MAX_ANSWER_CHARS, Parsed, finish, is_state_echo, missing, squash
from vlmproprio.parsing.frame_lines import Entry, labelled_entries, ordinal_entries, table_entries
from vlmproprio.parsing.reasoning import split_reasoning
from vlmproprio.parsing.wrappers import clean_fragment, first_json, strip_fences, text_of

_SENTENCE = re.compile(r"(?<=[.!?])\s+(?=[A-Z])")
_LIST_KEYS = ("captions", "frames", "answers", "images", "results", "descriptions", "frame_captions", "output")
_NUMBER_KEYS = ("frame", "frame_number", "frame_index", "index", "id", "image", "number", "n", "idx")
_NOT_A_CAPTION = re.compile(r"^\s{0,3}#{1,6}\s|:\s*$|^\s*\|")  # headings, preambles ending in ':', table rows


@dataclass(frozen=True)
class FrameAnswer:
    """A Process 1 answer read: one Parsed per frame, and the reasoning split off it (empty when none)."""

    captions: list[Parsed]
    reasoning: str


def parse_frame_answer(answer: str, count: int, *, offset: int = 0) -> FrameAnswer:
    if count <= 0:
        return FrameAnswer([], "")
    raw = (answer if isinstance(answer, str) else "")[:MAX_ANSWER_CHARS]
    split = split_reasoning(raw)
    body, fence = strip_fences(split.body)
    before = (*split.removed, *fence)
    lines = body.splitlines()
    found: dict[int, Entry] = {}
    for read in (labelled_entries(lines), table_entries(lines), json_entries(body), ordinal_entries(body, count)):
        for i, entry in renumber(read, count, offset).items():
            found.setdefault(i, entry)
    if not found:
        found = unnumbered(lines, count)
    exact = len(found) == count and not before and all(e.exact for e in found.values())
    captions = [
        finish(found[i].text, found[i].span, (*before, *found[i].removed), exact)
        if i in found
        else missing(raw, before)
        for i in range(1, count + 1)
    ]
    return FrameAnswer(captions, split.reasoning)


def parse_frame_captions(answer: str, count: int, *, offset: int = 0) -> list[Parsed]:
    """One Parsed per frame (1..count) from a Process 1 answer; ``offset``: frames before this group."""
    return parse_frame_answer(answer, count, offset=offset).captions


def renumber(entries: list[Entry], count: int, offset: int = 0) -> dict[int, Entry]:
    """The entries by frame (1..count), first one per number, under the numbering that places most of them:
    1-based, continued from the frames before the group, or zero-based (only when a 0 or the offset itself
    was written); a tie keeps the order named."""
    numbers = {e.number for e in entries}
    bases: list[tuple[int, tuple[str, ...]]] = [(1, ())]
    if offset > 0:
        bases.append((offset + 1, ("continued_numbering",)))
        if offset in numbers:
            bases.append((offset, ("zero_based", "continued_numbering")))
    if 0 in numbers:
        bases.append((0, ("zero_based",)))
    base, mapped = max(bases, key=lambda b: sum(b[0] <= n < b[0] + count for n in numbers))
    out: dict[int, Entry] = {}
    for e in entries:
        i = e.number - base + 1
        if 1 <= i <= count and i not in out:
            out[i] = replace(e, removed=(*e.removed, *mapped), exact=e.exact and not mapped)
    return out


def json_entries(body: str) -> list[Entry]:
    """Captions from the answer's first JSON array or object: a list (in order, or numbered by a "frame"
    key), an object keyed by frame ("frame_1", "Image 2", "3"), or either under a "captions" key."""
    data = first_json(body)
    if isinstance(data, dict):
        lowered = {str(k).lower(): v for k, v in data.items()}
        inner = next((lowered[k] for k in _LIST_KEYS if isinstance(lowered.get(k), (list, dict))), None)
        data = inner if inner is not None else data
    items: list[tuple[int, object]] = []
    if isinstance(data, list):
        items = [(_item_number(v, i), v) for i, v in enumerate(data, start=1)]
    elif isinstance(data, dict):
        for k, v in data.items():
            m = re.search(r"\d+", str(k))
            if m and len(m.group()) <= 9:  # a longer number is no frame, and past 4300 digits int() raises
                items.append((int(m.group()), v))
    out = []
    for n, v in items:
        text = text_of(v)
        if isinstance(text, str):
            cleaned, removed = clean_fragment(squash(text))
            if cleaned and not is_state_echo(cleaned):
                out.append(Entry(n, cleaned, str(v), ("json", *removed)))
    return out


def _item_number(value: object, position: int) -> int:
    """A list item's frame number: its "frame" (or alike) key when it has one, else its position."""
    if isinstance(value, dict):
        for key in _NUMBER_KEYS:
            v = value.get(key)
            if isinstance(v, int) and not isinstance(v, bool) and 0 <= v < 10_000:
                return v
            if isinstance(v, str) and re.fullmatch(r"\D{0,12}\d{1,4}", v.strip()):
                return int(re.sub(r"\D", "", v))
    return position


def unnumbered(lines: list[str], count: int) -> dict[int, Entry]:
    """Unnumbered lines (or else sentences) taken in order, only when there are exactly ``count``."""
    kept = [line for line in lines if line.strip() and not _NOT_A_CAPTION.search(line)]
    candidates = []
    for line in kept:
        text, removed = clean_fragment(squash(re.sub(r"^\s*[-*•+]\s+", "", line)))
        if text and not is_state_echo(text):
            candidates.append(Entry(0, text, line, ("unnumbered", *removed)))
    if len(candidates) != count:
        joined = " ".join(c.text for c in candidates)
        sentences = [squash(s) for s in _SENTENCE.split(joined)]
        candidates = [Entry(0, s, s, ("sentence_split",)) for s in sentences if s]
    if len(candidates) != count:
        return {}
    return dict(enumerate(candidates, start=1))
