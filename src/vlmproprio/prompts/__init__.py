"""The paper's prompts (Sec. III), rendered per process and condition into chat messages.

The texts live in ``prompts/paper/*.txt`` as printed in the paper, plus three
things the paper leaves out and we had to write: the answer-format lines (so
answers can be parsed), a sentence on units and axes in the Joint/Pose section,
and the worked cube-stacking example (``example_cube_stacking.json``;
switchable, on by default as in the paper).

How a condition changes the prompt:

* no numeric state (``none``): no Joint/Pose section, no guideline 4;
* ``ee`` / ``joint``: the Joint/Pose section keeps only the paragraph on the state it gives;
* ``primitives``: a Motion section instead of Joint/Pose and a guideline 4 that refers to the motion words;
* ``state_only``: no images; the state lines are the only view of the episode.

``prompt_version()`` names the template set; it enters the cache key, and the
rendered prompts are snapshot-tested, so editing a template without bumping
``paper/VERSION`` fails a test.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass
from functools import cache
from importlib import resources

import numpy as np

from vlmproprio.chat import ImagePart, Message, Part, TextPart
from vlmproprio.conditions import Condition, motion_words
from vlmproprio.prompts.state import format_state_line

TEMPLATE_SET = "paper"
NUMBER_WORDS = ("zero", "one", "two", "three", "four", "five", "six", "seven", "eight", "nine", "ten")


@cache
def template(name: str) -> str:
    return resources.files(__package__).joinpath(TEMPLATE_SET, name).read_text(encoding="utf-8").strip()


@cache
def _example() -> dict:
    return json.loads(template("example_cube_stacking.json"))


@dataclass(frozen=True)
class PromptOptions:
    """Switches that change the prompt text (and therefore the cache key)."""

    example: bool = True


def prompt_version(options: PromptOptions = PromptOptions()) -> str:
    return f"{TEMPLATE_SET}-{template('VERSION')}{'' if options.example else '-noexample'}"


@dataclass(frozen=True)
class FrameView:
    """One frame as a prompt shows it: its number in the prompt, its image (or None), its state text (or None)."""

    number: int
    image: ImagePart | None
    state: str | None


def state_text(number: int, condition: Condition, joints=None, ee=None, words: str | None = None) -> str | None:
    """The state line for one frame under a condition, or None when the condition gives no state."""
    if not condition.has_state:
        return None
    return format_state_line(
        number,
        joints if condition.joints else None,
        ee if condition.ee else None,
        words if condition.words else None,
    )


# ---------------------------------------------------------------------------------------------- sections


def _state_section(condition: Condition) -> str | None:
    if condition.words:
        return template("motion_words.txt")
    if not condition.numeric_state:
        return None
    parts = [template("joint_pose_intro.txt")]
    if condition.joints:
        parts.append(template("joint_pose_joint.txt"))
    if condition.ee:
        parts.append(template("joint_pose_ee.txt"))
    parts.append(template("joint_pose_units.txt"))
    return "\n".join(parts)


def _guidelines(condition: Condition) -> str:
    text = template("guidelines.txt")
    if condition.words:
        text += "\n" + template("guideline_words.txt")
    elif condition.numeric_state:
        text += "\n" + template("guideline_state.txt")
    return text


def _example_text(condition: Condition) -> str:
    ex = _example()
    joints = np.array([f["joints"] for f in ex["frames"]])
    ee = np.array([f["ee"] for f in ex["frames"]])
    words = motion_words(ee, joints) if condition.words else [None] * len(ex["frames"])
    lines = [ex["title"], "Input:"]
    for i in range(len(ex["frames"])):
        st = state_text(i + 1, condition, joints[i], ee[i], words[i])
        lines.append(f"Image {i + 1}: <image of frame {i + 1}>" if condition.images else "")
        if st:
            lines.append(st)
    lines = [line for line in lines if line]
    lines.append("Process 1 answer:")
    lines += [f"Frame {i + 1}: {f['caption']}" for i, f in enumerate(ex["frames"])]
    lines += ["Process 2 answer:", ex["scene"], "Process 3 answer:", ex["instruction"]]
    return "\n".join(lines)


def preamble(condition: Condition, options: PromptOptions) -> str:
    sections = [template("task.txt"), _state_section(condition), _guidelines(condition)]
    if options.example:
        sections.append(_example_text(condition))
    return "\n\n".join(s for s in sections if s)


def _frames_parts(frames: Sequence[FrameView], label: str = "Image") -> list[Part]:
    """Images interleaved with their labels, then every state line in one block."""
    parts: list[Part] = []
    for f in frames:
        if f.image is not None:
            parts.append(TextPart(f"{label} {f.number}:"))
            parts.append(f.image)
    states = [f.state for f in frames if f.state]
    if states:
        parts.append(TextPart("\n".join(states)))
    return parts


def _user(parts: Sequence[Part]) -> tuple[Message, ...]:
    # Chat templates concatenate text items as they are: end each with a line break so that sections,
    # state lines and labels never run into each other.
    parts = [TextPart(p.text + "\n") if isinstance(p, TextPart) and not p.text.endswith("\n") else p for p in parts]
    return (Message("user", tuple(parts)),)


# ---------------------------------------------------------------------------------------------- processes


def process1(frames: Sequence[FrameView], condition: Condition, options: PromptOptions = PromptOptions()):
    n = len(frames)
    count_words = NUMBER_WORDS[n] if n < len(NUMBER_WORDS) else str(n)
    parts: list[Part] = [
        TextPart(preamble(condition, options)),
        TextPart(template("process1.txt").format(count_words=count_words)),
        *_frames_parts(frames),
        TextPart(template("answer_process1.txt").format(count=n)),
    ]
    return _user(parts)


def process2(
    frames: Sequence[FrameView],
    captions: Sequence[str],
    condition: Condition,
    options: PromptOptions = PromptOptions(),
):
    described = "\n".join(f"Frame {f.number}: {c}" for f, c in zip(frames, captions, strict=True))
    parts: list[Part] = [
        TextPart(preamble(condition, options)),
        TextPart(template("process2.txt")),
        TextPart("Described robot arm actions:\n" + described),
        *_frames_parts(frames),
        TextPart(template("answer_process2.txt")),
    ]
    return _user(parts)


def process3(
    frames: Sequence[FrameView],
    scene_captions: Sequence[str],
    condition: Condition,
    options: PromptOptions = PromptOptions(),
):
    summaries = "\n".join(f"Scene {i + 1}: {c}" for i, c in enumerate(scene_captions))
    parts: list[Part] = [
        TextPart(preamble(condition, options)),
        TextPart(template("process3.txt")),
        TextPart("Summaries of the task:\n" + summaries),
        *_frames_parts(frames, label="Image of frame"),
        TextPart(template("answer_process3.txt")),
    ]
    return _user(parts)
