"""Any OpenAI-compatible chat-completions server through the official ``openai`` SDK.

GPT-4V/4o (the paper used ``gpt-4-vision-preview`` at temperature 0), or a
local vLLM / SGLang server via ``base_url``. Images go as base64 data URLs,
decoding is temperature 0 with a fixed seed where the server supports it.

Reliability. Retries are the SDK's own (``max_retries``): exponential backoff
with jitter on 408/409/429/5xx, timeouts and connection errors, honouring
``Retry-After``. The SDK does not retry a 200 whose body is not JSON, so this
module retries that itself, with the same backoff. When a request still fails,
the batch stops at once (queued requests are cancelled, so a dead server fails
in seconds, not once per request) and a BackendError says what happened, with
the answers already received attached (``BackendError.partial``) for the cache.

Bounds (``backends.http_bounds``). ``timeout_s`` bounds each attempt as a whole (connecting, sending, the
headers and the whole body), not each socket read, so a server trickling its answer times out like a silent
one. A body may hold at most ``max_response_bytes`` once decompressed, and a 2xx body must be UTF-8 and nest
at most 64 levels; a body refused so is retried like a reset connection, then named with the limit.

Answers. The answer is the first choice's ``content``; the reasoning a server returns beside it (``reasoning``,
``reasoning_content``) is ``Answer.reasoning``, never part of the text. An answer that holds no caption, or that
the response says another model gave, is classed (``chat.ANSWER_PROBLEMS``, in ``AnswerMeta.extra``) from the
response's own fields: refusal, finish reason, tool calls, model.

Secrets. The API key is read from the environment only (``OPENAI_API_KEY`` or
the variable named by ``api_key_env``) and handed to the SDK client; it is
never stored in the identity, metadata, cache, cassettes, logs or messages.
Error texts are scrubbed of it in case a server echoes it back.
"""

from __future__ import annotations

import base64
import json
import logging
import math
import os
import random
import threading
import time
from collections.abc import Sequence
from concurrent.futures import FIRST_EXCEPTION, ThreadPoolExecutor, wait
from dataclasses import asdict, dataclass
from typing import TYPE_CHECKING

from vlmproprio.backends.base import Availability, Backend, BackendError
from vlmproprio.backends.http_bounds import DEFAULT_MAX_RESPONSE_BYTES, Bounds, bounded_http_client, refusal_of
from vlmproprio.backends.openai_replies import MalformedCompletion, answer_problem_of, read_completion, token_count
from vlmproprio.backends.urls import check_server_url, server_url_argument
from vlmproprio.chat import Answer, AnswerMeta, ChatRequest, ImagePart
from vlmproprio.kinds import KindOption, KindSpec, register_kind
from vlmproprio.models import ModelRef, file_slug

if TYPE_CHECKING:
    from vlmproprio.backends.settings import BackendSettings

log = logging.getLogger(__name__)

DEFAULT_KEY_ENV = "OPENAI_API_KEY"
# What the SDK is given when a key-less local server (vLLM, SGLang) is used: it insists on some string.
NO_KEY_PLACEHOLDER = "no-key"


def _check_key(key: str, env: str) -> None:
    """An HTTP header carries printable ASCII only: say so (never showing the key) instead of letting the
    HTTP layer fail as "cannot reach the server" (a newline) or with a UnicodeEncodeError (non-ASCII)."""
    for i, c in enumerate(key):
        if not 33 <= ord(c) <= 126:
            what = {"\n": "a newline", "\r": "a carriage return", " ": "a space", "\t": "a tab"}.get(
                c, f"the non-ASCII character U+{ord(c):04X}" if ord(c) > 126 else f"control character {ord(c)}"
            )
            raise BackendError(
                f"${env} contains {what} at position {i + 1} of {len(key)}; an API key is printable ASCII only "
                f"(check how it was set, e.g. a trailing newline from a file: export {env}=\"$(tr -d '\\n' < FILE)\")"
            )


class OpenAIBackend(Backend):
    """Chat completions with bounded concurrency; answers come back in request order."""

    def __init__(
        self,
        model: str,
        *,
        base_url: str | None = None,
        api_key_env: str = DEFAULT_KEY_ENV,
        concurrency: int = 4,
        timeout_s: float = 120.0,
        max_retries: int = 4,
        max_batch_size: int | None = None,
        backoff_s: float = 0.5,
        max_response_bytes: int = DEFAULT_MAX_RESPONSE_BYTES,
    ) -> None:
        if concurrency < 1:
            raise BackendError(f"concurrency must be >= 1, got {concurrency}")
        if not (math.isfinite(timeout_s) and timeout_s > 0):  # the socket layer would raise deep inside a request
            raise BackendError(f"timeout must be a positive number of seconds, got {timeout_s}")
        if isinstance(max_response_bytes, bool) or not isinstance(max_response_bytes, int) or max_response_bytes < 1:
            raise BackendError(f"max_response_bytes must be a positive whole number, got {max_response_bytes!r}")
        if not api_key_env.replace("_", "").isalnum():
            raise BackendError(f"api_key_env must be an environment variable name, got {api_key_env!r}")
        if base_url is not None:
            check_server_url(base_url, "--base-url")
        elif os.environ.get("OPENAI_BASE_URL"):  # the SDK's own default: checked and named like --base-url
            check_server_url(os.environ["OPENAI_BASE_URL"], "$OPENAI_BASE_URL")
        self.model = model
        self.settings = OpenAISettings(
            base_url=base_url,
            api_key_env=api_key_env,
            concurrency=concurrency,
            timeout_s=timeout_s,
            max_retries=max_retries,
            max_response_bytes=max_response_bytes,
        )
        self.backoff_s = backoff_s
        # enough requests per call to keep every worker busy, few enough that a crash loses little
        self.max_batch_size = max_batch_size or max(16, 4 * concurrency)
        from vlmproprio.secrets import register_secret_env, register_secret_url

        register_secret_env(api_key_env)  # its value is masked in everything written or printed
        register_secret_url(base_url)  # and so are the URL's credentials, sent as Authorization: Basic
        key = os.environ.get(api_key_env)
        if key:
            _check_key(key, api_key_env)
        if not key and base_url is None:
            raise BackendError(
                f"no API key: set the environment variable {api_key_env} (the key is read from the environment "
                "only), or point --base-url at an OpenAI-compatible server that needs none"
            )
        self._client = None
        self._client_lock = threading.Lock()
        self._key_for_client = key or NO_KEY_PLACEHOLDER

    def _not_found_hint(self) -> str:
        """What a 404 most likely means: a model the server does not serve, or (vLLM, SGLang and transformers
        serve all answer under /v1) a base URL without its /v1 path."""
        hint = f"does the server serve model {self.model!r}?"
        base = self.settings.base_url
        if base is not None and not base.rstrip("/").endswith("/v1"):
            hint = hint[:-1] + " or does --base-url lack its /v1 path?"
        return hint

    def __repr__(self) -> str:  # never show the key, even by accident
        return f"OpenAIBackend(model={self.model!r}, base_url={self.settings.base_url!r}, concurrency={self.settings.concurrency})"

    def identity(self) -> dict[str, str]:
        # The server URL is not part of the identity: a recording replays wherever the cassette goes.
        return {"backend": "openai", "model_id": self.model, "revision": "", "dtype": "", "attn_implementation": ""}

    @property
    def client(self):
        with self._client_lock:
            if self._client is None:
                import openai

                bounds = Bounds(self.settings.timeout_s, self.settings.max_response_bytes)
                self._client = openai.OpenAI(
                    api_key=self._key_for_client,
                    base_url=self.settings.base_url,
                    timeout=self.settings.timeout_s,
                    max_retries=self.settings.max_retries,
                    http_client=bounded_http_client(bounds),
                )
            return self._client

    def close(self) -> None:
        with self._client_lock:
            if self._client is not None:
                self._client.close()
                self._client = None

    # -------------------------------------------------------------------------------- generation
    def generate(self, requests: Sequence[ChatRequest]) -> list[Answer]:
        results: list[Answer | None] = [None] * len(requests)
        if not requests:
            return []
        pool = ThreadPoolExecutor(
            max_workers=min(self.settings.concurrency, len(requests)), thread_name_prefix="openai"
        )
        try:
            futures = {pool.submit(self._one, r): i for i, r in enumerate(requests)}
            done, _ = wait(futures, return_when=FIRST_EXCEPTION)
            failed = next((f for f in done if f.exception() is not None), None)
            if failed is not None:
                pool.shutdown(wait=True, cancel_futures=True)  # drop the queue; let running requests finish
                for f, i in futures.items():
                    if f.done() and not f.cancelled() and f.exception() is None:
                        results[i] = f.result()
                exc = failed.exception()
                if not isinstance(exc, BackendError):
                    raise exc  # a bug, not a server fault: keep its traceback
                i = futures[failed]
                n_ok = sum(r is not None for r in results)
                raise BackendError(
                    self._scrub(f"{requests[i].tag}: {exc} ({n_ok} of {len(requests)} requests answered)"),
                    partial=results,
                ) from None
            for f, i in futures.items():
                results[i] = f.result()
        finally:
            pool.shutdown(wait=True, cancel_futures=True)
        return results  # type: ignore[return-value]

    def _one(self, request: ChatRequest) -> Answer:
        import openai

        body = self._body(request)
        where = self.settings.base_url or os.environ.get("OPENAI_BASE_URL") or "the OpenAI API"  # as the SDK picks
        attempts = 1 + self.settings.max_retries
        for attempt in range(1, attempts + 1):
            t0 = time.perf_counter()
            try:
                resp = self.client.chat.completions.create(**body)
                reply = read_completion(resp)
            except (json.JSONDecodeError, openai.APIResponseValidationError, MalformedCompletion) as exc:
                # a 200 whose body is not a chat completion: the SDK does not retry these
                if attempt == attempts:
                    what = _malformed_what(exc)
                    raise BackendError(
                        f"{where} kept answering with malformed responses ({attempts} tries): {what}"
                    ) from None
                delay = min(self.backoff_s * 2 ** (attempt - 1), 8.0) * (1 - 0.25 * random.random())
                log.info("malformed response from %s, retrying in %.2f s (%d of %d)", where, delay, attempt, attempts)
                time.sleep(delay)
                continue
            except openai.APITimeoutError:
                raise BackendError(
                    f"{where} did not answer within {self.settings.timeout_s:g} s ({attempts} tries); raise --timeout or check "
                    "the server"
                ) from None
            except openai.APIConnectionError as exc:
                refused = refusal_of(exc)
                if refused is not None:  # a body over a bound, retried by the SDK like a reset connection
                    raise BackendError(
                        f"{where} sent responses that were refused ({attempts} tries): {refused.reason}"
                    ) from None
                cause = type(exc.__cause__).__name__ if exc.__cause__ else "connection error"
                raise BackendError(
                    f"cannot reach {where} ({cause}, {attempts} tries): is the server running and the URL right?"
                ) from None
            except openai.APIStatusError as exc:
                detail = _error_detail(exc)
                hint = {
                    401: "check the API key in $" + self.settings.api_key_env,
                    403: "the key may lack access to this model",
                    404: self._not_found_hint(),
                    429: "lower --concurrency or wait",
                }.get(exc.status_code, "")
                retried = self._tries_phrase(exc.response, attempts)
                raise BackendError(
                    f"{where} answered HTTP {exc.status_code}{retried}: {detail}" + (f"; {hint}" if hint else "")
                ) from None
            latency = time.perf_counter() - t0
            usage = resp.usage
            extra = {**reply.extra, "malformed_retries": attempt - 1}
            problem = answer_problem_of(reply, self.model)
            if problem:  # only then: a plain answer's metadata stays what it always was
                extra["answer_problem"] = problem
            meta = AnswerMeta(
                **self.identity(),
                device="remote",
                prompt_tokens=token_count(getattr(usage, "prompt_tokens", 0)),
                completion_tokens=token_count(getattr(usage, "completion_tokens", 0)),
                latency_s=latency,
                extra=extra,
            )
            return Answer(text=reply.text, meta=meta, reasoning=reply.reasoning)
        raise AssertionError("unreachable")  # pragma: no cover

    def _tries_phrase(self, response, attempts: int) -> str:
        """What the SDK did with this failed response: " after N tries" when it retries such a response (so it
        stopped for running out of retries), ", not retried (why)" when the response itself told it to stop
        (a Retry-After over the SDK's limit, ``x-should-retry: false``), "" for a status it never retries."""
        should_retry = getattr(self.client, "_should_retry", None)  # the SDK's own rule, not a copy of it
        if should_retry is None:
            return ""
        if should_retry(response):
            return f" after {attempts} tries"
        if response.headers.get("x-should-retry") == "false":
            return ", not retried (the server sent x-should-retry: false)"
        wait = self.client._parse_retry_after_header(response.headers)
        if (
            wait is not None
            and math.isfinite(wait)
            and wait > 0
            and (response.status_code in (408, 409, 429) or response.status_code >= 500)
        ):
            return f", not retried (Retry-After asks to wait {wait:g} s, longer than the client waits)"
        return ""

    def _body(self, request: ChatRequest) -> dict:
        cfg = request.config
        body: dict = {
            "model": self.model,
            "messages": [_message(m) for m in request.messages],
            "temperature": cfg.temperature,
            "max_tokens": cfg.max_new_tokens,
        }
        if cfg.seed is not None:
            body["seed"] = cfg.seed
        extra: dict = {}
        if cfg.min_new_tokens:
            extra["min_tokens"] = cfg.min_new_tokens  # vLLM / SGLang extension
        if cfg.thinking is not None:  # vLLM / SGLang: passed to the chat template (only when asked for)
            extra["chat_template_kwargs"] = {"enable_thinking": cfg.thinking}
        if extra:
            body["extra_body"] = extra
        return body

    def _scrub(self, text: str) -> str:
        from vlmproprio.secrets import scrub

        return scrub(text)  # every encoding of the key and of the URL's credentials, not the raw key only


def _malformed_what(exc: Exception) -> str:
    """What was wrong with a 200 body that is not a chat completion, in words (for the one-line error)."""
    if isinstance(exc, json.JSONDecodeError):
        return f"the body is not JSON (character {exc.pos:,}: {exc.msg})"
    if isinstance(exc, MalformedCompletion):
        return str(exc)
    return f"the body is no chat completion ({type(exc).__name__})"


def _message(m) -> dict:
    if all(not isinstance(p, ImagePart) for p in m.parts):
        return {"role": m.role, "content": m.text}
    content = []
    for p in m.parts:
        if isinstance(p, ImagePart):
            url = f"data:{p.mime};base64,{base64.b64encode(p.data).decode('ascii')}"
            content.append({"type": "image_url", "image_url": {"url": url}})
        else:
            content.append({"type": "text", "text": p.text})
    return {"role": m.role, "content": content}


def _error_detail(exc) -> str:
    """The server's reason for an error status: OpenAI's ``{"error": {"message"}}``, or FastAPI's ``{"detail"}``
    (transformers serve, many vLLM front ends), whose detail is a string or a list of validation errors."""
    body = getattr(exc, "body", None)
    if isinstance(body, dict):
        err = body.get("error", body)
        msg = err.get("message") if isinstance(err, dict) else err if isinstance(err, str) else None
        if msg is None:
            msg = body.get("detail")
            if isinstance(msg, list):
                msg = "; ".join(str(d.get("msg", d)) if isinstance(d, dict) else str(d) for d in msg)
        if isinstance(msg, str) and msg.strip():
            return _cut(msg)
    return _cut(str(getattr(exc, "message", "") or exc))


def _cut(text: str) -> str:
    """At most 300 characters, masked first: a credential the server quoted and the cut split in two would be
    no longer recognised afterwards."""
    from vlmproprio.secrets import scrub

    return scrub(text)[:300]


# ---------------------------------------------------------------------------------------------- the openai kind


@dataclass(frozen=True)
class OpenAISettings:
    """A model behind an OpenAI-compatible server: the keyword arguments of OpenAIBackend a run sets."""

    base_url: str | None = None  # server URL, e.g. http://127.0.0.1:8000/v1 for vLLM
    api_key_env: str = DEFAULT_KEY_ENV  # the environment variable holding the key
    concurrency: int = 4  # requests in flight
    timeout_s: float = 120.0  # per attempt of a request, all of it: connect, send, headers, body
    max_retries: int = 4  # retries on 429 / 5xx / timeouts / connection errors / malformed JSON
    max_response_bytes: int = DEFAULT_MAX_RESPONSE_BYTES  # of a response body, once decompressed


def openai_slug(name: str, weights: str) -> str:
    """A served model's name is kept whole (with a digest where sanitising it loses information)."""
    return file_slug(name, "openai", weights, weights, lossless=True)


def _create_openai(ref: ModelRef, settings: BackendSettings) -> Backend:
    return OpenAIBackend(ref.weights, **asdict(settings.for_kind("openai")))


def _openai_live(ref: ModelRef, settings: BackendSettings) -> Availability:
    import importlib.util

    if importlib.util.find_spec("openai") is None:
        return Availability(False, "needs the openai SDK: pip install 'vlmproprio[openai]'")
    oa = settings.for_kind("openai")
    if os.environ.get(oa.api_key_env) or oa.base_url:  # as OpenAIBackend requires
        url = oa.base_url or os.environ.get("OPENAI_BASE_URL")  # the SDK's default when --base-url is not given
        return Availability(True, f"OpenAI-compatible server {url or '(OpenAI API)'}")
    return Availability(False, f"set ${oa.api_key_env} (OpenAI API) or a --base-url of an OpenAI-compatible server")


_OPENAI_OPTIONS = (
    KindOption(
        "--base-url",
        "base_url",
        {
            "run": "server URL, e.g. http://127.0.0.1:8000/v1 for vLLM (default: OpenAI)",
            "models": "OpenAI-compatible server the openai models would use",
            "score": "OpenAI-compatible server URL for an openai: judge",
        },
        server_url_argument,
    ),
    KindOption(
        "--api-key-env",
        "api_key_env",
        dict.fromkeys(("run", "models", "score"), "environment variable holding the key"),
        default=DEFAULT_KEY_ENV,
    ),
    KindOption("--concurrency", "concurrency", {"run": "requests in flight (default 4)"}, int, 4),
    KindOption(
        "--timeout",
        "timeout_s",
        {"run": "seconds for each try of a request, all of it: connect, send, headers, body (default 120)"},
        float,
        120.0,
    ),
)

register_kind(
    KindSpec(
        kind="openai",
        create=_create_openai,
        live=_openai_live,
        prefix="openai:",
        syntax="openai:<model name>",
        label="OpenAI API",
        slug=openai_slug,
        settings_type=OpenAISettings,
        options=_OPENAI_OPTIONS,
        option_group="OpenAI-compatible servers (openai)",
    )
)
