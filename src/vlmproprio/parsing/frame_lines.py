"""Numbered frame captions read line by line, as models lay them out.

A line is a label and a caption: ``Frame 1: …`` (the exact form), ``Image 1 - …``, ``1. …``, ``1) …``,
``**Image 1**: …``, ``1. **Frame 1:** …``, ``- Frame 1: …``, ``### Frame 1``, ``[Frame 1] …``, or a
Markdown table row ``| 1 | … |``. A label with no caption after it (``Frame 1:``, ``### Frame 1``) takes the
lines that follow, up to a blank line or the next label. Ordinal phrases (``In the first frame, …``) are
read from running text. Every entry keeps the raw lines it came from and the recovery classes it took; its
number is the one the model wrote (mapping zero-based or continued numbering is the caller's business).
"""

from __future__ import annotations

import re
from dataclasses import dataclass

from vlmproprio.parsing.common import is_state_echo, squash
from vlmproprio.parsing.wrappers import clean_fragment, compact_space

_WORDS = r"frame|image|img|picture|photo|pic|step|shot|view|keyframe|snapshot|caption"
_EM = r"(?:\*\*|__|\*|_)"
_SEP = r"(?:[:：)\-–—=]|\.(?=\s|$))"
_BULLET = re.compile(r"^\s*(?:[-*•+>]\s+|\d{1,3}[.)]\s+(?=\S*(?:" + _WORDS + r")))", re.IGNORECASE)
_HEADING = re.compile(r"^\s{0,3}#{1,6}\s*")
_WORDED = re.compile(
    rf"^{_EM}?\s*[\[<(]?\s*(?P<word>{_WORDS})\s*#?\s*(?P<n>\d{{1,4}})(?:\s*(?:/|of)\s*\d{{1,4}})?"
    rf"(?:\s*\([^)\n]{{0,40}}\))?\s*(?P<close>[\]>)])?\s*(?P<em>{_EM})?\s*(?P<sep>{_SEP})?\s*{_EM}?\s*(?P<rest>.*)$",
    re.IGNORECASE,
)
_BARE = re.compile(rf"^{_EM}?\s*[\[(]?(?P<n>\d{{1,4}})[\])]?\s*{_EM}?\s*(?P<sep>{_SEP})\s*{_EM}?\s*(?P<rest>.*)$")
_EXACT = re.compile(r"^Frame (\d{1,4}): (\S.*)$")
_TABLE_ROW = re.compile(r"^\s*\|(.*)\|\s*$")
_TABLE_RULE = re.compile(r"^[\s|:\-–]+$")
_CAPTION_HEADER = re.compile(r"caption|description|text|what|scene|action|content", re.IGNORECASE)
_ORDINALS = {
    "first": 1,
    "second": 2,
    "third": 3,
    "fourth": 4,
    "fifth": 5,
    "sixth": 6,
    "seventh": 7,
    "eighth": 8,
    "ninth": 9,
    "tenth": 10,
    "1st": 1,
    "2nd": 2,
    "3rd": 3,
    "4th": 4,
    "5th": 5,
}
_ORDINAL = re.compile(
    r"(?:^|(?<=[.!?])\s+|\n)\s*(?:[-*•]\s+)?(?:\*\*)?(?:(?:then|next|finally|lastly|and|now)\s*,?\s+)?"
    r"(?:(?:(?:in|at|for|by)\s+)?(?:the\s+)?(?P<w>" + "|".join(_ORDINALS) + r"|last|final)\s+(?:" + _WORDS + r")"
    r"|(?:in|at|for|by)\s+(?:the\s+)?(?:" + _WORDS + r")\s+(?P<d>\d{1,4}))\s*(?:\*\*)?\s*[,:\-–—]\s*",
    re.IGNORECASE,
)


@dataclass(frozen=True)
class Entry:
    number: int  # as written by the model
    text: str
    span: str
    removed: tuple[str, ...]
    exact: bool = False


@dataclass(frozen=True)
class _Label:
    number: int
    rest: str
    removed: tuple[str, ...]
    exact: bool


def read_label(line: str) -> _Label | None:
    """The frame label at the start of one line, and what follows it."""
    exact = _EXACT.match(line)
    if exact:
        return _Label(int(exact.group(1)), exact.group(2), (), True)
    removed: list[str] = []
    text = line
    heading = _HEADING.match(text)
    if heading:
        text, removed = text[heading.end() :], ["heading"]
    bullet = _BULLET.match(text)
    if bullet:
        text = text[bullet.end() :]
        removed.append("bullet")
    m = _WORDED.match(text.strip())
    if m and not (
        m.group("sep")
        or m.group("em")
        or m.group("close")
        or not m.group("rest").strip()
        or text.strip().startswith(("*", "_"))
    ):
        m = None  # "Frame 1 shows …": no label, a sentence
    if m is None:
        m = _BARE.match(text.strip())
        if m is None:
            return None
    removed.append("label")
    if "*" in text[: m.start("rest")] or "__" in text[: m.start("rest")]:
        removed.append("emphasis")
    return _Label(int(m.group("n")), m.group("rest"), tuple(removed), False)


def _caption(text: str, removed: tuple[str, ...]) -> tuple[str, tuple[str, ...]]:
    text, got = clean_fragment(squash(text))
    return text, (*removed, *got)


def labelled_entries(lines: list[str]) -> list[Entry]:
    """Every labelled caption of the answer's lines; a label alone takes the lines after it."""
    out: list[Entry] = []
    labels = [read_label(line) if not _TABLE_ROW.match(line) else None for line in lines]
    for i, label in enumerate(labels):
        if label is None:
            continue
        rest, removed, span = label.rest, label.removed, lines[i]
        if not rest.strip() or is_state_echo(rest):
            rest, span = _following(lines, labels, i)
            removed = (*removed, "label_line")
            if label.exact:
                removed = ("label", *removed)
        text, removed = _caption(rest, removed)
        if text and not is_state_echo(text):
            out.append(Entry(label.number, text, span, removed, label.exact and not removed))
    return out


def _following(lines: list[str], labels: list, i: int) -> tuple[str, str]:
    """The caption lines after a label alone: up to a blank line (once some text came) or the next label."""
    taken: list[str] = []
    for j in range(i + 1, len(lines)):
        line = lines[j]
        if labels[j] is not None or _TABLE_ROW.match(line) or _HEADING.match(line):
            break
        if not line.strip():
            if taken:
                break
            continue
        stripped = re.sub(r"^\s*[-*•+]\s+", "", line)
        if not is_state_echo(stripped):
            taken.append(stripped)
    return " ".join(taken), "\n".join(lines[i : i + 1 + len(taken)])


def table_entries(lines: list[str]) -> list[Entry]:
    """Captions from a Markdown table: the frame number in the first column, the caption in the column
    headed like one (else the second)."""
    out: list[Entry] = []
    column = 1
    for line in lines:
        row = _TABLE_ROW.match(line)
        if not row or _TABLE_RULE.match(line):
            continue
        cells = [c.strip() for c in row.group(1).split("|")]
        number = re.fullmatch(r"(?:\*\*)?(?:(?:" + _WORDS + r")\s*#?\s*)?(\d{1,4})(?:\*\*)?", cells[0], re.IGNORECASE)
        if number is None:
            heads = [j for j, c in enumerate(cells) if j and _CAPTION_HEADER.search(c)]
            column = heads[0] if heads else column
            continue
        if column < len(cells):
            text, removed = _caption(cells[column], ("table",))
            if text and not is_state_echo(text):
                out.append(Entry(int(number.group(1)), text, line, removed))
    return out


def ordinal_entries(body: str, count: int) -> list[Entry]:
    """Captions introduced by an ordinal phrase in running text ("In the first frame, …", "In image 2, …")."""
    body = compact_space(body)
    matches = list(_ORDINAL.finditer(body))
    out: list[Entry] = []
    for j, m in enumerate(matches):
        end = matches[j + 1].start() if j + 1 < len(matches) else len(body)
        segment = re.split(r"\n\s*\n", body[m.end() : end], maxsplit=1)[0]
        word = (m.group("w") or "").lower()
        number = int(m.group("d")) if m.group("d") else count if word in ("last", "final") else _ORDINALS[word]
        text, removed = _caption(segment, ("ordinal",))
        if text and not is_state_echo(text):
            out.append(Entry(number, text[:1].upper() + text[1:], body[m.start() : m.end()] + segment, removed))
    return out
