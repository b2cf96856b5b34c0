"""Caption rubric: lexicon matching, negation, wrong objects / directions / bins, spans, word counts."""

from __future__ import annotations

import pytest

from scoring_helpers import bin_episode, door_episode, make_episode
from vlmproprio.scoring import (
    CORRECT,
    IGNORED,
    MENTIONED,
    ScoringError,
    expectation_for,
    load_lexicon,
    score_caption,
)

DOOR = door_episode()
BIN3 = bin_episode(3)  # far / left
BIN0 = bin_episode(0)  # near / right

# (caption, episode, expected (mentioned, correct, wrong) per item: object, action, trajectory)
CASES = [
    pytest.param(
        "Grasp the door handle, turn it downward and then pull the door open toward the robot.",
        DOOR,
        {"object": (1, 1, 0), "action": (1, 1, 0), "trajectory": (1, 1, 0)},
        id="door-full-correct",
    ),
    pytest.param(
        "The robot opens the door.",
        DOOR,
        {"object": (1, 1, 0), "action": (1, 1, 0), "trajectory": (0, 0, 0)},
        id="door-no-trajectory",
    ),
    pytest.param(
        "The robot does not open the door.",
        DOOR,
        {"object": (1, 1, 0), "action": (1, 0, 1), "trajectory": (0, 0, 0)},
        id="door-negated-open-is-wrong",
    ),
    pytest.param(
        "The robot doesn't open the door.",
        DOOR,
        {"object": (1, 1, 0), "action": (1, 0, 1), "trajectory": (0, 0, 0)},
        id="door-negated-contraction",
    ),
    pytest.param(
        "The robot opens the door without closing the gripper.",
        DOOR,
        {"object": (1, 1, 0), "action": (1, 1, 0), "trajectory": (0, 0, 0)},
        id="door-without-closing-gripper-neutral",
    ),
    pytest.param(
        "Pull the door open without closing it.",
        DOOR,
        {"object": (1, 1, 0), "action": (1, 1, 0), "trajectory": (0, 0, 0)},
        id="door-negated-wrong-action-ignored",
    ),
    pytest.param(
        "The robot opens its gripper and closes the door.",
        DOOR,
        {"object": (1, 1, 0), "action": (1, 0, 1), "trajectory": (0, 0, 0)},
        id="door-close-is-wrong-open-gripper-is-not-open",
    ),
    pytest.param(
        "Turn the handle upward and pull the door open.",
        DOOR,
        {"object": (1, 1, 0), "action": (1, 1, 0), "trajectory": (1, 0, 1)},
        id="door-opposite-turn-direction",
    ),
    pytest.param(
        "Push the handle down and push the door forward to open it.",
        DOOR,
        {"object": (1, 1, 0), "action": (1, 0, 1), "trajectory": (1, 1, 0)},
        id="door-push-handle-turns-push-door-is-wrong",
    ),
    pytest.param(
        "Grab the handle and pull the door forward.",
        DOOR,
        {"object": (1, 1, 0), "action": (1, 1, 0), "trajectory": (1, 0, 1)},
        id="door-opposite-pull-direction",
    ),
    pytest.param(
        "Turn the handle down, not up, and pull the door back.",
        DOOR,
        {"object": (1, 1, 0), "action": (1, 1, 0), "trajectory": (1, 1, 0)},
        id="door-negated-opposite-ignored",
    ),
    pytest.param(
        "The robot moves down and then up near the window.",
        DOOR,
        {"object": (1, 0, 1), "action": (0, 0, 0), "trajectory": (1, 0, 0)},
        id="door-wrong-object-unbound-directions",
    ),
    pytest.param(
        "Pick up the cereal box and place it in the far left compartment.",
        BIN3,
        {"object": (1, 1, 0), "action": (1, 1, 0), "trajectory": (1, 1, 0)},
        id="bin-full-correct",
    ),
    pytest.param(
        "Pick up the cereal box and place it in the near-left bin.",
        BIN3,
        {"object": (1, 1, 0), "action": (1, 1, 0), "trajectory": (1, 0, 1)},
        id="bin-wrong-row",
    ),
    pytest.param(
        "Pick up the cereal box and place it in the far right compartment.",
        BIN3,
        {"object": (1, 1, 0), "action": (1, 1, 0), "trajectory": (1, 0, 1)},
        id="bin-wrong-side",
    ),
    pytest.param(
        "Take the cereal from the right bin and put it in the far left corner of the target bin.",
        BIN3,
        {"object": (1, 1, 0), "action": (1, 1, 0), "trajectory": (1, 1, 0)},
        id="bin-source-bin-ignored",
    ),
    pytest.param(
        "Place the cereal box in the left bin.",
        BIN3,
        {"object": (1, 1, 0), "action": (1, 0, 0), "trajectory": (1, 0, 0)},
        id="bin-partial-compartment-and-no-pick",
    ),
    pytest.param(
        "Grasp the cereal, lift it up and drop it into the near right section.",
        BIN0,
        {"object": (1, 1, 0), "action": (1, 1, 0), "trajectory": (1, 1, 0)},
        id="bin0-near-right",
    ),
    pytest.param(
        "Grasp the cereal, lift it down and drop it into the front right bin.",
        BIN0,
        {"object": (1, 1, 0), "action": (1, 1, 0), "trajectory": (1, 0, 1)},
        id="bin-opposite-lift-direction-front-synonym",
    ),
    pytest.param(
        "Pick up the milk carton and put it in the far left bin, not the near one.",
        BIN3,
        {"object": (1, 0, 1), "action": (1, 1, 0), "trajectory": (1, 1, 0)},
        id="bin-wrong-object-negated-wrong-row",
    ),
    pytest.param(
        "The robot does not place the cereal box in the bin.",
        BIN3,
        {"object": (1, 1, 0), "action": (1, 0, 1), "trajectory": (0, 0, 0)},
        id="bin-negated-place",
    ),
    pytest.param(
        "Grab the cereal box and move it to the upper-left corner of the bin.",
        BIN3,
        {"object": (1, 1, 0), "action": (1, 1, 0), "trajectory": (1, 1, 0)},
        id="bin-move-it-upper-left",
    ),
    pytest.param(
        "Lower the box into the bin on the left.",
        BIN3,
        {"object": (1, 1, 0), "action": (1, 0, 0), "trajectory": (1, 0, 0)},
        id="bin-lower-is-a-verb-not-a-row",
    ),
    pytest.param(
        "",
        BIN3,
        {"object": (0, 0, 0), "action": (0, 0, 0), "trajectory": (0, 0, 0)},
        id="empty-caption",
    ),
]


@pytest.mark.parametrize(("text", "episode", "expected"), CASES)
def test_rubric_table(text, episode, expected):
    s = score_caption(text, episode)
    got = {
        item: tuple(int(x) for x in (it.mentioned, it.correct, it.wrong)) for item in expected for it in [s.item(item)]
    }
    assert got == expected, [(h.text, h.kind, h.value, h.verdict, h.note) for h in s.matches]


def test_all_correct_needs_every_item():
    full = score_caption("Grasp the handle, turn it down and pull the door toward itself.", DOOR)
    assert full.all_correct
    assert not score_caption("Grasp the handle and pull the door.", DOOR).all_correct


def test_every_hit_has_an_auditable_span():
    text = "Pick up the cereal box and place it in the far left compartment."
    s = score_caption(text, BIN3)
    assert s.matches
    for h in s.matches:
        assert text[h.start : h.end] == h.text
        assert h.entry.split(":")[0] in ("common.json", "pick_place.json")
    by_text = {h.text: h for h in s.matches}
    assert by_text["far"].kind == "row" and by_text["far"].verdict == CORRECT
    assert by_text["left"].kind == "side" and by_text["left"].entry.endswith("sides.left")
    assert by_text["cereal box"].value == "cereal"


def test_negation_flag_and_verdicts_on_spans():
    s = score_caption("Open the door without closing it, not turning the handle up.", DOOR)
    hits = {h.text: h for h in s.matches}
    assert hits["closing"].negated and hits["closing"].verdict == IGNORED
    # turning is no required step of opening: denying it (here: its direction) does not make the action wrong
    assert hits["turning"].negated and hits["turning"].verdict == MENTIONED
    assert hits["up"].negated and hits["up"].verdict == IGNORED
    assert not hits["Open"].negated and hits["Open"].verdict == CORRECT


def test_word_count_and_hits_per_word():
    s = score_caption("The robot opens the door.", DOOR)
    assert s.words == 5
    assert s.hits == 2  # opens, door
    assert s.hits_per_word == pytest.approx(0.4)
    verbose = score_caption("The robot, which is a robot, is a robot that is near a thing and opens the door.", DOOR)
    assert verbose.hits == 2 and verbose.hits_per_word < s.hits_per_word


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


def test_unknown_object_and_task_raise_clean_errors():
    with pytest.raises(ScoringError, match="not in the object lexicon"):
        score_caption("anything", make_episode("door", ["a"], target_object="spaceship"))
    with pytest.raises(ScoringError, match="no lexicon for task"):
        load_lexicon("juggling")
    with pytest.raises(ScoringError, match="target_bin"):
        score_caption("anything", make_episode("pick_place", ["a"]))


def test_lexicon_versions_are_recorded():
    lex = load_lexicon("door")
    assert lex.version == "common-v2+door-v2"
    assert len(lex.sha256) == 64
