"""The manifest: every changed, missing or extra fixture file is named; writing is deterministic; a fixture file
is hashed once per process, again when it changes, never remembered while fresh, and a corrupt file is still
named after an earlier clean load."""

from __future__ import annotations

import hashlib
import json
import shutil
import time
from pathlib import Path

import pytest

import vlmproprio.digests as D
from vlmproprio import episodes as E
from vlmproprio.episodes import manifest as M

from .support import synthetic


def test_writers_are_deterministic(tmp_path: Path) -> None:
    a = E.build_manifest(synthetic(tmp_path / "a"))
    b = E.build_manifest(synthetic(tmp_path / "b"))
    assert a == b


@pytest.mark.parametrize("rel", ["episode.json", "steps.npz", "frames/002.png"])
def test_any_flipped_byte_is_named(fixture_root: Path, rel: str) -> None:
    path = fixture_root / "episodes" / "door_00" / rel
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0x01
    path.write_bytes(bytes(data))
    with pytest.raises(E.EpisodeError, match=rel.replace("/", ".")):
        E.load_episode(fixture_root, "door_00")


def test_missing_and_extra_files_are_named(fixture_root: Path) -> None:
    ep_dir = fixture_root / "episodes" / "door_00"
    (ep_dir / "frames" / "001.png").unlink()
    with pytest.raises(E.EpisodeError, match=r"001\.png: missing"):
        E.load_episode(fixture_root, "door_00")
    E.write_manifest(fixture_root)
    (ep_dir / "notes.txt").write_text("hi")
    with pytest.raises(E.EpisodeError, match=r"notes\.txt: extra file"):
        E.load_episode(fixture_root, "door_00")


def test_extra_episode_folder_is_an_error(fixture_root: Path) -> None:
    shutil.copytree(fixture_root / "episodes" / "door_00", fixture_root / "episodes" / "door_01")
    with pytest.raises(E.EpisodeError, match="door_01: extra episode"):
        E.load_episodes(fixture_root)


def test_a_changed_file_is_hashed_again(tmp_path, monkeypatch):
    monkeypatch.setattr(M, "_FILE_DIGESTS", {})
    monkeypatch.setattr(D, "SETTLED_NS", -1)  # remember even a file written just now
    f = tmp_path / "a.bin"
    f.write_bytes(b"x" * 1000)
    assert M._file_sha256(f) == hashlib.sha256(b"x" * 1000).hexdigest()
    assert len(M._FILE_DIGESTS) == 1
    time.sleep(0.02)  # past the timestamps' granularity
    f.write_bytes(b"y" * 1000)  # same size, same path and inode
    assert M._file_sha256(f) == hashlib.sha256(b"y" * 1000).hexdigest()


def test_a_fresh_file_is_not_remembered(tmp_path, monkeypatch):
    monkeypatch.setattr(M, "_FILE_DIGESTS", {})
    f = tmp_path / "b.bin"
    f.write_bytes(b"z")
    assert M._file_sha256(f) == hashlib.sha256(b"z").hexdigest()
    assert M._FILE_DIGESTS == {}


def test_corruption_after_a_clean_load_is_named(tmp_path, monkeypatch):
    fixtures = Path(__file__).resolve().parents[2] / "fixtures"
    root = tmp_path / "fx"
    (root / "episodes").mkdir(parents=True)
    shutil.copytree(fixtures / "episodes" / "door_00", root / "episodes" / "door_00")
    manifest = E.read_manifest(fixtures)
    files = {k: v for k, v in manifest.items() if k.startswith("episodes/door_00/")}
    (root / "manifest.json").write_text(json.dumps({"format_version": 1, "files": files}))
    monkeypatch.setattr(M, "_FILE_DIGESTS", {})
    monkeypatch.setattr(D, "SETTLED_NS", -1)
    E.load_episodes(root)
    assert M._FILE_DIGESTS  # remembered
    time.sleep(0.02)
    png = root / "episodes" / "door_00" / "frames" / "003.png"
    data = bytearray(png.read_bytes())
    data[100] ^= 1
    png.write_bytes(bytes(data))
    with pytest.raises(E.EpisodeError, match=r"003\.png"):
        E.load_episodes(root)
