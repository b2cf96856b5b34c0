"""What each condition's prompts say: only what that condition sends.

Every request the pipeline sends for one shipped episode is rendered under every condition and read as
text. The suite's prompts must not mention joint angles or hand positions where none are sent, nor images
where none are sent; the gripper value is described as a finger distance in metres; a short last group is
"one image", not "one images". ``--prompt-version paper-verbatim`` sends the paper's text as printed.
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from pathlib import Path

import pytest

from vlmproprio.chat import Answer, AnswerMeta, ChatRequest
from vlmproprio.conditions import CONDITIONS, get_condition
from vlmproprio.episodes import load_episodes
from vlmproprio.errors import UsageError
from vlmproprio.pipeline import PipelineSettings, caption_episodes
from vlmproprio.prompts import PromptOptions, prompt_version, template

FIXTURES = Path(__file__).resolve().parents[2] / "fixtures"
STATE_WORDS = re.compile(r"joint|end-effector|hand position|position and orientation|gripper opening", re.IGNORECASE)
IMAGE_WORDS = re.compile(r"\bimages?\b", re.IGNORECASE)


class Recorder:
    """Answers in the requested format and keeps every request's text."""

    def __init__(self) -> None:
        self.texts: list[str] = []

    def __call__(self, requests: Sequence[ChatRequest]) -> list[Answer]:
        out = []
        for r in requests:
            text = r.messages[0].text
            self.texts.append(text)
            if "# Process 1" in text:
                n = int(re.search(r"exactly (\d+) lines", text).group(1))
                ans = "\n".join(f"Frame {i}: the arm moves." for i in range(1, n + 1))
            else:
                ans = "The arm moves."
            out.append(Answer(ans, AnswerMeta(backend="rec", model_id="rec"), key=str(len(self.texts))))
        return out


@pytest.fixture(scope="module")
def episode():
    # door_00 has 31 frames: groups of 5 and a last group of one frame
    return load_episodes(FIXTURES, ["door_00"])[0]


def sent(episode, condition: str, **options) -> list[str]:
    rec = Recorder()
    settings = PipelineSettings(prompt=PromptOptions(**options))
    caption_episodes([episode], [get_condition(condition)], rec, "rec", settings=settings, progress=False)
    return rec.texts


def test_the_last_group_is_one_frame(episode):
    assert len(episode.frames) % 5 == 1


def test_none_mentions_no_state(episode):
    texts = sent(episode, "none")
    assert texts
    for t in texts:
        assert not STATE_WORDS.search(t), STATE_WORDS.search(t).group(0)


def test_state_only_mentions_no_images(episode):
    for t in sent(episode, "state_only"):
        words = {m.group(0).lower() for m in IMAGE_WORDS.finditer(t)}
        # the only allowed mention says that there are none
        assert not words or t.count("no images") == len(IMAGE_WORDS.findall(t)), t[:600]
        assert "joint angles" in t


@pytest.mark.parametrize("name", list(CONDITIONS))
def test_each_condition_names_what_it_sends(episode, name):
    cond = get_condition(name)
    texts = sent(episode, name)
    p1 = [t for t in texts if "# Process 1" in t]
    p3 = [t for t in texts if "# Process 3" in t]
    task = p1[0].split("### Guidelines ###")[0]
    assert ("joint angles" in task) == cond.joints
    assert ("position and orientation" in task) == cond.ee
    assert ("how the robot hand moves" in task) == cond.words
    assert ("there are no images" in task) == (not cond.images)
    assert ("incorporating" in p3[0]) == cond.has_state
    if cond.joints:  # the gripper value is a finger distance in metres, not the paper's "-1.0"
        assert "distance between the two fingers in metres" in p1[0] and "-1.0" not in p1[0]
    # the count of a group's frames reads as English, also for the last group of one frame
    assert "one images" not in p1[-1] and "one frames" not in p1[-1]
    assert re.search(r"consists of one (image|frame)\.", p1[-1])


def test_shuffled_and_noisy_controls_read_exactly_like_both(episode):
    """The model must not be told that its numbers are wrong: only the numbers differ."""
    strip = re.compile(r"\[[^\]]*\]")
    both = [strip.sub("[]", t) for t in sent(episode, "both")]
    for name in ("both_shuffled", "both_noisy"):
        assert [strip.sub("[]", t) for t in sent(episode, name)] == both


def test_paper_verbatim_sends_the_papers_text(episode):
    texts = sent(episode, "none", version="paper-verbatim")
    p1 = next(t for t in texts if "# Process 1" in t)
    # under none the paper's text still speaks of joint angles: that is what the switch is for
    assert template("task.txt") in p1 and template("process1.txt").format(count_words="five") in p1
    assert "Input is a sequence of robot motion frame images, robot joint angles" in p1
    both = next(t for t in sent(episode, "both", version="paper-verbatim") if "# Process 1" in t)
    assert template("joint_pose_joint.txt") in both and "(-1.0)" in both
    assert prompt_version(PromptOptions(version="paper-verbatim")) != prompt_version(PromptOptions())


def test_prompt_versions_name_the_set_and_enter_requests(episode):
    assert prompt_version() == f"suite-{template('VERSION', 'suite')}"
    assert prompt_version() != "paper-1"  # the paper's own text, before the condition-aware rewrites
    with pytest.raises(UsageError, match="prompt version"):
        PromptOptions(version="paper")


def test_cli_run_reference_under_none_sends_no_state_words(tmp_path, monkeypatch):
    """`vlmproprio run --model reference --conditions none`: every text the model receives, read at the backend."""
    from vlmproprio.backends.reference import ReferenceBackend
    from vlmproprio.cli import main

    seen: list[str] = []
    original = ReferenceBackend.generate

    def spy(self, requests):
        seen.extend(m.text for r in requests for m in r.messages)
        return original(self, requests)

    monkeypatch.setattr(ReferenceBackend, "generate", spy)
    args = [
        "run",
        "--model",
        "reference",
        "--conditions",
        "none",
        "--episodes",
        "bin1_00",
        "--no-progress",
        "--fixtures",
        str(FIXTURES),
    ]
    assert main([*args, "--out", str(tmp_path / "run"), "--cache-dir", str(tmp_path / "cache")]) == 0
    assert len(seen) > 10
    for text in seen:
        assert not STATE_WORDS.search(text), STATE_WORDS.search(text).group(0)
