"""No word of a reasoning block reaches a score: the same answers with and without a <think> block full of
rubric words give the same captions, word counts, rubric verdicts, traces and statistics; and so do the same
answers with that text in the server's reasoning field (``Answer.reasoning``: vLLM's and SGLang's
``reasoning`` / ``reasoning_content``) instead."""

from __future__ import annotations

import json
import re
from collections.abc import Sequence
from pathlib import Path

import pytest

from scoring_helpers import score_scripted_run
from vlmproprio.chat import Answer, AnswerMeta, ChatRequest

FIXTURES = Path(__file__).resolve().parents[2] / "fixtures"
EPISODES, CONDITIONS = ("door_00", "bin1_00"), ("none", "both")
# words the door and pick-and-place rubrics and the segmentation would read, if they reached them
DRAFT = (
    "<think>Frame 1: The robot grasps the handle and opens the door to the left. Frame 2: it picks the cube "
    "and places it in the third bin, moving right and down. Open the door, pull the handle.</think>\n"
)

# the same draft as a server's reasoning field carries it: no markers, and frame lines the parser would read
FIELD_DRAFT = DRAFT.strip().removeprefix("<think>").removesuffix("</think>").strip()


class Answers:
    """The answers of a plain captioner, optionally each behind a reasoning block."""

    def __init__(self, think: bool, field: bool = False):
        self.think, self.field = think, field

    def __call__(self, requests: Sequence[ChatRequest]) -> list[Answer]:
        out = []
        for r in requests:
            text = r.messages[0].text
            if "# Process 1" in text:
                n = int(re.search(r"exactly (\d+) lines", text).group(1))
                ans = "\n".join(
                    f"Frame {i}: The arm moves a little {'up' if i % 2 else 'on'}." for i in range(1, n + 1)
                )
            elif "# Process 2" in text:
                ans = f"The arm moves, part {r.tag.group}."
            else:
                ans = "Move the arm."
            ans = DRAFT + ans if self.think else ans
            reasoning = FIELD_DRAFT if self.field else ""
            meta = AnswerMeta(backend="scripted", model_id="scripted")
            out.append(Answer(ans, meta, key=f"k{len(out)}", reasoning=reasoning))
        return out


def _scored(base: Path, think: bool, field: bool = False) -> Path:
    run = base / ("field" if field else "think" if think else "plain")
    score_scripted_run(run, FIXTURES, EPISODES, CONDITIONS, Answers(think, field))
    return run


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> tuple[Path, Path]:
    base = tmp_path_factory.mktemp("reasoning")
    return _scored(base, False), _scored(base, True)


@pytest.fixture(scope="module")
def field_run(runs, tmp_path_factory) -> Path:
    return _scored(tmp_path_factory.mktemp("reasoning-field"), False, field=True)


def _scores(d):
    """A score file less the parse statuses: a caption behind a reasoning block is 'recovered', not 'ok'."""
    if isinstance(d, dict):
        return {k: _scores(v) for k, v in d.items() if k not in ("status", "frame_status") and "recovered" not in k}
    if isinstance(d, list):
        return [_scores(v) for v in d]
    return d


@pytest.mark.parametrize("name", ["rows", "aggregate", "sweep", "paired", "audit", "traces"])
def test_a_reasoning_block_changes_no_score(runs, name: str) -> None:
    plain, think = runs
    a = json.loads((plain / "scores" / f"{name}.json").read_text())
    b = json.loads((think / "scores" / f"{name}.json").read_text())
    assert _scores(a) == _scores(b)
    if name == "rows":
        assert {r["frames_recovered"] for r in b} == {r["n_frames"] for r in b} and {
            r["frames_recovered"] for r in a
        } == {0}


def test_the_reasoning_is_kept_apart_and_counted(runs) -> None:
    plain, think = runs
    t = json.loads(next((think / "transcripts" / "scripted").glob("*.json")).read_text())
    assert all(r["reasoning"].startswith("Frame 1: The robot grasps the handle") for r in t["requests"])
    assert all("handle" not in f["text"] and f["removed"] == ["reasoning"] for f in t["frames"])
    clean = json.loads(next((plain / "transcripts" / "scripted").glob("*.json")).read_text())
    assert all("reasoning" not in r for r in clean["requests"]) and all("removed" not in f for f in clean["frames"])
    parsing = json.loads((think / "scores" / "meta.json").read_text())["parsing"]["models"]["scripted"]
    assert parsing["answers_with_reasoning"] == parsing["answers"] > 0
    draft = DRAFT.strip().removeprefix("<think>").removesuffix("</think>").strip()
    assert parsing["reasoning_chars"] == parsing["answers"] * len(draft)
    reasoning = parsing["recoveries"]["reasoning"]
    assert reasoning["frames"] == parsing["frames"]["captions"] and reasoning["final"] == 4
    assert list(parsing["recoveries"]) == ["reasoning"] and parsing["frames"]["heavy"] == 0
    plain_parsing = json.loads((plain / "scores" / "meta.json").read_text())["parsing"]["models"]["scripted"]
    assert plain_parsing["answers_with_reasoning"] == plain_parsing["reasoning_chars"] == 0
    assert plain_parsing["recoveries"] == {}


@pytest.mark.parametrize("name", ["rows", "aggregate", "sweep", "paired", "audit", "traces"])
def test_the_servers_reasoning_field_changes_no_score(runs, field_run, name: str) -> None:
    plain, _ = runs
    a = json.loads((plain / "scores" / f"{name}.json").read_text())
    b = json.loads((field_run / "scores" / f"{name}.json").read_text())
    assert a == b  # not even a status moves: the field never was part of the answer text


def test_the_servers_reasoning_is_kept_apart_and_counted(field_run) -> None:
    t = json.loads(next((field_run / "transcripts" / "scripted").glob("*.json")).read_text())
    assert all(r["reasoning"] == FIELD_DRAFT for r in t["requests"])
    assert all("handle" not in f["text"] and "removed" not in f for f in t["frames"])
    parsing = json.loads((field_run / "scores" / "meta.json").read_text())["parsing"]["models"]["scripted"]
    assert parsing["answers_with_reasoning"] == parsing["answers"] > 0
    assert parsing["reasoning_chars"] == parsing["answers"] * len(FIELD_DRAFT)
    assert parsing["recoveries"] == {} and parsing["answer_problems"] == {}
