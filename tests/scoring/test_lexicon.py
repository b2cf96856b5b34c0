"""The scoring lexicons (vlmproprio.scoring.lexicon): merged per task, versioned, and clean errors for what
they do not know."""

from __future__ import annotations

import pytest

from scoring_helpers import make_episode
from vlmproprio.scoring import ScoringError, load_lexicon, score_caption


def test_unknown_object_and_task_raise_clean_errors():
    with pytest.raises(ScoringError, match="not in the object lexicon"):
        score_caption("anything", make_episode("door", ["a"], target_object="spaceship"))
    with pytest.raises(ScoringError, match="no lexicon for task"):
        load_lexicon("juggling")


def test_lexicon_versions_are_recorded():
    lex = load_lexicon("door")
    assert lex.version == "common-v2+door-v2"
    assert len(lex.sha256) == 64
