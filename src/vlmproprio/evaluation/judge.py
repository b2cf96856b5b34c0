"""An optional judge model's grades of the final captions, and their agreement with the rubric (scores/judge.json)."""

from __future__ import annotations

from vlmproprio.evaluation.cells import FinalCaption


def judge_table(backend, finals: list[FinalCaption]) -> dict:
    """Grade the final captions with a judge (a CachedBackend, or a Backend) and compare with the rubric."""
    from vlmproprio.scoring import judge_agreement, judge_captions

    verdicts = judge_captions(backend, [(text, ep, cond) for _, _, text, ep, cond in finals])
    identity = backend.identity if isinstance(getattr(backend, "identity", None), dict) else backend.identity()
    return {
        "backend": dict(identity),
        "agreement": judge_agreement([s for _, s, _, _, _ in finals], verdicts),
        "verdicts": {key: v.to_dict() for (key, _, _, _, _), v in zip(finals, verdicts, strict=True)},
    }
