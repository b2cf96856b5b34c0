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

from extras import needs_openai
from vlmproprio.testing import openai_server
from vlmproprio.testing.openai_server import FakeOpenAIServer

# checked, not imported: collecting this module on every xdist worker must not cost the SDK's ~1 CPU s
pytestmark = needs_openai

MODEL = "openai:fake-vlm"
DEBUG_LOGGING = "import logging, sys\nlogging.basicConfig(level=logging.DEBUG, stream=sys.stderr)"


def _echoing_handler(make_handler):
    """The loopback server's handler, but its error bodies quote the request's Authorization header back, as a
    careless proxy might: the key then comes back to us inside an error message."""

    def make(server):
        base = make_handler(server)

        class Echoing(base):
            def _send_json(self, status, payload, headers=None):
                auth = self.headers.get("Authorization", "")
                if status >= 400:
                    payload = {"error": {"message": f"rejected request with Authorization: {auth}", "type": "x"}}
                elif isinstance(payload, dict) and payload.get("choices"):
                    # a normal answer that quotes the request's headers (such a quote once reached the cassette)
                    message = payload["choices"][0]["message"]
                    token = auth.split()[-1] if auth else ""
                    message["content"] = (
                        f"{message['content']} [debug: Authorization: {auth}; token {token}; "
                        f"url https://u:{token}@example.org/v1?token={token}]"
                    )
                super()._send_json(status, payload, headers)

        return Echoing

    return make


@pytest.fixture(scope="module")
def secret_run(tmp_path_factory):
    """Every artefact of a recorded, cached, failed, exported and scored session, plus all its console output."""
    root = tmp_path_factory.mktemp("secrets")
    key = "sk-planted-" + secrets.token_hex(24)
    # a second key under a variable name the scrubber only knows from --api-key-env, and URL credentials
    other_key = "planted2-" + secrets.token_hex(20)
    url_pass, url_token = "urlpass-" + secrets.token_hex(12), "urltoken-" + secrets.token_hex(12)
    fixtures = fixture_subset(root / "fixtures", ["door_00"])
    for d in ("work", "home", "tmp"):
        (root / d).mkdir()
    env = cli_env(
        OPENAI_API_KEY=key,
        OPENAI_LOG="debug",
        HOME=str(root / "home"),
        TMPDIR=str(root / "tmp"),
        VLMPROPRIO_CACHE=str(root / "work" / "cache-root"),
        VLM_SERVER_CRED=other_key,
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
            other = vp(
                *("run", *common[:-2], "--cache-dir", root / "work" / "cache-other", "--out", root / "work" / "run4"),
                *("--api-key-env", "VLM_SERVER_CRED", "--max-new-tokens", "7", "--mode", "live"),
            )
            assert other.returncode != 0  # the server still fails every request: the errors echo the second key
            saw_key = [r.headers.get("authorization") for r in server.chat_requests]
        # credentials in the server URL, on a port where nothing listens: the error line names the server
        nowhere = f"http://vlmuser:{url_pass}@127.0.0.1:9/v1?token={url_token}&api_key={url_token}"
        unreachable = vp(
            *("run", "--model", MODEL, "--base-url", nowhere, "--fixtures", fixtures, "--episodes", "door_00"),
            *("--conditions", "none", "--frame-stride", "3", "--no-progress", "--timeout", "1", "--mode", "live"),
            *("--cache-dir", root / "work" / "cache-nowhere", "--out", root / "work" / "run5"),
            timeout=300,
        )
        assert unreachable.returncode != 0
        exported = vp("cassette", "export", "--model", MODEL, "--cache", cache, "--out", root / "work" / "export.jsonl")
        assert exported.returncode == 0, exported.stderr[-3000:]
        scored = vp("score", run_dir, "--embedding-cache", root / "work" / "embeddings", timeout=600)
        assert scored.returncode == 0, scored.stderr[-3000:]
    finally:
        monkeypatch.undo()
    return {
        "root": root,
        "key": key,
        "others": [other_key, url_pass, url_token],
        "run_dir": run_dir,
        "outputs": outputs,
        "saw_key": saw_key,
        "env": env,
    }


def _needles(key: str, others: list[str] = ()) -> list[bytes]:
    """The key, its random part, and a 16-character piece of that (a truncated or reformatted copy); the other
    planted secrets and their random parts."""
    token = key.removeprefix("sk-planted-")
    out = [key.encode(), token.encode(), token[:16].encode(), token[-16:].encode()]
    for o in others:
        out += [o.encode(), o.split("-", 1)[1].encode()]
    return out


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
    assert f"Bearer {secret_run['others'][0]}" in secret_run["saw_key"]  # the key of --api-key-env too


def test_answers_quoting_the_key_reached_transcripts_masked(secret_run):
    """The server's answers quoted the Authorization header: the transcripts hold the answers, masked."""
    texts = [p.read_text() for p in (secret_run["run_dir"] / "transcripts").rglob("*.json")]
    assert texts and any("Authorization: Bearer ***" in t for t in texts)


def test_secret_never_written_to_any_file_or_console(secret_run, figures):
    root, key = secret_run["root"], secret_run["key"]
    files = all_files(root)
    kinds = {p.name for p in files}
    # the session left every kind of artefact the check is about
    assert {"run.json", "cache.db", "openai_fake-vlm.jsonl", "manifest.json", "export.jsonl", "rows.csv"} <= kinds
    assert any(p.suffix == ".json" and "transcripts" in p.parts for p in files)
    assert any("embeddings" in p.parts for p in files)
    needles = _needles(key, secret_run["others"])
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
    assert _leaks(files, _needles(secret_run["key"], secret_run["others"])) == []
