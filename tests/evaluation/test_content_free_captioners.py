"""Captioners that read nothing in the state win no claim.

Each captioner below sees only whether the prompt has a state section (``### Joint/Pose ###``), never a number in
it, and is scored on every shipped episode under ``none``, ``both`` and ``both_shuffled``:

* a metronome: a new generic sentence every ``period`` frames from ``offset`` on, when a state section is there
  (one constant sentence otherwise), at several periods and offsets;
* presence: the canonical sentence of the task, with one fixed compartment, when a state section is there;
* constant: the same words everywhere.

None of them may get a combined claim supported (both > none AND both > both_shuffled), and a metronome's lift
over the best content-free baseline is at most 0 when averaged over its phase offsets. A captioner that is told the
ground truth (a leak) is named by a warning.
"""

from __future__ import annotations

import json
import re
from collections.abc import Sequence
from pathlib import Path

import pytest

from scoring_helpers import score_scripted_run
from vlmproprio.chat import Answer, AnswerMeta, ChatRequest
from vlmproprio.episodes import list_episode_ids, load_episodes

FIXTURES = Path(__file__).resolve().parents[2] / "fixtures"
CONDITIONS = ("none", "both", "both_shuffled")
STATE_MARK = "### Joint/Pose ###"
GROUP = 5  # Process 1 frames per request (the suite's k)
# sentences whose first words differ, so that each change is a boundary (the fake encoder groups by opening words)
GENERIC = (
    "Alpha the robot arm is working on its task.",
    "Bravo the manipulator continues with the job.",
    "Charlie movement of the arm goes on steadily.",
)
DOOR_FINAL = "Grasp the door handle, turn it downward and then pull the door open toward the robot."
BIN_FINAL = "Pick up the cereal box, lift it up and place it in the far left compartment of the target bin."
PLAIN_FINAL = {"door": "The robot opens the door.", "pick_place": "The robot picks up the box and puts it in a bin."}


def _answer(text: str) -> Answer:
    return Answer(text, AnswerMeta(backend="scripted", model_id="scripted"), key=str(hash(text)))


def _frames_of(r: ChatRequest) -> int:
    return int(re.search(r"exactly (\d+) lines", r.messages[0].text).group(1))


class ContentFree:
    """Base: Process 1 lines from ``frame_caption``, Process 2 a fixed sentence, Process 3 from ``final``."""

    def frame_caption(self, r: ChatRequest, frame: int, state: bool) -> str:
        return GENERIC[0]

    def final(self, r: ChatRequest, state: bool) -> str:
        return PLAIN_FINAL[self.task_of(r)]

    def task_of(self, r: ChatRequest) -> str:
        return "door" if r.tag.episode_id.startswith("door") else "pick_place"

    def __call__(self, requests: Sequence[ChatRequest]) -> list[Answer]:
        out = []
        for r in requests:
            text = r.messages[0].text
            state = STATE_MARK in text
            if "# Process 1" in text:
                n = _frames_of(r)
                first = GROUP * r.tag.group
                lines = [f"Frame {i + 1}: {self.frame_caption(r, first + i, state)}" for i in range(n)]
                out.append(_answer("\n".join(lines)))
            elif "# Process 2" in text:
                out.append(_answer("The robot arm carries out its task."))
            else:
                out.append(_answer(self.final(r, state)))
        return out


class Metronome(ContentFree):
    def __init__(self, period: int, offset: int):
        self.period, self.offset = period, offset

    def frame_caption(self, r, frame, state):
        if not state:
            return GENERIC[0]
        return GENERIC[((frame - self.offset) // self.period) % len(GENERIC)]


class Presence(ContentFree):
    def final(self, r, state):
        if not state:
            return PLAIN_FINAL[self.task_of(r)]
        return DOOR_FINAL if self.task_of(r) == "door" else BIN_FINAL


class Leak(ContentFree):
    """Told the ground truth: each frame's phase, and the episode's compartment, under every condition."""

    def __init__(self):
        self.episodes = {e.episode_id: e for e in load_episodes(FIXTURES, list_episode_ids(FIXTURES))}

    def frame_caption(self, r, frame, state):
        ep = self.episodes[r.tag.episode_id]
        return f"{ep.frames[min(frame, len(ep.frames) - 1)].phase} phase of the robot arm now."

    def final(self, r, state):
        ep = self.episodes[r.tag.episode_id]
        if ep.target_bin is None:
            return DOOR_FINAL
        return f"Pick up the cereal box and place it in {ep.target_bin.description} of the target bin."


def _score(tmp_path: Path, captioner) -> dict:
    run = tmp_path / "run"
    score_scripted_run(run, FIXTURES, list_episode_ids(FIXTURES), CONDITIONS, captioner)
    return {
        "verdicts": json.loads((run / "scores" / "verdicts.json").read_text()),
        "rows": json.loads((run / "scores" / "rows.json").read_text()),
    }


def _supported_claims(doc: dict) -> list[str]:
    return [c["claim"] for c in doc["verdicts"]["combined"] if c["verdict"] == "supported"]


@pytest.mark.parametrize(("period", "offset"), [(6, 0), (3, 1), (4, 2), (7, 3), (5, 4)])
def test_a_metronome_wins_no_claim(tmp_path, period, offset):
    doc = _score(tmp_path, Metronome(period, offset))
    assert _supported_claims(doc) == [], json.dumps(doc["verdicts"]["combined"], indent=1)
    kinds = {w["kind"] for w in doc["verdicts"]["warnings"]}
    assert kinds & {"periodic", "group-edges"}, kinds  # its schedule is named


@pytest.mark.parametrize("captioner", [Presence(), ContentFree()], ids=["presence", "constant"])
def test_presence_and_constant_captioners_win_no_claim(tmp_path, captioner):
    doc = _score(tmp_path, captioner)
    assert _supported_claims(doc) == [], json.dumps(doc["verdicts"]["combined"], indent=1)


@pytest.mark.slow
def test_a_metronome_does_not_beat_the_content_free_baseline_on_average(tmp_path):
    period = 6
    lifts = []
    for offset in range(period):
        rows = _score(tmp_path / str(offset), Metronome(period, offset))["rows"]
        lifts += [
            float(r["seg_loo_f1_tol1_lift_cf"])
            for r in rows
            if r["condition"] == "both" and r.get("seg_loo_f1_tol1_lift_cf") is not None
        ]
    assert lifts and sum(lifts) / len(lifts) <= 1e-12, sum(lifts) / len(lifts)


def test_a_ground_truth_leak_is_named(tmp_path):
    doc = _score(tmp_path, Leak())
    leaks = [w for w in doc["verdicts"]["warnings"] if w["kind"] == "leak"]
    assert leaks, doc["verdicts"]["warnings"]
    assert any("none" in w["message"] for w in leaks)
