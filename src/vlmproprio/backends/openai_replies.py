"""What a chat completion says: its first choice's answer, the reasoning beside it, and the response's own
account of it (finish reason, model, refusal, tool calls), classed into chat.ANSWER_PROBLEMS. Read from the
openai SDK's response objects, which it does not check: a body that is no chat completion is
``MalformedCompletion``."""

from __future__ import annotations

from dataclasses import dataclass

from vlmproprio.chat import valid_unicode


class MalformedCompletion(Exception):
    """A 200 response whose body parsed but is not a usable chat completion (no choices, non-text content)."""


def _server_text(value: object) -> str:
    """A string field of a response as valid Unicode. JSON escapes can carry lone surrogates ("\\ud800"), which
    no UTF-8 file can hold: they would break the cache checksum and the transcript writer."""
    return valid_unicode(value) if isinstance(value, str) else ""


def token_count(value: object) -> int:
    """A token count as the server gave it; anything but a non-negative integer counts as unknown (0)."""
    return value if isinstance(value, int) and not isinstance(value, bool) and value >= 0 else 0


@dataclass(frozen=True)
class _Reply:
    """What a chat completion's first choice says: the answer, the server's reasoning beside it, and the
    response's own account of it (finish reason, model, refusal, tool calls) for the answer's metadata."""

    text: str
    reasoning: str
    extra: dict


# vLLM named the field reasoning_content (as DeepSeek did), then reasoning (OpenAI's guidance for gpt-oss,
# OpenRouter's name; vLLM PR #27752), sending both for a while; SGLang sends reasoning_content.
_REASONING_FIELDS = ("reasoning", "reasoning_content")


def _reasoning(message: object) -> str:
    found: list[str] = []
    for name in _REASONING_FIELDS:
        value = _server_text(getattr(message, name, None)).strip()
        if value and value not in found:
            found.append(value)
    return "\n\n".join(found)


def _tool_names(message: object) -> list[str]:
    calls = getattr(message, "tool_calls", None)
    calls = calls if isinstance(calls, list) else []
    legacy = getattr(message, "function_call", None)
    names = [_server_text(getattr(getattr(c, "function", None), "name", None)) or "?" for c in calls]
    if legacy is not None:
        names.append(_server_text(getattr(legacy, "name", None)) or "?")
    return names


def read_completion(resp) -> _Reply:
    """The answer of a chat completion; MalformedCompletion when the body is not one (the SDK does not check)."""
    choices = getattr(resp, "choices", None)
    if not isinstance(choices, list) or not choices:
        raise MalformedCompletion("no choices in the response")
    choice = choices[0]
    message = getattr(choice, "message", None)
    content = getattr(message, "content", None)
    if content is not None and not isinstance(content, str):
        raise MalformedCompletion(f"message content is a JSON {type(content).__name__}, not text")
    extra: dict = {
        "response_model": _server_text(getattr(resp, "model", "")),
        "system_fingerprint": _server_text(getattr(resp, "system_fingerprint", "")),
        "finish_reason": _server_text(getattr(choice, "finish_reason", "")),
    }
    refusal = _server_text(getattr(message, "refusal", None)).strip()
    tools = _tool_names(message)
    if refusal:
        extra["refusal"] = refusal
    if tools:
        extra["tool_calls"] = tools
    return _Reply(_server_text(content).strip(), _reasoning(message), extra)


def _model_name(name: str) -> str:
    """A model name without its date or snapshot numbers: OpenAI answers "gpt-4o" as "gpt-4o-2024-08-06" and
    "gpt-4-vision-preview" as "gpt-4-1106-vision-preview", snapshots the alias stood for when asked."""
    return "-".join(p for p in name.lower().split("-") if not (p.isdigit() and len(p) >= 2))


def _same_model(asked: str, answered: str) -> bool:
    """Whether ``answered`` is the model ``asked`` names: an alias is answered by any of its snapshots, a name
    with its snapshot numbers (the registry's "gpt-4o-2024-08-06") by that snapshot only."""
    if _model_name(asked) != asked.lower():
        return answered.lower() == asked.lower()
    return _model_name(answered) == _model_name(asked)


def answer_problem_of(reply: _Reply, asked: str) -> str:
    """The chat.ANSWER_PROBLEMS class of a reply ("" when it is a plain answer), the first that applies."""
    extra = reply.extra
    finish = extra["finish_reason"]
    if extra.get("refusal"):
        return "refusal"
    if finish == "content_filter":
        return "content_filter"
    if extra.get("tool_calls") or finish in ("tool_calls", "function_call"):
        return "tool_calls"
    if finish == "length":
        return "length"
    if not reply.text:
        return "reasoning_only" if reply.reasoning else "empty"
    got = extra["response_model"]
    if got and not _same_model(asked, got):
        return "other_model"
    return ""
