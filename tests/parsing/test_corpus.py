"""The answers corpus (tests/data/answers_corpus.yaml): answers written in the styles current VLMs use for
multi-image and single answers, each with the captions it must give. At least 95 % of frames must parse to
exactly their caption; single answers must all; no reasoning word may reach a caption."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from vlmproprio.parsing import parse_frame_answer, parse_single_answer

CORPUS = yaml.safe_load((Path(__file__).parents[1] / "data" / "answers_corpus.yaml").read_text(encoding="utf-8"))
FRAMES = [e for e in CORPUS if e["kind"] == "frames"]
SINGLES = [e for e in CORPUS if e["kind"] == "single"]
FRAME_SHARE = 0.95


def test_the_corpus_is_large_enough():
    assert len(CORPUS) >= 60 and len(FRAMES) >= 40 and len(SINGLES) >= 15


def test_at_least_95_percent_of_frames_parse_exactly():
    right = total = 0
    wrong = []
    for e in FRAMES:
        got = [p.text for p in parse_frame_answer(e["answer"], e["count"], offset=e["offset"]).captions]
        for g, x in zip(got, e["expected"], strict=True):
            total += 1
            right += g == x
            if g != x:
                wrong.append((e["id"], e["style"], g, x))
    assert right / total >= FRAME_SHARE, wrong


@pytest.mark.parametrize("entry", SINGLES, ids=[e["id"] for e in SINGLES])
def test_single_answers_parse_exactly(entry):
    got = parse_single_answer(entry["answer"])
    assert got.caption.text == entry["expected"]
    assert got.caption.status == ("ok" if entry["style"] == "plain" else "recovered")


@pytest.mark.parametrize("entry", [e for e in CORPUS if e.get("reasoning_words")], ids=lambda e: e["id"])
def test_reasoning_words_never_reach_a_caption(entry):
    if entry["kind"] == "frames":
        parsed = parse_frame_answer(entry["answer"], entry["count"], offset=entry["offset"])
        texts, reasoning = [p.text for p in parsed.captions], parsed.reasoning
    else:
        parsed = parse_single_answer(entry["answer"])
        texts, reasoning = [parsed.caption.text], parsed.reasoning
    for word in entry["reasoning_words"]:
        assert all(word not in t for t in texts)
        assert word in reasoning
