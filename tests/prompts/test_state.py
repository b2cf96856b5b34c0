"""State text and the reference captioner's motions remembered: the same text and motions as computed
afresh, and a value that cannot be written still refused."""

from __future__ import annotations

import math

import numpy as np
import pytest

from vlmproprio.backends import reference as R
from vlmproprio.prompts import state as S


def _fresh_vector(values) -> str:
    return "[" + ", ".join(S.format_number(float(v)) for v in values) + "]"


def test_format_vector_remembered_equals_fresh():
    rng = np.random.default_rng(3)
    rows = [rng.normal(size=8) for _ in range(50)] + [np.array([-0.0, 0.0, -0.0004, 0.0004, 1, 2, 3, 4])]
    for row in rows:
        for values in (row, tuple(row.tolist()), list(row.tolist())):
            assert S.format_vector(values) == _fresh_vector(values)
            assert S.format_vector(values) == _fresh_vector(values)  # from memory


def test_format_vector_still_refuses_non_finite():
    for bad in (math.nan, math.inf):
        for _ in range(2):
            with pytest.raises(ValueError, match="not finite"):
                S.format_vector([0.1, bad])


def test_motion_between_ignores_frame_numbers_and_matches_fresh():
    a = S.ParsedState(1, (0.0,) * 7 + (0.08,), (0.1, 0.0, 1.0, 0.0, 0.0, 0.0))
    b = S.ParsedState(2, (0.0,) * 7 + (0.02,), (0.2, 0.0, 0.9, 0.0, 0.0, 0.5))
    m = R.motion_between(a, b)
    assert m == R.motion_between(S.ParsedState(7, a.joints, a.ee), S.ParsedState(9, b.joints, b.ee))
    R._motion.cache_clear()
    assert R.motion_between(a, b) == m
    assert m.grip == "closes" and m.rotates and m.direction


def test_parsed_state_lines_remembered_equal_fresh_and_are_the_callers_to_change():
    rng = np.random.default_rng(5)
    lines = [S.format_state_line(n, rng.normal(size=8), rng.normal(size=6)) for n in range(1, 6)]
    lines.append(S.format_state_line(6, None, rng.normal(size=6)))
    text = "intro\n" + "\n".join(lines) + "\nFrame 7: no numbers\n"
    first = S.parse_state_lines(text)
    assert first == list(S._parse_state_text.__wrapped__(text)) and [s.number for s in first] == [1, 2, 3, 4, 5, 6]
    first.append("changed by a caller")  # as prompt_states extends the list it gets
    assert S.parse_state_lines(text) == list(S._parse_state_text.__wrapped__(text))
