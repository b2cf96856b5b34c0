"""Server URLs (``--base-url``, ``$OPENAI_BASE_URL``): checked once where they come in, so a port out of range or a
missing host is one line naming the flag or variable, not a ValueError from deep inside a request or run.json."""

from __future__ import annotations

from urllib.parse import urlsplit

from vlmproprio.errors import VlmproprioError

SCHEMES = ("http", "https")


class ServerURLError(VlmproprioError):
    """A server URL that cannot be used; the message names where it came from, never the URL (which may carry
    credentials)."""


def server_url_problem(url: str) -> str | None:
    """What is wrong with ``url`` as an OpenAI-compatible server's base URL, or None when it is usable."""
    if not url.strip():
        return "empty URL"
    if any(ord(c) < 33 or ord(c) == 127 for c in url):
        return "the URL holds a space or a control character"
    try:
        parts = urlsplit(url)
        port = parts.port  # ValueError for a port out of 0-65535 or not a number
    except ValueError as exc:
        return f"not a valid URL ({exc})"
    if parts.scheme not in SCHEMES:
        return f"the URL must start with http:// or https://, not {parts.scheme + '://' if parts.scheme else 'nothing'}"
    if not parts.hostname:
        return "the URL names no host"
    if port == 0:
        return "port 0 is not a server's port"
    return None


def check_server_url(url: str, where: str) -> str:
    """``url`` when usable; else ServerURLError naming ``where`` (``--base-url``, ``$OPENAI_BASE_URL``)."""
    problem = server_url_problem(url)
    if problem:
        raise ServerURLError(f"{where}: {problem}")
    return url


def server_url_argument(text: str) -> str:
    """argparse ``type`` of ``--base-url``: a usage error naming the flag for an unusable URL."""
    import argparse

    problem = server_url_problem(text)
    if problem:
        raise argparse.ArgumentTypeError(problem)
    return text
