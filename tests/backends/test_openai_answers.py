"""What the openai backend takes from a completion, against the loopback server: the answer, the server's
reasoning beside it (never the answer), and the response's own account of an answer without a caption.

vLLM and SGLang with a reasoning parser return the model's draft in ``message.reasoning_content``; vLLM renamed
it ``reasoning`` (OpenAI's guidance for gpt-oss, OpenRouter's name), sending both for a while. Whichever is
sent, it is ``Answer.reasoning``, kept through the cache and the cassette, and masked like the answer.
"""

from __future__ import annotations

import json
import secrets

import pytest

from extras import needs_openai
from vlmproprio.answering import Answerer
from vlmproprio.cache import ResponseCache, canonical_json
from vlmproprio.cassettes import read_cassette
from vlmproprio.chat import ANSWER_PROBLEMS, GenerationConfig, RequestTag
from vlmproprio.testing import openai_server
from vlmproprio.testing.openai_server import FakeOpenAIServer, expected_answer

pytestmark = needs_openai

KEY_ENV = "VLMPROPRIO_TEST_OPENAI_KEY"
# a draft that reads like an answer: were it parsed, its frame lines would become the captions
DRAFT = "Frame 1: the robot opens the door.\nFrame 2: it lets go."


@pytest.fixture
def api_key(monkeypatch):
    key = "sk-planted-" + secrets.token_hex(16)
    monkeypatch.setenv(KEY_ENV, key)
    return key


def backend_for(server: FakeOpenAIServer, model: str = "gpt-4o"):
    from vlmproprio.backends.openai import OpenAIBackend

    return OpenAIBackend(model, base_url=server.base_url, api_key_env=KEY_ENV, max_retries=0, timeout_s=5.0)


def requests_for(request_factory, n: int = 3):
    return [
        request_factory(
            f"# Process 2\nGroup {i}: describe.",
            (),
            config=GenerationConfig(max_new_tokens=32, seed=7),
            tag=RequestTag("door_01", "both", "p2", i),
        )
        for i in range(n)
    ]


@pytest.mark.parametrize("field", ["reasoning_content", "reasoning", "both"])
def test_the_servers_reasoning_is_kept_apart_from_the_answer(api_key, request_factory, field):
    with FakeOpenAIServer(reasoning=lambda body: DRAFT, reasoning_field=field) as server:
        answers = backend_for(server).generate(requests_for(request_factory))
        bodies = [r.body for r in server.chat_requests]
    by_text = {expected_answer(b) for b in bodies}
    assert {a.text for a in answers} == by_text  # the answer alone
    assert all(a.reasoning == DRAFT for a in answers)  # once, even when both fields carry it
    assert all("answer_problem" not in a.meta.extra for a in answers)


def test_reasoning_goes_through_the_cache_and_the_cassette_masked(api_key, request_factory, tmp_path):
    reqs = requests_for(request_factory)
    with FakeOpenAIServer(reasoning=lambda body: f"{DRAFT} (key {api_key})") as server:
        with ResponseCache(tmp_path / "cache") as cache:
            recorder = Answerer(backend_for(server), mode="record", cache=cache, model="gpt-4o")
            first = recorder.answer(reqs)
            cassette = recorder.export_cassette(tmp_path / "gpt-4o.jsonl")
            again = Answerer(backend_for(server), mode="live", cache=cache).answer(reqs)
            stored = [canonical_json(cache._cache.get(k)) for k in cache]
        sent = len(server.chat_requests)
    assert sent == len(reqs)  # the second pass was served by the cache
    assert all(a.from_cache for a in again)
    assert [a.reasoning for a in again] == [a.reasoning for a in first]
    assert all(a.reasoning.startswith(DRAFT) and api_key not in a.reasoning for a in first)
    assert all('"reasoning":' in s and api_key not in s for s in stored)
    assert api_key not in cassette.read_text()
    entries = read_cassette(cassette).entries.values()
    assert sorted(e.to_answer().reasoning for e in entries) == sorted(a.reasoning for a in first)


def test_a_plain_answer_is_stored_as_it_always_was(api_key, request_factory, tmp_path):
    with FakeOpenAIServer() as server, ResponseCache(tmp_path / "cache") as cache:
        recorder = Answerer(backend_for(server), mode="record", cache=cache, model="gpt-4o")
        recorder.answer(requests_for(request_factory, 1))
        cassette = recorder.export_cassette(tmp_path / "gpt-4o.jsonl")
        (record,) = [cache._cache.get(k) for k in cache]
    line = json.loads(cassette.read_text().splitlines()[1])
    assert set(line) == {"key", "text", "meta", "tag", "status", "checksum"}
    assert set(record) == {"key", "text", "meta", "tag", "status", "model", "identity", "checksum"}
    assert set(line["meta"]["extra"]) == {"response_model", "system_fingerprint", "finish_reason", "malformed_retries"}


@pytest.mark.parametrize(
    ("asked", "answered", "other"),
    [
        ("gpt-4o", "gpt-4o-2024-08-06", False),  # OpenAI names the dated snapshot that answered
        ("gpt-4-vision-preview", "gpt-4-1106-vision-preview", False),
        ("Qwen/Qwen2.5-VL-7B-Instruct", "Qwen/Qwen2.5-VL-7B-Instruct", False),
        ("gpt-4o", "gpt-4o-mini-2024-07-18", True),
        ("gpt-4o-2024-08-06", "gpt-4o-2024-08-06", False),  # the registry's gpt-4o: a snapshot
        ("gpt-4o-2024-08-06", "gpt-4o-2024-11-20", True),  # another snapshot is another model
        ("Qwen/Qwen2.5-VL-7B-Instruct", "Qwen/Qwen2.5-VL-3B-Instruct", True),
    ],
)
def test_an_answer_from_another_model_is_named(api_key, request_factory, monkeypatch, asked, answered, other):
    real = openai_server._completion

    def renamed(body: dict, text: str) -> dict:
        return real(body, text) | {"model": answered}

    monkeypatch.setattr(openai_server, "_completion", renamed)
    with FakeOpenAIServer() as server:
        (answer,) = backend_for(server, asked).generate(requests_for(request_factory, 1))
    assert answer.meta.extra["response_model"] == answered
    assert answer.meta.extra.get("answer_problem") == ("other_model" if other else None)
    assert answer.text  # the text is kept: the class says whose it is


@pytest.mark.parametrize("kind", openai_server.NO_CAPTION_KINDS)
def test_each_answer_without_a_caption_gets_its_class(api_key, request_factory, kind):
    with FakeOpenAIServer() as server:
        server.inject(kind)
        (answer,) = backend_for(server).generate(requests_for(request_factory, 1))
    problem = answer.meta.extra["answer_problem"]
    assert problem == ("empty" if kind == "empty_choice" else kind) and problem in ANSWER_PROBLEMS
    assert (answer.text == "") is (kind != "other_model")
    if kind == "refusal":
        assert answer.meta.extra["refusal"].startswith("I'm sorry")
    if kind == "tool_calls":
        assert answer.meta.extra["tool_calls"] == ["describe_frames"]
    if kind == "reasoning_only":  # the answer the server put in the reasoning field is never taken as one
        assert answer.reasoning.startswith("echo ")
