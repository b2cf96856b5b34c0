"""The hostile response bodies of the fake OpenAI server (``FakeOpenAIServer.inject``): 200s that must not be
read to the end or used, as a hostile or broken server sends them.

``trickle`` (the headers at once, then the body one byte every ``trickle_s`` seconds), ``trickle_headers`` (the
whole response so, from the status line on), ``gzip_bomb`` and ``deflate_bomb`` (a small compressed body that
inflates to a completion of ``bomb_bytes``), ``huge`` (``bomb_bytes`` of completion sent as they are, chunked,
with no Content-Length), ``non_utf8`` (a completion with a Latin-1 byte in it) and ``deep_json`` (JSON nested
``deep_levels`` deep). Each closes its connection after it (``Connection: close``).
"""

from __future__ import annotations

import functools
import json
import zlib
from dataclasses import dataclass

# 200s whose body must not be read to the end or used: too slow, too big once inflated, not UTF-8, too deep
HOSTILE_BODY_KINDS: tuple[str, ...] = (
    "trickle",
    "trickle_headers",
    "gzip_bomb",
    "deflate_bomb",
    "huge",
    "non_utf8",
    "deep_json",
)


@dataclass(frozen=True)
class Trickle:
    """One trickled response: bytes sent of all it had, and whether the client read it all (else it hung up)."""

    kind: str
    sent: int
    total: int
    finished: bool


def serve_hostile_body(handler, kind: str, doc: dict) -> None:
    """Answer ``handler``'s request (a BaseHTTPRequestHandler of the fake server) with the hostile ``kind`` of
    ``doc``, the completion it would have sent."""
    # the client may hang up mid-body: the connection is closed after it, and says so (Connection: close), so
    # the client never sends its retry on a connection this end is closing (a lost try, seen as a reset)
    close = {"Connection": "close"}
    if kind in ("trickle", "trickle_headers"):
        data = json.dumps(doc).encode("utf-8")
        head = f"HTTP/1.1 200 OK\r\nContent-Type: application/json\r\nContent-Length: {len(data)}\r\n"
        _trickle(handler, kind, (head + "Connection: close\r\n\r\n").encode("ascii"), data)
    elif kind in ("gzip_bomb", "deflate_bomb"):
        encoding = kind.split("_")[0]
        bomb = _bomb(doc, handler.fake.bomb_bytes, encoding)
        handler._send_bytes(200, bomb, {"Content-Encoding": encoding, **close})
    elif kind == "huge":
        _send_chunked(handler, _padded(doc, handler.fake.bomb_bytes))
    elif kind == "non_utf8":
        doc["choices"][0]["message"]["content"] += " caf\u00e9"
        latin1 = json.dumps(doc, ensure_ascii=False).encode("utf-8").replace("\u00e9".encode(), b"\xe9")
        handler._send_bytes(200, latin1, close)
    elif kind == "deep_json":
        n = handler.fake.deep_levels
        handler._send_bytes(200, b'{"id": "chatcmpl-deep", "choices": ' + b"[" * n + b"]" * n + b"}", close)


def _trickle(handler, kind: str, head: bytes, data: bytes) -> None:
    """``head`` at once and ``data`` a byte at a time (for trickle_headers, all of it a byte at a time)."""
    handler.close_connection = True
    slow = head + data if kind == "trickle_headers" else data
    sent = 0
    try:
        if kind == "trickle":
            handler.wfile.write(head)
            handler.wfile.flush()
        for i in range(len(slow)):
            if handler.fake._closing.wait(handler.fake.trickle_s):
                break
            handler.wfile.write(slow[i : i + 1])
            handler.wfile.flush()
            sent = i + 1
    except OSError:  # the client hung up: what it did is in the record
        pass
    handler.fake._trickled(Trickle(kind, sent, len(slow), sent == len(slow)))


def _send_chunked(handler, pieces) -> None:
    handler.close_connection = True
    handler.send_response(200)
    handler.send_header("Content-Type", "application/json")
    handler.send_header("Transfer-Encoding", "chunked")
    handler.send_header("Connection", "close")
    handler.end_headers()
    try:
        for piece in pieces:
            handler.wfile.write(f"{len(piece):x}\r\n".encode("ascii") + piece + b"\r\n")
        handler.wfile.write(b"0\r\n\r\n")
    except OSError:  # the client stopped reading
        pass


_PAD = "\u0000PAD\u0000"


def _split_padded(doc: dict) -> tuple[bytes, bytes]:
    """``doc`` as JSON bytes before and after the end of its answer, where the padding goes."""
    doc["choices"][0]["message"]["content"] += _PAD
    before, after = json.dumps(doc).split(json.dumps(_PAD)[1:-1])
    return before.encode("utf-8"), after.encode("utf-8")


def _pieces(before: bytes, after: bytes, size: int, piece: int = 1024 * 1024):
    """``before``, spaces, ``after``: ``size`` bytes in all, in pieces of ``piece``, never all in memory."""
    yield before
    left = max(0, size - len(before) - len(after))
    while left > 0:
        n = min(piece, left)
        yield b" " * n
        left -= n
    yield after


def _padded(doc: dict, size: int):
    """``doc`` as JSON bytes of about ``size``, its answer padded with spaces (the answer, once stripped, is
    still the one asked for), in pieces."""
    return _pieces(*_split_padded(doc), size)


def _bomb(doc: dict, size: int, encoding: str) -> bytes:
    """A gzip or deflate (zlib) body that inflates to a ``size``-byte completion: ~1/1000 of it."""
    return _compressed(*_split_padded(doc), size, encoding)


@functools.lru_cache(maxsize=8)  # a retried request gets the same bomb: made once, not at every try
def _compressed(before: bytes, after: bytes, size: int, encoding: str) -> bytes:
    z = zlib.compressobj(9, zlib.DEFLATED, zlib.MAX_WBITS | 16 if encoding == "gzip" else zlib.MAX_WBITS)
    return b"".join(z.compress(p) for p in _pieces(before, after, size)) + z.flush()
