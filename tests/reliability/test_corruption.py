"""Item 3, corruption: damaged fixtures, cassettes and cache entries are detected, named and handled.

* Fixtures: one byte flipped in a seeded sample of the shipped fixture files (every kind: frame PNGs,
  episode.json, steps.npz, a recorded cassette, the manifest) fails the manifest check with an error that
  names the file: through ``verify_files`` for each sampled file, through ``load_episodes`` (what every run
  calls) for episode files, and through the CLI (``vlmproprio verify``, ``vlmproprio run``) for one of each.
* Cassettes: single-byte flips anywhere in a cassette either fail its per-line checksums with an error naming
  file and line, or leave every answer exactly as recorded (a flip that JSON reads as whitespace); a
  damaged answer line makes ``vlmproprio run --mode replay`` stop with one line naming it.
* Cache entries: entries damaged in the SQLite file in five ways are reported (one warning line each) and
  recomputed by ``vlmproprio run`` in live mode, which then gives the transcripts of a clean run. Replay
  through the CLI never reads the response cache (only the committed cassette); that a corrupt entry is fatal
  for a replaying ``Answerer`` is checked in
  tests/test_cache.py::test_corrupt_entry_is_recomputed_in_live_mode_and_fatal_in_replay.

The CLI runs in this process (``cli_in_process``) where what is checked is its one error line and the files:
a subprocess cost ~1.5 CPU s of imports per command. The cache-entry test's damaged run stays a subprocess:
the warnings it counts are log records, which only a process of its own prints to stderr.
"""

from __future__ import annotations

import json
import random
import zlib
from pathlib import Path

import pytest
from fault_support import cli_in_process
from reliability_support import (
    assert_one_line_error,
    cache_answers,
    cache_rows,
    caption_responder,
    cli,
    fixture_copy,
    fixture_subset,
    set_cache_row,
    transcripts_of,
)

from vlmproprio.cassettes import CassetteError, read_cassette
from vlmproprio.episodes import EpisodeError, load_episodes, read_manifest, verify_files
from vlmproprio.testing.openai_server import FakeOpenAIServer

SEED = 3_2026
SAMPLE = 50
CASSETTE_FLIPS = 200
MODEL = "openai:fake-vlm"


def _kind(rel: str) -> str:
    if rel.endswith(".png"):
        return "png"
    if rel.endswith("episode.json"):
        return "episode.json"
    if rel.endswith(".npz"):
        return "steps.npz"
    if rel.endswith(".jsonl"):
        return "cassette"
    if rel == "manifest.json":
        return "manifest"
    return "other"


def _record(server: FakeOpenAIServer, fixtures: Path, tmp: Path) -> Path:
    """A cassette recorded through the CLI into <fixtures>/responses/ (registered in the manifest)."""
    args = ["run", "--model", MODEL, "--mode", "record", "--base-url", server.base_url, "--fixtures", fixtures]
    args += ["--episodes", "door_00", "--conditions", "none,both", "--frame-stride", "2", "--no-progress"]
    proc = cli_in_process([*args, "--out", tmp / "record-run", "--cache-dir", tmp / "record-cache"])
    assert proc.returncode == 0, proc.stderr
    path = fixtures / "responses" / "openai_fake-vlm.jsonl"
    assert path.is_file() and "responses/openai_fake-vlm.jsonl" in read_manifest(fixtures)
    return path


@pytest.fixture(scope="module")
def recorded_fixtures(tmp_path_factory):
    """A full copy of the fixtures plus a recorded cassette: every kind of fixture file there is."""
    pytest.importorskip("openai", reason="recording through the openai backend needs the openai SDK")
    tmp = tmp_path_factory.mktemp("corruption")
    fixtures = fixture_copy(tmp / "fixtures")
    with FakeOpenAIServer(responder=caption_responder) as server:
        _record(server, fixtures, tmp)
    return fixtures


def _flip(path: Path, rng: random.Random) -> tuple[bytes, int]:
    data = path.read_bytes()
    pos = rng.randrange(len(data))
    damaged = bytearray(data)
    damaged[pos] ^= rng.randint(1, 255)
    path.write_bytes(bytes(damaged))
    return data, pos


def test_a_flipped_byte_in_any_fixture_file_is_named(recorded_fixtures, figures):
    root = recorded_fixtures
    manifest = read_manifest(root)
    files = [*sorted(manifest), "manifest.json"]
    rng = random.Random(SEED)
    sample = rng.sample(files, SAMPLE)
    for kind in ("png", "episode.json", "steps.npz", "cassette", "manifest"):  # at least one of every kind
        if not any(_kind(f) == kind for f in sample):
            sample.append(rng.choice([f for f in files if _kind(f) == kind]))
    caught: dict[str, int] = {}
    for rel in sample:
        path = root / rel
        original, pos = _flip(path, rng)
        try:
            with pytest.raises(EpisodeError) as info:
                verify_files(root)
            msg = str(info.value)
            named = "manifest.json" if rel == "manifest.json" else str(path)
            assert named in msg, f"flip at byte {pos} of {rel}: error does not name it: {msg}"
            if rel.startswith("episodes/") or rel == "manifest.json":
                with pytest.raises(EpisodeError, match="manifest.json" if rel == "manifest.json" else None) as info:
                    load_episodes(root)  # what `vlmproprio run` and scoring call
                assert named in str(info.value)
        finally:
            path.write_bytes(original)
        caught[_kind(rel)] = caught.get(_kind(rel), 0) + 1
    verify_files(root)  # restored
    assert set(caught) == {"png", "episode.json", "steps.npz", "cassette", "manifest"}
    figures(
        "fixture byte flips",
        files_in_manifest=len(manifest),
        flipped=len(sample),
        detected_and_named=len(sample),
        **caught,
    )


@pytest.mark.parametrize(
    "rel",
    [
        "episodes/door_03/frames/007.png",
        "episodes/bin2_01/episode.json",
        "episodes/bin0_00/steps.npz",
        "responses/openai_fake-vlm.jsonl",
    ],
)
def test_the_cli_names_a_damaged_fixture_file(recorded_fixtures, rel):
    path = recorded_fixtures / rel
    original, _ = _flip(path, random.Random(rel))
    try:
        proc = cli_in_process(["verify", "--fixtures", recorded_fixtures])
        assert_one_line_error(proc, str(path), "sha256 differs")
        if rel.startswith("episodes/"):
            episode = rel.split("/")[1]
            run = ["run", "--model", "reference", "--fixtures", recorded_fixtures, "--episodes", episode]
            proc = cli_in_process(run)
            assert_one_line_error(proc, str(path), "sha256 differs")
    finally:
        path.write_bytes(original)


def test_single_byte_flips_in_a_cassette_never_change_an_answer_silently(recorded_fixtures, figures):
    path = recorded_fixtures / "responses" / "openai_fake-vlm.jsonl"
    clean = read_cassette(path)
    rng = random.Random(SEED)
    detected = harmless = 0
    for _ in range(CASSETTE_FLIPS):
        original, pos = _flip(path, rng)
        try:
            try:
                damaged = read_cassette(path)
            except CassetteError as exc:
                line = original[:pos].count(b"\n") + 1
                # the named line is the damaged one (or the one a damaged newline ran into)
                assert f"{path}:{line}:" in str(exc) or f"{path}:{line + 1}:" in str(exc), (pos, str(exc))
                detected += 1
            else:
                # only a flip that JSON reads as whitespace gets through, and then nothing changed
                assert (damaged.model, damaged.identity, damaged.entries) == (
                    clean.model,
                    clean.identity,
                    clean.entries,
                )
                harmless += 1
        finally:
            path.write_bytes(original)
    assert detected + harmless == CASSETTE_FLIPS and detected >= CASSETTE_FLIPS * 0.95
    figures("cassette byte flips", flips=CASSETTE_FLIPS, detected=detected, harmless_whitespace=harmless, changed=0)


def test_a_damaged_cassette_line_stops_a_replay_with_one_line(recorded_fixtures, tmp_path):
    path = recorded_fixtures / "responses" / "openai_fake-vlm.jsonl"
    original = path.read_bytes()
    lines = original.decode().splitlines()
    rec = json.loads(lines[3])
    edited = rec["text"].replace("the", "a", 1) if "the" in rec["text"] else rec["text"] + "."
    assert edited != rec["text"]
    rec["text"] = edited  # a plausible change, its checksum kept
    lines[3] = json.dumps(rec, sort_keys=True, separators=(",", ":"), ensure_ascii=False)
    path.write_text("\n".join(lines) + "\n")
    args = ["run", "--model", MODEL, "--mode", "replay", "--fixtures", recorded_fixtures, "--episodes", "door_00"]
    args += ["--conditions", "none,both", "--frame-stride", "2", "--no-progress", "--out", tmp_path / "replay"]
    try:
        proc = cli_in_process(args)
        assert_one_line_error(proc, f"{path}:4: bad answer line: checksum mismatch")
        assert not (tmp_path / "replay" / "transcripts").exists()  # nothing was captioned from a damaged cassette
    finally:
        path.write_bytes(original)
    assert cli_in_process(args).returncode == 0  # the restored cassette replays


# ---------------------------------------------------------------------------------------------- cache entries


def _recompress(blob: bytes, change) -> bytes:
    rec = json.loads(zlib.decompress(blob))
    rec = change(rec)
    return zlib.compress(json.dumps(rec).encode("utf-8"), 6)


DAMAGE = {
    "flipped byte": lambda blob, other: blob[:20] + bytes([blob[20] ^ 0x5A]) + blob[21:],
    "truncated": lambda blob, other: blob[: len(blob) // 2],
    "text changed, checksum kept": lambda blob, other: _recompress(blob, lambda r: {**r, "text": r["text"] + "!"}),
    "not an object": lambda blob, other: zlib.compress(b"[1, 2, 3]", 6),
    "another key's entry": lambda blob, other: other,
}


def test_corrupt_cache_entries_are_reported_and_recomputed_in_live_mode(tmp_path, figures):
    fixtures = fixture_subset(tmp_path / "fixtures", ["door_02"])
    cache = tmp_path / "cache"
    args = ["run", "--model", "reference", "--fixtures", fixtures, "--conditions", "ee,both", "--no-progress"]
    args += ["--cache-dir", cache]
    clean = cli_in_process([*args, "--out", tmp_path / "clean"])
    assert clean.returncode == 0, clean.stderr
    expected = cache_answers(cache)
    rows = cache_rows(cache)
    keys = sorted(rows)
    damaged = dict(zip(DAMAGE, keys[: len(DAMAGE)], strict=False))
    for (how, key), other in zip(damaged.items(), keys[len(DAMAGE) :], strict=False):
        rowid, blob = rows[key]
        set_cache_row(cache, rowid, DAMAGE[how](blob, rows[other][1]))

    proc = cli([*args, "--out", tmp_path / "again"])
    assert proc.returncode == 0, proc.stderr
    warnings = [line for line in proc.stderr.splitlines() if "corrupt cache entry dropped and recomputed" in line]
    assert len(warnings) == len(DAMAGE)  # each reported once, on one line, naming its entry
    for key in damaged.values():
        assert sum(key in w for w in warnings) >= 1
    assert "Traceback" not in proc.stderr
    run_stats = json.loads((tmp_path / "again" / "run.json").read_text())["models"][0]["stats"]
    assert run_stats["corrupt"] == len(DAMAGE) and run_stats["misses"] == len(DAMAGE)  # only those recomputed
    assert transcripts_of(tmp_path / "again") == transcripts_of(tmp_path / "clean")
    assert cache_answers(cache) == expected  # repaired in place
    figures(
        "cache entry corruption (live)",
        entries=len(expected),
        damaged=len(DAMAGE),
        reported=len(warnings),
        recomputed=run_stats["misses"],
        kinds=len(DAMAGE),
        entries_lost=0,
    )
