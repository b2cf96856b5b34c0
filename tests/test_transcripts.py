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


def test_to_dict_is_asdict():
    t = _transcript("door_00")
    d = t.to_dict()
    assert d == dataclasses.asdict(t)
    assert list(d) == list(dataclasses.asdict(t))
    assert json.dumps(d, indent=1) == json.dumps(dataclasses.asdict(t), indent=1)
    d["timing"]["p1_s"] = 9.0  # a copy, as asdict's
    assert t.timing["p1_s"] == 0.125


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
