"""Turn model answers into captions, and say how each was obtained.

* ``frames``: Process 1 answers, one caption per frame of a group (``parse_frame_captions``);
* ``single``: Process 2 and 3 answers, one text (``parse_single``);
* ``reasoning``: reasoning blocks split off before either looks for a caption;
* ``wrappers``: fences, JSON, quotes, emphasis, preambles, headings and trailers taken off;
* ``frame_lines``: the line grammar of numbered frame captions, tables and ordinal phrases;
* ``common``: ``Parsed`` (text, status ``ok | recovered | missing``, and its audit: the raw span and the
  recovery classes applied) and the limits.

Parsing never raises on any string and always returns one result per frame.
"""

from vlmproprio.parsing.common import (
    HEAVY_CLASSES,
    MAX_ANSWER_CHARS,
    MAX_CAPTION_CHARS,
    RECOVERY_CLASSES,
    Parsed,
)
from vlmproprio.parsing.frames import FrameAnswer, parse_frame_answer, parse_frame_captions
from vlmproprio.parsing.reasoning import Split, split_reasoning
from vlmproprio.parsing.single import SingleAnswer, parse_single, parse_single_answer

__all__ = [
    "HEAVY_CLASSES",
    "MAX_ANSWER_CHARS",
    "MAX_CAPTION_CHARS",
    "RECOVERY_CLASSES",
    "FrameAnswer",
    "Parsed",
    "SingleAnswer",
    "Split",
    "parse_frame_answer",
    "parse_frame_captions",
    "parse_single",
    "parse_single_answer",
    "split_reasoning",
]
