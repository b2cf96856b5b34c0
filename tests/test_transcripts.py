"""A transcript's file: the dict and the bytes of its canonical JSON, and back."""

from __future__ import annotations

import dataclasses
import json

import pytest

from vlmproprio.io import WriteError
from vlmproprio.transcripts import (
    FrameCaption,
    RequestRecord,
    SceneCaption,
    Transcript,
    read_transcript,
    transcript_path,
    write_transcript,
    write_transcripts,
)


def _transcript(episode: str, condition: str = "none") -> Transcript:
    return Transcript(
        model="m",
        episode_id=episode,
        task="door",
        condition=condition,
        prompt_version="v1",
        frames=[FrameCaption(0, 0, 'reach \u00e9 "x"', "ok"), FrameCaption(1, 20, "", "missing")],
        scenes=[SceneCaption(0, (0, 1), "scene", "recovered")],
        final="open the door",
        final_status="ok",
        requests=[RequestRecord("p1", 0, "ab" * 32, False, 0.125), RequestRecord("p3", -1, "cd" * 32, True, 0.0)],
        timing={"p1_s": 0.125, "p2_s": 0.0, "p3_s": 0.0},
    )


# fields written only when not empty (a clean caption, a backend that reports no finish reason or model)
AUDIT_FIELDS = {
    "span",
    "removed",
    "reasoning",
    "final_span",
    "final_removed",
    "finish_reason",
    "response_model",
    "problem",
}


def _without_empty_audit(d):
    """asdict's output less the audit fields left empty (what to_dict leaves out)."""
    if isinstance(d, dict):
        return {k: _without_empty_audit(v) for k, v in d.items() if not (k in AUDIT_FIELDS and not v)}
    if isinstance(d, list):
        return [_without_empty_audit(v) for v in d]
    return d


def test_to_dict_is_asdict_without_the_empty_audit_fields():
    t = _transcript("door_00")
    d = t.to_dict()
    expected = _without_empty_audit(dataclasses.asdict(t))
    assert d == expected
    assert list(d) == list(expected)
    assert json.dumps(d, indent=1) == json.dumps(expected, indent=1)
    d["timing"]["p1_s"] = 9.0  # a copy, as asdict's
    assert t.timing["p1_s"] == 0.125


def test_a_clean_transcript_has_only_the_keys_it_always_had():
    d = _transcript("door_00").to_dict()
    assert list(d) == [
        *("model", "episode_id", "task", "condition", "prompt_version", "frames", "scenes", "final"),
        *("final_status", "requests", "timing", "version"),
    ]
    assert all(list(f) == ["frame_index", "step", "text", "status"] for f in d["frames"])
    assert all(list(r) == ["stage", "group", "key", "from_cache", "latency_s"] for r in d["requests"])


def test_the_audit_of_a_recovered_caption_and_the_reasoning_round_trip(tmp_path):
    t = dataclasses.replace(
        _transcript("door_00"),
        frames=[FrameCaption(0, 0, "reach", "recovered", "1. **Image 1**: reach", ("label", "emphasis"))],
        scenes=[SceneCaption(0, (0,), "scene", "recovered", '"scene"', ("quotes",))],
        final_span="Here is the instruction: open the door",
        final_removed=("preamble",),
        requests=[RequestRecord("p1", 0, "ab" * 32, False, 0.1, reasoning="the handle is on the left")],
    )
    d = t.to_dict()
    assert d["frames"][0]["removed"] == ["label", "emphasis"] and d["frames"][0]["span"].startswith("1.")
    assert d["final_removed"] == ["preamble"] and d["requests"][0]["reasoning"] == "the handle is on the left"
    write_transcript(tmp_path, t)
    assert read_transcript(transcript_path(tmp_path, t.model, t.episode_id, t.condition)) == t


def test_write_transcripts_writes_what_write_transcript_writes(tmp_path):
    ts = [_transcript(f"door_{i:02d}", c) for i in range(5) for c in ("none", "images")]
    one, many = tmp_path / "one", tmp_path / "many"
    for t in ts:
        write_transcript(one, t)
    paths = write_transcripts(many, ts)
    assert paths == [transcript_path(many, t.model, t.episode_id, t.condition) for t in ts]
    for t, p in zip(ts, paths, strict=True):
        assert p.read_bytes() == transcript_path(one, t.model, t.episode_id, t.condition).read_bytes()
        assert read_transcript(p) == t
    assert not [p for p in many.rglob("*") if p.name.startswith(".")]  # no temp file left


def test_write_transcripts_raises_the_first_failure(tmp_path):
    ts = [_transcript(f"door_{i:02d}") for i in range(4)]
    (tmp_path / "transcripts" / "m" / "door_01__none.json").mkdir(
        parents=True
    )  # a folder in the way of the second file
    with pytest.raises(WriteError, match=r"door_01__none\.json"):
        write_transcripts(tmp_path, ts)
    assert not [p for p in tmp_path.rglob(".*") if p.is_file()]
