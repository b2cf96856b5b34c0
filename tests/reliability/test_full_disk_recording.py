"""Issue 36, class 16: a disk that fills up while a recording writes into the fixtures.

A recording writes two files that must agree: the cassette (or the embeddings sidecar) and the fixtures'
manifest entry that blesses it. The disk fills up while the second of them is written (ENOSPC from its
fsync, made in this process); afterwards the cassette and the manifest are both as they were, no temporary
file is left, and `verify` passes -- the recording can simply be made again once there is room.
"""

from __future__ import annotations

import errno
import os
import shutil
from pathlib import Path

import pytest
from fault_support import cli_in_process
from reliability_support import FIXTURES, assert_one_line_error, fixture_subset, temp_leftovers

from vlmproprio.episodes import write_manifest

CASSETTE = "tiny-qwen2-vl"


def _fill_disk_at(monkeypatch, name: str) -> list[str]:
    """ENOSPC from the fsync of the temp file of ``name`` (the second file of the pair); the files fsynced."""
    real_fsync, synced = os.fsync, []

    def fsync(fd: int) -> None:
        target = os.path.basename(os.readlink(f"/proc/self/fd/{fd}"))
        synced.append(target)
        if target.startswith(f".{name}."):
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        real_fsync(fd)

    monkeypatch.setattr(os, "fsync", fsync)
    return synced


def _fixtures(tmp_path: Path, with_cassette: bool) -> Path:
    fixtures = fixture_subset(tmp_path / "fixtures", ["door_00"])
    if with_cassette:  # a cassette recorded earlier: the new recording merges into it
        (fixtures / "responses").mkdir()
        shutil.copy(FIXTURES / "responses" / f"{CASSETTE}.jsonl", fixtures / "responses")
        write_manifest(fixtures)
    return fixtures


def _state(fixtures: Path) -> dict[str, bytes]:
    return {p.relative_to(fixtures).as_posix(): p.read_bytes() for p in sorted(fixtures.rglob("*")) if p.is_file()}


@pytest.mark.parametrize("with_cassette", [False, True], ids=["new cassette", "merged into a cassette"])
def test_a_full_disk_while_exporting_a_cassette_changes_neither_file(tmp_path, monkeypatch, with_cassette, figures):
    fixtures = _fixtures(tmp_path, with_cassette)
    cache = tmp_path / "cache"
    proc = cli_in_process(["cassette", "import", FIXTURES / "responses" / f"{CASSETTE}.jsonl", "--cache-dir", cache])
    assert proc.returncode == 0, proc.stderr
    if with_cassette:  # a recording that adds an answer the cassette lacks
        text = (fixtures / "responses" / f"{CASSETTE}.jsonl").read_text().splitlines()
        (fixtures / "responses" / f"{CASSETTE}.jsonl").write_text("\n".join(text[:-1]) + "\n")
        write_manifest(fixtures)
    before = _state(fixtures)
    synced = _fill_disk_at(monkeypatch, "manifest.json")
    proc = cli_in_process(
        ["cassette", "export", "--model", CASSETTE, "--fixtures", fixtures, "--cache-dir", cache, "--no-embed"]
    )
    monkeypatch.undo()
    assert any(s.startswith(".manifest.json.") for s in synced), synced  # the disk filled at the second file
    assert_one_line_error(proc, "manifest.json", "No space left on device")
    assert _state(fixtures) == before  # neither the cassette nor the manifest changed
    assert temp_leftovers(fixtures) == []
    proc = cli_in_process(["verify", "--fixtures", fixtures])
    assert proc.returncode == 0, proc.stderr
    # with room again, the same command records it
    proc = cli_in_process(
        ["cassette", "export", "--model", CASSETTE, "--fixtures", fixtures, "--cache-dir", cache, "--no-embed"]
    )
    assert proc.returncode == 0, proc.stderr
    assert cli_in_process(["verify", "--fixtures", fixtures]).returncode == 0
    figures("full disk while recording", attempts=1, half_written=0)


def test_a_full_disk_while_writing_a_sidecar_changes_neither_file(tmp_path, monkeypatch, figures):
    from vlmproprio.embeddings.sidecar import read_sidecar, write_sidecar
    from vlmproprio.io import WriteError

    fixtures = _fixtures(tmp_path, with_cassette=True)
    shipped = read_sidecar(FIXTURES / "responses" / f"{CASSETTE}.embeddings.npz")
    before = _state(fixtures)
    _fill_disk_at(monkeypatch, "manifest.json")
    with pytest.raises(WriteError, match=r"manifest\.json"):
        write_sidecar(fixtures / "responses" / f"{CASSETTE}.embeddings.npz", shipped.model, shipped.sections.values())
    monkeypatch.undo()
    assert _state(fixtures) == before
    assert temp_leftovers(fixtures) == []
    assert cli_in_process(["verify", "--fixtures", fixtures]).returncode == 0
    figures("full disk while recording", attempts=1, half_written=0)
