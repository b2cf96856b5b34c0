"""Property tests: generated captions in every numbering, label style, spacing and wrapper the parser reads
must come back exactly, and no word of a reasoning block may reach a caption."""

from __future__ import annotations

import json

from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from vlmproprio.parsing import parse_frame_answer, parse_single_answer

FAST = {"deadline": None, "derandomize": True, "database": None, "suppress_health_check": list(HealthCheck)}
# Words of captions: robot scenes, none of them a label, ordinal or wrapper word.
VOCAB = [
    "arm",
    "gripper",
    "cube",
    "drawer",
    "handle",
    "bin",
    "block",
    "table",
    "red",
    "blue",
    "green",
    "left",
    "right",
    "above",
    "below",
    "moves",
    "lowers",
    "lifts",
    "closes",
    "opens",
    "reaches",
    "pulls",
    "pushes",
    "toward",
    "over",
    "into",
    "onto",
    "the",
    "a",
    "its",
    "slowly",
    "then",
    "and",
    "holds",
    "rotates",
    "places",
]
REASONING = "zqxdraft"  # a word no caption has
CAPTION = st.lists(st.sampled_from(VOCAB), min_size=2, max_size=12).map(lambda ws: " ".join(ws).capitalize() + ".")
LABELS = (
    "Frame {n}: {c}",
    "Image {n}: {c}",
    "{n}. {c}",
    "{n}) {c}",
    "**Image {n}**: {c}",
    "**Frame {n}:** {c}",
    "- Frame {n}: {c}",
    "{i}. **Image {n}**: {c}",
    "Frame {n} - {c}",
    "Frame {n}:\n{c}",
    "### Frame {n}\n{c}",
    "| {n} | {c} |",
    'Frame {n}: "{c}"',
    'Frame {n}: "caption": "{c}"',
    "[Frame {n}] {c}",
)
NUMBERING = st.sampled_from([("one", 1, 0), ("zero", 0, 0), ("continued", 6, 5), ("zero continued", 5, 5)])
SEPARATORS = st.sampled_from(["\n", "\n\n", "  \n", "\r\n", "\n \n"])
WRAPPERS = st.sampled_from(["none", "fence", "think", "lone_close", "preamble", "trailer_line"])


def wrap(body: str, wrapper: str) -> str:
    if wrapper == "fence":
        return f"```\n{body}\n```"
    if wrapper == "think":
        return f"<think>\nFrame 1: {REASONING} maybe\nFrame 2: {REASONING}\n</think>\n\n{body}"
    if wrapper == "lone_close":
        return f"Let me see, {REASONING}.\n1. {REASONING}\n</think>\n{body}"
    if wrapper == "preamble":
        return f"Here are the captions for each frame:\n\n{body}"
    if wrapper == "trailer_line":
        return f"{body}\n\nThese captions describe the robot's progress."
    return body


@settings(max_examples=600, **FAST)
@given(
    captions=st.lists(CAPTION, min_size=1, max_size=5),
    label=st.sampled_from(LABELS),
    numbering=NUMBERING,
    sep=SEPARATORS,
    wrapper=WRAPPERS,
)
def test_generated_frame_answers_give_back_exactly_the_captions(captions, label, numbering, sep, wrapper):
    _, start, offset = numbering
    if label.startswith("|"):
        sep = "\n"  # a table's rows are consecutive lines
    lines = [label.format(n=start + i, i=i + 1, c=c) for i, c in enumerate(captions)]
    if label.startswith("|"):
        lines = ["| Frame | Caption |", "|---|---|", *lines]
    answer = wrap(sep.join(lines), wrapper)
    parsed = parse_frame_answer(answer, len(captions), offset=offset)
    assert [p.text for p in parsed.captions] == captions, answer
    assert all(REASONING not in p.text for p in parsed.captions)
    if wrapper in ("think", "lone_close"):
        assert REASONING in parsed.reasoning
    exact = label == "Frame {n}: {c}" and start == 1 and wrapper in ("none", "preamble", "trailer_line")
    assert {p.status for p in parsed.captions} == ({"ok"} if exact else {"recovered"})


SINGLE_WRAPPERS = (
    "{c}",
    '"{c}"',
    "“{c}”",
    "**{c}**",
    "Here is the instruction:\n\n{c}",
    "Sure! Here's the summary: {c}",
    "### Instruction\n{c}",
    "Instruction: {c}",
    "{c}\n\nThis instruction incorporates the motion of the hand.",
    "{c} This instruction captures the whole task.",
    "{c}\n\nNote: the scene is simple.",
    "<think>" + REASONING + " {c}</think>\n{c}",
    REASONING + " plan\n</think>\n\n{c}",
    "[THINK]" + REASONING + "[/THINK]{c}",
    "◁think▷" + REASONING + "◁/think▷{c}",
)


@settings(max_examples=400, **FAST)
@given(caption=CAPTION, style=st.sampled_from(SINGLE_WRAPPERS), form=st.sampled_from(["text", "json", "fenced"]))
def test_generated_single_answers_give_back_exactly_the_caption(caption, style, form):
    inner = {"text": caption, "json": json.dumps({"instruction": caption})}.get(form)
    if form == "fenced":
        inner = "```json\n" + json.dumps({"summary": caption}) + "\n```"
    answer = style.replace("{c}", inner) if "{c}</think>" not in style else style.format(c=caption)
    if "{c}</think>" in style:
        answer = answer.rsplit(caption, 1)[0] + inner
    got = parse_single_answer(answer)
    assert got.caption.text == caption, answer
    assert REASONING not in got.caption.text
    assert got.caption.status == ("ok" if style == "{c}" and form == "text" else "recovered")
