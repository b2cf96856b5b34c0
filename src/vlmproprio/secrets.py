"""One secret scrubber for everything vlmproprio writes or prints, model answers included.

``scrub(text)`` replaces, with ``***``:

* every credential the suite was given, in every encoding it sends or a server may quote back: the raw value,
  its URL-quoted, JSON- and HTML-escaped forms, its base64, and for URL credentials the ``user:password`` pair
  and its base64 (the ``Authorization: Basic`` header the HTTP layer builds from them). The credentials given
  are the value of ``OPENAI_API_KEY`` and of the variable named by ``--api-key-env`` (``register_secret_env``),
  digits-only keys included; the password (or a lone user name, a token) and the secret query parameters of
  every URL the command line or the environment holds (``register_secret_url``; ``OPENAI_BASE_URL``, proxies
  ...); and any value registered with ``register_secret``;
* the value of any other environment variable whose name ends in KEY, TOKEN, SECRET, PASSWORD or PASSWD
  (values of 8 characters or more with a letter, so numbers in score tables are never hit);
* credentials in URLs by their shape: ``scheme://user:password@host`` and query parameters whose name says
  they carry a secret (``token``, ``api_key``, ``code``, ``sig``, ``client_secret``, ``X-Amz-Signature`` ...);
* ``Authorization:`` header values and ``Bearer <token>``.

A server that echoes a credential transformed (reversed, re-encoded, split) is out of scope: only the forms
above are known. It is idempotent and leaves a text without secrets unchanged, so scrubbing data that is later
checksummed (cassette lines, score files) never changes clean data.
"""

from __future__ import annotations

import base64
import html
import json
import os
import re
from urllib.parse import parse_qsl, quote, quote_plus, unquote, urlsplit

MASK = "***"
MIN_SECRET_LEN = 8
# a credential the suite was given is masked from this length when it holds a non-digit (a short URL password
# "hunter2" or pair "user:pw"); digits-only ones from MIN_SECRET_LEN, as they also occur inside numbers
MIN_GIVEN_LEN = 6
_SECRET_NAME = re.compile(r"(?:^|_)(?:API_?KEY|KEY|TOKEN|SECRET|PASSWORD|PASSWD)$", re.IGNORECASE)
_ALWAYS = {"OPENAI_API_KEY"}
_registered: set[str] = set()
_given: set[str] = set()  # credentials registered by value (register_secret, register_secret_url)

_URL_USERINFO = re.compile(r"(?P<scheme>[A-Za-z][A-Za-z0-9+.-]*://)[^/\s@'\"<>]+@")
# a query parameter whose name ends in a word that says it carries a secret: token, api_key, access_token,
# client_secret, code (OAuth), sig / signature (signed URLs: Azure SAS, X-Amz-Signature), credential, ...
_SECRET_PARAM_NAME = (
    r"(?:[A-Za-z0-9_.\[\]-]*[_.-])?"  # any words before, ending in a separator: client_, X-Amz-Security-
    r"(?:api[_-]?key|apikey|key|access[_-]?token|auth[_-]?token|token|jwt|otp|secret|password|passwd|pwd|pass|"
    r"passcode|passphrase|code|sig|signature|hmac|auth|authorization|credentials?|ticket|session(?:[_-]?id)?|sid)"
)
_SECRET_PARAM = re.compile(_SECRET_PARAM_NAME, re.IGNORECASE)
_QUERY_SECRET = re.compile(rf"(?P<name>[?&;]{_SECRET_PARAM_NAME}=)[^&#\s'\"<>]+", re.IGNORECASE)
_URL = re.compile(r"[A-Za-z][A-Za-z0-9+.-]*://[^\s'\"<>]+")
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


def register_secret(value: str) -> None:
    """Treat ``value`` (a credential given other than by the environment) as a secret, in all its encodings."""
    if value:
        _given.add(value)


def register_secret_url(text: str | None) -> None:
    """Treat the credentials of every URL in ``text`` (``--base-url``: its password, the pair with the user name,
    secret query parameters) as secrets, in all their encodings."""
    for value in url_credentials(text or ""):
        _given.add(value)


def url_credentials(text: str) -> set[str]:
    """The credentials the URLs in ``text`` carry, as written: the password and the ``user:password`` pair (the
    user name when it is alone: a token), and the values of secret query parameters."""
    out: set[str] = set()
    for m in _URL.finditer(text):
        try:
            parts = urlsplit(m.group())
        except ValueError:  # a malformed authority ([::1 without its bracket): no credentials to take
            continue
        netloc = parts.netloc
        if "@" in netloc:
            userinfo = netloc.rsplit("@", 1)[0]
            user, colon, password = userinfo.partition(":")
            out.add(userinfo if colon else user)
            if password:
                out.add(password)
            if not colon:  # a token as the user name: HTTP clients send it as "token:" in Basic auth
                out.add(user + ":")
        for name, value in parse_qsl(parts.query, keep_blank_values=False):
            if _SECRET_PARAM.fullmatch(name):
                out.add(value)
                out.add(quote_plus(value))  # parse_qsl decoded it; the URL may hold it encoded
    return {v for v in out if v}


def secret_values() -> list[str]:
    """The credential values present in the environment now, longest first."""
    return list(_current_secrets())


# (environment copy, registered names and values, secrets): scrub runs for every answer and every metadata
# string (tens of thousands of calls per run), and rescanning the environment with a regex each time cost
# seconds; the secrets are recomputed only when os.environ or what is registered differs from the copies they
# came from
_memo: tuple[dict, frozenset[str], frozenset[str], tuple[str, ...]] | None = None


def _current_secrets() -> tuple[str, ...]:
    global _memo
    env = getattr(os.environ, "_data", os.environ)  # os.environ's own dict: comparing it copies nothing
    memo = _memo
    if memo is None or memo[0] != env or memo[1] != _registered or memo[2] != _given:
        memo = _memo = (dict(env), frozenset(_registered), frozenset(_given), _scan())
    return memo[3]


def _scan() -> tuple[str, ...]:
    out: set[str] = set()
    given = set(_given)
    for name, value in os.environ.items():
        if not value:
            continue
        if name in _ALWAYS or name in _registered:
            given.add(value)  # a key the suite sends: masked whatever its shape, digits only included
        elif _SECRET_NAME.search(name) and len(value.strip()) >= MIN_SECRET_LEN and any(c.isalpha() for c in value):
            out.update(_pieces(value))  # a digits-only value (a seed, a port list) would mask numbers: no key
        if "://" in value:
            given.update(url_credentials(value))  # OPENAI_BASE_URL, HTTPS_PROXY ...: what the HTTP layer sends
    for value in given:
        out.update(v for v in _encodings(value) if _maskable(v))
    return tuple(sorted(out, key=len, reverse=True))


def _pieces(value: str) -> set[str]:
    # a key with a newline is split across lines by the HTTP layer: mask each piece
    return {value, value.strip(), *(p for p in value.split() if len(p) >= MIN_SECRET_LEN)}


def _encodings(value: str) -> set[str]:
    """``value`` as it may travel or be quoted back: raw, URL-quoted and -unquoted, JSON- and HTML-escaped, base64 (a
    ``user:password`` pair is the Basic credential), padded or not."""
    forms = _pieces(value) | {unquote(value), quote(value, safe=""), quote_plus(value)}
    forms |= {json.dumps(f)[1:-1] for f in list(forms)}  # as a JSON string holds it ("\\", "\\u00e9")
    forms |= {html.escape(f) for f in list(forms)}  # as a page holds it ("&amp;")
    for form in list(forms):
        b64 = base64.b64encode(form.encode("utf-8")).decode("ascii")
        forms.update({b64, b64.rstrip("=")})
    return forms


def _maskable(value: str) -> bool:
    value = value.strip()
    if MASK in value:  # a value that holds the mask would make scrubbing not idempotent
        return False
    return len(value) >= MIN_SECRET_LEN or (len(value) >= MIN_GIVEN_LEN and not value.isdigit())


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
