"""The caption rubric (vlmproprio.scoring.rubric): verdicts per item, negation, wrong objects / directions /
bins, contextual and split verbs, compartments, spans and word counts.

The phrasing tests score captions against shipped fixture episodes (the ``ep`` fixture): each covers a class
of caption (pushing the door, split phrasal verbs, compartments named without the camera's words, the lever
springing back), phrased several ways.
"""

from __future__ import annotations

import pytest

from scoring_helpers import bin_episode, door_episode
from vlmproprio.scoring import CORRECT, IGNORED, MENTIONED, score_caption

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


def test_contextual_split_and_source_verdicts_keep_their_spans(ep):
    text = "The robot shoves the door, sets the lever down, and transfers it from one side next to the source bin."
    for h in score_caption(text, ep("door_00")).matches + score_caption(text, ep("bin0_00")).matches:
        assert text[h.start : h.end] == h.text and h.entry and h.verdict
