"""The captioning pipeline on the shipped fixtures, with scripted answerers (no model needed)."""

from __future__ import annotations

import math
import re
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import pytest

from vlmproprio.chat import Answer, AnswerMeta, ChatRequest, ImagePart
from vlmproprio.conditions import CONDITIONS, frame_states, get_condition
from vlmproprio.episodes import load_episodes
from vlmproprio.pipeline import PipelineSettings, caption_episodes, groups
from vlmproprio.prompts import PromptOptions
from vlmproprio.prompts.state import parse_state_lines

FIXTURES = Path(__file__).resolve().parents[1] / "fixtures"


@pytest.fixture(scope="module")
def episodes():
    return load_episodes(FIXTURES, ["door_00", "bin2_01"])


@pytest.fixture(scope="module")
def all_episodes():
    return load_episodes(FIXTURES)


class Scripted:
    """Answers every request in the requested format and records what it was asked, in order."""

    def __init__(self, p1=None):
        self.requests: list[ChatRequest] = []
        self.p1 = p1 or (lambda n: "\n".join(f"Frame {i}: caption {i}." for i in range(1, n + 1)))

    def __call__(self, requests: Sequence[ChatRequest]) -> list[Answer]:
        out = []
        for r in requests:
            self.requests.append(r)
            text = r.messages[0].text
            if "# Process 1" in text:
                n = int(re.search(r"exactly (\d+) lines", text).group(1))
                ans = self.p1(n)
            elif "# Process 2" in text:
                ans = f"Scene summary {r.tag.group}."
            else:
                ans = "Final instruction."
            out.append(Answer(ans, AnswerMeta(backend="scripted", model_id="scripted"), key=str(len(self.requests))))
        return out


def test_calls_per_episode_and_stage_order(episodes) -> None:
    ans = Scripted()
    conds = [get_condition("both"), get_condition("none")]
    ts = caption_episodes(episodes, conds, ans, "scripted", progress=False)
    assert len(ts) == 4
    expected = sum((2 * math.ceil(len(e.frames) / 5) + 1) * len(conds) for e in episodes)
    assert len(ans.requests) == expected
    stages = [r.tag.stage for r in ans.requests]
    # every Process 1 request before any Process 2, every Process 2 before any Process 3
    assert stages == sorted(stages, key=["p1", "p2", "p3"].index)
    for t, e in zip(ts, [episodes[0]] * 2 + [episodes[1]] * 2, strict=True):
        assert len(t.frames) == len(e.frames)
        assert all(f.status == "ok" for f in t.frames)
        assert len(t.scenes) == math.ceil(len(e.frames) / 5)
        assert t.final == "Final instruction." and t.final_status == "ok"
        assert [r.stage for r in t.requests].count("p3") == 1


def test_later_processes_see_earlier_answers(episodes) -> None:
    ans = Scripted()
    caption_episodes(episodes[:1], [get_condition("both")], ans, "scripted", progress=False)
    p2 = [r for r in ans.requests if r.tag.stage == "p2"]
    p3 = next(r for r in ans.requests if r.tag.stage == "p3")
    assert "Frame 3: caption 3." in p2[0].messages[0].text
    assert "Scene 2: Scene summary 1." in p3.messages[0].text
    # Process 2 re-introduces its group's images and states, as in the paper
    assert len(p2[0].images) == 5
    assert len(parse_state_lines(p2[0].messages[0].text)) == 5 + 5  # its group's, after the example's five


@pytest.mark.parametrize("name", list(CONDITIONS))
def test_what_each_condition_shows(episodes, name: str) -> None:
    cond = get_condition(name)
    ans = Scripted()
    caption_episodes(episodes[:1], [cond], ans, "scripted", progress=False)
    p1 = ans.requests[0]
    text = p1.messages[0].text
    states = parse_state_lines(text)
    example_states = 5 if cond.numeric_state else 0  # the worked example shows the same kind of state
    assert len(p1.images) == (5 if cond.images else 0)
    assert ("### Joint/Pose ###" in text) == cond.numeric_state
    assert ("4. When creating captions" in text) == cond.has_state
    assert len(states) == (5 + example_states if cond.numeric_state else 0)
    real = states[example_states:]
    assert all((s.joints is not None) == cond.joints and (s.ee is not None) == cond.ee for s in real)
    assert ("the hand moves" in text or "the hand holds still" in text) == cond.words


def test_controls_change_the_numbers_the_right_way(all_episodes) -> None:
    ep = next(e for e in all_episodes if e.episode_id == "bin2_01")
    own = frame_states(ep, get_condition("both"), all_episodes)
    shuffled = frame_states(ep, get_condition("both_shuffled"), all_episodes)
    noisy = frame_states(ep, get_condition("both_noisy"), all_episodes)
    assert shuffled.joints.shape == own.joints.shape
    assert not np.allclose(shuffled.ee, own.ee)
    # borrowed from an episode with another target compartment, played backwards: it ends where that one began
    partners = [e for e in all_episodes if e.task == "pick_place" and e.target_bin.index != 2]
    assert any(np.allclose(shuffled.ee[-1], p.ee_array()[0]) for p in partners)
    diff = noisy.ee - own.ee
    assert 0.005 < np.std(diff[:, :3]) < 0.05  # position noise has sd 0.02 m
    again = frame_states(ep, get_condition("both_noisy"), all_episodes)
    assert np.array_equal(again.ee, noisy.ee)  # seeded by the episode: the same prompt every run


def test_process3_image_cap(episodes) -> None:
    ans = Scripted()
    caption_episodes(
        episodes[:1], [get_condition("ee")], ans, "scripted", PipelineSettings(max_images_p3=4), progress=False
    )
    p3 = next(r for r in ans.requests if r.tag.stage == "p3")
    assert len(p3.images) == 4
    n = len(episodes[0].frames)
    assert len(parse_state_lines(p3.messages[0].text)) == n + 5  # every frame's state (+ the example's)


def test_malformed_answers_leave_every_frame_with_a_status(episodes) -> None:
    ans = Scripted(p1=lambda n: "Frame 1: only the first one." if n > 1 else "nonsense")
    [t] = caption_episodes(episodes[:1], [get_condition("joint")], ans, "scripted", progress=False)
    assert len(t.frames) == len(episodes[0].frames)
    assert {f.status for f in t.frames} <= {"ok", "recovered", "missing"}
    assert sum(f.status == "missing" for f in t.frames) >= len(t.frames) - math.ceil(len(t.frames) / 5)
    # a missing caption reaches Process 2 as a visible placeholder, never as a silently shorter list
    p2 = next(r for r in ans.requests if r.tag.stage == "p2")
    assert "Frame 2: (no caption)" in p2.messages[0].text


def test_groups_and_stride() -> None:
    assert [list(g) for g in groups(12, 5)] == [[0, 1, 2, 3, 4], [5, 6, 7, 8, 9], [10, 11]]
    with pytest.raises(Exception, match="k must be at least 1"):
        PipelineSettings(k=0)


def test_images_are_read_once_and_shared(episodes) -> None:
    ans = Scripted()
    caption_episodes(episodes[:1], [get_condition("none"), get_condition("both")], ans, "scripted", progress=False)
    first = {id(p) for r in ans.requests for p in r.images if p.sha256 == ans.requests[0].images[0].sha256}
    assert len(first) == 1 and isinstance(ans.requests[0].images[0], ImagePart)


def test_reference_reads_only_this_episodes_states(episodes) -> None:
    """The worked example in the preamble has state lines too; the reference captioner must skip them."""
    from vlmproprio.backends.reference import ReferenceBackend

    ref = ReferenceBackend()
    with_example = caption_episodes(episodes[:1], [get_condition("ee")], ref.generate, "reference", progress=False)
    no_example = caption_episodes(
        episodes[:1],
        [get_condition("ee")],
        ref.generate,
        "reference",
        PipelineSettings(prompt=PromptOptions(example=False)),
        progress=False,
    )
    assert with_example[0].frame_texts == no_example[0].frame_texts
    assert [s.text for s in with_example[0].scenes] == [s.text for s in no_example[0].scenes]
    assert with_example[0].final == no_example[0].final


def test_every_episode_is_a_partner_once_and_permuted_states_have_no_timeline(all_episodes) -> None:
    from vlmproprio.conditions import _partner, state_correlations

    for task in ("door", "pick_place"):
        eps = [e for e in all_episodes if e.task == task]
        partners = [_partner(e, all_episodes).episode_id for e in eps]
        assert sorted(partners) == sorted(e.episode_id for e in eps)  # a permutation: each used exactly once
        assert all(p != e.episode_id for p, e in zip(partners, eps, strict=True))
        if task == "pick_place":
            by_id = {e.episode_id: e for e in eps}
            assert all(by_id[p].target_bin.index != e.target_bin.index for p, e in zip(partners, eps, strict=True))
    ep = next(e for e in all_episodes if e.episode_id == "bin2_01")
    shuffled = frame_states(ep, get_condition("both_shuffled"), all_episodes)
    permuted = frame_states(ep, get_condition("both_permuted"), all_episodes)
    # the same numbers as the partner's (resampled) states, in another order, and the same order every run
    assert np.array_equal(np.sort(permuted.ee, axis=0), np.sort(shuffled.ee, axis=0))
    assert not np.array_equal(permuted.ee, shuffled.ee[::-1])
    assert np.array_equal(frame_states(ep, get_condition("both_permuted"), all_episodes).joints, permuted.joints)
    own = state_correlations(ep, get_condition("both"), all_episodes)
    assert all(r is None or r == pytest.approx(1.0) for r in own.values()) and own["z"] == pytest.approx(1.0)
    rs = [
        abs(r)
        for e in all_episodes
        for r in state_correlations(e, get_condition("both_permuted"), all_episodes).values()
        if r is not None
    ]
    assert np.mean(rs) < 0.35  # a random order keeps next to nothing of the timeline
    assert state_correlations(ep, get_condition("none"), all_episodes) == {}


def test_pipeline_settings_round_trip_through_what_a_run_records():
    from vlmproprio import prompts
    from vlmproprio.pipeline import PipelineSettings

    for version in prompts.PROMPT_VERSIONS:
        for example in (True, False):
            s = PipelineSettings(k=4, frame_stride=2, max_images_p3=3, prompt=prompts.PromptOptions(example, version))
            assert PipelineSettings.from_dict(s.to_dict()) == s
