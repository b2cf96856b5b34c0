"""A caption's analysis (vlmproprio.scoring.matching) depends on the text and the lexicon only: one analysis,
reused for every episode of the task, scores as the caption scored alone."""

from __future__ import annotations

from pathlib import Path

from vlmproprio.episodes import load_episodes
from vlmproprio.scoring import Expectation, analyse_text, expectation_for, load_lexicon, score_text

FIXTURES = Path(__file__).resolve().parents[2] / "fixtures"


def test_score_text_with_a_shared_analysis_is_score_text():
    lex = load_lexicon("door")
    texts = [
        "The robot grasps the handle, turns it down and pulls the door open.",
        "It does not push the door but fails to open it; then it sets it down.",
        "",
    ]
    exps = [expectation_for(ep, lex) for ep in load_episodes(FIXTURES, ["door_00", "door_01"], verify=False)]
    assert exps and all(isinstance(e, Expectation) for e in exps)
    for text in texts:
        analysis = analyse_text(text, lex)
        for exp in exps:
            assert score_text(text, exp, lex, analysis) == score_text(text, exp, lex)
            assert score_text(text, exp, lex, analysis).to_dict() == score_text(text, exp, lex).to_dict()
