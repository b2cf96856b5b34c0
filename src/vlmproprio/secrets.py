"""One secret scrubber for everything vlmproprio writes or prints, model answers included.

``scrub(text)`` replaces, with ``***``:

* the value of every environment variable that holds a credential: ``OPENAI_API_KEY``, the variable named
  by ``--api-key-env`` (``register_secret_env``), and any variable whose name ends in KEY, TOKEN, SECRET,
  PASSWORD or PASSWD (values of 8 characters or more with a letter, so numbers in score tables are never hit);
* credentials in URLs: ``scheme://user:password@host`` and ``?token=``, ``api_key=``, ``access_token=``,
  ``key=``, ``password=``, ``secret=``, ``sig=``, ``signature=`` query parameters;
* ``Authorization:`` header values and ``Bearer <token>``.

It is idempotent and leaves a text without secrets unchanged, so scrubbing data that is later
checksummed (cassette lines, score files) never changes clean data.
"""

from __future__ import annotations

import os
import re

MASK = "***"
MIN_SECRET_LEN = 8
_SECRET_NAME = re.compile(r"(?:^|_)(?:API_?KEY|KEY|TOKEN|SECRET|PASSWORD|PASSWD)$", re.IGNORECASE)
_ALWAYS = {"OPENAI_API_KEY"}
_registered: set[str] = set()

_URL_USERINFO = re.compile(r"(?P<scheme>[A-Za-z][A-Za-z0-9+.-]*://)[^/\s@'\"<>]+@")
_QUERY_SECRET = re.compile(
    r"(?P<name>[?&;](?:api[_-]?key|access[_-]?token|token|key|password|passwd|secret|sig|signature|auth)=)"
    r"[^&#\s'\"<>]+",
    re.IGNORECASE,
)
_AUTH_HEADER = re.compile(
    r"(?P<name>(?:authorization|proxy-authorization|x-api-key|api-key)[\"']?\s*[:=]\s*[\"']?)"
    r"(?:(?P<scheme>bearer|basic|token)\s+)?[^\s\"',}]+",
    re.IGNORECASE,
)
_BEARER = re.compile(r"(?P<name>\bbearer\s+)(?!\*\*\*)[A-Za-z0-9._~+/=-]{4,}", re.IGNORECASE)


def register_secret_env(name: str) -> None:
    """Treat the value of environment variable ``name`` as a secret too (e.g. ``--api-key-env MY_KEY``)."""
    if name:
        _registered.add(name)


def secret_values() -> list[str]:
    """The credential values present in the environment now, longest first."""
    return list(_current_secrets())


# (environment copy, registered names, secrets): scrub runs for every answer and every metadata string (tens
# of thousands of calls per run), and rescanning the environment with a regex each time cost seconds; the
# secrets are recomputed only when os.environ or the registered names differ from the copies they came from
_memo: tuple[dict, frozenset[str], tuple[str, ...]] | None = None


def _current_secrets() -> tuple[str, ...]:
    global _memo
    env = getattr(os.environ, "_data", os.environ)  # os.environ's own dict: comparing it copies nothing
    memo = _memo
    if memo is None or memo[0] != env or memo[1] != _registered:
        memo = _memo = (dict(env), frozenset(_registered), _scan_environment())
    return memo[2]


def _scan_environment() -> tuple[str, ...]:
    out = set()
    for name, value in os.environ.items():
        if not value or len(value.strip()) < MIN_SECRET_LEN or not any(c.isalpha() for c in value):
            continue  # digits only (a seed, a port list) would mask numbers in score tables, and is no key
        if name in _ALWAYS or name in _registered or _SECRET_NAME.search(name):
            out.add(value)
            out.add(value.strip())
            # a key with a newline is split across lines by the HTTP layer: mask each piece
            out.update(p for p in value.split() if len(p) >= MIN_SECRET_LEN)
    return tuple(sorted(out, key=len, reverse=True))


def scrub(text: str) -> str:
    """``text`` with every secret replaced by ``***``; unchanged when there is none."""
    return _scrub(text, _current_secrets())


def _scrub(text: str, secrets: tuple[str, ...]) -> str:
    if not text:
        return text
    for value in secrets:
        if value in text:
            text = text.replace(value, MASK)
    if "://" in text and "@" in text:
        text = _URL_USERINFO.sub(lambda m: m.group("scheme") + MASK + "@", text)
    if "=" in text:
        text = _QUERY_SECRET.sub(lambda m: m.group("name") + MASK, text)
    lower = text.lower()
    if "auth" in lower or "api-key" in lower or "api_key" in lower:
        text = _AUTH_HEADER.sub(
            lambda m: m.group("name") + (m.group("scheme") + " " if m.group("scheme") else "") + MASK, text
        )
    if "bearer" in lower:
        text = _BEARER.sub(lambda m: m.group("name") + MASK, text)
    return text


def public_url(url: str | None) -> str | None:
    """A URL fit to print: credentials masked."""
    return scrub(url) if url else url


def scrub_obj(obj):
    """``obj`` (decoded JSON: dicts, lists, strings, numbers) with every string scrubbed."""
    return _scrub_obj(obj, _current_secrets())


def _scrub_obj(obj, secrets: tuple[str, ...]):
    if isinstance(obj, str):
        return _scrub(obj, secrets)
    if isinstance(obj, dict):
        return {_scrub(k, secrets) if isinstance(k, str) else k: _scrub_obj(v, secrets) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_scrub_obj(v, secrets) for v in obj]
    return obj
