"""What a correct caption says (vlmproprio.scoring.expectation): expected directions from the episode's own
ground truth, and side and row words read in the camera's image."""

from __future__ import annotations

import dataclasses
import shutil

import pytest

from scoring_helpers import bin_episode, make_episode
from vlmproprio.episodes import StepStates, read_steps, write_steps
from vlmproprio.scoring import CORRECT, WRONG, ScoringError, expectation_for, score_caption

BIN3 = bin_episode(3)  # far / left
BIN0 = bin_episode(0)  # near / right


def test_transport_direction_comes_from_ground_truth():
    exp = expectation_for(BIN3)
    place = next(m for m in exp.motions if m.name == "place")
    # the synthetic episode's camera is unknown: plain left/right are the robot's (= robot_left/robot_right)
    assert place.expected == ("forward", "left", "robot_left")
    assert place.opposite == ("backward", "right", "robot_right")
    assert "ground truth" in place.source
    exp0 = expectation_for(BIN0)
    assert next(m for m in exp0.motions if m.name == "place").expected == ("backward", "left", "robot_left")
    wrong = score_caption("Pick the cereal up and carry it to the right.", BIN3)
    assert wrong.trajectory.wrong


def test_a_pick_place_episode_needs_a_target_bin():
    with pytest.raises(ScoringError, match="target_bin"):
        score_caption("anything", make_episode("pick_place", ["a"]))


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
