"""A scored model result crosses between pytest-xdist workers as JSON (vlmproprio.bench.ModelResult)."""

from __future__ import annotations

import math
from pathlib import Path

from vlmproprio.bench import ModelResult, run_and_score
from vlmproprio.models import resolve_model

REPO = Path(__file__).resolve().parents[1]


def _same(a, b) -> bool:
    """Equal values of equal types, NaN equal to NaN (a round trip must not turn a tuple into a list, an int
    into a float or drop a NaN)."""
    if type(a) is not type(b):
        return False
    if isinstance(a, float):
        return a == b or (math.isnan(a) and math.isnan(b))
    if isinstance(a, dict):
        return a.keys() == b.keys() and all(_same(a[k], b[k]) for k in a)
    if isinstance(a, (list, tuple)):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b, strict=True))
    return a == b


def test_a_scored_result_comes_back_from_json_unchanged(tmp_path: Path, vlmproprio_home) -> None:
    model = resolve_model("reference")
    result = run_and_score(model, REPO / "fixtures", "replay", ["door_00", "bin1_00"], ["none", "both"], tmp_path)
    assert result.rows and result.sweep and result.paired
    back = ModelResult.from_json(result.to_json())
    assert back.model == result.model and back.run_dir == result.run_dir
    for field in ("rows", "sweep", "paired", "episodes", "conditions"):
        assert _same(getattr(back, field), getattr(result, field)), field
    assert back.to_json() == result.to_json()
