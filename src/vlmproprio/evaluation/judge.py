"""An optional judge model's grades of the final captions, and their agreement with the rubric (scores/judge.json)."""

from __future__ import annotations

from typing import TYPE_CHECKING

from vlmproprio.evaluation.cells import FinalCaption

if TYPE_CHECKING:
    from vlmproprio.answering import Answerer


def judge_table(judge: Answerer, finals: list[FinalCaption]) -> dict:
    """Grade the final captions with a judge (an Answerer: cached and replayable) and compare with the rubric."""
    from vlmproprio.scoring import judge_agreement, judge_captions

    verdicts = judge_captions(judge.answer, [(text, ep, cond) for _, _, text, ep, cond in finals])
    return {
        "backend": dict(judge.identity),
        "agreement": judge_agreement([s for _, s, _, _, _ in finals], verdicts),
        "verdicts": {key: v.to_dict() for (key, _, _, _, _), v in zip(finals, verdicts, strict=True)},
    }
