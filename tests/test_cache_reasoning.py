"""The reasoning a server returns beside an answer, in the cache and cassette formats: kept apart from the text,
checksummed with the entry, and written only when there is some, so every cassette and cache entry made before
reads, replays and is rewritten byte for byte as it was."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from vlmproprio.cache import CacheEntry, ResponseCache, checksum, entry_from_record
from vlmproprio.cassettes import CassetteError, read_cassette, write_cassette
from vlmproprio.chat import Answer, AnswerMeta, RequestTag

FIXTURES = Path(__file__).resolve().parents[1] / "fixtures"
COMMITTED = sorted((FIXTURES / "responses").glob("*.jsonl"))


def _answer(text: str = "Frame 1: reach.", reasoning: str = "") -> Answer:
    return Answer(text, AnswerMeta(backend="openai", model_id="m"), reasoning=reasoning)


def _entry(reasoning: str = "", key: str = "a" * 64) -> CacheEntry:
    return CacheEntry.from_answer(key, _answer(reasoning=reasoning), RequestTag("e", "none", "p1", 0), "m", {})


@pytest.mark.parametrize("path", COMMITTED, ids=[p.name for p in COMMITTED])
def test_committed_cassettes_read_and_rewrite_byte_for_byte(path, tmp_path):
    cas = read_cassette(path)
    assert cas.entries and all(e.reasoning == "" for e in cas.entries.values())
    out = write_cassette(tmp_path / path.name, cas.model, cas.identity, cas.entries.values(), merge=False)
    assert out.read_bytes() == path.read_bytes()


def test_an_entry_without_reasoning_keeps_its_record_and_checksum():
    rec = _entry().cassette_record()
    assert "reasoning" not in rec and "reasoning" not in _entry().cache_record()
    old = {k: v for k, v in rec.items() if k != "checksum"}  # the record as the code before wrote it
    assert rec["checksum"] == checksum(old)


def test_reasoning_round_trips_through_cache_and_cassette(tmp_path):
    entry = _entry("I think the arm reaches.")
    assert entry_from_record(entry.cassette_record()).reasoning == entry.reasoning
    with ResponseCache(tmp_path / "cache") as cache:
        cache.add(entry)
        got = cache.get(entry.key)
    assert got.reasoning == entry.reasoning and got.to_answer().reasoning == entry.reasoning
    assert got.to_answer().text == "Frame 1: reach."
    path = write_cassette(tmp_path / "m.jsonl", "m", {}, [entry, _entry(key="b" * 64)])
    lines = [json.loads(line) for line in path.read_text().splitlines()[1:]]
    assert [line.get("reasoning") for line in lines] == [entry.reasoning, None]
    assert read_cassette(path).entries[entry.key].reasoning == entry.reasoning


def test_tampered_or_mistyped_reasoning_is_refused(tmp_path):
    rec = _entry("draft").cassette_record()
    with pytest.raises(ValueError, match="checksum"):
        entry_from_record({**rec, "reasoning": "other draft"})
    bad = {k: v for k, v in rec.items() if k != "checksum"} | {"reasoning": ["not", "text"]}
    with pytest.raises(ValueError, match="reasoning"):
        entry_from_record({**bad, "checksum": checksum(bad)})
    path = write_cassette(tmp_path / "m.jsonl", "m", {}, [_entry("draft")])
    head, line = path.read_text().splitlines()
    path.write_text(head + "\n" + line.replace('"draft"', '"trafd"') + "\n")
    with pytest.raises(CassetteError, match="checksum"):
        read_cassette(path)


def test_a_changed_reasoning_alone_rewrites_the_line(tmp_path):
    path = write_cassette(tmp_path / "m.jsonl", "m", {}, [_entry("first")])
    write_cassette(path, "m", {}, [_entry("second")])
    assert read_cassette(path).entries["a" * 64].reasoning == "second"
