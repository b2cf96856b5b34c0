"""The reference captioner: NOT a vision-language model.

A deterministic rule set that reads only the robot-state lines of a prompt
(``vlmproprio.prompts.state.parse_state_lines``; it never looks at the images
or at any other text) and turns state changes into motion-primitive words
with ``vlmproprio.primitives``, in the spirit of ECoT's primitive movements.
It is a baseline: how far reading the numbers alone gets. When a prompt has no
state numbers (the ``none`` and ``primitives`` conditions) it says that it
cannot tell instead of guessing.

Prompt/answer conventions (shared with the VLMs, produced by the pipeline):

* the text holds exactly one line ``# Process 1``, ``# Process 2`` or ``# Process 3``;
* Process 1 (k frames numbered 1..k): one line per frame, ``Frame <n>: <caption>``;
* Process 2 (one group): one short paragraph describing the group;
* Process 3 (all groups): one instruction of one or two sentences.

A frame's caption describes the motion from it to the next frame (the last
frame of a group: from the previous one), like the primitive a policy would
execute there.
"""

from __future__ import annotations

import itertools
import re
import time
from collections.abc import Sequence
from dataclasses import dataclass
from functools import lru_cache
from typing import TYPE_CHECKING

from vlmproprio.backends.base import Availability, Backend, BackendError
from vlmproprio.chat import Answer, AnswerMeta, ChatRequest, TextPart
from vlmproprio.kinds import KindSpec, register_kind
from vlmproprio.models import STATE_RULES, ModelRef
from vlmproprio.primitives import direction_words, gripper_word
from vlmproprio.prompts.state import ParsedState, parse_state_lines

if TYPE_CHECKING:
    from vlmproprio.backends.settings import BackendSettings

RULES_VERSION = "primitives-rules-1"
MODEL_ID = "reference-primitives"
NO_STATE = "No robot state was given; the motion cannot be described."
PROCESS_RE = re.compile(r"^# Process ([123])[ \t]*$", re.MULTILINE)
# A wrist rotation counts when roll, pitch or yaw changes by at least this much (rad) between frames.
MIN_ROTATION_RAD = 0.15
# Joint-only prompts: a joint counts as moving when it turns by at least this much (rad).
MIN_JOINT_RAD = 0.05
# Gripper opening (m) at or above which the gripper is called open (the Panda opens to ~0.08 m).
OPEN_GRIPPER_M = 0.06
MAX_INSTRUCTION_STEPS = 5


@dataclass(frozen=True)
class Motion:
    """What changed between two states, in words."""

    direction: tuple[str, ...]  # e.g. ("forward", "down"); () when the hand holds still or is unknown
    grip: str | None  # "opens" | "closes" | None
    rotates: bool
    joint: int | None  # 1-based joint that moved most, only when there is no end-effector state
    known_position: bool  # False when neither end-effector nor joint angles were given

    @property
    def still(self) -> bool:
        return not self.direction and self.grip is None and not self.rotates and self.joint is None


def motion_between(a: ParsedState, b: ParsedState) -> Motion:
    # the same pair of states recurs in Processes 1, 2 and 3 and under several conditions; the frame numbers
    # do not matter
    return _motion(a.joints, a.ee, b.joints, b.ee)


@lru_cache(maxsize=1 << 16)
def _motion(a_joints, a_ee, b_joints, b_ee) -> Motion:
    a, b = ParsedState(0, a_joints, a_ee), ParsedState(0, b_joints, b_ee)
    direction: tuple[str, ...] = ()
    rotates = False
    joint = None
    if a.ee is not None and b.ee is not None and len(a.ee) >= 3 and len(b.ee) >= 3:
        direction = tuple(direction_words([b.ee[i] - a.ee[i] for i in range(3)]))
        if len(a.ee) >= 6 and len(b.ee) >= 6:
            rotates = max(abs(b.ee[i] - a.ee[i]) for i in range(3, 6)) >= MIN_ROTATION_RAD
    grip = None
    if a.joints is not None and b.joints is not None:
        if len(a.joints) >= 8 and len(b.joints) >= 8:
            grip = gripper_word(b.joints[7] - a.joints[7])
        if a.ee is None or b.ee is None:
            arm = [abs(b.joints[i] - a.joints[i]) for i in range(min(7, len(a.joints), len(b.joints)))]
            if arm and max(arm) >= MIN_JOINT_RAD:
                joint = arm.index(max(arm)) + 1
    known = (a.ee is not None and b.ee is not None) or (a.joints is not None and b.joints is not None)
    return Motion(direction, grip, rotates, joint, known)


def _join(phrases: Sequence[str]) -> str:
    if len(phrases) <= 1:
        return "".join(phrases)
    return ", ".join(phrases[:-1]) + " and " + phrases[-1]


@dataclass(frozen=True)
class _Voice:
    """How a motion is put into words: the reference captions describe (third person), instructions command."""

    move: str
    joint: str  # with {} for the joint number
    rotate: str
    grip: dict[str, str]  # primitives.gripper_word -> verb


_DESCRIBE = _Voice(
    "moves ", "turns its joints, mostly joint {}", "rotates the gripper", {"closes": "closes", "opens": "opens"}
)
_COMMAND = _Voice("move ", "turn joint {}", "rotate the gripper", {"closes": "close", "opens": "open"})


def _phrases(m: Motion, voice: _Voice) -> list[str]:
    phrases = []
    if m.direction:
        phrases.append(voice.move + " and ".join(m.direction))
    if m.joint is not None:
        phrases.append(voice.joint.format(m.joint))
    if m.rotates:
        phrases.append(voice.rotate)
    if m.grip:
        phrases.append(f"{voice.grip[m.grip]} the gripper")
    return phrases


def motion_phrases(m: Motion) -> list[str]:
    """Verb phrases in the third person: ['moves forward and down', 'closes the gripper']."""
    return _phrases(m, _DESCRIBE) or ["holds still" if m.known_position else "keeps the gripper as it is"]


def gripper_state(s: ParsedState) -> str | None:
    if s.joints is None or len(s.joints) < 8:
        return None
    return "open" if s.joints[7] >= OPEN_GRIPPER_M else "closed"


def frame_caption(states: dict[int, ParsedState], n: int) -> str:
    cur = states.get(n)
    if cur is None:
        return NO_STATE
    nxt, prev = states.get(n + 1), states.get(n - 1)
    sentences = []
    m = None
    if nxt is not None or prev is not None:
        m = motion_between(cur, nxt) if nxt is not None else motion_between(prev, cur)
        sentences.append("The robot " + _join(motion_phrases(m)) + ".")
    else:
        sentences.append("A single frame: the motion cannot be told from one state.")
    grip = gripper_state(cur)
    if grip and (m is None or m.grip is None):  # an opening or closing gripper is already described
        sentences.append(f"The gripper is {grip}.")
    return " ".join(sentences)


def _merged_steps(seq: Sequence[ParsedState]) -> list[tuple[Motion, int, int]]:
    """Consecutive intervals with the same motion merged: (motion, first frame number, last frame number)."""
    runs: list[tuple[Motion, int, int]] = []
    for a, b in itertools.pairwise(seq):
        m = motion_between(a, b)
        if runs and runs[-1][0] == m:
            runs[-1] = (m, runs[-1][1], b.number)
        else:
            runs.append((m, a.number, b.number))
    return runs


def group_caption(seq: Sequence[ParsedState]) -> str:
    if not seq:
        return NO_STATE
    if len(seq) == 1:
        grip = gripper_state(seq[0])
        tail = f" The gripper is {grip}." if grip else ""
        return "Only one frame has a state, so the motion cannot be told." + tail
    runs = _merged_steps(seq)
    parts = [_join(motion_phrases(m)) for m, _, _ in runs]
    sentences = ["The robot " + ", then ".join(parts) + "."]
    events = [(m.grip, a, b) for m, a, b in runs if m.grip]
    for grip, a, b in events:
        sentences.append(f"It {grip} the gripper between frames {a} and {b}.")
    end = gripper_state(seq[-1])
    if end:
        sentences.append(f"At the end the gripper is {end}.")
    return " ".join(sentences)


def _imperative(m: Motion) -> str | None:
    return None if m.still else " and ".join(_phrases(m, _COMMAND))


def instruction(seq: Sequence[ParsedState]) -> str:
    if len(seq) < 2:
        return NO_STATE if not seq else "Keep the arm where it is."
    steps = [s for s in (_imperative(m) for m, _, _ in _merged_steps(seq)) if s]
    # drop immediate repeats left by still intervals in between, then keep the main steps in order
    deduped = [s for i, s in enumerate(steps) if i == 0 or s != steps[i - 1]]
    if not deduped:
        return "Keep the arm where it is."
    if len(deduped) > MAX_INSTRUCTION_STEPS:
        # the gripper steps carry the task (grasp, release); fill the rest with the earliest motions
        grips = {i for i, step in enumerate(deduped) if "gripper" in step}
        others = [i for i in range(len(deduped)) if i not in grips]
        chosen = sorted(grips | set(others[: max(0, MAX_INSTRUCTION_STEPS - len(grips))]))
        deduped = [deduped[i] for i in chosen]
    text = deduped[0] if len(deduped) == 1 else ", ".join(deduped[:-1]) + ", then " + deduped[-1]
    return text[0].upper() + text[1:] + "."


def _process_error(found: int) -> BackendError:
    return BackendError(
        f"reference captioner: the prompt must hold exactly one '# Process N' line (N = 1, 2 or 3), "
        f"found {found}; it only answers prompts built by vlmproprio.prompts"
    )


def process_number(text: str) -> int:
    found = PROCESS_RE.findall(text)
    if len(found) != 1:
        raise _process_error(len(found))
    return int(found[0])


@lru_cache(maxsize=4096)  # every prompt starts with one of a few preambles: each is searched once
def _process_lines(text: str) -> tuple[tuple[int, int], ...]:
    """(N, end offset) of every '# Process N' line in one text part."""
    return tuple((int(m.group(1)), m.end()) for m in PROCESS_RE.finditer(text))


def _line_aligned_texts(request: ChatRequest) -> list[str] | None:
    """The request's text parts in order, or None when a line of its text may run across two of them (a text
    part other than a message's last that does not end with a line break; messages are joined by one). Cut at
    line ends, a pattern anchored to whole lines finds in the parts exactly what it finds in the joined text."""
    texts: list[str] = []
    for m in request.messages:
        parts = [p.text for p in m.parts if isinstance(p, TextPart)]
        if any(not t.endswith("\n") for t in parts[:-1]):
            return None
        texts += parts
    return texts


def prompt_states(request: ChatRequest) -> tuple[int, list[ParsedState]]:
    """The request's process number and the state lines after its '# Process N' line (the worked example in
    the preamble before it has state lines of its own), read part by part without joining the prompt's text."""
    texts = _line_aligned_texts(request)
    if texts is None:
        text = "\n".join(m.text for m in request.messages)
        return process_number(text), parse_state_lines(text[PROCESS_RE.search(text).end() :])
    found = [(i, n, end) for i, t in enumerate(texts) for n, end in _process_lines(t)]
    if len(found) != 1:
        raise _process_error(len(found))
    i, process, end = found[0]
    states = parse_state_lines(texts[i][end:])
    for t in texts[i + 1 :]:
        states += parse_state_lines(t)
    return process, states


def reference_answer(request: ChatRequest) -> str:
    """The reference captioner's answer to one request (see the module docstring)."""
    process, states = prompt_states(request)
    if process == 1:
        by_number = {s.number: s for s in states}
        k = max([len(request.images), *by_number.keys()])
        if k == 0:
            return f"Frame 1: {NO_STATE}"
        return "\n".join(f"Frame {n}: {frame_caption(by_number, n)}" for n in range(1, k + 1))
    if process == 2:
        return group_caption(states)
    return instruction(states)


class ReferenceBackend(Backend):
    """Motion-primitive captions from the state numbers alone. Deterministic, instant, not a VLM."""

    max_batch_size = 1024
    calls_model = False
    # what a rule-based captioner is (its cache identity) and says about itself; subclasses change these four
    model_id = MODEL_ID
    rules_version = RULES_VERSION
    note = "rule-based reference captioner, not a vision-language model"

    def answer(self, request: ChatRequest) -> str:
        return reference_answer(request)

    def identity(self) -> dict[str, str]:
        return {
            "backend": "reference",
            "model_id": self.model_id,
            "revision": self.rules_version,
            "dtype": "",
            "attn_implementation": "",
        }

    def generate(self, requests: Sequence[ChatRequest]) -> list[Answer]:
        out = []
        for req in requests:
            t0 = time.perf_counter()
            text = self.answer(req)
            meta = AnswerMeta(
                **self.identity(),
                device="cpu",
                completion_tokens=len(text.split()),
                latency_s=time.perf_counter() - t0,
                extra={"note": self.note},
            )
            out.append(Answer(text=text, meta=meta))
        return out


# ---------------------------------------------------------------------------------------------- the reference kind


def _create_rules(ref: ModelRef, settings: BackendSettings) -> Backend:
    if ref.weights == STATE_RULES:
        from vlmproprio.backends.reference_state import ReferenceStateBackend

        return ReferenceStateBackend()
    return ReferenceBackend()


def _rules_live(ref: ModelRef, settings: BackendSettings) -> Availability:
    return Availability(True, "rule-based reference captioner (no model, always available)")


# only the registry's short names (reference, reference-state): no prefix, no settings, no cassette
register_kind(KindSpec(kind="reference", create=_create_rules, live=_rules_live, needs_cassette=False))
