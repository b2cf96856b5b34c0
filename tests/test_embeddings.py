"""The embedding cache and the encoder: batch-mate independence, byte-only storage, lazy torch."""

from __future__ import annotations

import dataclasses
import hashlib
import multiprocessing
import random
import sqlite3

import diskcache
import numpy as np
import pytest

from scoring_helpers import fake_spec
from vlmproprio.embeddings import (
    CachedEmbedder,
    EmbeddingError,
    EmbeddingStore,
    SentenceEncoder,
    encoder_spec,
    folder_revision,
    text_key,
)


def test_store_round_trip_is_bytes_exact(tmp_path):
    vec = np.array([0.1, -2.5, 3.25, np.float32(1) / 3], dtype=np.float32)
    with EmbeddingStore(tmp_path / "emb") as store:
        store.put_many("enc-a", {"hello": vec, "": vec * 2})
    with EmbeddingStore(tmp_path / "emb") as store:
        got = store.get_many("enc-a", ["hello", "missing", ""])
        assert set(got) == {"hello", ""}
        assert got["hello"].tobytes() == vec.tobytes()
        assert store.get_many("enc-b", ["hello"]) == {}  # another encoder never sees these vectors


def test_store_refuses_pickled_rows(tmp_path):
    d = tmp_path / "emb"
    with diskcache.Cache(str(d)) as plain:  # somebody wrote a pickled object where a vector should be
        plain.set(text_key("enc", "evil"), {"not": "bytes"})
    with EmbeddingStore(d) as store, pytest.raises(EmbeddingError, match="refused"):
        store.get_many("enc", ["evil"])
    with EmbeddingStore(d) as store, pytest.raises(EmbeddingError, match="vectors"):
        store.put_many("enc", {"x": "not a vector"})  # type: ignore[dict-item]


def _vector(text: str) -> np.ndarray:
    """A vector of its own for each text, the same in every process."""
    seed = int.from_bytes(hashlib.sha256(text.encode("utf-8")).digest()[:8], "little")
    return np.random.default_rng(seed).standard_normal(16).astype(np.float32)


def _store_worker(directory: str, seed: int, texts: list[str], barrier, results) -> None:
    """Stores the texts' vectors in small transactions and reads back all it stored so far after each; puts
    (seed, vectors read back at the end) or (seed, the error) on ``results``, so the test never waits on a
    worker that died."""
    order = list(texts)
    random.Random(seed).shuffle(order)  # overlapping texts, another order per process
    try:
        with EmbeddingStore(directory) as store:
            barrier.wait(timeout=60)  # all four open the store, then start together
            for start in range(0, len(order), 5):  # small transactions, so the writers interleave
                store.put_many("enc", {t: _vector(t) for t in order[start : start + 5]})
                got = store.get_many("enc", order[: start + 5])
                lost = [t for t in order[: start + 5] if t not in got or got[t].tobytes() != _vector(t).tobytes()]
                if lost:
                    raise AssertionError(f"lost or changed after storing: {lost}")
        results.put((seed, len(got)))
    except Exception as exc:  # reported to the test, which fails on it
        results.put((seed, f"{type(exc).__name__}: {exc}"))


def test_four_processes_share_one_embedding_store(tmp_path):
    """Parallel scoring runs (a tox matrix, xdist workers) share one embedding cache: the writers interleave,
    nobody loses or damages a vector, and the SQLite file passes its own integrity check."""
    texts, procs = [f"caption number {i}" for i in range(60)], 4
    ctx = multiprocessing.get_context("spawn")  # no fork: the parent may hold open databases
    barrier, results = ctx.Barrier(procs), ctx.Queue()
    directory = str(tmp_path / "emb")
    workers = [ctx.Process(target=_store_worker, args=(directory, s, texts, barrier, results)) for s in range(procs)]
    for w in workers:
        w.start()
    got = sorted(results.get(timeout=120) for _ in workers)
    for w in workers:
        w.join(timeout=60)
        assert w.exitcode == 0  # no "database is locked", no failed read-back
    assert got == [(seed, len(texts)) for seed in range(procs)]
    with sqlite3.connect(tmp_path / "emb" / "cache.db") as db:
        assert db.execute("PRAGMA integrity_check").fetchall() == [("ok",)]
    assert len({_vector(t).tobytes() for t in texts}) == len(texts)  # a swapped vector would show
    with EmbeddingStore(tmp_path / "emb") as store:
        assert len(store) == len(texts)
        stored = store.get_many("enc", texts)
        assert all(stored[t].tobytes() == _vector(t).tobytes() for t in texts)


def test_cached_embedder_never_loads_an_encoder_when_all_is_cached(tmp_path):
    spec = fake_spec()
    vec = np.ones(4, dtype=np.float32)
    with EmbeddingStore(tmp_path / "emb") as store:
        store.put_many(spec.key, {"a": vec, "b": vec})
        emb = CachedEmbedder(spec, store)
        assert set(emb.embed(["a", "b", "a"])) == {"a", "b"}
        assert emb.stats.cached == 2 and emb.stats.computed == 0 and not emb.stats.torch_loaded
        with pytest.raises(EmbeddingError, match="nonexistent"):
            emb.embed(["c"])  # the fake encoder cannot load: proves the cold path is taken only here


def test_encoder_key_covers_what_decides_the_bits(tmp_path):
    spec = fake_spec()
    assert dataclasses.replace(spec, batch_size=16).key != spec.key
    assert dataclasses.replace(spec, revision="test-2").key != spec.key
    assert dataclasses.replace(spec, threads=7).key != spec.key  # the thread count can change the bits on some CPUs
    (tmp_path / "m").mkdir()
    (tmp_path / "m" / "w.bin").write_bytes(b"abc")
    r1 = folder_revision(tmp_path / "m")
    (tmp_path / "m" / "w.bin").write_bytes(b"abd")
    assert folder_revision(tmp_path / "m") != r1
    with pytest.raises(EmbeddingError, match="not found"):
        folder_revision(tmp_path / "nope")


# ---------------------------------------------------------------------------------------------- real encoder

TEXTS = [
    "The robot turns the handle down.",
    "The robot pulls the door open toward itself while holding the handle firmly.",
    "The gripper opens.",
    "The robot lifts the cereal box up.",  # same token length as the first: they share batches
    "The arm moves forward and down toward the door handle with its gripper open; x 0.512, y -0.031.",
    "Release.",
    "The robot carries the cereal box left toward the far left compartment of the target bin.",
    "The gripper closes on the box.",
    "The robot arm moves back.",
]


@pytest.fixture(scope="module")
def encoder():
    pytest.importorskip("sentence_transformers")  # the [embed] extra; replay never needs it
    return SentenceEncoder(encoder_spec(threads=1))


def test_embedding_is_independent_of_batch_mates(encoder):
    mixed = encoder.encode(TEXTS)
    assert mixed.dtype == np.float32 and mixed.shape == (len(TEXTS), 384)
    for i in (0, 3, 5):
        alone = encoder.encode([TEXTS[i]])
        assert alone[0].tobytes() == mixed[i].tobytes(), TEXTS[i]
    reordered = encoder.encode(TEXTS[::-1] + TEXTS[:4])
    assert reordered[: len(TEXTS)][::-1].tobytes() == mixed.tobytes()


def test_a_thread_count_that_can_change_the_bits_is_in_the_key(encoder):
    """Two threads may split a reduction differently (CPU-dependent), so their vectors never share a cache entry
    with one thread's; the default thread count keeps the key the shipped sidecars were written under."""
    two = dataclasses.replace(encoder.spec, threads=2)
    assert two.key != encoder.spec.key and two.key.endswith("|threads=2")
    assert "threads" not in encoder.spec.key


def test_one_thread_gives_the_same_bits_twice(encoder):
    again = SentenceEncoder(encoder.spec)
    again._model = encoder._load()
    assert again.encode(TEXTS[:2]).tobytes() == encoder.encode(TEXTS[:2]).tobytes()


def test_embedding_is_the_sentence_transformers_embedding(encoder):
    ours = encoder.encode(TEXTS[:4])
    ref = encoder._load().encode(TEXTS[:4], batch_size=1, convert_to_numpy=True)
    np.testing.assert_allclose(ours, ref, atol=1e-5)
    assert encoder.spec.revision.startswith("sha256:")
