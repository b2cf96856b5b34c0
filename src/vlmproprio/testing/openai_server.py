"""A small OpenAI-compatible chat-completions server on 127.0.0.1, for tests and benchmarks.

It is a real HTTP server (stdlib ``ThreadingHTTPServer`` in a background
thread), so the openai SDK talks to it exactly as it would to vLLM or the
OpenAI API. Answers are deterministic: by default a digest of the request
(model, messages, decoding settings), so equal requests get equal answers and
a test can compute the expected text with :func:`expected_answer`.

Faults are injected per request, first in first out::

    with FakeOpenAIServer(latency_s=0.2) as server:
        server.inject("429", times=2, retry_after=0.5)
        server.inject("malformed")
        client = openai.OpenAI(base_url=server.base_url, api_key="x")

Fault kinds: ``429`` (rate limit, with ``Retry-After``), ``500``, ``hang``
(no answer until the client gives up), ``reset`` (TCP reset before any
response), ``malformed`` (HTTP 200 whose body is not JSON) and ``empty``
(a valid completion with empty content). Valid completions that hold no
caption, as real servers send them: ``refusal`` (``message.refusal``, no
content), ``tool_calls`` (a tool call, ``finish_reason`` tool_calls),
``content_filter``, ``length`` (``finish_reason`` length with the answer
cut to nothing, the reasoning model's fate at a small token limit),
``empty_choice`` (a first choice without a message), ``reasoning_only``
(the answer in the reasoning field, content null) and ``other_model`` (the
answer, from a model with another name).

Hostile bodies, each a 200 the SDK would read to the end: ``trickle`` (the headers at once, then the body one
byte every ``trickle_s`` seconds), ``trickle_headers`` (the whole response so, from the status line on),
``gzip_bomb`` and ``deflate_bomb`` (a small compressed body that inflates to a completion of ``bomb_bytes``),
``huge`` (``bomb_bytes`` of completion sent as they are, chunked, with no Content-Length), ``non_utf8`` (a
completion with a Latin-1 byte in it) and ``deep_json`` (JSON nested ``deep_levels`` deep). Each trickle the
server sent, and whether the client read it to the end, is kept in :attr:`FakeOpenAIServer.trickles`
(the bodies are built in :mod:`vlmproprio.testing.hostile_bodies`).

Reasoning: ``reasoning=`` a function of the request body returns the text a
reasoning server (vLLM, SGLang with a reasoning parser) puts beside the
answer, in ``reasoning_field`` (``reasoning_content``, vLLM's newer
``reasoning``, or ``both``, as vLLM sent during its rename).

Credentials: with ``echo_credentials=True`` every answer and every error message quotes what the request
carried, as a careless proxy or debugging server would: the ``Authorization`` header, its credential, the
``user:password`` a Basic one decodes to and the password alone, the request path's query and its values.
A test of the secret scrubber then finds each encoding the client sent in what comes back.

Every request the server saw, with
its headers and body, is kept in :attr:`FakeOpenAIServer.requests`; nothing is
logged or written to disk.
"""

from __future__ import annotations

import base64
import hashlib
import json
import socket
import struct
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import Literal
from urllib.parse import parse_qsl, urlsplit

from vlmproprio.testing.hostile_bodies import HOSTILE_BODY_KINDS, Trickle, serve_hostile_body

FaultKind = Literal[
    "429",
    "500",
    "hang",
    "reset",
    "malformed",
    "empty",
    "refusal",
    "tool_calls",
    "content_filter",
    "length",
    "empty_choice",
    "reasoning_only",
    "other_model",
    "trickle",
    "trickle_headers",
    "gzip_bomb",
    "deflate_bomb",
    "huge",
    "non_utf8",
    "deep_json",
]
# completions without a caption in them: valid JSON the SDK accepts, each as the servers that send it shape it
NO_CAPTION_KINDS: tuple[str, ...] = (
    "refusal",
    "tool_calls",
    "content_filter",
    "length",
    "empty_choice",
    "reasoning_only",
    "other_model",
)
FAULT_KINDS: tuple[str, ...] = (
    "429",
    "500",
    "hang",
    "reset",
    "malformed",
    "empty",
    *NO_CAPTION_KINDS,
    *HOSTILE_BODY_KINDS,
)
OTHER_MODEL = "some-other-model"


@dataclass(frozen=True)
class Fault:
    kind: FaultKind
    retry_after: float | None = None  # seconds, sent as Retry-After with a 429 or 500


@dataclass(frozen=True)
class RecordedRequest:
    method: str
    path: str
    headers: dict[str, str]  # names in lower case
    body: dict | None
    fault: str | None  # the fault served to this request, None when answered normally
    received_at: float


def request_digest(body: dict) -> str:
    """sha256 over what determines an answer: model, messages and decoding settings."""
    keep = {k: body.get(k) for k in ("model", "messages", "temperature", "seed", "max_tokens")}
    blob = json.dumps(keep, sort_keys=True, separators=(",", ":"), ensure_ascii=False)
    return hashlib.sha256(blob.encode("utf-8")).hexdigest()


def expected_answer(body: dict) -> str:
    """The default deterministic answer for a chat-completions request body."""
    n_images = sum(
        1
        for m in body.get("messages", [])
        if isinstance(m.get("content"), list)
        for part in m["content"]
        if part.get("type") == "image_url"
    )
    return f"echo {request_digest(body)[:16]} ({n_images} images)"


Responder = Callable[[dict], str]


class FakeOpenAIServer:
    """OpenAI-compatible ``/v1/chat/completions`` (and ``/v1/models``) on an ephemeral loopback port."""

    def __init__(
        self,
        *,
        latency_s: float = 0.0,
        hang_s: float = 30.0,
        responder: Responder | None = None,
        reasoning: Responder | None = None,
        reasoning_field: str = "reasoning_content",
        host: str = "127.0.0.1",
        port: int = 0,
        echo_credentials: bool = False,
        trickle_s: float = 0.05,
        bomb_bytes: int = 200 * 1024 * 1024,
        deep_levels: int = 100_000,
    ) -> None:
        if reasoning_field not in ("reasoning_content", "reasoning", "both"):
            raise ValueError(f"reasoning_field must be reasoning_content, reasoning or both, not {reasoning_field!r}")
        self.latency_s = latency_s
        self.hang_s = hang_s
        self.responder: Responder = responder or expected_answer
        self.reasoning = reasoning
        self.reasoning_field = reasoning_field
        self.echo_credentials = echo_credentials
        self.trickle_s = trickle_s  # seconds between the bytes of a trickle
        self.bomb_bytes = bomb_bytes  # what a bomb or a huge body holds, once inflated
        self.deep_levels = deep_levels  # nesting of deep_json
        self.trickles: list[Trickle] = []
        self._faults: deque[Fault] = deque()
        self._requests: list[RecordedRequest] = []
        self._lock = threading.Lock()
        self._closing = threading.Event()
        self._in_flight = 0
        self.max_in_flight = 0  # the most chat requests handled at the same moment
        self._httpd = ThreadingHTTPServer((host, port), _make_handler(self))
        self._httpd.daemon_threads = True
        self._httpd.block_on_close = False  # a hanging handler must not block close()
        self._thread: threading.Thread | None = None

    # -------------------------------------------------------------------------------- lifecycle
    @property
    def port(self) -> int:
        return self._httpd.server_address[1]

    @property
    def base_url(self) -> str:
        return f"http://127.0.0.1:{self.port}/v1"

    def start(self) -> FakeOpenAIServer:
        if self._thread is None:
            self._thread = threading.Thread(target=self._httpd.serve_forever, name="fake-openai", daemon=True)
            self._thread.start()
        return self

    def close(self) -> None:
        self._closing.set()
        if self._thread is not None:
            self._httpd.shutdown()
        self._httpd.server_close()
        if self._thread is not None:
            self._thread.join(timeout=5)
            self._thread = None

    def __enter__(self) -> FakeOpenAIServer:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.close()

    # -------------------------------------------------------------------------------- faults and records
    def inject(self, kind: FaultKind, times: int = 1, *, retry_after: float | None = None) -> None:
        """Serve ``kind`` to the next ``times`` chat requests (after any faults already queued)."""
        if kind not in FAULT_KINDS:
            raise ValueError(f"unknown fault {kind!r}; choose from {', '.join(FAULT_KINDS)}")
        with self._lock:
            self._faults.extend(Fault(kind, retry_after) for _ in range(times))

    def clear_faults(self) -> None:
        with self._lock:
            self._faults.clear()

    @property
    def requests(self) -> list[RecordedRequest]:
        with self._lock:
            return list(self._requests)

    @property
    def chat_requests(self) -> list[RecordedRequest]:
        return [r for r in self.requests if r.path.endswith("/chat/completions")]

    def _enter(self) -> None:
        with self._lock:
            self._in_flight += 1
            self.max_in_flight = max(self.max_in_flight, self._in_flight)

    def _leave(self) -> None:
        with self._lock:
            self._in_flight -= 1

    def _next_fault(self) -> Fault | None:
        with self._lock:
            return self._faults.popleft() if self._faults else None

    def _record(self, rec: RecordedRequest) -> None:
        with self._lock:
            self._requests.append(rec)

    def _trickled(self, trickle: Trickle) -> None:
        with self._lock:
            self.trickles.append(trickle)


def _completion(body: dict, text: str) -> dict:
    prompt_words = sum(
        len(str(part.get("text", "")).split())
        for m in body.get("messages", [])
        for part in (m["content"] if isinstance(m.get("content"), list) else [{"text": m.get("content", "")}])
    )
    return {
        "id": "chatcmpl-" + request_digest(body)[:24],
        "object": "chat.completion",
        "created": 0,
        "model": str(body.get("model", "")),
        "system_fingerprint": "fake-openai-server",
        "choices": [
            {
                "index": 0,
                "message": {"role": "assistant", "content": text},
                "finish_reason": "stop",
                "logprobs": None,
            }
        ],
        "usage": {
            "prompt_tokens": prompt_words,
            "completion_tokens": len(text.split()),
            "total_tokens": prompt_words + len(text.split()),
        },
    }


def credential_echo(headers: dict[str, str], path: str) -> str:
    """What a request carried that is a credential, quoted in every form it came in (``echo_credentials``)."""
    auth = headers.get("authorization", "")
    scheme, _, credential = auth.partition(" ")
    parts = [f"Authorization: {auth}", f"credential {credential}"]
    if scheme.lower() == "basic":
        try:
            decoded = base64.b64decode(credential, validate=True).decode("utf-8")
        except (ValueError, UnicodeDecodeError):
            decoded = ""
        parts += [f"decoded {decoded}", f"password {decoded.partition(':')[2]}"]
    query = urlsplit(path).query
    if query:
        parts += [f"query {query}", "values " + " ".join(v for _, v in parse_qsl(query))]
    return "[credentials seen: " + "; ".join(parts) + "]"


def _headers(handler: BaseHTTPRequestHandler) -> dict[str, str]:
    return {k.lower(): v for k, v in handler.headers.items()}  # HTTP header names are case-insensitive


_MODELS = {"object": "list", "data": [{"id": "fake", "object": "model", "owned_by": "me"}]}
# A body cut off mid-JSON, as a proxy dropping the connection would leave it.
_MALFORMED = b'{"id": "chatcmpl-broken", "choices": [{"index": 0, "message": {"conte'
# status, message and error type of the injected HTTP errors
_ERRORS = {
    "429": (429, "rate limited (injected)", "rate_limit"),
    "500": (500, "internal error (injected)", "server_error"),
}


class _Handler(BaseHTTPRequestHandler):
    """The request handler; ``fake`` (set per server by ``_make_handler``) holds the faults and records."""

    protocol_version = "HTTP/1.1"  # keep-alive, like real servers; every response has Content-Length
    fake: FakeOpenAIServer

    def setup(self) -> None:
        super().setup()
        # headers and body go out in two writes; with Nagle's algorithm the second waits for the client's
        # delayed ACK (~40 ms per request on Linux). Real servers (uvicorn, vLLM) turn it off too.
        self.connection.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)

    def handle(self) -> None:
        try:
            super().handle()
        except (ConnectionResetError, BrokenPipeError):  # a client that hung up (e.g. on a bomb): not an error here
            self.close_connection = True

    def log_message(self, format: str, *args) -> None:
        """Silent: request lines may carry anything, and tests want clean output."""

    # ------------------------------------------------------------------------ responses
    def _send_json(self, status: int, payload: object, headers: dict[str, str] | None = None) -> None:
        data = json.dumps(payload).encode("utf-8")
        self._send_bytes(status, data, headers)

    def _send_bytes(self, status: int, data: bytes, headers: dict[str, str] | None = None) -> None:
        self.send_response(status)
        self.send_header("Content-Type", "application/json")
        self.send_header("Content-Length", str(len(data)))
        for k, v in (headers or {}).items():
            self.send_header(k, v)
        self.end_headers()
        try:
            self.wfile.write(data)
        except OSError:  # the client hung up (a bomb it stopped reading): nothing to print, as a real server
            self.close_connection = True

    def _send_error(self, status: int, message: str, kind: str, headers: dict[str, str] | None = None) -> None:
        if self.fake.echo_credentials:
            message = f"{message} {credential_echo(_headers(self), self.path)}"
        self._send_json(status, {"error": {"message": message, "type": kind}}, headers=headers)

    def _not_found(self) -> None:
        self._send_error(404, f"no route {self.path}", "not_found")

    def _reset(self) -> None:
        # SO_LINGER with a zero timeout turns close() into a TCP RST: the client sees "connection reset".
        self.connection.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
        self.close_connection = True
        self.rfile.close()
        self.connection.close()

    # ------------------------------------------------------------------------ requests
    def _record(self, method: str, body: dict | None, fault: Fault | None = None) -> None:
        kind = fault.kind if fault else None
        self.fake._record(RecordedRequest(method, self.path, _headers(self), body, kind, time.time()))

    def _read_body(self):
        """The request's JSON body, None when there is none or it is not JSON."""
        length = int(self.headers.get("Content-Length") or 0)
        raw = self.rfile.read(length) if length else b""
        try:
            return json.loads(raw.decode("utf-8")) if raw else None
        except (UnicodeDecodeError, ValueError):
            return None

    def do_GET(self) -> None:
        self._record("GET", None)
        if self.path.rstrip("/").endswith("/v1/models"):
            self._send_json(200, _MODELS)
        else:
            self._not_found()

    def do_POST(self) -> None:
        self.fake._enter()
        try:
            self._post()
        finally:
            self.fake._leave()

    def _post(self) -> None:
        body = self._read_body()
        if not self.path.rstrip("/").endswith("/v1/chat/completions"):  # served under /v1, as vLLM and OpenAI do
            self._record("POST", body)
            self._not_found()
            return
        fault = self.fake._next_fault()
        self._record("POST", body, fault)
        if not isinstance(body, dict) or not isinstance(body.get("messages"), list):
            self._send_error(400, "body must be JSON with 'messages'", "invalid")
            return
        if self.fake.latency_s > 0 and self.fake._closing.wait(self.fake.latency_s):
            return
        if fault is None:
            self._send_json(200, self._with_reasoning(body, _completion(body, self._answer(body))))
        elif fault.kind in NO_CAPTION_KINDS:
            doc = _completion(body, self._answer(body))
            self._send_json(200, _no_caption(fault.kind, self._with_reasoning(body, doc)))
        else:
            self._serve_fault(fault, body)

    def _answer(self, body: dict) -> str:
        text = self.fake.responder(body)
        return f"{text} {credential_echo(_headers(self), self.path)}" if self.fake.echo_credentials else text

    def _with_reasoning(self, body: dict, doc: dict) -> dict:
        if self.fake.reasoning is not None and isinstance(doc.get("choices"), list) and doc["choices"]:
            field = self.fake.reasoning_field
            names = ("reasoning_content", "reasoning") if field == "both" else (field,)
            text = self.fake.reasoning(body)
            for name in names:
                doc["choices"][0]["message"][name] = text
        return doc

    def _serve_fault(self, fault: Fault, body: dict) -> None:
        if fault.kind in _ERRORS:
            headers = {} if fault.retry_after is None else {"Retry-After": f"{fault.retry_after:g}"}
            self._send_error(*_ERRORS[fault.kind], headers=headers)
        elif fault.kind == "malformed":
            self._send_bytes(200, _MALFORMED)
        elif fault.kind == "empty":
            self._send_json(200, _completion(body, ""))
        elif fault.kind == "reset":
            self._reset()
        elif fault.kind == "hang":
            self.fake._closing.wait(self.fake.hang_s)
            self.close_connection = True
        else:
            serve_hostile_body(self, fault.kind, _completion(body, self.fake.responder(body)))


def _no_caption(kind: str, doc: dict) -> dict:
    """``doc`` (a normal completion) turned into one of NO_CAPTION_KINDS."""
    choice = doc["choices"][0]
    message = choice["message"]
    if kind == "refusal":
        message.update(content=None, refusal="I'm sorry, I can't help with that.")
    elif kind == "tool_calls":
        call = {"id": "call_0", "type": "function", "function": {"name": "describe_frames", "arguments": "{}"}}
        message.update(content=None, tool_calls=[call])
        choice["finish_reason"] = "tool_calls"
    elif kind == "content_filter":
        message["content"] = None
        choice["finish_reason"] = "content_filter"
    elif kind == "length":
        message["content"] = ""
        choice["finish_reason"] = "length"
    elif kind == "empty_choice":
        doc["choices"] = [{"index": 0, "finish_reason": None}]
    elif kind == "reasoning_only":
        message["reasoning_content"], message["content"] = message["content"], None
    elif kind == "other_model":
        doc["model"] = OTHER_MODEL
    return doc


def _make_handler(server: FakeOpenAIServer) -> type[BaseHTTPRequestHandler]:
    """A handler class bound to ``server`` (tests wrap this to serve a variant)."""
    return type("Handler", (_Handler,), {"fake": server})
