"""One test per class of rubric error named in issue 13, phrased differently from the issue's examples.

Each test failed with the scorer before the fix (lexicons v1): the point is the class, not the sentence.
The captions are scored against shipped fixture episodes, whose expected directions come from their own
ground truth (steps.npz) and whose camera pose comes from lexicons/cameras.json.
"""

from __future__ import annotations

import dataclasses
import shutil
from pathlib import Path

import pytest

from vlmproprio.episodes import StepStates, load_episode, read_steps, write_steps
from vlmproprio.scoring import CORRECT, WRONG, expectation_for, score_caption

FIXTURES = Path(__file__).resolve().parents[1] / "fixtures"


@pytest.fixture(scope="module")
def ep():
    cache = {}

    def get(eid: str):
        if eid not in cache:
            cache[eid] = load_episode(FIXTURES, eid, verify=False)
        return cache[eid]

    return get


def verdicts(text, episode):
    s = score_caption(text, episode)
    return s, {k: (s.item(k).mentioned, s.item(k).correct) for k in ("object", "action", "trajectory")}


# ------------------------------------------------------------------ the opposite motion is no opening


@pytest.mark.parametrize(
    "text",
    [
        "The arm nudges the door outward until it swings open.",
        "Holding the lever, the robot pushed the door so that it opened.",
        "Gripper shoving door open",
    ],
)
def test_pushing_the_door_is_a_wrong_action(ep, text):
    s, v = verdicts(text, ep("door_05"))
    assert v["action"] == (True, False), [(h.text, h.kind, h.value, h.verdict) for h in s.matches]
    assert s.action.wrong
    push = next(h for h in s.matches if h.kind == "wrong_action")
    assert push.entry.endswith("contextual.push") and text[push.start : push.end] == push.text


def test_pushing_the_lever_down_is_still_turning_it(ep):
    s, v = verdicts("It pushes the lever downward, then tugs the door toward itself until it is open.", ep("door_05"))
    assert v == {"object": (True, True), "action": (True, True), "trajectory": (True, True)}
    assert any(h.kind == "action" and h.value == "turn" and h.text == "pushes" for h in s.matches)


# ------------------------------------------------------------------ placing and pick-and-place phrasings


@pytest.mark.parametrize(
    "text",
    [
        "The robot lifts the cereal and lays the box down in the top-left compartment.",
        "Robot takes the box out of the right bin and puts the cereal down in the far left section.",
        "The gripper moves the cereal box from the source bin into the far left compartment.",
        "It carried the cereal from one bin to the far-left part of the other.",
    ],
)
def test_split_and_transfer_phrasings_are_pick_and_place(ep, text):
    s, v = verdicts(text, ep("bin3_01"))
    assert v["action"] == (True, True), [(h.text, h.kind, h.value, h.verdict) for h in s.matches]
    for h in s.matches:
        assert text[h.start : h.end] == h.text


def test_a_split_verb_owns_its_particle(ep):
    s, _ = verdicts("It picks the cereal box up and sets the box down in the far left bin.", ep("bin3_01"))
    up = next(h for h in s.matches if h.text == "up")
    assert up.verdict == CORRECT and "'lift'" in up.note  # picks ... up: the lift, whose ground truth is up
    assert any(h.text == "sets the box down" and h.value == "place" for h in s.matches)


# ------------------------------------------------------------------ compartments without the camera's words


@pytest.mark.parametrize(
    ("eid", "text", "correct"),
    [
        ("bin3_01", "It drops the cereal into the rear compartment on the opposite side from the source bin.", True),
        ("bin1_01", "It drops the cereal into the rear compartment on the opposite side from the source bin.", False),
        (
            "bin0_01",
            "The box is placed, after being picked, in the compartment nearest to the robot beside the source bin.",
            True,
        ),
        (
            "bin2_01",
            "The box is picked and placed in the compartment nearest to the robot beside the source bin.",
            False,
        ),
        (
            "bin1_02",
            "Picks the cereal and places it in the compartment farthest from the robot, adjacent to the source bin.",
            True,
        ),
    ],
)
def test_compartments_named_by_the_robot_and_the_source_bin(ep, eid, text, correct):
    s, v = verdicts(text, ep(eid))
    assert v["trajectory"] == (True, correct), [(h.text, h.kind, h.value, h.verdict, h.note) for h in s.matches]
    assert s.trajectory.wrong == (not correct)


# ------------------------------------------------------------------ the lever springs back after release


@pytest.mark.parametrize(
    "text",
    [
        "It rotates the knob down, swings the door toward itself, and the knob rotates upward again once let go.",
        "Turning the lever downward, the robot draws the door back; on release the lever turns back upward.",
    ],
)
def test_the_handle_returning_up_is_part_of_a_correct_description(ep, text):
    s, v = verdicts(text, ep("door_03"))
    assert v["trajectory"] == (True, True), [(h.text, h.kind, h.value, h.verdict, h.note) for h in s.matches]
    assert any("return" in h.note for h in s.matches if h.value == "up")


def test_turning_the_handle_up_alone_is_still_wrong(ep):
    _, v = verdicts("The robot rotates the knob upward and draws the door toward itself.", ep("door_03"))
    assert v["trajectory"] == (True, False)


# ------------------------------------------------------------------ expected directions from ground truth


def test_door_directions_come_from_the_episodes_own_steps(ep):
    exp = expectation_for(ep("door_00"))
    pull = next(m for m in exp.motions if m.name == "pull door")
    turn = next(m for m in exp.motions if m.name == "turn handle")
    assert "steps.npz" in pull.source and "steps.npz" in turn.source
    # the pull is mostly sideways (the robot's left) and partly back toward the robot, as the hand moved
    assert {"backward", "robot_left"} <= set(pull.expected)
    assert {"forward", "robot_right"} <= set(pull.opposite)
    assert turn.expected == ("down",) and turn.returns == ("up",)


def test_expected_directions_follow_a_changed_ground_truth(ep, tmp_path):
    """Mirror the hand's y in steps.npz: the expected side of the pull flips (no constant behind it)."""
    door = ep("door_00")
    root = tmp_path / "door_00"
    shutil.copytree(door.root, root, ignore=shutil.ignore_patterns("frames"))
    st = read_steps(root / "steps.npz")
    ee = st.ee.copy()
    ee[:, 1] = -ee[:, 1]
    write_steps(root / "steps.npz", StepStates(st.step, st.joints, ee, st.phase, st.direction))
    mirrored = dataclasses.replace(door, root=root)
    pull = next(m for m in expectation_for(mirrored).motions if m.name == "pull door")
    assert "robot_right" in pull.expected and "robot_left" in pull.opposite
    text = "It turns the lever down and pulls the door open toward the robot's left."
    assert score_caption(text, door).trajectory.correct
    assert score_caption(text, mirrored).trajectory.wrong


# ------------------------------------------------------------------ side words follow the camera


def test_side_words_follow_the_camera(ep):
    bin3 = ep("bin3_02")  # far-left for the robot; the bin camera shows the robot's left on the image's left
    front = dataclasses.replace(bin3, camera="agentview")  # looks at the robot: the image is mirrored
    own = dataclasses.replace(
        bin3, camera="custom", extra={"camera_axes": {"right": [0, 1, 0], "up": [-1, 0, 0.1], "view": [0, 0, -1]}}
    )
    left = "The robot picks up the cereal box and places it in the far left compartment."
    right = "The robot picks up the cereal box and places it in the far right compartment."
    assert score_caption(left, bin3).trajectory.correct and score_caption(right, bin3).trajectory.wrong
    assert score_caption(right, front).trajectory.correct and score_caption(left, front).trajectory.wrong
    assert expectation_for(own).image_side == "right"
    # the image's top is near the robot for the agentview and the custom camera
    assert score_caption("It picks the cereal and places it in the bottom right compartment.", own).trajectory.correct
    # words that do not depend on the camera are right under every camera
    neutral = "The robot picks up the cereal box and places it in the far compartment away from the source bin."
    robot_words = "The robot picks up the cereal and places it in the far bin on the robot's left side."
    for e in (bin3, front, own):
        assert score_caption(neutral, e).trajectory.correct, e.camera
        assert score_caption(robot_words, e).trajectory.correct, e.camera


def test_door_side_words_are_the_cameras(ep):
    door = ep("door_00")  # sideview: the door's pull toward the robot shows as a move to the image's right
    exp = expectation_for(door)
    assert "sideview" in exp.camera
    pull = next(m for m in exp.motions if m.name == "pull door")
    assert "right" in pull.expected and "left" in pull.opposite
    s = score_caption("Turning the handle down, it pulls the door to the right.", door)
    assert next(h for h in s.matches if h.value == "right").verdict == CORRECT
    s = score_caption("Turning the handle down, it pulls the door to the left.", door)
    assert next(h for h in s.matches if h.value == "left").verdict == WRONG


def test_every_new_verdict_keeps_its_span(ep):
    text = "The robot shoves the door, sets the lever down, and transfers it from one side next to the source bin."
    for h in score_caption(text, ep("door_00")).matches + score_caption(text, ep("bin0_00")).matches:
        assert text[h.start : h.end] == h.text and h.entry and h.verdict
