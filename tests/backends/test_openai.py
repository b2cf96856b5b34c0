"""The OpenAI-compatible backend against a real HTTP server on 127.0.0.1, with injected faults."""

from __future__ import annotations

import base64
import contextlib
import logging
import secrets
import threading

import pytest

from extras import needs_openai
from vlmproprio.answering import Answerer
from vlmproprio.backends.base import BackendError
from vlmproprio.cache import ResponseCache, canonical_json
from vlmproprio.chat import GenerationConfig, RequestTag
from vlmproprio.testing.openai_server import FakeOpenAIServer, expected_answer

# checked, not imported: collecting this module on every xdist worker must not cost the SDK's ~1 CPU s
pytestmark = needs_openai

KEY_ENV = "VLMPROPRIO_TEST_OPENAI_KEY"


@pytest.fixture
def server():
    with FakeOpenAIServer() as s:
        yield s


@pytest.fixture
def api_key(monkeypatch):
    key = "sk-planted-" + secrets.token_hex(16)
    monkeypatch.setenv(KEY_ENV, key)
    return key


def backend_for(server: FakeOpenAIServer, **kw):
    from vlmproprio.backends.openai import OpenAIBackend

    kw.setdefault("api_key_env", KEY_ENV)
    kw.setdefault("max_retries", 2)
    kw.setdefault("timeout_s", 5.0)
    return OpenAIBackend("gpt-4o", base_url=server.base_url, **kw)


def requests_for(request_factory, png_factory, n: int = 3):
    return [
        request_factory(
            f"# Process 2\nGroup {i}: describe.",
            (png_factory(i), png_factory(100 + i)),
            system="You caption robot episodes.",
            config=GenerationConfig(max_new_tokens=32, seed=7),
            tag=RequestTag("door_01", "both", "p2", i),
        )
        for i in range(n)
    ]


def test_request_format_and_answers(server, api_key, request_factory, png_factory):
    reqs = requests_for(request_factory, png_factory, 1)
    answer = backend_for(server).generate(reqs)[0]
    (seen,) = server.chat_requests
    body = seen.body
    assert answer.text == expected_answer(body)
    assert seen.headers["authorization"] == f"Bearer {api_key}"
    assert (body["model"], body["temperature"], body["seed"], body["max_tokens"]) == ("gpt-4o", 0.0, 7, 32)
    system, user = body["messages"]
    assert system == {"role": "system", "content": "You caption robot episodes."}
    urls = [p["image_url"]["url"] for p in user["content"] if p["type"] == "image_url"]
    assert [base64.b64decode(u.split(",", 1)[1]) for u in urls] == [png_factory(0), png_factory(100)]
    assert all(u.startswith("data:image/png;base64,") for u in urls)
    assert user["content"][-1] == {"type": "text", "text": "# Process 2\nGroup 0: describe."}
    assert answer.meta.backend == "openai" and answer.meta.model_id == "gpt-4o"
    assert answer.meta.completion_tokens == len(answer.text.split())


def test_concurrency_is_bounded_and_order_kept(api_key, request_factory, png_factory):
    """Proved by counts, not a clock: the server holds each answer until 4 requests are in flight together (a
    barrier), so the 8 requests are answered only if the backend keeps 4 going at once; and they were sent from
    4 threads, each waiting for its answer, so never more than 4 were in flight. A slow machine only makes it
    slower."""
    reqs = requests_for(request_factory, png_factory, 8)
    together = threading.Barrier(4, timeout=60)  # the timeout only ends a hang: a broken barrier fails the test

    def answer_when_four_are_in(body: dict) -> str:
        together.wait()
        return expected_answer(body)

    with FakeOpenAIServer(responder=answer_when_four_are_in) as server:
        backend = backend_for(server, concurrency=4, max_retries=0)
        senders, one = [], backend._one

        def sent_from_a_thread(request):
            senders.append(threading.current_thread().name)
            return one(request)

        backend._one = sent_from_a_thread
        answers = backend.generate(reqs)
        bodies = {canonical_json(r.body["messages"]): r.body for r in server.chat_requests}
    assert len(bodies) == 8 and not together.broken
    assert server.max_in_flight == 4 and len(senders) == 8 and len(set(senders)) == 4
    for r, a in zip(reqs, answers, strict=True):  # in request order, whatever order they finished in
        group = r.tag.group
        body = next(
            b for b in bodies.values() if b["messages"][1]["content"][-1]["text"].endswith(f"{group}: describe.")
        )
        assert a.text == expected_answer(body)


@pytest.mark.parametrize("fault", ["500", "reset", "malformed", "hang"])
def test_transient_faults_are_retried(server, api_key, request_factory, png_factory, fault):
    server.hang_s = 3.0
    server.inject(fault)
    answer = backend_for(server, timeout_s=0.5).generate(requests_for(request_factory, png_factory, 1))[0]
    seen = server.chat_requests
    assert [r.fault for r in seen] == [fault, None]
    assert answer.text == expected_answer(seen[-1].body)
    assert answer.meta.extra["malformed_retries"] == (1 if fault == "malformed" else 0)


def test_429_honours_retry_after(server, api_key, request_factory, png_factory):
    server.inject("429", retry_after=0.8)
    answer = backend_for(server).generate(requests_for(request_factory, png_factory, 1))[0]
    seen = server.chat_requests
    assert [r.fault for r in seen] == ["429", None]
    # the server's record of arrivals: the retry came as told, not after the default 0.5 s backoff (a lower bound:
    # a busy machine only widens the gap)
    assert seen[1].received_at - seen[0].received_at >= 0.75
    assert answer.text == expected_answer(seen[-1].body)


@pytest.mark.parametrize(
    ("fault", "match"),
    [
        ("500", r"HTTP 500 after 3 tries: internal error \(injected\)"),
        ("429", r"HTTP 429 after 3 tries.*lower --concurrency"),
        ("malformed", r"malformed responses \(3 tries\)"),
        ("hang", r"did not answer within 0.3 s \(3 tries\)"),
        ("reset", r"cannot reach http://127.0.0.1:\d+/v1 \(\w+, 3 tries\)"),
    ],
)
def test_persistent_faults_end_in_a_clear_error(server, api_key, request_factory, png_factory, fault, match):
    server.hang_s = 2.0
    server.inject(fault, times=10, retry_after=0.05)
    with pytest.raises(BackendError, match=match) as info:
        backend_for(server, max_retries=2, timeout_s=0.3, backoff_s=0.05).generate(
            requests_for(request_factory, png_factory, 1)
        )
    assert len(server.chat_requests) == 3  # one try + two retries, then it gives up
    assert "door_01" in str(info.value)  # names the request


def test_dead_server_fails_fast(api_key, request_factory, png_factory, monkeypatch):
    """Fast means one request's retries, not one per request: counted (the SDK's retries), not timed."""
    import openai._base_client as sdk

    retries, real_sleep = [], sdk.SyncAPIClient._sleep_for_retry

    def counted_sleep(self, **kwargs) -> None:
        retries.append(1)  # list.append is atomic: the four workers retry at once
        real_sleep(self, **kwargs)

    monkeypatch.setattr(sdk.SyncAPIClient, "_sleep_for_retry", counted_sleep)
    dead = FakeOpenAIServer()
    dead.close()  # nothing listens on its port any more
    reqs = requests_for(request_factory, png_factory, 20)
    with pytest.raises(BackendError, match=r"cannot reach http://127\.0\.0\.1:\d+/v1 \(ConnectError") as info:
        backend_for(dead, max_retries=2, concurrency=4).generate(reqs)
    assert "0 of 20 requests answered" in str(info.value)
    # the 4 requests in flight, and at most one more each a worker took before the batch stopped: not all 20
    assert len(retries) % 2 == 0 and 2 <= len(retries) <= 2 * 8


def test_server_dying_mid_run_keeps_what_was_answered(api_key, request_factory, png_factory, tmp_path):
    served = []

    def responder(body: dict) -> str:
        served.append(1)
        if len(served) == 4:
            server.inject("500", times=1000)  # from the fifth request on, the server is broken
        return expected_answer(body)

    reqs = requests_for(request_factory, png_factory, 8)
    with FakeOpenAIServer(responder=responder) as server, ResponseCache(tmp_path / "c") as cache:
        cached = Answerer(backend_for(server, concurrency=1, max_retries=0), mode="live", cache=cache)
        with pytest.raises(BackendError, match="4 of 8 requests answered"):
            cached.answer(reqs)
        assert len(cache) == 4
        server.clear_faults()
        answers = cached.answer(reqs)  # resumed: only the missing four go to the server
    assert [a.from_cache for a in answers] == [True] * 4 + [False] * 4
    assert len(served) == 8


def test_missing_key_is_a_clear_error(monkeypatch):
    from vlmproprio.backends.openai import OpenAIBackend

    monkeypatch.delenv(KEY_ENV, raising=False)
    with pytest.raises(BackendError, match=f"set the environment variable {KEY_ENV}"):
        OpenAIBackend("gpt-4o", api_key_env=KEY_ENV)
    # a local key-less server (vLLM) is fine without one
    assert OpenAIBackend("m", api_key_env=KEY_ENV, base_url="http://127.0.0.1:9/v1").identity()["model_id"] == "m"


def test_planted_api_key_never_reaches_any_file(api_key, request_factory, png_factory, tmp_path):
    log_path = tmp_path / "run.log"
    handler = logging.FileHandler(log_path)
    handler.setLevel(logging.DEBUG)
    root = logging.getLogger()
    old_level = root.level
    root.addHandler(handler)
    root.setLevel(logging.DEBUG)  # everything the SDK, httpx and we log, at the most verbose level
    try:
        reqs = requests_for(request_factory, png_factory, 4)
        with FakeOpenAIServer() as server, ResponseCache(tmp_path / "cache") as cache:
            for fault in ("429", "500", "malformed", "reset"):
                server.inject(fault, retry_after=0.05)
            backend = backend_for(server, max_retries=3, backoff_s=0.05)
            cached = Answerer(backend, mode="record", cache=cache, model="gpt-4o")
            answers = cached.answer(reqs)
            cassette = cached.export_cassette(tmp_path / "responses" / "gpt-4o.jsonl")
            server.inject("500", times=10)
            with pytest.raises(BackendError) as info:
                backend_for(server, max_retries=1, backoff_s=0.05).generate([request_factory("# Process 3\nx", ())])
            logging.getLogger("test").error("final error: %s | %r | %s", info.value, backend, backend.identity())
            logging.getLogger("test").error("answers: %s", [a.meta for a in answers])
            decoded = [canonical_json(cache._cache.get(k)) for k in cache]
            saw_key = [r.headers.get("authorization") for r in server.chat_requests]
    finally:
        root.removeHandler(handler)
        root.setLevel(old_level)
        handler.close()
    assert f"Bearer {api_key}" in saw_key  # the key was really used ...
    assert len(decoded) == 4 and cassette.exists() and log_path.stat().st_size > 0
    files = [p for p in tmp_path.rglob("*") if p.is_file()]
    leaked = [p for p in files if api_key.encode() in p.read_bytes()]
    assert leaked == []  # ... and is in no file: cache database, cassette, log
    assert not any(api_key in d for d in decoded)  # nor in the (compressed) cache values
    assert api_key not in str(info.value) and api_key not in repr(backend)


@contextlib.contextmanager
def status_server(status: int, body: dict):
    """A server on 127.0.0.1 that answers every POST with ``status`` and the JSON ``body``; yields its root URL."""
    import json
    from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

    class Answers(BaseHTTPRequestHandler):
        def do_POST(self):
            self.rfile.read(int(self.headers["Content-Length"]))
            data = json.dumps(body).encode()
            self.send_response(status)
            self.send_header("Content-Type", "application/json")
            self.send_header("Content-Length", str(len(data)))
            self.end_headers()
            self.wfile.write(data)

        def log_message(self, *args):
            pass

    httpd = ThreadingHTTPServer(("127.0.0.1", 0), Answers)
    threading.Thread(target=httpd.serve_forever, daemon=True).start()
    try:
        yield f"http://127.0.0.1:{httpd.server_address[1]}"
    finally:
        httpd.shutdown()
        httpd.server_close()


@pytest.mark.parametrize(
    "body",
    [
        {"error": {"message": "The prompt has 14489 tokens, but the model takes at most 4096", "code": 400}},
        {"detail": "The prompt has 14489 tokens, but the model takes at most 4096"},  # FastAPI (transformers serve)
        {
            "detail": [
                {"loc": ["body", "messages"], "msg": "The prompt has 14489 tokens, but the model takes at most 4096"}
            ]
        },
    ],
    ids=["openai", "fastapi", "fastapi-validation"],
)
def test_a_refused_request_shows_the_servers_reason(body, api_key, request_factory, png_factory):
    from vlmproprio.backends.openai import OpenAIBackend

    with status_server(400, body) as root:
        backend = OpenAIBackend("m", base_url=f"{root}/v1", api_key_env=KEY_ENV, max_retries=0, timeout_s=5.0)
        with pytest.raises(BackendError, match=r"answered HTTP 400: The prompt has 14489 tokens, but the model takes"):
            backend.generate(requests_for(request_factory, png_factory, 1))


def test_a_404_from_a_base_url_without_v1_asks_about_the_path(server, api_key, request_factory, png_factory):
    """vLLM, SGLang and transformers serve answer under /v1: a URL without it gets a 404 for every request."""
    from vlmproprio.backends.openai import OpenAIBackend

    root = server.base_url.removesuffix("/v1")
    backend = OpenAIBackend("gpt-4o", base_url=root, api_key_env=KEY_ENV, max_retries=0, timeout_s=5.0)
    with pytest.raises(BackendError, match=r"HTTP 404.*serve model 'gpt-4o' or does --base-url lack its /v1 path\?"):
        backend.generate(requests_for(request_factory, png_factory, 1))
    assert [r.path for r in server.requests] == ["/chat/completions"]  # asked once, at the path without /v1


def test_a_404_at_a_v1_url_asks_only_about_the_model(api_key, request_factory, png_factory):
    from vlmproprio.backends.openai import OpenAIBackend

    with status_server(404, {"error": {"message": "The model `m` does not exist.", "code": 404}}) as root:
        backend = OpenAIBackend("m", base_url=f"{root}/v1/", api_key_env=KEY_ENV, max_retries=0, timeout_s=5.0)
        with pytest.raises(BackendError, match=r"HTTP 404: The model `m` does not exist\.; does the server") as info:
            backend.generate(requests_for(request_factory, png_factory, 1))
        assert "serve model 'm'? (0 of 1" in str(info.value) and "/v1 path" not in str(info.value)


def test_the_thinking_switch_goes_to_the_server_as_chat_template_kwargs(server, api_key, request_factory, png_factory):
    """vLLM and SGLang read ``chat_template_kwargs``; it is sent only when --thinking was given (the OpenAI API
    itself refuses fields it does not know)."""
    from dataclasses import replace

    backend = backend_for(server)
    plain = requests_for(request_factory, png_factory, 1)[0]
    off = replace(plain, config=replace(plain.config, thinking=False))
    backend.generate([plain, off])
    bodies = [r.body for r in server.chat_requests]
    sent = sorted(repr(b.get("chat_template_kwargs")) for b in bodies)  # in flight together: any order
    assert sent == ["None", "{'enable_thinking': False}"]
