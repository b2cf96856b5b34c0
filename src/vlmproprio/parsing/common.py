"""What every parser returns, and the cleaning they share.

A parsed caption carries its audit: the raw span of the answer it came from and the recovery classes that
were applied to get from that span to the caption (``RECOVERY_CLASSES``). The status says how much to
trust it:

* ``ok``        the exact requested form, nothing removed;
* ``recovered`` found another way; ``removed`` says what was taken away or mapped;
* ``missing``   nothing usable (the caption is the empty string; the raw answer is kept in the audit).
"""

from __future__ import annotations

import re
from dataclasses import dataclass

from vlmproprio.chat import valid_unicode
from vlmproprio.prompts.state import EE_LABEL, JOINT_LABEL
from vlmproprio.transcripts import ParseStatus

MAX_CAPTION_CHARS = 2000
# Answers beyond this are not searched further (a runaway model can emit megabytes).
MAX_ANSWER_CHARS = 200_000
# A raw span kept in an audit is cut here: it shows where a caption came from, it does not archive the answer.
MAX_SPAN_CHARS = 4000

# Every class a recovery can record, so counts per run have a fixed vocabulary.
RECOVERY_CLASSES: tuple[str, ...] = (
    "reasoning",  # a <think>…</think> (or alike) block removed before the answer
    "unclosed_reasoning",  # everything before a lone closing tag, or an opened block never closed
    "fence",  # ``` code fence markers
    "json",  # read out of a JSON value or a "caption": "…" field
    "label",  # a frame label other than the exact "Frame <n>: " (Image 1 -, 1., **Frame 1**:)
    "label_line",  # the label on its own line, the caption on the next
    "bullet",  # a list marker (-, *, •, 1.)
    "emphasis",  # markdown bold/italic markers
    "heading",  # a markdown heading (### Frame 1, ### Instruction)
    "table",  # a markdown table row
    "zero_based",  # frames numbered from 0
    "continued_numbering",  # frames numbered on from the previous group (6-10 for the second)
    "ordinal",  # "In the first frame, …"
    "quotes",  # surrounding quotation marks
    "preamble",  # "Here is the instruction:", "Sure! …:"
    "trailer",  # "This instruction incorporates …", "Note: …"
    "sublabel",  # a "Caption:" / "Description:" label after the frame label
    "unnumbered",  # unnumbered lines taken in order because their count matched
    "sentence_split",  # sentences taken in order because their count matched
    "truncated",  # cut to MAX_CAPTION_CHARS
)
# Recoveries that guess from position rather than read a label: the ones a sanity warning watches.
HEAVY_CLASSES: frozenset[str] = frozenset({"unnumbered", "sentence_split", "ordinal", "unclosed_reasoning"})

_STATE_ECHO = re.compile(rf"^(?:{re.escape(JOINT_LABEL)}|{re.escape(EE_LABEL)})\s*[\[:(]", re.IGNORECASE)
_ECHO_LABEL = re.compile(r"^(?:frame|image)\s*\d{1,4}\s*(?:\*\*)?\s*[:.)\-–—]\s*(?:\*\*)?\s*", re.IGNORECASE)
_NUMBER = re.compile(r"[-+]?\d+(?:\.\d+)?")
_PAIRED_EMPHASIS = re.compile(r"(\*\*|__)(?=\S)(.+?)(?<=\S)\1")


@dataclass(frozen=True)
class Parsed:
    """One caption: its text, status and audit (``span``: the raw text it came from; ``removed``: recovery
    classes applied, in the order met)."""

    text: str
    status: ParseStatus
    span: str = ""
    removed: tuple[str, ...] = ()

    @property
    def heavy(self) -> bool:
        return any(c in HEAVY_CLASSES for c in self.removed)


def squash(text: str) -> str:
    """One line: runs of whitespace made one space, ends stripped, lone surrogates replaced (a JSON answer's
    ``"\\ud800"`` escape decodes to one, and no UTF-8 transcript could hold it)."""
    return valid_unicode(re.sub(r"\s+", " ", text).strip())


def strip_emphasis(text: str) -> tuple[str, bool]:
    """``text`` without markdown emphasis around it or paired ``**``/``__`` inside it; whether any went."""
    out = _PAIRED_EMPHASIS.sub(r"\2", text)
    out = out.strip().strip("*_").strip()
    return out, out != text.strip()


def is_state_echo(text: str) -> bool:
    """A prompt's own state text repeated back (``joint angles [...]``), or a line that is mostly numbers
    (a state vector in another dress): never a caption."""
    text = _ECHO_LABEL.sub("", text.strip().strip("*_-•> ").strip(), count=1)
    if _STATE_ECHO.match(text):
        return True
    numbers = _NUMBER.findall(text)
    words = re.findall(r"[A-Za-z]{2,}", text)
    return len(numbers) >= 4 and len(numbers) > 2 * len(words)


def cut_span(text: str) -> str:
    return valid_unicode(text[:MAX_SPAN_CHARS])


def finish(text: str, span: str, removed: tuple[str, ...], exact: bool = False) -> Parsed:
    """The Parsed for a found caption: capped at MAX_CAPTION_CHARS, ``ok`` only when exact and nothing was
    removed; the empty text is ``missing``."""
    text = squash(text)
    if not text:
        return Parsed("", "missing", cut_span(span), removed)
    if len(text) > MAX_CAPTION_CHARS:
        text, removed = text[:MAX_CAPTION_CHARS].rstrip() + "…", (*removed, "truncated")
    status: ParseStatus = "ok" if exact and not removed else "recovered"
    return Parsed(text, status, cut_span(span), tuple(dict.fromkeys(removed)))


def missing(span: str, removed: tuple[str, ...] = ()) -> Parsed:
    return Parsed("", "missing", cut_span(span), removed)
