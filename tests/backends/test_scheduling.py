"""The batching scheduler on made-up shapes (pure Python, no model)."""

from __future__ import annotations

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from vlmproprio.backends.base import Backend
from vlmproprio.backends.scheduling import (
    RequestShape,
    contiguous_batches,
    padding_stats,
    plan_batches,
    round_up,
    rows_allowed,
)
from vlmproprio.pipeline import answer_chunk

GREEDY = '{"max_new_tokens": 64}'


def wave_like(n_cells: int = 12) -> list[RequestShape]:
    """Shapes in the pipeline's order (episode, condition, group) with the spread of a Process 1 wave:
    5 images and a last group of 1-4, a condition without images, and state text of several lengths."""
    out = []
    for cell in range(n_cells):
        text = (120, 260, 420, 560)[cell % 4]
        images = 0 if cell % 4 == 3 else 5
        for group in range(3):
            n = images if group < 2 else min(images, 1 + cell % 4)
            out.append(RequestShape(GREEDY, text + 83 * n, n))
    return out


def test_every_request_once_and_batches_full_but_the_last():
    shapes = wave_like()
    batches = plan_batches(shapes, 8)
    flat = [i for b in batches for i in b]
    assert sorted(flat) == list(range(len(shapes)))
    assert [len(b) for b in batches] == [8, 8, 8, 8, 4]
    assert all(b.padded_tokens == max(shapes[i].prompt_tokens for i in b) for b in batches)


def test_longest_first_and_alike_shapes_together():
    shapes = wave_like()
    batches = plan_batches(shapes, 8)
    lengths = [shapes[i].prompt_tokens for b in batches for i in b]
    assert lengths == sorted(lengths, reverse=True)
    # the arrival order mixes 5-image and image-less prompts in every batch; the plan does not
    before, after = padding_stats(shapes, contiguous_batches(len(shapes), 8)), padding_stats(shapes, batches)
    assert before.prompt_tokens == after.prompt_tokens
    assert after.padded_tokens < before.padded_tokens
    assert after.waste < 0.5 * before.waste
    image_counts = [{shapes[i].images for i in b} for b in batches]
    assert image_counts[0] == {5}  # the longest prompts: 5 frames and the longest state text


def test_different_decoding_settings_never_share_a_batch():
    other = '{"max_new_tokens": 8}'
    shapes = [RequestShape(GREEDY if i % 3 else other, 100 + i, 1) for i in range(10)]
    batches = plan_batches(shapes, 4)
    assert all(len({shapes[i].setting for i in b}) == 1 for b in batches)
    assert sorted(i for b in batches for i in b) == list(range(10))
    # 4 requests of the other setting (seen first), then 6 greedy ones in 4 + 2
    assert [(shapes[b.indices[0]].setting, len(b)) for b in batches] == [(other, 4), (GREEDY, 4), (GREEDY, 2)]


def test_ties_keep_request_order_so_a_plan_is_reproducible():
    shapes = [RequestShape(GREEDY, 100, 1)] * 5 + [RequestShape(GREEDY, 200, 2)] * 3
    batches = plan_batches(shapes, 4)
    assert [b.indices for b in batches] == [(5, 6, 7, 0), (1, 2, 3, 4)]
    assert plan_batches(shapes, 4) == batches


def test_a_token_budget_gives_long_prompts_smaller_batches():
    long = [RequestShape(GREEDY, 9000, 30)] * 3  # Process 3 sized
    short = [RequestShape(GREEDY, 2000, 5)] * 10
    batches = plan_batches(short + long, 8, max_batch_tokens=16384)
    assert [(len(b), b.padded_tokens) for b in batches] == [(1, 9000), (1, 9000), (1, 9000), (8, 2000), (2, 2000)]
    assert all(len(b) * b.padded_tokens <= 16384 for b in batches)
    huge = plan_batches([RequestShape(GREEDY, 50_000, 1)] * 2, 8, max_batch_tokens=16384)
    assert [len(b) for b in huge] == [1, 1]  # longer than the cap: alone, never dropped
    assert [len(b) for b in plan_batches(short + long, 8)] == [8, 5]  # no cap: rows only


@settings(max_examples=200, deadline=None)
@given(
    st.lists(st.tuples(st.sampled_from(["a", "b"]), st.integers(1, 3000), st.integers(0, 6)), min_size=0, max_size=60),
    st.integers(1, 16),
    st.one_of(st.none(), st.integers(1, 20000)),
)
def test_plan_is_a_partition_into_sorted_runs(raw, size, budget):
    shapes = [RequestShape(s, n, k) for s, n, k in raw]
    batches = plan_batches(shapes, size, budget)
    assert sorted(i for b in batches for i in b) == list(range(len(shapes)))
    assert all(1 <= len(b) <= size for b in batches)
    assert all(b.padded_tokens == max(shapes[i].prompt_tokens for i in b) for b in batches)
    if budget is not None:
        assert all(len(b) == 1 or len(b) * b.padded_tokens <= budget for b in batches)
    per_setting: dict[str, list] = {}
    for b in batches:
        per_setting.setdefault(shapes[b.indices[0]].setting, []).append(b)
    for runs in per_setting.values():
        # every batch as full as its rows and budget allow; only the last batch of a setting may be short
        assert all(len(b) == rows_allowed(b.padded_tokens, size, budget) for b in runs[:-1])
        lengths = [shapes[i].prompt_tokens for b in runs for i in b]
        assert lengths == sorted(lengths, reverse=True)


def test_the_default_backend_plan_is_arrival_order():
    class Plain(Backend):
        max_batch_size = 3

        def identity(self):
            return {"backend": "plain"}

        def generate(self, requests):
            return []

    assert Plain().plan_batches(list(range(7))) == [(0, 1, 2), (3, 4, 5), (6,)]
    assert Plain().plan_batches([]) == []


def test_small_helpers():
    assert [round_up(n, 256) for n in (1, 256, 257, 700)] == [256, 256, 512, 768]
    assert contiguous_batches(5, 2) == [(0, 1), (2, 3), (4,)]
    assert padding_stats([], []).waste == 0.0
    assert (answer_chunk(1), answer_chunk(8), answer_chunk(32), answer_chunk(64)) == (64, 64, 256, 512)
    bad_calls = (
        lambda: plan_batches([], 0),
        lambda: plan_batches([], 4, max_batch_tokens=0),
        lambda: round_up(3, 0),
        lambda: contiguous_batches(3, 0),
    )
    for bad in bad_calls:
        with pytest.raises(ValueError):
            bad()
