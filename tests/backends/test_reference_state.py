"""The state-aware reference captioner (`reference-state`): a positive control whose effect is known.

Checked on the shipped fixtures through the real pipeline and the real rubric: with the episode's own state
the final instruction gets the trajectory right, without state it cannot, and with another episode's
reversed states it names that episode's compartment (wrong by construction).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from vlmproprio.backends.reference import reference_answer
from vlmproprio.backends.reference_state import (
    DOOR,
    PICK_PLACE,
    SCENES,
    ReferenceStateBackend,
    compartment,
    panda_hand_position,
    scene_of_image,
    state_answer,
)
from vlmproprio.backends.registry import create_backend, model_availability
from vlmproprio.chat import ImagePart, RequestTag
from vlmproprio.conditions import get_condition
from vlmproprio.episodes import load_episodes
from vlmproprio.models import REGISTRY
from vlmproprio.pipeline import caption_episodes
from vlmproprio.prompts.state import format_state_line
from vlmproprio.scoring import score_caption

FIXTURES = Path(__file__).resolve().parents[2] / "fixtures"


@pytest.fixture(scope="module")
def episodes():
    return load_episodes(FIXTURES)


@pytest.fixture(scope="module")
def transcripts(episodes):
    conds = [get_condition(c) for c in ("none", "ee", "joint", "both", "both_shuffled", "state_only")]
    backend = ReferenceStateBackend()
    out = caption_episodes(episodes, conds, backend.generate, "reference-state", progress=False)
    return {(t.episode_id, t.condition): t for t in out}


def test_registry_labels_it_as_a_rule_set_available_everywhere():
    spec = REGISTRY["reference-state"]
    assert spec.kind == "reference" and "NOT a VLM" in spec.weights and "NOT a VLM" in spec.description
    for mode in ("live", "record", "replay"):
        backend = create_backend("reference-state", mode)
        assert isinstance(backend, ReferenceStateBackend) and not backend.calls_model
        assert model_availability("reference-state", mode).available
    ident = ReferenceStateBackend().identity()
    assert ident["model_id"] != create_backend("reference").identity()["model_id"]  # separate cache entries


def test_scene_from_the_picture_separates_the_two_shipped_scenes(episodes):
    for ep in episodes:
        seen = {scene_of_image(ImagePart(f.image_bytes())) for f in ep.frames}
        assert seen == {DOOR if ep.task == "door" else PICK_PLACE}, ep.episode_id
    assert scene_of_image(ImagePart(b"not a png")) is None


def test_forward_kinematics_matches_the_recorded_hand_position(episodes):
    for ep in (e for e in episodes if e.episode_id in ("door_00", "door_07", "bin0_00", "bin3_02")):
        base = SCENES[DOOR if ep.task == "door" else PICK_PLACE].base_xyz
        err = max(np.abs(np.subtract(panda_hand_position(f.joints, base), f.ee[:3])).max() for f in ep.frames)
        assert err < 1e-3, (ep.episode_id, err)


def test_layout_puts_every_release_in_its_episodes_compartment(episodes):
    """The documented layout constants agree with where the recorded hand lets go (gripper opening)."""
    for ep in (e for e in episodes if e.task == "pick_place"):
        grip = np.array([f.joints[7] for f in ep.frames])
        closed = next(i for i in range(1, len(grip)) if grip[i] - grip[i - 1] <= -0.01)  # the grasp
        opening = next(i for i in range(closed + 1, len(grip)) if grip[i] - grip[i - 1] >= 0.01)  # the release
        row, side = compartment(ep.frames[opening - 1].ee, SCENES[PICK_PLACE])
        assert (row, side) == (ep.target_bin.row, ep.target_bin.side), ep.episode_id


def _final_correct(transcripts, episodes, condition: str) -> list[bool]:
    return [score_caption(transcripts[(ep.episode_id, condition)].final, ep).trajectory.correct for ep in episodes]


def test_known_effect_on_trajectory_correctness(transcripts, episodes):
    for cond in ("ee", "joint", "both"):
        assert all(_final_correct(transcripts, episodes, cond)), cond
    assert not any(_final_correct(transcripts, episodes, "none"))
    assert not any(_final_correct(transcripts, episodes, "both_shuffled"))
    for ep in episodes:  # object and action need no state: any caption of the scene says them
        s = score_caption(transcripts[(ep.episode_id, "none")].final, ep)
        assert s.object.correct and s.action.correct and not s.trajectory.mentioned, ep.episode_id


def test_shuffled_states_name_the_partner_compartment(transcripts, episodes):
    for ep in (e for e in episodes if e.task == "pick_place"):
        final = transcripts[(ep.episode_id, "both_shuffled")].final
        own = f"{ep.target_bin.row}-{ep.target_bin.side} compartment"
        assert "compartment" in final and own not in final, (ep.episode_id, final)
        assert score_caption(final, ep).trajectory.wrong


def test_frame_captions_change_with_the_gripper_and_stay_constant_without_state(transcripts, episodes):
    for ep in episodes:
        none = {f.text for f in transcripts[(ep.episode_id, "none")].frames}
        assert len(none) == 1, ep.episode_id  # nothing to segment on
        both = [f.text for f in transcripts[(ep.episode_id, "both")].frames]
        assert len(set(both)) >= 4, ep.episode_id
        grip = [f.joints[7] for f in ep.frames]
        closing = [i for i in range(len(grip) - 1) if grip[i + 1] - grip[i] <= -0.01 and i > 0]
        # where the gripper closes on the object the caption changes (a segmentation point can fall there)
        assert closing and all(len({both[i - 1], both[i], both[i + 1]}) > 1 for i in closing), ep.episode_id


def test_without_images_it_answers_as_the_plain_reference(transcripts, episodes, request_factory):
    ep = episodes[0]
    text = "# Process 1\n" + "\n".join(format_state_line(i + 1, f.joints, f.ee) for i, f in enumerate(ep.frames[:5]))
    req = request_factory(text, ())
    assert state_answer(req) == reference_answer(req)


def test_reads_the_numbers_not_the_tag_or_the_pictures(episodes, request_factory):
    """Same pictures, another episode's states: the other compartment. Another tag: the same answer."""
    bins = {e.episode_id: e for e in episodes if e.task == "pick_place"}
    own, other = bins["bin0_00"], bins["bin3_00"]

    def p3(states_of, tag):
        lines = [format_state_line(i + 1, f.joints, f.ee) for i, f in enumerate(states_of.frames)]
        body = "# Process 3\n" + "\n".join(lines)
        return request_factory(body, (own.frames[0].image_bytes(),), tag=tag)

    a = state_answer(p3(own, RequestTag("bin0_00", "both", "p3")))
    assert a == state_answer(p3(own, RequestTag("bin3_00", "none", "p3")))
    assert "near-right compartment" in a
    assert "far-left compartment" in state_answer(p3(other, RequestTag("bin0_00", "both", "p3")))
