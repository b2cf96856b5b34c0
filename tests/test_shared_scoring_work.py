"""Work shared between cells (issue 17) gives the numbers computed alone: a caption's analysis reused for another
episode of the task, and a sweep scoring each distinct boundary set once."""

from __future__ import annotations

import numpy as np

from vlmproprio.scoring import analyse_text, load_lexicon, score_text
from vlmproprio.segmentation import THRESHOLDS, score_masks, sweep, truth_of


def test_score_text_with_a_shared_analysis_is_score_text():
    from vlmproprio.scoring import Expectation

    lex = load_lexicon("door")
    texts = [
        "The robot grasps the handle, turns it down and pulls the door open.",
        "It does not push the door but fails to open it; then it sets it down.",
        "",
    ]
    exps = _expectations(lex)
    assert exps and all(isinstance(e, Expectation) for e in exps)
    for text in texts:
        analysis = analyse_text(text, lex)
        for exp in exps:
            assert score_text(text, exp, lex, analysis) == score_text(text, exp, lex)
            assert score_text(text, exp, lex, analysis).to_dict() == score_text(text, exp, lex).to_dict()


def _expectations(lex):
    from pathlib import Path

    from vlmproprio.episodes import load_episodes
    from vlmproprio.scoring import expectation_for

    fixtures = Path(__file__).resolve().parents[1] / "fixtures"
    return [expectation_for(ep, lex) for ep in load_episodes(fixtures, ["door_00", "door_01"], verify=False)]


def test_sweep_scores_equal_per_row_scores():
    rng = np.random.default_rng(7)
    labels = ["a"] * 6 + ["b"] * 9 + ["c"] * 5 + ["a"] * 4  # a phase that comes back: the general algorithm too
    for trial in range(20):
        trace = np.round(rng.uniform(0.2, 1.0, len(labels) - 1), 1)
        if trial % 3 == 0:
            trace[rng.integers(0, len(trace), 3)] = np.nan
        points = sweep(trace, labels, THRESHOLDS)
        truth = truth_of(labels)
        masks = np.stack([trace < thr for thr in THRESHOLDS])
        whole = score_masks(masks, truth)
        for i, sp in enumerate(points):
            alone = score_masks(masks[i : i + 1], truth)
            assert sp.points == int(whole["points"][i]) == int(alone["points"][0])
            for tol, prf in sp.prf.items():
                assert prf.f1 == float(whole[f"f1_tol{tol}"][i]) == float(alone[f"f1_tol{tol}"][0])
            assert sp.edit == float(whole["edit"][i])
            assert sp.segmental["frame_acc"] == float(whole["frame_acc"][i])
            assert sp.segmental["f1_at_50"] == float(whole["f1_at_50"][i])
