"""The prompts of the paper's three processes (Sec. III), rendered per process and condition into chat messages.

Two template sets, chosen with ``PromptOptions.version`` (CLI ``--prompt-version``):

* ``suite`` (default, ``prompts/suite/``): the paper's structure and wording, with every sentence about the
  input saying only what the condition sends (``suite/conditions.json``): under ``none`` no word about joint
  angles or hand positions, under ``state_only`` no word about images, under ``primitives`` motion words;
  the gripper value explained as a finger distance in metres; "one image" for a short last group.
* ``paper-verbatim`` (``prompts/paper/``): the texts as printed in the paper, whatever the condition sends
  (as the paper did), to compare against. docs/paper-fidelity.md lists every difference.

Both add what the paper leaves out and we had to write: the answer-format lines (so answers can be
parsed) and the worked cube-stacking example (``paper/example_cube_stacking.json``; switchable, on by
default as in the paper). The ``primitives`` control has no paper text: its Motion section is ours.

How a condition changes the prompt:

* no numeric state (``none``): no Joint/Pose section, no guideline 4;
* ``ee`` / ``joint``: the Joint/Pose section keeps only the paragraph on the state it gives;
* ``primitives``: a Motion section instead of Joint/Pose and a guideline 4 that refers to the motion words;
* ``state_only``: no images; the state lines are the only view of the episode.

``prompt_version()`` names the template set and its version; it enters the cache key, and the rendered
prompts are tested (tests/prompts/test_rendering.py), so a template edit that changes what is sent needs a bump of
the set's ``VERSION``.
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
from vlmproprio.errors import UsageError
from vlmproprio.prompts.state import format_state_line

PAPER_SET = "paper"  # the paper's texts verbatim, plus the shared answer lines and example
SUITE_SET = "suite"  # condition-aware rewrites; files it lacks come from the paper set
PROMPT_VERSIONS = ("suite", "paper-verbatim")
NUMBER_WORDS = ("zero", "one", "two", "three", "four", "five", "six", "seven", "eight", "nine", "ten")


@cache
def template(name: str, template_set: str = PAPER_SET) -> str:
    """A template of the set; the suite set falls back to the paper's file where it has none of its own."""
    folder = resources.files(__package__).joinpath(template_set)
    if template_set != PAPER_SET and not folder.joinpath(name).is_file():
        folder = resources.files(__package__).joinpath(PAPER_SET)
    return folder.joinpath(name).read_text(encoding="utf-8").strip()


@cache
def _example() -> dict:
    return json.loads(template("example_cube_stacking.json"))


@cache
def _condition_words() -> dict:
    return json.loads(template("conditions.json", SUITE_SET))


@dataclass(frozen=True)
class PromptOptions:
    """Switches that change the prompt text (and therefore the cache key)."""

    example: bool = True
    version: str = "suite"  # suite | paper-verbatim

    def __post_init__(self) -> None:
        if self.version not in PROMPT_VERSIONS:
            raise UsageError(f"prompt version {self.version!r} is not one of {', '.join(PROMPT_VERSIONS)}")

    @property
    def template_set(self) -> str:
        return SUITE_SET if self.version == "suite" else PAPER_SET


def prompt_version(options: PromptOptions = PromptOptions()) -> str:
    name = SUITE_SET if options.version == "suite" else "paper-verbatim"
    return f"{name}-{template('VERSION', options.template_set)}{'' if options.example else '-noexample'}"


def condition_kind(condition: Condition) -> str:
    """What a condition sends, as one of the kinds in suite/conditions.json (controls read like what they send)."""
    if condition.words:
        return "primitives"
    if not condition.images:
        return "state_only"
    if condition.joints and condition.ee:
        return "both"
    return "joint" if condition.joints else "ee" if condition.ee else "none"


def _words_for(condition: Condition) -> dict:
    return _condition_words()["kinds"][condition_kind(condition)]


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


def _task(condition: Condition, options: PromptOptions) -> str:
    if options.version != "suite":
        return template("task.txt")
    return template("task.txt", SUITE_SET).format(input=_words_for(condition)["input"])


def _state_section(condition: Condition, options: PromptOptions) -> str | None:
    ts = options.template_set
    if condition.words:
        return template("motion_words.txt", ts)
    if not condition.numeric_state:
        return None
    parts = [template("joint_pose_intro.txt", ts)]
    if condition.joints:
        parts.append(template("joint_pose_joint.txt", ts))
    if condition.ee:
        parts.append(template("joint_pose_ee.txt", ts))
    if options.version == "suite":
        gripper = _condition_words()["gripper"] if condition.joints else ""
        parts.append(template("joint_pose_units.txt", ts).format(gripper=gripper))
    return "\n".join(parts)


def _guidelines(condition: Condition, options: PromptOptions) -> str:
    text = template("guidelines.txt")
    if not condition.has_state:
        return text
    if options.version == "suite":
        return text + "\n" + template("guideline_state.txt", SUITE_SET).format(state=_words_for(condition)["state"])
    return text + "\n" + template("guideline_words.txt" if condition.words else "guideline_state.txt")


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


@cache  # a pure function of two frozen values; every request starts with it (2,646 a run, ~14 distinct)
def preamble(condition: Condition, options: PromptOptions) -> str:
    sections = [_task(condition, options), _state_section(condition, options), _guidelines(condition, options)]
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


def _process_prompt(
    condition: Condition,
    options: PromptOptions,
    texts: Sequence[str],
    frames: Sequence[FrameView],
    answer: str,
    label: str = "Image",
) -> tuple[Message, ...]:
    """Every process's message: the preamble, the process's own texts, the frames, then the answer format."""
    parts: list[Part] = [
        TextPart(preamble(condition, options)),
        *(TextPart(t) for t in texts),
        *_frames_parts(frames, label=label),
        TextPart(answer),
    ]
    return _user(parts)


# ---------------------------------------------------------------------------------------------- processes


def process1(frames: Sequence[FrameView], condition: Condition, options: PromptOptions = PromptOptions()):
    n = len(frames)
    count_words = NUMBER_WORDS[n] if n < len(NUMBER_WORDS) else str(n)
    if options.version == "suite":
        w = _words_for(condition)
        unit = w["unit"][0] if n == 1 else w["unit"][1]
        head = template("process1.txt", SUITE_SET).format(basis=w["basis"], count_words=count_words, unit=unit)
    else:
        head = template("process1.txt").format(count_words=count_words)
    answer = template("answer_process1.txt", options.template_set).format(count=n)
    return _process_prompt(condition, options, [head], frames, answer)


def process2(
    frames: Sequence[FrameView],
    captions: Sequence[str],
    condition: Condition,
    options: PromptOptions = PromptOptions(),
):
    described = "\n".join(f"Frame {f.number}: {c}" for f, c in zip(frames, captions, strict=True))
    texts = [template("process2.txt"), "Described robot arm actions:\n" + described]
    return _process_prompt(condition, options, texts, frames, template("answer_process2.txt"))


def process3(
    frames: Sequence[FrameView],
    scene_captions: Sequence[str],
    condition: Condition,
    options: PromptOptions = PromptOptions(),
):
    summaries = "\n".join(f"Scene {i + 1}: {c}" for i, c in enumerate(scene_captions))
    head = (
        template("process3.txt", SUITE_SET).format(incorporating=_words_for(condition)["incorporating"])
        if options.version == "suite"
        else template("process3.txt")
    )
    texts = [head, "Summaries of the task:\n" + summaries]
    answer = template("answer_process3.txt")
    return _process_prompt(condition, options, texts, frames, answer, label="Image of frame")
