"""Item 7, secrets: an API key planted in the environment is used, and never written anywhere.

One module-scoped run builds everything a user's session could leave behind, in a sandbox: ``vlmproprio
--debug run`` in record mode through the openai backend (the planted key in OPENAI_API_KEY, sent to the
loopback server as its bearer token), with logging at DEBUG for every library (``logging.basicConfig`` and
the SDK's OPENAI_LOG=debug), transient faults (429, 500, reset, malformed) whose error bodies echo the
request's Authorization header back, a second live run from the cache, a run that fails on a server
echoing the key in every error (the traceback is printed: --debug), a cassette export, and ``vlmproprio
score`` with its embedding cache. Then every file under the sandbox (run directory, response cache, its
SQLite database and WAL, the values inside it decompressed, the cassette, the manifest, scores, the
embedding cache, HOME, TMPDIR) and every captured stdout/stderr is searched for the key and for pieces of it;
then the run's HTML report (page, Markdown, figures) is written and searched too.
"""

from __future__ import annotations

import contextlib
import secrets
import sqlite3
import zlib
from pathlib import Path

import pytest
from reliability_support import all_files, caption_responder, cli, cli_env, fixture_subset

from vlmproprio.testing import openai_server
from vlmproprio.testing.openai_server import FakeOpenAIServer

pytest.importorskip("openai", reason="the openai backend needs the openai SDK (pip install 'vlmproprio[openai]')")

MODEL = "openai:fake-vlm"
DEBUG_LOGGING = "import logging, sys\nlogging.basicConfig(level=logging.DEBUG, stream=sys.stderr)"


def _echoing_handler(make_handler):
    """The loopback server's handler, but its error bodies quote the request's Authorization header back, as a
    careless proxy might: the key then comes back to us inside an error message."""

    def make(server):
        base = make_handler(server)

        class Echoing(base):
            def _send_json(self, status, payload, headers=None):
                if status >= 400:
                    auth = self.headers.get("Authorization", "")
                    payload = {"error": {"message": f"rejected request with Authorization: {auth}", "type": "x"}}
                super()._send_json(status, payload, headers)

        return Echoing

    return make


@pytest.fixture(scope="module")
def secret_run(tmp_path_factory):
    """Every artefact of a recorded, cached, failed, exported and scored session, plus all its console output."""
    root = tmp_path_factory.mktemp("secrets")
    key = "sk-planted-" + secrets.token_hex(24)
    fixtures = fixture_subset(root / "fixtures", ["door_00"])
    for d in ("work", "home", "tmp"):
        (root / d).mkdir()
    env = cli_env(
        OPENAI_API_KEY=key,
        OPENAI_LOG="debug",
        HOME=str(root / "home"),
        TMPDIR=str(root / "tmp"),
        VLMPROPRIO_CACHE=str(root / "work" / "cache-root"),
    )
    run_dir, cache = root / "work" / "run", root / "work" / "cache"
    outputs: list[str] = []
    saw_key = []

    def vp(*args, **kw):
        proc = cli(["--debug", *args], cwd=root / "work", env=env, python_prelude=DEBUG_LOGGING, **kw)
        outputs.extend([proc.stdout, proc.stderr])
        return proc

    monkeypatch = pytest.MonkeyPatch()
    monkeypatch.setattr(openai_server, "_make_handler", _echoing_handler(openai_server._make_handler))
    try:
        with FakeOpenAIServer(responder=caption_responder) as server:
            for fault in ("429", "500", "reset", "malformed"):
                server.inject(fault, retry_after=0.05)
            common = ["--model", MODEL, "--base-url", server.base_url, "--fixtures", fixtures, "--episodes", "door_00"]
            common += ["--conditions", "none,both", "--frame-stride", "2", "--no-progress", "--cache-dir", cache]
            recorded = vp("run", *common, "--mode", "record", "--out", run_dir, "--concurrency", "1")
            assert recorded.returncode == 0, recorded.stderr[-3000:]
            again = vp("run", *common, "--mode", "live", "--out", root / "work" / "run2")
            assert again.returncode == 0, again.stderr[-3000:]
            server.inject("500", times=1000, retry_after=0.05)
            failed = vp(
                # --mode live: the default (auto) would replay the cassette the record run just wrote
                "run",
                *common[:-2],
                "--mode",
                "live",
                "--cache-dir",
                root / "work" / "cache-fail",
                "--out",
                root / "work" / "run3",
            )
            assert failed.returncode != 0 and "Traceback" in failed.stderr  # --debug: the full traceback
            assert "rejected request with Authorization" in failed.stderr  # the echo came back ...
            saw_key = [r.headers.get("authorization") for r in server.chat_requests]
        exported = vp("cassette", "export", "--model", MODEL, "--cache", cache, "--out", root / "work" / "export.jsonl")
        assert exported.returncode == 0, exported.stderr[-3000:]
        scored = vp("score", run_dir, "--embedding-cache", root / "work" / "embeddings", timeout=600)
        assert scored.returncode == 0, scored.stderr[-3000:]
    finally:
        monkeypatch.undo()
    return {"root": root, "key": key, "run_dir": run_dir, "outputs": outputs, "saw_key": saw_key, "env": env}


def _needles(key: str) -> list[bytes]:
    """The key, its random part, and a 16-character piece of that (a truncated or reformatted copy)."""
    token = key.removeprefix("sk-planted-")
    return [key.encode(), token.encode(), token[:16].encode(), token[-16:].encode()]


def _sqlite_values(path: Path) -> list[bytes]:
    """Every key and value stored in a diskcache database, decompressed where they are zlib'd JSON."""
    out = []
    with sqlite3.connect(path) as conn:
        for row in conn.execute("SELECT key, value FROM Cache"):
            for blob in row:
                if isinstance(blob, (bytes, memoryview)):
                    blob = bytes(blob)
                    out.append(blob)
                    with contextlib.suppress(zlib.error):  # keys and values are zlib'd JSON; others are not
                        out.append(zlib.decompress(blob))
                elif blob is not None:
                    out.append(str(blob).encode())
    return out


def _leaks(paths: list[Path], needles: list[bytes]) -> list[str]:
    found = []
    for p in paths:
        data = p.read_bytes()
        blobs = [data] + (_sqlite_values(p) if p.name == "cache.db" else [])
        if any(n in b for n in needles for b in blobs):
            found.append(str(p))
    return found


def test_the_planted_key_was_really_used(secret_run):
    assert f"Bearer {secret_run['key']}" in secret_run["saw_key"]  # else this suite would prove nothing


def test_secret_never_written_to_any_file_or_console(secret_run, figures):
    root, key = secret_run["root"], secret_run["key"]
    files = all_files(root)
    kinds = {p.name for p in files}
    # the session left every kind of artefact the check is about
    assert {"run.json", "cache.db", "openai_fake-vlm.jsonl", "manifest.json", "export.jsonl", "rows.csv"} <= kinds
    assert any(p.suffix == ".json" and "transcripts" in p.parts for p in files)
    assert any("embeddings" in p.parts for p in files)
    needles = _needles(key)
    assert _leaks(files, needles) == []
    console = "\n".join(secret_run["outputs"])
    assert "DEBUG" in console and len(console) > 10_000  # logging really was at DEBUG
    assert not any(n.decode() in console for n in needles)
    figures(
        "secrets",
        files_searched=len(files),
        bytes_searched=sum(p.stat().st_size for p in files),
        console_chars_searched=len(console),
        leaks=0,
    )


def test_secret_absent_from_html_report(secret_run):
    """The report of the secret run (captions, run settings, server URL on the page) is searched too."""
    from vlmproprio.report import write_report

    index = write_report(secret_run["run_dir"])
    assert index.is_file()
    files = all_files(secret_run["run_dir"])
    assert any(p.suffix == ".html" for p in files)
    assert _leaks(files, _needles(secret_run["key"])) == []
