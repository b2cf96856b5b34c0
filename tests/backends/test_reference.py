"""The reference captioner on hand-written prompts in the pipeline's conventions."""

from __future__ import annotations

import re

import pytest

from vlmproprio.answering import Answerer
from vlmproprio.backends.base import BackendError
from vlmproprio.backends.reference import NO_STATE, ReferenceBackend, reference_answer
from vlmproprio.prompts.state import format_state_line

OPEN, CLOSED = 0.08, 0.01
# A pick: forward, down, close, up-and-left with a wrist turn. ee = x, y, z, roll, pitch, yaw; joints end in gripper.
EE = [
    [0.50, 0.00, 1.10, 3.14, 0.0, 0.0],
    [0.60, 0.00, 1.10, 3.14, 0.0, 0.0],
    [0.60, 0.00, 0.95, 3.14, 0.0, 0.0],
    [0.60, 0.00, 0.95, 3.14, 0.0, 0.0],
    [0.60, 0.12, 1.15, 3.14, 0.0, 0.6],
]
GRIP = [OPEN, OPEN, OPEN, CLOSED, CLOSED]
JOINTS = [[0.0, 0.1 * i, 0.0, -2.0, 0.0, 2.0, 0.8, g] for i, g in enumerate(GRIP)]


def state_lines(joints: bool = True, ee: bool = True) -> str:
    return "\n".join(
        format_state_line(i + 1, JOINTS[i] if joints else None, EE[i] if ee else None) for i in range(len(EE))
    )


def prompt(process: int, body: str) -> str:
    return f"You see frames from a robot episode.\n# Process {process}\n{body}\nAnswer in the format asked."


def test_process_1_one_line_per_frame_from_the_numbers(request_factory):
    images = tuple(b"frame%d" % i for i in range(5))
    text = reference_answer(request_factory(prompt(1, state_lines()), images))
    lines = text.splitlines()
    assert [re.match(r"Frame (\d+): ", line).group(1) for line in lines] == ["1", "2", "3", "4", "5"]
    assert "moves forward" in lines[0] and "open" in lines[0]
    assert "moves down" in lines[1]
    assert "closes the gripper" in lines[2]
    assert "moves up and left" in lines[3] and "rotates the gripper" in lines[3]
    assert "closed" in lines[4]  # the last frame looks back at the motion into it


def test_process_1_without_numbers_says_it_cannot_tell(request_factory):
    images = tuple(b"frame%d" % i for i in range(5))
    words_only = "\n".join(f"Frame {i}: moves forward" for i in range(1, 6))  # the `primitives` control
    for body in ("", words_only):
        text = reference_answer(request_factory(prompt(1, body), images))
        assert text.splitlines() == [f"Frame {i}: {NO_STATE}" for i in range(1, 6)]


def test_joint_angles_only_still_track_the_gripper(request_factory):
    text = reference_answer(request_factory(prompt(1, state_lines(ee=False)), ()))
    lines = text.splitlines()
    assert len(lines) == 5
    assert "closes the gripper" in lines[2]
    assert "joint 2" in lines[0]  # no end-effector: the joint that moved most is named


def test_process_2_one_paragraph(request_factory):
    text = reference_answer(request_factory(prompt(2, state_lines()), ()))
    assert "\n" not in text and 2 <= text.count(".") <= 6
    assert text.startswith("The robot moves forward, then moves down, then closes the gripper")
    assert "between frames 3 and 4" in text and text.endswith("the gripper is closed.")
    assert reference_answer(request_factory(prompt(2, ""), ())) == NO_STATE


def test_process_3_one_instruction(request_factory):
    text = reference_answer(request_factory(prompt(3, state_lines()), ()))
    assert text == "Move forward, move down, close the gripper, then move up and left and rotate the gripper."
    assert reference_answer(request_factory(prompt(3, "Group 1: The robot moves."), ())) == NO_STATE


@pytest.mark.parametrize("body", ["no process line", "# Process 1\n# Process 2", "# Process 4"])
def test_prompt_without_exactly_one_process_line_is_refused(request_factory, body):
    with pytest.raises(BackendError, match="exactly one '# Process N' line"):
        reference_answer(request_factory(body, ()))


def test_backend_is_deterministic_labelled_and_never_a_model(request_factory):
    b = ReferenceBackend()
    ident = b.identity()
    assert ident["backend"] == "reference" and ident["model_id"] == "reference-primitives" and ident["revision"]
    assert b.calls_model is False
    reqs = [request_factory(prompt(p, state_lines()), ()) for p in (1, 2, 3)]
    first, second = b.generate(reqs), b.generate(reqs)
    assert [a.text for a in first] == [a.text for a in second]
    assert "not a vision-language model" in first[0].meta.extra["note"]
    # allowed to answer misses in replay mode, because it runs no model
    answers = Answerer(b, mode="replay").answer(reqs)
    assert [a.text for a in answers] == [a.text for a in first]


# ---------------------------------------------------------------------------------------------- reading prompts


def _joined(request):
    """What prompt_states must give: the prompt's text joined as a chat template sees it, then searched."""
    from vlmproprio.backends.reference import PROCESS_RE, process_number
    from vlmproprio.prompts.state import parse_state_lines

    text = "\n".join(m.text for m in request.messages)
    return process_number(text), parse_state_lines(text[PROCESS_RE.search(text).end() :])


def _cut(text: str, rng, at_line_ends: bool) -> list[str]:
    """``text`` in pieces: cut only after line breaks, or anywhere (mid-line too, empty pieces included)."""
    spots = [i + 1 for i, ch in enumerate(text) if ch == "\n"] if at_line_ends else list(range(len(text) + 1))
    cuts = sorted(rng.sample(spots, min(len(spots), rng.randint(0, 8))))
    return [text[a:b] for a, b in zip([0, *cuts], [*cuts, len(text)], strict=True)]


def _request_of(pieces: list[str], rng):
    from vlmproprio.chat import ChatRequest, GenerationConfig, ImagePart, Message, RequestTag, TextPart

    parts = []
    for p in pieces:
        parts.append(TextPart(p))
        if rng.random() < 0.3:
            parts.append(ImagePart(b"frame"))
    split = rng.randint(0, len(parts))  # a second message (joined to the first by a line break) or none
    messages = tuple(Message("user", tuple(ps)) for ps in (parts[:split], parts[split:]) if ps)
    return ChatRequest(messages=messages, config=GenerationConfig(), prompt_version="t", tag=RequestTag())


@pytest.mark.parametrize("at_line_ends", [True, False])
@pytest.mark.parametrize("seed", range(30))
def test_prompt_states_reads_the_parts_as_the_joined_text(seed, at_line_ends):
    """The worked example's states come before the process line; the parts may split lines or not."""
    import random

    from vlmproprio.backends.reference import _line_aligned_texts, prompt_states

    rng = random.Random(seed)
    example = "A worked example:\n" + state_lines() + "\n"
    text = example + prompt(rng.choice([1, 2, 3]), state_lines(joints=rng.random() < 0.5, ee=rng.random() < 0.8))
    request = _request_of(_cut(text, rng, at_line_ends), rng)
    assert prompt_states(request) == _joined(request)
    if at_line_ends:
        assert _line_aligned_texts(request) is not None  # read part by part, not joined


@pytest.mark.parametrize("body", ["no process line\n", "# Process 1\n", "# Process 2\n# Process 2\n"])
def test_a_process_line_in_each_of_two_parts_is_counted_as_in_the_joined_text(body):
    import random

    from vlmproprio.backends.reference import prompt_states

    request = _request_of(["# Process 1\n", body], random.Random(0))
    found = 1 + body.count("# Process")
    if found == 1:
        assert prompt_states(request) == _joined(request)
    else:
        with pytest.raises(BackendError, match=f"exactly one '# Process N' line .*found {found};"):
            prompt_states(request)
