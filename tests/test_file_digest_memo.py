"""Fixture files hashed once per process (issue 17): a file that changes is hashed again, a fresh one is not
remembered, and a corrupt file is still named by load_episodes after an earlier clean load."""

from __future__ import annotations

import hashlib
import json
import time

import pytest

import vlmproprio.digests as D
import vlmproprio.episodes as E


def test_a_changed_file_is_hashed_again(tmp_path, monkeypatch):
    monkeypatch.setattr(E, "_FILE_DIGESTS", {})
    monkeypatch.setattr(D, "SETTLED_NS", -1)  # remember even a file written just now
    f = tmp_path / "a.bin"
    f.write_bytes(b"x" * 1000)
    assert E._file_sha256(f) == hashlib.sha256(b"x" * 1000).hexdigest()
    assert len(E._FILE_DIGESTS) == 1
    time.sleep(0.02)  # past the timestamps' granularity
    f.write_bytes(b"y" * 1000)  # same size, same path and inode
    assert E._file_sha256(f) == hashlib.sha256(b"y" * 1000).hexdigest()


def test_a_fresh_file_is_not_remembered(tmp_path, monkeypatch):
    monkeypatch.setattr(E, "_FILE_DIGESTS", {})
    f = tmp_path / "b.bin"
    f.write_bytes(b"z")
    assert E._file_sha256(f) == hashlib.sha256(b"z").hexdigest()
    assert E._FILE_DIGESTS == {}


def test_corruption_after_a_clean_load_is_named(tmp_path, monkeypatch):
    import shutil
    from pathlib import Path

    fixtures = Path(__file__).resolve().parents[1] / "fixtures"
    root = tmp_path / "fx"
    (root / "episodes").mkdir(parents=True)
    shutil.copytree(fixtures / "episodes" / "door_00", root / "episodes" / "door_00")
    manifest = E.read_manifest(fixtures)
    files = {k: v for k, v in manifest.items() if k.startswith("episodes/door_00/")}
    (root / "manifest.json").write_text(json.dumps({"format_version": 1, "files": files}))
    monkeypatch.setattr(E, "_FILE_DIGESTS", {})
    monkeypatch.setattr(D, "SETTLED_NS", -1)
    E.load_episodes(root)
    assert E._FILE_DIGESTS  # remembered
    time.sleep(0.02)
    png = root / "episodes" / "door_00" / "frames" / "003.png"
    data = bytearray(png.read_bytes())
    data[100] ^= 1
    png.write_bytes(bytes(data))
    with pytest.raises(E.EpisodeError, match=r"003\.png"):
        E.load_episodes(root)
