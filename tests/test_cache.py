"""The request key, the diskcache store, cassettes and cached answering (no model needed)."""

from __future__ import annotations

import hashlib
import json
import multiprocessing
import os
import pickle
import random
import re
import sqlite3
import subprocess
import sys
import time
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path

import pytest

from vlmproprio.answering import Answerer
from vlmproprio.backends.base import Backend, BackendError
from vlmproprio.backends.replay import ReplayBackend
from vlmproprio.cache import CacheCorruptError, CacheEntry, ResponseCache, canonical_json, key_document, request_key
from vlmproprio.cassettes import (
    CassetteError,
    ReplayMissError,
    export_cassette,
    import_cassette,
    read_cassette,
    write_cassette,
)
from vlmproprio.chat import (
    Answer,
    AnswerMeta,
    ChatRequest,
    GenerationConfig,
    ImagePart,
    Message,
    RequestTag,
    TextPart,
)

IDENTITY = {
    "backend": "fake",
    "model_id": "echo",
    "revision": "r1",
    "dtype": "float32",
    "attn_implementation": "sdpa",
}


def req(text: str = "# Process 1\nhello", images: Sequence[bytes] = (b"img-a", b"img-b"), **kw) -> ChatRequest:
    tag = kw.pop("tag", RequestTag("door_00", "both", "p1", 0))
    parts = (*tuple(ImagePart(b) for b in images), TextPart(text))
    return ChatRequest(
        messages=(Message("system", (TextPart("You caption robots."),)), Message("user", parts)),
        config=kw.pop("config", GenerationConfig(max_new_tokens=16)),
        prompt_version=kw.pop("prompt_version", "p-1"),
        tag=tag,
    )


class EchoBackend(Backend):
    """A fake model: answers a digest of the prompt text; empty for texts containing EMPTY; counts calls."""

    def __init__(self, max_batch_size: int = 4, delay_s: float = 0.0, fail_on: str | None = None) -> None:
        self.max_batch_size = max_batch_size
        self.delay_s = delay_s
        self.fail_on = fail_on
        self.batches: list[int] = []

    def identity(self) -> dict[str, str]:
        return dict(IDENTITY)

    def generate(self, requests: Sequence[ChatRequest]) -> list[Answer]:
        self.batches.append(len(requests))
        out: list[Answer | None] = []
        for r in requests:
            text = "\n".join(m.text for m in r.messages)
            if self.fail_on and self.fail_on in text:
                raise BackendError("injected failure", partial=out + [None] * (len(requests) - len(out)))
            time.sleep(self.delay_s)
            answer = "" if "EMPTY" in text else "echo " + hashlib.sha256(text.encode()).hexdigest()[:12]
            out.append(Answer(text=answer, meta=AnswerMeta(backend="fake", model_id="echo", latency_s=0.001)))
        return out  # type: ignore[return-value]


def expected_text(r: ChatRequest) -> str:
    text = "\n".join(m.text for m in r.messages)
    return "echo " + hashlib.sha256(text.encode()).hexdigest()[:12]


# ---------------------------------------------------------------------------------------------- the key


def test_key_is_pinned_and_hex():
    # The key is a cross-machine contract (cassettes are looked up by it): a change here breaks every cassette.
    key = request_key(IDENTITY, req())
    assert len(key) == 64 and int(key, 16) >= 0
    assert key == "2223dc8cfc5c8f5b1fcc42c8ece5e8d5afa6d488949700d7e89fd52a3bd7fe47"


def _variants() -> dict[str, tuple[dict, ChatRequest]]:
    base = req()
    v: dict[str, tuple[dict, ChatRequest]] = {"base": (IDENTITY, base)}
    for f in ("backend", "model_id", "revision", "dtype", "attn_implementation"):
        v[f"identity.{f}"] = ({**IDENTITY, f: IDENTITY[f] + "x"}, base)
    for f, val in (("max_new_tokens", 17), ("temperature", 0.5), ("seed", 1), ("min_new_tokens", 4)):
        v[f"config.{f}"] = (IDENTITY, replace(base, config=replace(base.config, **{f: val})))
    v["config.seed_none"] = (IDENTITY, replace(base, config=replace(base.config, seed=None)))
    v["prompt_version"] = (IDENTITY, replace(base, prompt_version="p-2"))
    v["text"] = (IDENTITY, req(text="# Process 1\nhello!"))
    v["text.whitespace"] = (IDENTITY, req(text="# Process 1\nhello "))
    v["image.bytes"] = (IDENTITY, req(images=(b"img-a", b"img-c")))
    v["image.order"] = (IDENTITY, req(images=(b"img-b", b"img-a")))
    v["image.count"] = (IDENTITY, req(images=(b"img-a",)))
    sys_msg, user = base.messages
    v["role"] = (IDENTITY, replace(base, messages=(replace(sys_msg, role="user"), user)))
    v["system.text"] = (IDENTITY, replace(base, messages=(Message("system", (TextPart("Other."),)), user)))
    v["part.order"] = (IDENTITY, replace(base, messages=(sys_msg, replace(user, parts=user.parts[::-1]))))
    v["image.mime"] = (
        IDENTITY,
        replace(base, messages=(sys_msg, replace(user, parts=(ImagePart(b"img-a", "image/jpeg"), *user.parts[1:])))),
    )
    v["message.count"] = (IDENTITY, replace(base, messages=(user,)))
    return v


def test_changing_any_one_input_changes_the_key():
    keys = {name: request_key(ident, r) for name, (ident, r) in _variants().items()}
    assert len(set(keys.values())) == len(keys), "two different inputs share a key"


def test_what_must_not_change_the_key():
    base = request_key(IDENTITY, req())
    reordered = dict(reversed(list(IDENTITY.items())))
    assert list(reordered) != list(IDENTITY)
    assert request_key(reordered, req()) == base
    # device, base URL, ... are not part of the identity in the key; the tag (where a request comes from) neither
    assert request_key({**IDENTITY, "device": "cuda:0", "base_url": "http://x"}, req()) == base
    assert request_key(IDENTITY, req(tag=RequestTag("bin3_02", "none", "p3", -1))) == base


def test_canonical_json_ignores_dict_order():
    doc = key_document(IDENTITY, req())
    shuffled = json.loads(json.dumps(doc), object_pairs_hook=lambda pairs: dict(reversed(pairs)))
    assert list(shuffled) != list(doc)
    assert canonical_json(shuffled) == canonical_json(doc)


def test_key_is_the_same_in_a_fresh_process():
    code = (
        "import json, sys\n"
        "sys.path.insert(0, sys.argv[1])\n"
        "from test_cache import IDENTITY, req\n"
        "from vlmproprio.cache import request_key\n"
        "print(request_key(IDENTITY, req()))\n"
    )
    env_path = str(Path(__file__).parent)
    out = subprocess.run(
        [sys.executable, "-c", code, env_path],
        capture_output=True,
        text=True,
        check=True,
        env={**os.environ, "PYTHONHASHSEED": "12345", "PYTHONPATH": os.pathsep.join(sys.path)},
    )
    assert out.stdout.strip() == request_key(IDENTITY, req())


# ---------------------------------------------------------------------------------------------- the store


def _entry(key: str = "k" * 64, text: str = "hello", status: str = "ok") -> CacheEntry:
    meta = {"backend": "fake", "model_id": "echo"}
    return CacheEntry(key=key, text=text, meta=meta, tag={}, status=status, model="echo")


def test_store_roundtrip_and_first_writer_wins(tmp_path):
    with ResponseCache(tmp_path / "c") as cache:
        assert cache.get("k" * 64) is None
        assert cache.add(_entry()) is True
        assert cache.add(_entry(text="other")) is False
        assert cache.get("k" * 64).text == "hello"
        # an ok answer replaces an empty one, never the other way round
        assert cache.store(_entry("e" * 64, "", status="empty")) is True
        assert cache.store(_entry("e" * 64, "now")) is True
        assert cache.store(_entry("e" * 64, "", status="empty")) is False
        assert cache.get("e" * 64).text == "now"
        assert [e.key for e in cache.entries(model="echo")] == ["e" * 64, "k" * 64]


def _sqlite_rows(cache_dir: Path) -> list[tuple]:
    with sqlite3.connect(cache_dir / "cache.db") as db:
        return db.execute("SELECT rowid, key, value, filename, mode FROM Cache").fetchall()


def test_tampered_entry_fails_its_checksum(tmp_path):
    with ResponseCache(tmp_path / "c") as cache:
        cache.add(_entry())
        rec = _entry().cache_record()
        rec["text"] = "tampered"  # checksum kept: as if a disk or a person changed the text
        cache._cache.set("k" * 64, rec)
        with pytest.raises(CacheCorruptError, match="checksum"):
            cache.get("k" * 64)


def test_flipped_byte_in_the_database_is_detected(tmp_path):
    with ResponseCache(tmp_path / "c") as cache:
        cache.add(_entry())
    (rowid, _key, value, _fn, _mode) = _sqlite_rows(tmp_path / "c")[0]
    damaged = bytearray(value)
    damaged[len(damaged) // 2] ^= 0xFF
    with sqlite3.connect(tmp_path / "c" / "cache.db") as db:
        db.execute("UPDATE Cache SET value = ? WHERE rowid = ?", (bytes(damaged), rowid))
    with ResponseCache(tmp_path / "c") as cache, pytest.raises(CacheCorruptError, match=r"entry k+"):
        cache.get("k" * 64)


class _Evil:
    def __init__(self, marker: str) -> None:
        self.marker = marker

    def __reduce__(self):
        return (open, (self.marker, "w"))  # unpickling would create the marker file


def test_a_pickled_value_is_refused_not_unpickled(tmp_path):
    marker = tmp_path / "pwned"
    with ResponseCache(tmp_path / "c") as cache:
        cache.add(_entry())
    # someone plants a pickle under our key, stored the way diskcache's default disk stores pickles (mode 4)
    blob = pickle.dumps(_Evil(str(marker)))
    with sqlite3.connect(tmp_path / "c" / "cache.db") as db:
        rowid = db.execute("SELECT rowid FROM Cache").fetchone()[0]
        db.execute("UPDATE Cache SET value = ?, mode = 4 WHERE rowid = ?", (blob, rowid))
    pickle.loads(blob).close()  # the payload is live: unpickling it creates the marker
    assert marker.exists()
    marker.unlink()
    with ResponseCache(tmp_path / "c") as cache, pytest.raises(CacheCorruptError, match="unpickle"):
        cache.get("k" * 64)
    assert not marker.exists()


# ---------------------------------------------------------------------------------------------- concurrency


def _worker(cache_dir: str, seed: int, n: int, barrier, results) -> None:
    requests = [req(text=f"# Process 1\nrequest {i}") for i in range(n)]
    order = list(range(n))
    random.Random(seed).shuffle(order)  # overlapping work in a different order per process
    backend = EchoBackend(max_batch_size=3, delay_s=0.003)
    with ResponseCache(cache_dir) as cache:
        cb = Answerer(backend, mode="live", cache=cache, model="echo")
        barrier.wait(timeout=60)  # all four open the cache, then start together
        answers = {}
        for start in range(0, n, 5):  # several small calls, so the processes interleave
            chunk = [requests[i] for i in order[start : start + 5]]
            for a in cb.answer(chunk):
                answers[a.key] = a.text
    results.put({"seed": seed, "stored": cb.stats["stored"], "answers": answers})


def test_four_processes_share_one_cache(tmp_path):
    n, procs = 40, 4
    ctx = multiprocessing.get_context("spawn")  # no fork: the parent may hold torch threads and open databases
    barrier, results = ctx.Barrier(procs), ctx.Queue()
    workers = [
        ctx.Process(target=_worker, args=(str(tmp_path / "c"), seed, n, barrier, results)) for seed in range(procs)
    ]
    for w in workers:
        w.start()
    got = [results.get(timeout=120) for _ in workers]
    for w in workers:
        w.join(timeout=60)
        assert w.exitcode == 0  # no "database is locked", no crash
    expected = {
        request_key(IDENTITY, r): expected_text(r) for r in (req(text=f"# Process 1\nrequest {i}") for i in range(n))
    }
    for res in got:
        assert res["answers"] == expected  # every process got every answer, and the right one
    assert sum(res["stored"] for res in got) == n  # each answer stored exactly once, by one process
    assert sum(res["stored"] > 0 for res in got) >= 2  # they really did work side by side
    with ResponseCache(tmp_path / "c") as cache:
        assert cache.keys() == sorted(expected)
        assert {k: cache.get(k).text for k in expected} == expected


# ---------------------------------------------------------------------------------------------- cached answering


def test_live_batches_misses_dedupes_and_keeps_order(tmp_path):
    backend = EchoBackend(max_batch_size=3)
    requests = [req(text=f"# Process 1\nr{i}") for i in range(7)]
    requests.insert(3, requests[1])  # the same request twice in one call
    with ResponseCache(tmp_path / "c") as cache:
        cb = Answerer(backend, mode="live", cache=cache, model="echo")
        first = cb.answer(requests)
        assert backend.batches == [3, 3, 1]  # 7 distinct misses in batches of max_batch_size
        assert [a.text for a in first] == [expected_text(r) for r in requests]
        assert [a.key for a in first] == [request_key(IDENTITY, r) for r in requests]
        assert not any(a.from_cache for a in first)
        again = cb.answer(requests[::-1])
        assert backend.batches == [3, 3, 1]  # no model call
        assert [a.text for a in again] == [a.text for a in first][::-1]
        assert all(a.from_cache for a in again)


def test_empty_answers_are_not_successes(tmp_path):
    backend = EchoBackend()
    r = req(text="# Process 1\nEMPTY please")
    with ResponseCache(tmp_path / "c") as cache:
        assert Answerer(backend, mode="live", cache=cache).answer([r])[0].text == ""
        assert cache.get(request_key(IDENTITY, r)).status == "empty"
        Answerer(backend, mode="live", cache=cache).answer([r])
        assert backend.batches == [1, 1]  # live mode asked again
        # replay serves what the recording said, so a replay equals the live run
        replayed = Answerer(backend, mode="replay", cache=cache).answer([r])
        assert replayed[0].text == "" and replayed[0].from_cache and backend.batches == [1, 1]


def test_failed_batch_keeps_what_was_answered(tmp_path):
    backend = EchoBackend(max_batch_size=10, fail_on="BOOM")
    requests = [req(text="# Process 1\nfine 1"), req(text="# Process 1\nfine 2"), req(text="# Process 1\nBOOM")]
    with ResponseCache(tmp_path / "c") as cache:
        with pytest.raises(BackendError, match="injected"):
            Answerer(backend, mode="live", cache=cache).answer(requests)
        assert sorted(cache.keys()) == sorted(request_key(IDENTITY, r) for r in requests[:2])


def test_corrupt_entry_is_recomputed_in_live_mode_and_fatal_in_replay(tmp_path, caplog):
    backend = EchoBackend()
    r = req()
    key = request_key(IDENTITY, r)
    with ResponseCache(tmp_path / "c") as cache:
        Answerer(backend, mode="live", cache=cache).answer([r])
        rec = cache._cache.get(key)
        rec["text"] = "silently changed"
        cache._cache.set(key, rec)
        with pytest.raises(CacheCorruptError, match=r"checksum.*Replay mode cannot recompute"):
            Answerer(backend, mode="replay", cache=cache).answer([r])
        assert backend.batches == [1]
        live = Answerer(backend, mode="live", cache=cache)
        assert live.answer([r])[0].text == expected_text(r)
        assert backend.batches == [1, 1] and live.stats["corrupt"] == 1
        assert "corrupt cache entry dropped and recomputed" in caplog.text
        assert cache.get(key).text == expected_text(r)  # repaired


def test_replay_miss_names_the_request_and_how_to_record(tmp_path):
    r = req(tag=RequestTag("bin2_01", "joint", "p2", 3))
    with ResponseCache(tmp_path / "c") as cache, pytest.raises(ReplayMissError) as info:
        Answerer(EchoBackend(), mode="replay", cache=cache, model="echo").answer([r])
    msg = str(info.value)
    for part in ("bin2_01", "stage p2", "group 3", request_key(IDENTITY, r), "record", "cassette export"):
        assert part in msg
    assert info.value.key == request_key(IDENTITY, r)


def test_unknown_mode_is_a_usage_error():
    from vlmproprio.errors import UsageError

    with pytest.raises(UsageError, match="replay, live, record"):
        Answerer(EchoBackend(), mode="fast")


# ---------------------------------------------------------------------------------------------- cassettes


def _recorded(tmp_path: Path, n: int = 5) -> tuple[Path, list[ChatRequest]]:
    requests = [req(text=f"# Process 1\nr{i}") for i in range(n)]
    cb = Answerer(EchoBackend(), mode="record", cache=None, model="echo")
    cb.answer(requests)
    return cb.export_cassette(tmp_path / "echo.jsonl"), requests


def test_record_then_replay_from_the_cassette(tmp_path):
    path, requests = _recorded(tmp_path)
    lines = path.read_text().splitlines()
    assert len(lines) == 6
    keys = [json.loads(x)["key"] for x in lines[1:]]
    assert keys == sorted(keys)
    assert json.loads(lines[0])["identity"] == IDENTITY
    replay = ReplayBackend(path)
    assert replay.identity() == IDENTITY and replay.calls_model is False
    answers = Answerer(replay, mode="replay").answer(requests)
    assert [a.text for a in answers] == [expected_text(r) for r in requests]
    assert all(a.from_cache for a in answers)
    # writing the same answers again gives the same bytes (diff-friendly, deterministic)
    before = path.read_bytes()
    write_cassette(path, "echo", IDENTITY, read_cassette(path).entries.values())
    assert path.read_bytes() == before
    # re-recorded answers with the same text keep their old lines, even if the latency differs
    slower = [replace(e, meta={**e.meta, "latency_s": 9.9}) for e in read_cassette(path).entries.values()]
    write_cassette(path, "echo", IDENTITY, slower)
    assert path.read_bytes() == before


def test_cassette_merge_keeps_old_answers_and_refuses_another_identity(tmp_path):
    path, _requests = _recorded(tmp_path, 3)
    extra = Answerer(EchoBackend(), mode="record", model="echo")
    extra.answer([req(text="# Process 1\nnew one")])
    before = path.read_text().splitlines()
    extra.export_cassette(path)
    after = path.read_text().splitlines()
    assert len(read_cassette(path).entries) == 4 and len(after) == 5
    assert set(before) <= set(after)  # the old lines are kept as they were
    with pytest.raises(CassetteError, match="recorded from"):
        write_cassette(path, "echo", {**IDENTITY, "revision": "r2"}, [])


@pytest.mark.parametrize(
    ("damage", "match"),
    [
        (lambda line: line.replace('"text":"echo', '"text":"ECHO'), r":3: bad answer line: checksum mismatch"),
        (lambda line: line[: len(line) // 2], r":3: not valid JSON"),
        (lambda line: "[1, 2]", r":3: expected a JSON object"),
    ],
)
def test_corrupt_cassette_line_is_reported_with_its_line_number(tmp_path, damage, match):
    path, _ = _recorded(tmp_path)
    lines = path.read_text().splitlines()
    lines[2] = damage(lines[2])
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(CassetteError, match=re.escape(str(path)) + match):
        read_cassette(path)


def test_cassette_header_and_order_are_checked(tmp_path):
    path, _ = _recorded(tmp_path)
    lines = path.read_text().splitlines()
    head = json.loads(lines[0])
    head["identity"]["revision"] = "forged"
    path.write_text("\n".join([json.dumps(head), *lines[1:]]) + "\n")
    with pytest.raises(CassetteError, match=r":1: header checksum mismatch"):
        read_cassette(path)
    path.write_text("\n".join([lines[0], lines[2], lines[1], *lines[3:]]) + "\n")
    with pytest.raises(CassetteError, match=r":3: keys not strictly increasing"):
        read_cassette(path)


def test_replay_backend_miss(tmp_path):
    path, _ = _recorded(tmp_path, 2)
    r = req(text="# Process 3\nnever recorded", tag=RequestTag("door_04", "ee", "p3", -1))
    with pytest.raises(ReplayMissError, match=r"door_04.*stage p3.*cassette .*echo\.jsonl"):
        Answerer(ReplayBackend(path), mode="replay").answer([r])


def test_export_and_import_through_the_cli(tmp_path, capsys):
    from vlmproprio.cli import main

    requests = [req(text=f"# Process 2\ng{i}") for i in range(3)]
    with ResponseCache(tmp_path / "c1") as cache:
        Answerer(EchoBackend(), mode="live", cache=cache, model="openai_echo").answer(requests)
    out = tmp_path / "responses"
    assert (
        main(
            [
                "cassette",
                "export",
                "--model",
                "openai:echo",
                "--cache-dir",
                str(tmp_path / "c1"),
                "--cassette-dir",
                str(out),
            ]
        )
        == 0
    )
    cassette = out / "openai_echo.jsonl"
    assert len(read_cassette(cassette).entries) == 3
    assert main(["cassette", "import", str(cassette), "--cache-dir", str(tmp_path / "c2")]) == 0
    with ResponseCache(tmp_path / "c2") as cache:
        answers = Answerer(EchoBackend(), mode="replay", cache=cache).answer(requests)
    assert [a.text for a in answers] == [expected_text(r) for r in requests]
    # a model with nothing in the cache is a clean one-line error, not a traceback
    assert (
        main(
            [
                "cassette",
                "export",
                "--model",
                "reference",
                "--cache-dir",
                str(tmp_path / "c1"),
                "--cassette-dir",
                str(out),
            ]
        )
        == 2
    )
    assert "holds no answers for model 'reference' (it holds: openai_echo (3))" in capsys.readouterr().err
    assert main(["cassette", "export", "--model", "hf:../../etc", "--cache-dir", str(tmp_path / "c1")]) == 2
    assert "refused" in capsys.readouterr().err


def test_export_refuses_mixed_identities(tmp_path):
    with ResponseCache(tmp_path / "c") as cache:
        cache.add(replace(_entry("a" * 64), identity=IDENTITY))
        cache.add(replace(_entry("b" * 64), identity={**IDENTITY, "revision": "r2"}))
        with pytest.raises(Exception, match="2 different identities"):
            export_cassette(cache, "echo", tmp_path / "x.jsonl")
        model, n = import_cassette(cache, _recorded(tmp_path, 2)[0])
        assert (model, n) == ("echo", 2)


def test_explicit_to_dicts_equal_dataclasses_asdict():
    # the hot paths build these dicts by hand; they must stay what dataclasses.asdict gave (cache keys, entries)
    from dataclasses import asdict

    meta = AnswerMeta("hf", "m", "r", "bf16", "cpu", "sdpa", 3, 4, 0.5, {"a": [1, {"b": (2, 3)}], "c": None})
    for obj in (meta, GenerationConfig(max_new_tokens=7, seed=None, min_new_tokens=2), RequestTag("e", "c", "p2", 3)):
        plain = {k: v for k, v in asdict(obj).items() if not (k == "thinking" and v is None)}
        assert obj.to_dict() == plain and list(obj.to_dict()) == list(plain)
    # the thinking switch enters the dict (and so the cache key) only when it is set: older keys stay valid
    switched = GenerationConfig(max_new_tokens=7, thinking=False)
    assert switched.to_dict() == asdict(switched) and list(switched.to_dict()) == list(asdict(switched))
    copied = meta.to_dict()["extra"]
    assert copied is not meta.extra and copied["a"] is not meta.extra["a"] and copied["a"][1] is not meta.extra["a"][1]


def test_replay_answers_by_the_answerers_keys_and_still_names_a_miss(tmp_path, monkeypatch):
    requests = [req(f"# Process 1\nq{i}") for i in range(3)]
    entries = [
        CacheEntry(request_key(IDENTITY, r), f"a{i}", {"backend": "fake", "model_id": "echo"}, {})
        for i, r in enumerate(requests)
    ]
    path = write_cassette(tmp_path / "echo.jsonl", "echo", IDENTITY, entries[:2])
    backend = ReplayBackend(path)
    hashed = []
    monkeypatch.setattr("vlmproprio.backends.replay.request_key", lambda *a: hashed.append(a) or request_key(*a))
    answers = Answerer(backend, mode="replay").answer(requests[:2])
    assert [a.text for a in answers] == ["a0", "a1"] and [a.key for a in answers] == [e.key for e in entries[:2]]
    assert hashed == []  # the Answerer's keys were used, not computed again
    assert [a.text for a in backend.generate(requests[:2])] == ["a0", "a1"]  # plain generate hashes itself
    with pytest.raises(ReplayMissError, match=entries[2].key):
        Answerer(backend, mode="replay").answer(requests)
