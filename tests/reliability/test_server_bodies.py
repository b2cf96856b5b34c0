"""Hostile response bodies from an OpenAI-compatible server (issue 36, items 9, 10 and 12).

* ``--timeout`` bounds a whole attempt: a server trickling its response one byte at a time, in the body or
  from the status line on, times out like a silent one (each byte alone arrives well within the timeout, so a
  per-read timeout never fires). Proved by the server's record: it never got to send the whole response.
* What is read from a server is bounded after decompression: a gzip or deflate body that inflates past
  ``max_response_bytes``, or a plain chunked body with no length that runs past it, is refused; nothing of it is
  cached. A compressed body under the limit is decoded and used.
* A 200 body that is not UTF-8, or JSON nested 100,000 deep, is not a traceback.

Each is retried like other faults (a transient one ends in the fault-free answer) and, when it persists, ends in
one error naming the server, the bound and the tries. The backend is checked with small bounds (a limit of
1 MiB, a 0.5 s timeout), then the CLI with its defaults, in one line and no traceback.
"""

from __future__ import annotations

import gzip
import json
import secrets
import zlib
from pathlib import Path

import pytest
from fault_support import cli_in_process, scaled_retry_backoff
from reliability_support import assert_one_line_error, cache_answers, caption_responder, fixture_subset

from extras import needs_openai
from vlmproprio.answering import Answerer
from vlmproprio.backends.base import BackendError
from vlmproprio.cache import ResponseCache
from vlmproprio.testing import openai_server
from vlmproprio.testing.openai_server import HOSTILE_BODY_KINDS, FakeOpenAIServer, expected_answer

pytestmark = needs_openai

KEY_ENV = "VLMPROPRIO_TEST_BODIES_KEY"
LIMIT = 1024 * 1024  # max_response_bytes of the backend tests
TIMEOUT = 0.5  # seconds; the trickle sends a byte every 0.02 s, so each read alone is quick
TRIES = 2
# what each kind's persistent error says, beside the server's URL and the tries
MESSAGES = {
    "trickle": f"did not answer within {TIMEOUT:g} s ({TRIES} tries)",
    "trickle_headers": f"did not answer within {TIMEOUT:g} s ({TRIES} tries)",
    "gzip_bomb": f"({TRIES} tries): its body is larger than the {LIMIT:,}-byte limit once gzip-decoded",
    "deflate_bomb": f"({TRIES} tries): its body is larger than the {LIMIT:,}-byte limit once deflate-decoded",
    "huge": f"({TRIES} tries): its body is larger than the {LIMIT:,}-byte limit",
    "non_utf8": f"({TRIES} tries): its body is not UTF-8 (byte 0xe9 at offset",
    "deep_json": f"({TRIES} tries): its JSON body nests deeper than 64 levels",
}


@pytest.fixture
def api_key(monkeypatch):
    monkeypatch.setenv(KEY_ENV, "sk-bodies-" + secrets.token_hex(8))


def hostile_server() -> FakeOpenAIServer:
    # a bomb of 8 MiB inflated (8 KiB sent) is 8 times the limit; the trickle would take ~8 s a response
    return FakeOpenAIServer(trickle_s=0.02, bomb_bytes=8 * LIMIT)


def backend_for(server: FakeOpenAIServer, **kw):
    from vlmproprio.backends.openai import OpenAIBackend

    kw = {"max_retries": TRIES - 1, "timeout_s": TIMEOUT, "backoff_s": 0.05, "max_response_bytes": LIMIT, **kw}
    return OpenAIBackend("fake-vlm", base_url=server.base_url, api_key_env=KEY_ENV, **kw)


def test_every_hostile_kind_is_checked_here():
    assert set(MESSAGES) == set(HOSTILE_BODY_KINDS)


@pytest.mark.parametrize("kind", HOSTILE_BODY_KINDS)
def test_a_persistent_hostile_body_ends_in_one_clear_error(api_key, request_factory, tmp_path, kind, figures):
    with hostile_server() as server, ResponseCache(tmp_path / "cache") as cache:
        server.inject(kind, times=10)
        answerer = Answerer(backend_for(server), mode="live", cache=cache)
        with pytest.raises(BackendError) as info:
            answerer.answer([request_factory()])
        message = str(info.value)
        assert server.base_url in message and MESSAGES[kind] in message, message
        assert "\n" not in message and "door_00" in message
        assert [r.fault for r in server.chat_requests] == [kind] * TRIES  # retried, then given up
        assert len(cache) == 0  # nothing of it accepted
        trickles = list(server.trickles)
    if kind.startswith("trickle"):
        # the client hung up on every try before the server could finish: the whole attempt was bounded
        assert trickles and all(not t.finished and t.sent < t.total for t in trickles), trickles
    figures("server bodies: persistent", kinds=1, one_line_errors=1, tracebacks=0, cached=0)


@pytest.mark.parametrize("kind", HOSTILE_BODY_KINDS)
def test_a_transient_hostile_body_is_retried(api_key, request_factory, kind, figures):
    with hostile_server() as server:
        server.inject(kind)
        (answer,) = backend_for(server).generate([request_factory()])
        seen = server.chat_requests
    assert [r.fault for r in seen] == [kind, None]
    assert answer.text == expected_answer(seen[-1].body)
    figures("server bodies: transient", kinds=1, survived=1)


@pytest.mark.parametrize("kind", ["gzip_bomb", "deflate_bomb", "huge"])
def test_a_body_under_the_limit_is_decoded_and_used(api_key, request_factory, kind):
    """A compressed (or long) completion below the limit is an answer: the bound refuses size, not encoding."""
    with FakeOpenAIServer(bomb_bytes=LIMIT // 2) as server:
        server.inject(kind)
        (answer,) = backend_for(server).generate([request_factory()])
        (seen,) = server.chat_requests
    assert answer.text == expected_answer(seen.body)  # the padding is spaces, stripped from the answer


def test_an_announced_length_over_the_limit_is_refused_before_reading(api_key, request_factory):
    announced = rf"announced a [\d,]+-byte body, over the {LIMIT:,}-byte limit"
    with (
        FakeOpenAIServer(responder=lambda body: "x" * (2 * LIMIT)) as server,
        pytest.raises(BackendError, match=announced),
    ):
        backend_for(server).generate([request_factory()])


_OK = json.dumps({"choices": [{"message": {"content": "ok"}}]}).encode("utf-8")
# other shapes of the same classes: (status, body, headers, what the error says; None: a usable answer "ok")
OTHER_SHAPES = {
    "brotli, never asked for": (200, _OK, {"Content-Encoding": "br"}, "in the 'br' content encoding"),
    "zstd, never asked for": (200, _OK, {"Content-Encoding": "zstd"}, "in the 'zstd' content encoding"),
    "damaged gzip": (200, gzip.compress(_OK)[:-12] + b"x" * 12, {"Content-Encoding": "gzip"}, "gzip body is damaged"),
    "gzip of a gzip bomb": (
        200,
        gzip.compress(gzip.compress(b" " * (4 * LIMIT))),
        {"Content-Encoding": "gzip, gzip"},
        "larger than the 1,048,576-byte limit once gzip-decoded",
    ),
    "a bomb in a 500": (500, gzip.compress(b" " * (4 * LIMIT)), {"Content-Encoding": "gzip"}, "once gzip-decoded"),
    "UTF-16 JSON": (200, _OK.decode().encode("utf-16"), {}, "not UTF-8 (byte 0xff at offset 0)"),
    "a lone surrogate encoded": (200, _OK.replace(b'"ok"', b'"o\xed\xa0\x80k"'), {}, "not UTF-8 (byte 0xed"),
    "objects 500 deep (parses, then walked)": (200, b'{"a":' * 500 + b"1" + b"}" * 500, {}, "deeper than 64 levels"),
    "gzip of gzip, small": (200, gzip.compress(gzip.compress(_OK)), {"Content-Encoding": "gzip, gzip"}, None),
    "raw deflate (no zlib header)": (200, zlib.compress(_OK)[2:-4], {"Content-Encoding": "deflate"}, None),
    "UTF-8 with a BOM": (200, b"\xef\xbb\xbf" + _OK, {}, None),
}


@pytest.mark.parametrize("shape", OTHER_SHAPES)
def test_other_shapes_of_the_same_classes(api_key, request_factory, monkeypatch, shape, figures):
    status, data, headers, refused = OTHER_SHAPES[shape]
    real_send = openai_server._Handler._send_bytes

    def send(self, _status, _data, _headers=None) -> None:  # every response of the server is this one
        real_send(self, status, data, {**(_headers or {}), **headers})

    monkeypatch.setattr(openai_server._Handler, "_send_bytes", send)
    with FakeOpenAIServer() as server:
        if refused is None:
            (answer,) = backend_for(server).generate([request_factory()])
            assert answer.text == "ok"
            figures("server bodies: other shapes", refused_and_named=0, answered=1)
            return
        with pytest.raises(BackendError) as info:
            backend_for(server).generate([request_factory()])
    message = str(info.value)
    assert f"{server.base_url} sent responses that were refused ({TRIES} tries)" in message and refused in message
    figures("server bodies: other shapes", refused_and_named=1, answered=0)


def test_the_hops_of_a_redirect_share_one_deadline(api_key, request_factory, monkeypatch, figures):
    """A server that redirects to itself, a little slowly each time, cannot stretch one try to 20 hops."""
    hops = []

    def redirect_slowly(self) -> None:
        self._read_body()
        hops.append(self.path)
        if not self.fake._closing.wait(0.3):  # each hop well within the timeout on its own
            self.send_response(307)
            self.send_header("Location", self.path)
            self.send_header("Content-Length", "0")
            self.end_headers()

    monkeypatch.setattr(openai_server._Handler, "_post", redirect_slowly)
    with FakeOpenAIServer() as server, pytest.raises(BackendError, match=r"did not answer within 1 s \(1 tries\)"):
        backend_for(server, timeout_s=1.0, max_retries=0).generate([request_factory()])
    assert 1 <= len(hops) < 10  # about 1 s / 0.3 s of them, not the library's 20 redirects
    figures("server bodies: other shapes", refused_and_named=1, answered=0)


def test_a_proxy_from_the_environment_is_bounded_too(api_key, request_factory, monkeypatch, figures):
    """HTTP_PROXY's transport is the library's own too (built from the environment): it gets the same bounds. The
    loopback server is the proxy here (it answers the proxied URL's path), the API host does not exist."""
    for name in ("NO_PROXY", "no_proxy", "ALL_PROXY", "all_proxy", "HTTPS_PROXY", "https_proxy", "http_proxy"):
        monkeypatch.delenv(name, raising=False)
    with hostile_server() as proxy:
        proxy.inject("trickle", times=10)
        monkeypatch.setenv("HTTP_PROXY", f"http://127.0.0.1:{proxy.port}")
        from vlmproprio.backends.openai import OpenAIBackend

        backend = OpenAIBackend(
            "fake-vlm",
            base_url="http://api.vlmproprio.invalid/v1",
            api_key_env=KEY_ENV,
            max_retries=TRIES - 1,
            timeout_s=TIMEOUT,
            backoff_s=0.05,
        )
        with pytest.raises(BackendError, match=MESSAGES["trickle"].replace("(", r"\(").replace(")", r"\)")):
            backend.generate([request_factory()])
        seen, trickles = proxy.chat_requests, list(proxy.trickles)
    assert [r.fault for r in seen] == ["trickle"] * TRIES and seen[0].path.startswith("http://api.vlmproprio.invalid/")
    assert trickles and not any(t.finished for t in trickles)
    figures("server bodies: other shapes", refused_and_named=1, answered=0)


def test_the_deadline_covers_each_try_not_the_whole_call(api_key, request_factory):
    """A slow but steady answer within the timeout still arrives; the SDK's retries each get the whole timeout."""
    with FakeOpenAIServer(latency_s=0.1) as server:
        server.inject("hang")
        server.hang_s = 2.0
        (answer,) = backend_for(server, timeout_s=1.0).generate([request_factory()])
        seen = server.chat_requests
    assert [r.fault for r in seen] == ["hang", None] and answer.text == expected_answer(seen[-1].body)


# ---------------------------------------------------------------------------------------------- through the CLI

MODEL = "openai:fake-vlm"


@pytest.fixture(scope="module")
def fixtures(tmp_path_factory) -> Path:
    return fixture_subset(tmp_path_factory.mktemp("server-bodies") / "fixtures", ["door_00"])


@pytest.mark.parametrize("kind", HOSTILE_BODY_KINDS)
def test_the_cli_names_a_hostile_server_in_one_line(fixtures, tmp_path, monkeypatch, kind, figures):
    """The run's defaults (5 tries, the 32 MiB limit), --timeout 0.5: one error line, no traceback, no answer kept."""
    from vlmproprio.backends.http_bounds import DEFAULT_MAX_RESPONSE_BYTES

    counts = scaled_retry_backoff(monkeypatch, 0.1)
    out = tmp_path / "run"
    with FakeOpenAIServer(
        responder=caption_responder, trickle_s=0.05, bomb_bytes=DEFAULT_MAX_RESPONSE_BYTES + 1
    ) as server:
        server.inject(kind, times=10_000)
        args = ["run", "--model", MODEL, "--base-url", server.base_url, "--fixtures", fixtures, "--conditions", "none"]
        args += ["--frame-stride", "2", "--no-progress", "--out", out, "--cache-dir", tmp_path / "cache"]
        proc = cli_in_process([*args, "--timeout", "0.5", "--concurrency", "1"])
        tries = len(server.chat_requests)
    expected = "did not answer within 0.5 s (5 tries)" if kind.startswith("trickle") else "were refused (5 tries)"
    assert_one_line_error(proc, server.base_url, expected)
    # one request's tries, and at most one more request the worker took from the queue before the run stopped
    assert tries in (5, 10) and counts["retries"] == tries // 5 * 4
    assert cache_answers(tmp_path / "cache") == {}
    figures("server bodies: CLI", kinds=1, one_line_errors=1, tracebacks=0, answers_kept=0)
