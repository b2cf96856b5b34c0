"""The fast indented JSON writer gives json.dumps's text to the byte, and leaves what it does not know to it."""

from __future__ import annotations

import json
import math
from enum import IntEnum

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from vlmproprio.evaluation.formats import _json_safe, dumps_json
from vlmproprio.json_text import NotPlain, dumps_indented

scalars = (
    st.none()
    | st.booleans()
    | st.integers(min_value=-(2**70), max_value=2**70)
    | st.floats(allow_nan=True, allow_infinity=True)
    | st.sampled_from([0.0, -0.0, 1e-300, 5e-324, 1e16, 0.1])
    | st.text(max_size=8)  # unicode, quotes, backslashes and control characters included
)
documents = st.recursive(
    scalars,
    lambda inner: (
        st.lists(inner, max_size=5)
        | st.lists(inner, max_size=3).map(tuple)
        | st.dictionaries(st.text(max_size=4), inner, max_size=5)
    ),
    max_leaves=40,
)


def reference(obj, nan_as_null: bool) -> str:
    if nan_as_null:
        return json.dumps(_json_safe(obj), indent=1, ensure_ascii=False, allow_nan=False)
    return json.dumps(obj, indent=1, ensure_ascii=False)


@settings(max_examples=400, deadline=None)
@given(documents)
def test_the_same_text_as_json_dumps(obj):
    assert dumps_indented(obj) == reference(obj, False)
    assert dumps_indented(obj, nan_as_null=True) == reference(obj, True)
    assert dumps_json(obj) == reference(obj, True) + "\n"


@pytest.mark.parametrize(
    "obj",
    [
        {},
        [],
        (),
        {"a": {}, "b": [], "c": [[], {}]},
        {"x": math.nan, "y": [1.0, -math.inf, math.inf], "z": {"n": None, "t": True, "f": False}},
        [{"row": 1, "v": 0.5}, {"row": 2, "v": math.nan}],
        {"é": "ünïcode ☃", "q": 'quo"te\\back\nline\t'},
        [[[1]], [[2.5, "s"]]],
        math.nan,
        "top-level",
        -0.0,
    ],
)
def test_edge_cases(obj):
    assert dumps_indented(obj) == reference(obj, False)
    assert dumps_json(obj) == reference(obj, True) + "\n"


class Level(IntEnum):
    LOW = 1


@pytest.mark.parametrize(
    "obj",
    [{1: "int key"}, {"v": np.float64(math.nan)}, [np.float64(0.5)], {"e": Level.LOW}, {"k": {True: 1}}],
)
def test_what_it_does_not_know_goes_to_json_dumps(obj):
    with pytest.raises(NotPlain):
        dumps_indented(obj)
    assert dumps_json(obj) == reference(obj, True) + "\n"
