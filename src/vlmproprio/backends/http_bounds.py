"""Bounds on what an OpenAI-compatible server can make the openai backend wait for and read.

The SDK's HTTP library (httpx, or httpx2 in newer SDKs) applies ``timeout`` to each socket operation, so a server
that sends one byte a second (in the headers or the body) is never timed out, and it inflates a compressed body
without limit. This module gives the SDK a client of its own HTTP library in which every request is bounded:

* a deadline (``--timeout``) over one whole attempt: connecting, sending the request, reading the headers and
  the whole body. Each socket operation's timeout is cut to what is left of it, so a trickling server ends in the
  same timeout (``ReadTimeout``) as a silent one, which the SDK retries with its usual backoff;
* a limit on the bytes of a body, counted after decompression (gzip and deflate are asked for and decoded here,
  in bounded steps, so a small compressed body never expands in memory past the limit);
* a 2xx body must be UTF-8 and nest at most ``max_depth`` levels (a completion nests about 6): anything else is
  refused before the SDK parses it, where it would raise ``UnicodeDecodeError`` or ``RecursionError``.

A refused body raises the HTTP library's ``DecodingError`` (a request error the SDK retries like a reset
connection), caused by :class:`ResponseRefused`, whose ``reason`` names the limit; :func:`refusal_of` finds it in
the SDK's exception. Proxies from the environment are bounded too: the client builds every transport, direct or
proxied, through the same wrapper.
"""

from __future__ import annotations

import functools
import json
import sys
import threading
import time
import zlib
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from types import ModuleType
from typing import Any

from vlmproprio.io import MAX_JSON_DEPTH

# A chat completion is a few KB; with logprobs of a long answer a few MB. 32 MiB is far above any of them and
# small enough to hold twice (the HTTP library keeps the body, the 2xx check reads it once more).
DEFAULT_MAX_RESPONSE_BYTES = 32 * 1024 * 1024
# the encodings asked for (Accept-Encoding) and decoded here; any other one a server sends is refused
DECODED_ENCODINGS = ("gzip", "deflate")
_WRITE_PIECE = 64 * 1024  # a request body is sent in pieces, each with what is left of the deadline


class ResponseRefused(Exception):
    """A response not read to the end or not used: over the size limit, not UTF-8, nested too deeply, or in a
    content encoding not decoded. ``reason`` says which, with the limit."""

    def __init__(self, reason: str) -> None:
        super().__init__(reason)
        self.reason = reason


@dataclass(frozen=True)
class Bounds:
    """What one attempt of one request may cost: seconds in all, and bytes of body after decompression."""

    timeout_s: float
    max_bytes: int = DEFAULT_MAX_RESPONSE_BYTES
    max_depth: int = MAX_JSON_DEPTH


def refusal_of(exc: BaseException | None) -> ResponseRefused | None:
    """The ResponseRefused behind an exception the SDK raised (it wraps the HTTP library's, which wraps ours)."""
    seen: set[int] = set()
    while exc is not None and id(exc) not in seen:
        if isinstance(exc, ResponseRefused):
            return exc
        seen.add(id(exc))
        exc = exc.__cause__ or exc.__context__
    return None


# ---------------------------------------------------------------------------------------------- the deadline


class _Deadline(threading.local):
    """The monotonic time the current attempt of this thread must end by (None: no bounded request running).
    The HTTP library does a request's socket operations in the thread that sent it, so a thread-local is the
    request's own; each attempt (the SDK's retries included) sets it anew."""

    at: float | None = None


_DEADLINE = _Deadline()
_DEADLINE_KEY = "vlmproprio_deadline"  # in a request's extensions: the monotonic time its attempt ends by


def _left(timeout: float | None, expired: type[Exception]) -> float | None:
    """``timeout`` cut to what is left of this thread's deadline; ``expired`` (a timeout of the HTTP core
    library, which the SDK retries as a timeout) once nothing is left."""
    at = _DEADLINE.at
    if at is None:
        return timeout
    left = at - time.monotonic()
    if left <= 0:
        raise expired("no complete response before the request's deadline (--timeout bounds the whole request)")
    return left if timeout is None else min(timeout, left)


class _DeadlineStream:
    """A network stream whose every operation ends by the deadline."""

    def __init__(self, inner: Any, core: ModuleType) -> None:
        self._inner = inner
        self._core = core

    def read(self, max_bytes: int, timeout: float | None = None) -> bytes:
        return self._inner.read(max_bytes, _left(timeout, self._core.ReadTimeout))

    def write(self, buffer: bytes, timeout: float | None = None) -> None:
        # one write of a large body would wait up to the whole timeout for each partial send
        for start in range(0, len(buffer), _WRITE_PIECE):
            piece = buffer[start : start + _WRITE_PIECE]
            self._inner.write(piece, _left(timeout, self._core.WriteTimeout))

    def close(self) -> None:
        self._inner.close()

    def start_tls(self, ssl_context: Any, server_hostname: str | None = None, timeout: float | None = None):
        tls = self._inner.start_tls(ssl_context, server_hostname, _left(timeout, self._core.ConnectTimeout))
        return _DeadlineStream(tls, self._core)

    def get_extra_info(self, info: str) -> Any:
        return self._inner.get_extra_info(info)


class _DeadlineBackend:
    """The HTTP core library's network backend, with streams that keep the deadline."""

    def __init__(self, inner: Any, core: ModuleType) -> None:
        self._inner = inner
        self._core = core

    def connect_tcp(self, host, port, timeout=None, local_address=None, socket_options=None):
        t = _left(timeout, self._core.ConnectTimeout)
        return _DeadlineStream(self._inner.connect_tcp(host, port, t, local_address, socket_options), self._core)

    def connect_unix_socket(self, path, timeout=None, socket_options=None):
        t = _left(timeout, self._core.ConnectTimeout)
        return _DeadlineStream(self._inner.connect_unix_socket(path, t, socket_options), self._core)

    def sleep(self, seconds: float) -> None:
        self._inner.sleep(seconds)


def _arm(transport: Any) -> ModuleType:
    """Put the deadline into ``transport``'s connection pool; returns the HTTP core module it uses.

    The HTTP library has no option for a network backend, but its pool (``httpcore.ConnectionPool`` and the
    proxy pools, which subclass it) takes one and keeps it in ``_network_backend`` for every new connection."""
    pool = getattr(transport, "_pool", None)
    inner = getattr(pool, "_network_backend", None)
    if inner is None:
        raise RuntimeError(
            f"{type(transport).__module__}.{type(transport).__name__} has no connection pool with a network backend: "
            "this version of the HTTP library cannot bound --timeout; install the versions in pyproject.toml"
        )
    core = sys.modules[type(pool).__module__.split(".")[0]]
    if not isinstance(inner, _DeadlineBackend):
        pool._network_backend = _DeadlineBackend(inner, core)
    return core


# ---------------------------------------------------------------------------------------------- the body


def _refuse(http: ModuleType, reason: str) -> Exception:
    exc = http.DecodingError(reason)
    exc.__cause__ = ResponseRefused(reason)
    return exc


def _over(max_bytes: int, what: str) -> str:
    return f"its body is larger than the {max_bytes:,}-byte limit{what} (max_response_bytes)"


def _inflate(chunks: Iterable[bytes], encoding: str, max_bytes: int, http: ModuleType) -> Iterator[bytes]:
    """Decode one content encoding in steps of at most ``max_bytes`` (plus one) out: a bomb is refused after
    the limit, never expanded whole."""
    z = zlib.decompressobj(zlib.MAX_WBITS | 16 if encoding == "gzip" else zlib.MAX_WBITS)
    raw_deflate_tried = encoding != "deflate"  # "deflate" is zlib-wrapped by the RFC, raw from some servers
    started, total = False, 0
    for chunk in chunks:
        data = chunk
        while data and not z.eof:
            try:
                out = z.decompress(data, max_bytes - total + 1)
            except zlib.error as exc:
                if started or raw_deflate_tried:
                    raise _refuse(http, f"its {encoding} body is damaged ({exc})")  # noqa: B904 (the cause is ours)
                z, raw_deflate_tried = zlib.decompressobj(-zlib.MAX_WBITS), True
                continue
            started, data = True, z.unconsumed_tail
            total += len(out)
            if total > max_bytes:
                raise _refuse(http, _over(max_bytes, f" once {encoding}-decoded"))
            if out:
                yield out
    tail = z.flush(max_bytes - total + 1)
    if total + len(tail) > max_bytes:
        raise _refuse(http, _over(max_bytes, f" once {encoding}-decoded"))
    if tail:
        yield tail


def body_problem(body: bytes, max_depth: int) -> str | None:
    """Why a 2xx body is refused before the SDK parses it (None: let the SDK parse it, and the backend retry it
    as malformed when it is not a completion): not UTF-8, or JSON nested deeper than ``max_depth``."""
    try:
        text = body.decode("utf-8")
    except UnicodeDecodeError as exc:
        return f"its body is not UTF-8 (byte 0x{body[exc.start]:02x} at offset {exc.start:,})"
    if text.count("[") + text.count("{") <= max_depth:  # cannot nest deeper than it has brackets
        return None
    deep = f"its JSON body nests deeper than {max_depth} levels"
    try:
        doc = json.loads(text)
    except RecursionError:
        return deep
    except ValueError:
        return None
    stack: list[tuple[object, int]] = [(doc, 1)]  # iteratively: a walk must not recurse either
    while stack:
        node, depth = stack.pop()
        if depth > max_depth:
            return deep
        children = node.values() if isinstance(node, dict) else node if isinstance(node, list) else ()
        stack.extend((c, depth + 1) for c in children if isinstance(c, dict | list))
    return None


class _BoundedBody:
    """A response body, decoded and counted as it is read, checked at its end when it is a 2xx one."""

    def __init__(self, raw: Any, encodings: list[str], bounds: Bounds, check: bool, http: ModuleType) -> None:
        self._raw = raw
        self._encodings = encodings
        self._bounds = bounds
        self._check = check
        self._http = http

    def __iter__(self) -> Iterator[bytes]:
        limit = self._bounds.max_bytes
        stream: Iterable[bytes] = self._raw
        for encoding in reversed(self._encodings):  # listed in the order they were applied
            stream = _inflate(stream, encoding, limit, self._http)
        total, kept = 0, []
        for piece in stream:
            total += len(piece)
            if total > limit:
                raise _refuse(self._http, _over(limit, ""))
            if self._check:
                kept.append(piece)
            yield piece
        if self._check and (problem := body_problem(b"".join(kept), self._bounds.max_depth)):
            raise _refuse(self._http, problem)
        _DEADLINE.at = None

    def close(self) -> None:
        _DEADLINE.at = None
        self._raw.close()  # the library's own stream: it always has close()


@functools.cache
def _body_type(http: ModuleType) -> type:
    """_BoundedBody as the library's SyncByteStream, which its client insists a response stream is."""
    return type("BoundedBody", (_BoundedBody, http.SyncByteStream), {})


class BoundedTransport:
    """An HTTP transport of the SDK's library with the deadline armed in its pool and every body bounded."""

    def __init__(self, inner: Any, bounds: Bounds) -> None:
        _arm(inner)
        self._inner = inner
        self._bounds = bounds
        self._http = sys.modules[type(inner).__module__.split(".")[0]]

    def handle_request(self, request: Any) -> Any:
        # this attempt's deadline; a retry is a new request and gets its own, but a redirect's request carries
        # the extensions of the one it follows, so the hops of one attempt share one deadline
        at = request.extensions.get(_DEADLINE_KEY)
        if at is None:
            at = request.extensions[_DEADLINE_KEY] = time.monotonic() + self._bounds.timeout_s
        _DEADLINE.at = at
        request.headers["Accept-Encoding"] = ", ".join(DECODED_ENCODINGS)
        response = self._inner.handle_request(request)
        try:
            return self._bounded(response)
        except BaseException:
            response.close()
            raise

    def _bounded(self, response: Any) -> Any:
        http, limit = self._http, self._bounds.max_bytes
        declared = response.headers.get("content-length", "").strip()
        if declared.isdigit() and int(declared) > limit:
            raise _refuse(http, f"it announced a {int(declared):,}-byte body, over the {limit:,}-byte limit")
        named = [e.strip().lower() for e in response.headers.get("content-encoding", "").split(",")]
        encodings = [e for e in named if e and e != "identity"]
        for e in encodings:
            if e not in DECODED_ENCODINGS:
                raise _refuse(
                    http, f"its body is in the {e!r} content encoding (asked for {', '.join(DECODED_ENCODINGS)})"
                )
        # decoded here, so the library must not decode again (nor check a length it no longer has)
        headers = [(k, v) for k, v in response.headers.raw if k.lower() not in (b"content-encoding", b"content-length")]
        body = _body_type(http)(response.stream, encodings, self._bounds, 200 <= response.status_code < 300, http)
        return http.Response(
            status_code=response.status_code, headers=headers, stream=body, extensions=response.extensions
        )

    def close(self) -> None:
        self._inner.close()

    def __enter__(self) -> BoundedTransport:
        self._inner.__enter__()
        return self

    def __exit__(self, *exc: Any) -> None:
        self._inner.__exit__(*exc)


def bounded_http_client(bounds: Bounds) -> Any:
    """A client of the SDK's own HTTP library, with the SDK's defaults (``openai.DefaultHttpxClient``), whose
    transports (direct, and each proxy the environment names) are all BoundedTransport."""
    import openai

    class BoundedClient(openai.DefaultHttpxClient):  # type: ignore[misc, valid-type]
        # the library's factories for its direct and proxy transports; the proxy map from the environment stays
        # the library's own (passing transport= instead would turn it off)
        def _init_transport(self, *args: Any, **kwargs: Any) -> Any:
            return BoundedTransport(super()._init_transport(*args, **kwargs), bounds)

        def _init_proxy_transport(self, *args: Any, **kwargs: Any) -> Any:
            return BoundedTransport(super()._init_proxy_transport(*args, **kwargs), bounds)

    return BoundedClient(timeout=bounds.timeout_s)
