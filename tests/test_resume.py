"""Resume: a run interrupted part-way and started again asks the model only for what it had not answered."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import pytest

from vlmproprio.answering import Answerer
from vlmproprio.backends.base import Backend
from vlmproprio.backends.reference import ReferenceBackend
from vlmproprio.cache import ResponseCache
from vlmproprio.chat import Answer, ChatRequest
from vlmproprio.conditions import parse_conditions
from vlmproprio.episodes import load_episodes
from vlmproprio.pipeline import caption_episodes

FIXTURES = Path(__file__).resolve().parents[1] / "fixtures"


class Interrupted(Exception):
    pass


class Counting(Backend):
    """The reference captioner, counting every request it answers; optionally stops after ``stop_after``."""

    max_batch_size = 4

    def __init__(self, stop_after: int | None = None):
        self.inner = ReferenceBackend()
        self.asked: list[str] = []
        self.stop_after = stop_after

    def identity(self) -> dict[str, str]:
        return self.inner.identity()

    def generate(self, requests: Sequence[ChatRequest]) -> list[Answer]:
        if self.stop_after is not None and len(self.asked) + len(requests) > self.stop_after:
            raise Interrupted(f"stopped after {len(self.asked)} answers")
        self.asked += [str(r.tag) for r in requests]
        return self.inner.generate(requests)


@pytest.mark.parametrize("stop_after", [0, 7, 33, 60])
def test_resume_asks_only_for_what_is_missing(tmp_path: Path, stop_after: int) -> None:
    episodes = load_episodes(FIXTURES, ["door_01", "bin1_00"])
    conds = parse_conditions("none,both,primitives")

    def run(backend: Backend, cache_dir: Path):
        with ResponseCache(cache_dir) as cache:
            cached = Answerer(backend, mode="live", cache=cache, model="reference")
            return caption_episodes(episodes, conds, cached.answer, "reference", progress=False)

    straight = Counting()
    expected = run(straight, tmp_path / "straight")

    first = Counting(stop_after=stop_after)
    with pytest.raises(Interrupted):
        run(first, tmp_path / "resumed")
    second = Counting()
    resumed = run(second, tmp_path / "resumed")

    assert len(first.asked) <= stop_after and (stop_after < 4 or first.asked)
    assert not set(first.asked) & set(second.asked)  # nothing asked twice
    assert len(first.asked) + len(second.asked) == len(straight.asked)

    def captions(ts):  # what the model said; request records and timings differ by design (cache hits)
        return [t.to_dict() | {"requests": None, "timing": None} for t in ts]

    assert captions(resumed) == captions(expected)
