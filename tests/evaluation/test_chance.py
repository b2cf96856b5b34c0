"""The precomputed chance table: it covers every fixture episode with every count of points, holds exactly what
``chance_random`` computes, and is never read for a ground truth, count or setting it was not made for."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from vlmproprio.episodes import load_episodes
from vlmproprio.evaluation.chance import (
    CHANCE_TABLE_FILE,
    ChanceTable,
    build_chance_table,
    chance_settings,
    load_chance_table,
)
from vlmproprio.segmentation import CHANCE_DRAWS, chance_is_exact, chance_random, truth_of

FIXTURES = Path(__file__).resolve().parents[2] / "fixtures"


@pytest.fixture(scope="module")
def truths():
    return {ep.episode_id: truth_of(ep.frame_phases) for ep in load_episodes(FIXTURES, verify=False)}


def test_the_table_matches_this_code_and_covers_every_fixture_episode(truths):
    assert json.loads(CHANCE_TABLE_FILE.read_text())["settings"] == chance_settings()
    table = load_chance_table()
    for truth in truths.values():
        assert all((truth.labels, k) in table for k in range(truth.n_frames)), truth.labels


def test_table_values_are_the_computed_values_to_the_bit(truths):
    table = load_chance_table()
    truth = min(truths.values(), key=lambda t: t.n_frames)
    ks = [0, 1, truth.n_frames // 3, truth.n_frames - 1]  # exact and drawn (10 000 sets) counts
    assert {chance_is_exact(truth.n_frames, k, CHANCE_DRAWS) for k in ks} == {True, False}
    for k in ks:
        assert table[(truth.labels, k)] == chance_random(truth, k), k  # == on floats: the same bits


def test_build_writes_what_load_reads(tmp_path):
    labels = ["a"] * 3 + ["b"] * 4 + ["c"] * 3
    path = tmp_path / "table.json"
    path.write_text(json.dumps(build_chance_table([labels, labels])))
    load_chance_table.cache_clear()
    try:
        table = load_chance_table(path)
    finally:
        load_chance_table.cache_clear()
    assert sorted(table) == [(tuple(labels), k) for k in range(len(labels))]
    assert table[(tuple(labels), 2)] == chance_random(truth_of(labels), 2)


def test_a_table_made_with_other_settings_is_not_read(tmp_path):
    doc = build_chance_table([["a", "a", "b"]])
    doc["settings"][2] += 1  # another seed
    path = tmp_path / "table.json"
    path.write_text(json.dumps(doc))
    assert load_chance_table(path) == {}
    assert load_chance_table(tmp_path / "missing.json") == {}


def test_the_table_first_then_the_disk_cache_then_drawing(tmp_path):
    truth = truth_of(["a"] * 3 + ["b"] * 4 + ["c"] * 3)
    other = truth_of(["x"] * 6 + ["y"] * 6)
    fake = {m: -1.0 for m in chance_random(truth, 2)}  # not what chance_random gives: shows where it came from
    with ChanceTable(tmp_path / "chance", table={(truth.labels, 2): fake}) as chance:
        assert chance.random(truth, 2) == fake
        assert chance.random(truth, 3) == chance_random(truth, 3)  # another count: computed
        assert chance.random(other, 2) == chance_random(other, 2)  # another ground truth: computed
        assert (chance.precomputed, chance.cached, chance.computed) == (1, 0, 2)
    with ChanceTable(tmp_path / "chance", table={}) as chance:
        assert chance.random(truth, 3) == chance_random(truth, 3)
        assert (chance.precomputed, chance.cached, chance.computed) == (0, 1, 0)
