"""The 'no-answers' sanity warning: when most of a model's frame captions are missing because the server's
answers held none (a refusal, a tool call, a content filter, ...; chat.ANSWER_PROBLEMS), the score says so, with
the requests counted per class, and the score meta counts them too. Missing captions from plain answers the
parser could not read are the 'missing-captions' warning's, not this one's."""

from __future__ import annotations

import json
import re
from collections.abc import Sequence
from pathlib import Path

import pytest

from scoring_helpers import score_scripted_run
from vlmproprio.chat import Answer, AnswerMeta, ChatRequest
from vlmproprio.sanity import MIN_NO_ANSWER_SHARE

FIXTURES = Path(__file__).resolve().parents[2] / "fixtures"
EPISODES, CONDITIONS = ("door_00",), ("none", "both")


class Answers:
    """Plain answers, except that every ``flag_every``-th Process 1 request comes back flagged (text empty, the
    class in the metadata as the openai backend records it) or, with ``problem`` empty, simply blank."""

    def __init__(self, problem: str, flag_every: int = 1):
        self.problem, self.flag_every, self.p1 = problem, flag_every, 0

    def __call__(self, requests: Sequence[ChatRequest]) -> list[Answer]:
        out = []
        for r in requests:
            text = r.messages[0].text
            extra: dict = {}
            if "# Process 1" in text:
                n = int(re.search(r"exactly (\d+) lines", text).group(1))
                ans = "\n".join(f"Frame {i}: The arm moves {'up' if i % 2 else 'on'}." for i in range(1, n + 1))
                self.p1 += 1
                if self.p1 % self.flag_every == 0:
                    ans = ""
                    extra = {"answer_problem": self.problem} if self.problem else {}
            elif "# Process 2" in text:
                ans = f"The arm moves, part {r.tag.group}."
            else:
                ans = "Open the door."
            meta = AnswerMeta(backend="scripted", model_id="scripted", extra=extra)
            out.append(Answer(ans, meta, key=f"k{len(out)}"))
        return out


def _score(run: Path, answers: Answers) -> tuple[list[dict], dict]:
    score_scripted_run(run, FIXTURES, EPISODES, CONDITIONS, answers)
    warnings = json.loads((run / "scores" / "verdicts.json").read_text())["warnings"]
    parsing = json.loads((run / "scores" / "meta.json").read_text())["parsing"]["models"]["scripted"]
    return warnings, parsing


@pytest.mark.parametrize("problem", ["refusal", "tool_calls", "content_filter", "length"])
def test_most_captions_lost_to_flagged_answers_is_a_warning(tmp_path, problem):
    warnings, parsing = _score(tmp_path / "run", Answers(problem))
    (w,) = [w for w in warnings if w["kind"] == "no-answers"]
    assert w["value"] == 1.0 and w["answer_problems"] == {problem: parsing["answer_problems"][problem]}
    assert f"requests: {problem} {parsing['answer_problems'][problem]}" in w["message"]
    p1 = (parsing["answers"] - len(CONDITIONS)) // 2  # as many Process 1 as Process 2 requests, one Process 3
    assert parsing["answer_problems"] == {problem: p1}


def test_a_few_flagged_answers_are_counted_but_not_warned(tmp_path):
    warnings, parsing = _score(tmp_path / "run", Answers("refusal", flag_every=4))
    assert parsing["answer_problems"]["refusal"] >= 1
    share = parsing["frames"]["missing"] / parsing["frames"]["captions"]
    assert share < MIN_NO_ANSWER_SHARE and not [w for w in warnings if w["kind"] == "no-answers"]


def test_blank_answers_without_a_reason_are_not_this_warning(tmp_path):
    warnings, parsing = _score(tmp_path / "run", Answers(""))
    kinds = {w["kind"] for w in warnings}
    assert "missing-captions" in kinds and "no-answers" not in kinds and parsing["answer_problems"] == {}
