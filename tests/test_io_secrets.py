"""vlmproprio.io (atomic writes, one-line write errors, bounded JSON) and vlmproprio.secrets (the scrubber)."""

from __future__ import annotations

import errno
import json
import os
import sqlite3

import pytest

from vlmproprio.errors import VlmproprioError
from vlmproprio.io import (
    MAX_JSON_DEPTH,
    JSONLoadError,
    WriteError,
    atomic_write_text,
    load_json,
    loads_json,
    writing,
)
from vlmproprio.secrets import register_secret_env, scrub, scrub_obj, secret_values


@pytest.mark.parametrize(
    ("text", "hidden"),
    [
        ("see http://alice:s3cr3t-pass@host:8000/v1 now", "s3cr3t-pass"),
        ("GET /v1?token=abcdef123456&x=1", "abcdef123456"),
        ("url https://h/v1?foo=1&api_key=KEYVALUE99", "KEYVALUE99"),
        ("Authorization: Bearer sk-live-abcdefgh", "sk-live-abcdefgh"),
        ('{"authorization": "Basic dXNlcjpwYXNz"}', "dXNlcjpwYXNz"),
        ("the header was bearer tok_ABCDEFGH1234", "tok_ABCDEFGH1234"),
    ],
)
def test_patterns_are_masked(text, hidden):
    out = scrub(text)
    assert hidden not in out and "***" in out
    assert scrub(out) == out  # idempotent


def test_environment_keys_are_masked_and_clean_text_is_untouched(monkeypatch):
    monkeypatch.setenv("OPENAI_API_KEY", "sk-planted-1234567890abcdef")
    monkeypatch.setenv("MY_VLM_CRED", "credential-value-42")
    monkeypatch.setenv("RUN_SEED_KEY", "12345678")  # digits only: never treated as a secret
    text = "answer: sk-planted-1234567890abcdef and credential-value-42; 0.12345678"
    assert "credential-value-42" in scrub(text)  # not known as a secret yet
    register_secret_env("MY_VLM_CRED")
    out = scrub(text)
    assert "sk-planted" not in out and "credential-value-42" not in out and "0.12345678" in out
    clean = "The robot opens the door; F1 0.75 at threshold 0.65 (key frame 3)."
    assert scrub(clean) is clean or scrub(clean) == clean
    assert scrub_obj({"a": [text, 1.5, None]})["a"][0] == out


def test_the_secret_set_follows_the_environment_between_calls(monkeypatch):
    # the secrets are computed once and reused: a variable set, changed or removed after a scrub must count
    text = "echo: late-token-value-77 and changed-token-value-88"
    monkeypatch.delenv("LATE_SERVICE_TOKEN", raising=False)
    assert scrub(text) == text and "late-token-value-77" not in secret_values()
    monkeypatch.setenv("LATE_SERVICE_TOKEN", "late-token-value-77")
    assert "late-token-value-77" not in scrub(text) and "late-token-value-77" in secret_values()
    assert "late-token-value-77" not in scrub_obj({"k": [text]})["k"][0]
    monkeypatch.setenv("LATE_SERVICE_TOKEN", "changed-token-value-88")
    out = scrub(text)
    assert "late-token-value-77" in out and "changed-token-value-88" not in out
    monkeypatch.delenv("LATE_SERVICE_TOKEN")
    assert scrub(text) == text
    monkeypatch.setenv("LATE_PLAIN_NAME", "registered-later-99")
    assert "registered-later-99" in scrub("x registered-later-99")
    register_secret_env("LATE_PLAIN_NAME")  # a name registered after a scrub counts from then on
    assert "registered-later-99" not in scrub("x registered-later-99")


def test_deep_json_is_one_line_naming_the_file(tmp_path):
    for text in ("[" * 100_000, "[" * (MAX_JSON_DEPTH + 1) + "]" * (MAX_JSON_DEPTH + 1), '{"a": '):
        path = tmp_path / "doc.json"
        path.write_text(text)
        with pytest.raises(JSONLoadError) as info:
            load_json(path)
        assert str(path) in str(info.value) and "\n" not in str(info.value)
    assert loads_json("[" * MAX_JSON_DEPTH + "]" * MAX_JSON_DEPTH, "ok") == loads_json("[" * 64 + "]" * 64, "x")
    with pytest.raises(JSONLoadError, match="more than the 10 allowed"):
        loads_json(json.dumps(list(range(20))), "big", max_bytes=10)


def test_a_failed_atomic_write_keeps_the_old_file_and_leaves_no_temp(tmp_path, monkeypatch):
    path = tmp_path / "out.json"
    atomic_write_text(path, "old\n")

    def no_space(fd):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(os, "fsync", no_space)
    with pytest.raises(WriteError, match=r"cannot write .*out\.json: No space left on device \(ENOSPC\)"):
        atomic_write_text(path, "new\n")
    assert path.read_text() == "old\n" and sorted(p.name for p in tmp_path.iterdir()) == ["out.json"]


def test_sqlite_full_is_a_write_error_and_other_sqlite_errors_are_not(tmp_path):
    conn = sqlite3.connect(tmp_path / "db.sqlite")
    conn.execute("CREATE TABLE t (x BLOB)")
    conn.commit()
    pages = conn.execute("PRAGMA page_count").fetchone()[0]
    conn.execute(f"PRAGMA max_page_count = {pages}")
    with pytest.raises(WriteError, match="database or disk is full"), writing(tmp_path / "db.sqlite"):
        conn.execute("INSERT INTO t VALUES (?)", (b"x" * 100_000,))
    with pytest.raises(sqlite3.OperationalError), writing(tmp_path):  # a bug, not a write failure: unchanged
        conn.execute("SELECT * FROM no_such_table")
    assert issubclass(WriteError, VlmproprioError)
