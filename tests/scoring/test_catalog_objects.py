"""Every object the recorder can put in a scene (record/catalog.json) is scored from data: a caption that names
the episode's own object is right, one that names another object of the same task is wrong. With four objects
in the pick-place episodes, "object correct" is no longer a constant a captioner gets by always saying "cereal"."""

from __future__ import annotations

import dataclasses

import pytest

from scoring_helpers import bin_episode
from vlmproprio.record.catalog import families
from vlmproprio.scoring.rubric import score_caption

CASES = [
    (task, obj.name, other.name)
    for task, fam in families().items()
    for obj in fam.objects
    for other in fam.objects
    if other.name != obj.name
]


def test_the_pick_place_family_has_several_objects():
    assert len(families()["pick_place"].objects) >= 4
    assert len(CASES) >= 12


@pytest.mark.parametrize(("task", "name", "other"), CASES, ids=[f"{t}-{n}-not-{o}" for t, n, o in CASES])
def test_the_episodes_own_object_is_right_and_another_is_wrong(task: str, name: str, other: str):
    ep = dataclasses.replace(bin_episode(3), task=task, target_object=name)
    right = score_caption(f"The robot picks up the {name} and places it in the bin.", ep)
    wrong = score_caption(f"The robot picks up the {other} and places it in the bin.", ep)
    assert right.object.correct and not right.object.wrong
    assert wrong.object.wrong and not wrong.object.correct
