"""What models wrap around a caption, and taking it off: code fences, JSON values and fields, quotes,
emphasis, sub-labels, preambles ("Here is the instruction:"), headings ("### Instruction") and trailers
("This instruction incorporates …"). Each remover returns the text and the recovery classes it applied.
"""

from __future__ import annotations

import json
import re

from vlmproprio.parsing.common import strip_emphasis

_FENCE_LINE = re.compile(r"^[ \t]*(?:```|~~~)[\w+-]*[ \t]*$", re.MULTILINE)
_INLINE_FENCE = re.compile(r"^\s*```[\w+-]*\s*(.*?)\s*```\s*$", re.DOTALL)
_QUOTES = (('"', '"'), ("“", "”"), ("'", "'"), ("‘", "’"), ("«", "»"), ("`", "`"), ("„", "“"))
# Keys a model puts its caption under, in order of preference.
TEXT_KEYS = (
    "caption",
    "description",
    "text",
    "instruction",
    "final_instruction",
    "summary",
    "scene_caption",
    "scene",
    "answer",
    "output",
    "response",
    "content",
)
_FIELD = re.compile(r'^\s*[{\[]?\s*"(\w+)"\s*:\s*"((?:[^"\\]|\\.)*)"\s*[,}\]]*\s*$', re.DOTALL)
_SUBLABEL = re.compile(
    r"^\s*(?:\*\*|__)?\s*(?:caption|description|scene caption|scene summary|summary|instruction|final instruction|"
    r"answer|final answer|output|response|task instruction)\s*(?:\*\*|__)?\s*[:：]\s*(?:\*\*|__)?\s*",
    re.IGNORECASE,
)
_HEADING = re.compile(r"^\s{0,3}#{1,6}\s+\S.*$")
_PREAMBLE = re.compile(
    r"^\s*(?:(?:sure|certainly|of course|okay|ok|alright|absolutely)\b[^.:\n]{0,40}[.!,]\s*)?"
    r"(?:(?:here(?:\s+is|\s+are|'s|’s)|below\s+(?:is|are)|the\s+following\s+(?:is|are))\b[^:\n]{0,80}|"
    r"(?:based on|given|after|from|looking at|considering)\b[^:\n]{0,160}?,\s*(?:here(?:\s+is|\s+are|'s|’s))?[^:\n]{0,80})"
    r":\s*",
    re.IGNORECASE,
)
_COURTESY = re.compile(r"^\s*(?:sure|certainly|of course|okay|alright|absolutely)\s*[.!,]\s*", re.IGNORECASE)
_TRAILER = re.compile(
    r"(?:^|(?<=[.!?\"”)])\s+|\n\s*)(?:\(?\s*)?(?:this|the above|that|the)\s+(?:instruction|summary|caption|"
    r"description|scene caption|answer|sentence|command)\s+(?:incorporates|captures|reflects|describes|"
    r"summarizes|summarises|covers|includes|combines|uses|is based|conveys|highlights|follows|accounts|"
    r"integrates|takes|focuses|emphasizes|emphasises|mentions|keeps|ensures|should|was|would)\b.*$|"
    r"(?:^|(?<=[.!?\"”)])\s+|\n\s*)(?:\(\s*)?(?:note|explanation|reasoning|rationale|justification)\s*[:：-].*$|"
    r"(?:^|(?<=[.!?\"”)])\s+|\n\s*)(?:i hope this|let me know|feel free|hope this helps)\b.*$",
    re.IGNORECASE | re.DOTALL,
)


def compact_space(text: str) -> str:
    """Whitespace runs made short (a blank line stays a blank line): the patterns that may start after any
    whitespace would otherwise rescan a long run from each of its characters."""
    text = re.sub(r"[^\S\n]+", " ", text)  # each run matched once from its start: linear
    text = re.sub(r"\n(?: ?\n)+ ?", "\n\n", text)
    return re.sub(r" ?\n ?", "\n", text)


def strip_fences(text: str) -> tuple[str, tuple[str, ...]]:
    """Code fence markers removed, their content kept."""
    m = _INLINE_FENCE.match(text)
    if m and "\n" not in m.group(1):
        return m.group(1), ("fence",)
    out = _FENCE_LINE.sub("", text)
    return out, (("fence",) if out != text else ())


_DECODER = json.JSONDecoder()
# Where a JSON answer can start: the first bracket, or one that opens a line. A failed decode may read to the end
# of the text, so trying every bracket of a long answer would cost its length times its brackets.
_JSON_START = re.compile(r"^[ \t]*([\[{])", re.M)
_JSON_TRIES = 8
_JSON_WITHIN = 2000  # prose with brackets: a JSON answer starts near the top


def decode_json(text: str, start: int = 0):
    """The JSON value that starts at ``start`` in ``text``, or None (also for a value too deep to decode)."""
    try:
        value, _ = _DECODER.raw_decode(text, start)
    except (ValueError, RecursionError):
        return None
    return value


def _json_starts(text: str) -> list[int]:
    first = re.search(r"[\[{]", text[:_JSON_WITHIN])
    starts = {m.start(1) for m in _JSON_START.finditer(text, 0, _JSON_WITHIN)}
    if first:
        starts.add(first.start())
    return sorted(starts)[:_JSON_TRIES]


def first_json(text: str):
    """The first JSON array or object in ``text`` that decodes, or None."""
    for start in _json_starts(text):
        value = decode_json(text, start)
        if isinstance(value, (list, dict)):
            return value
    return None


def text_of(value) -> str | None:
    """The caption inside a decoded JSON value: a string, the string under a caption-like key, or a dict's
    only string value."""
    if isinstance(value, str):
        return value
    if isinstance(value, list) and len(value) == 1:
        return text_of(value[0])
    if not isinstance(value, dict):
        return None
    lowered = {str(k).lower(): v for k, v in value.items()}
    for key in TEXT_KEYS:
        if isinstance(lowered.get(key), str):
            return lowered[key]
    strings = [v for v in value.values() if isinstance(v, str)]
    return strings[0] if len(strings) == 1 else None


def unquote(text: str) -> tuple[str, tuple[str, ...]]:
    t = text.strip()
    for a, b in _QUOTES:
        if len(t) >= 2 and t.startswith(a) and t.endswith(b) and a not in t[1:-1] and b not in t[1:-1]:
            return t[1:-1].strip(), ("quotes",)
    return text, ()


def json_field(text: str) -> tuple[str, tuple[str, ...]]:
    """A ``"caption": "…"`` field (alone, or as a one-field object) read out."""
    m = _FIELD.match(text)
    if not m:
        return text, ()
    value = decode_json('"' + m.group(2) + '"')
    return (value, ("json",)) if isinstance(value, str) else (text, ())


def clean_fragment(text: str) -> tuple[str, tuple[str, ...]]:
    """One caption's text with its wrappers off: emphasis, a sub-label, a JSON field, quotes; repeated while
    any goes (``**Caption:** "…"`` takes three rounds)."""
    removed: list[str] = []
    for _ in range(6):
        before = text
        text, changed = strip_emphasis(text)
        if changed:
            removed.append("emphasis")
        sub = _SUBLABEL.sub("", text, count=1)
        if sub != text and sub.strip():
            text = sub
            removed.append("sublabel")
        for step in (json_field, unquote):
            text, got = step(text)
            removed += got
        text = text.strip()
        if text.endswith(",") and removed and removed[-1] in ("json", "quotes"):
            text = text[:-1].rstrip()
        if text == before:
            break
    return text, tuple(dict.fromkeys(removed))


def strip_preamble(text: str) -> tuple[str, tuple[str, ...]]:
    """A leading "Here is the instruction:" (or alike) and a leading courtesy word removed."""
    out = _PREAMBLE.sub("", text, count=1)
    out = _COURTESY.sub("", out, count=1) if out != text else out
    return (out, ("preamble",)) if out != text and out.strip() else (text, ())


def strip_headings(text: str) -> tuple[str, tuple[str, ...]]:
    """Markdown heading lines removed (a one-line answer that is a heading keeps its words)."""
    lines = text.splitlines()
    kept = [line for line in lines if not _HEADING.match(line)]
    if len(kept) == len(lines) or not "".join(kept).strip():
        return text, ()
    return "\n".join(kept), ("heading",)


def strip_trailer(text: str) -> tuple[str, tuple[str, ...]]:
    """A trailing explanation ("This instruction incorporates …", "Note: …") removed when text remains."""
    text = compact_space(text)
    m = _TRAILER.search(text)
    if not m or not text[: m.start()].strip():
        return text, ()
    return text[: m.start()].rstrip(), ("trailer",)
