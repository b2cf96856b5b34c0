"""Item 6, server faults, end to end: ``vlmproprio run --model openai:NAME --base-url http://127.0.0.1:PORT/v1``
against the loopback server in this process.

* Transient faults (429 with Retry-After, 500, a connection reset, a body that is not JSON, a JSON body that
  is not a usable completion, a request that hangs past --timeout) are retried with backoff; the run
  completes with exactly the transcripts of a fault-free run, and Retry-After is honoured.
* Answers no UTF-8 file can hold (lone surrogates) are stored and transcribed, not a crash.
* An empty answer is kept (replay gives what live gave) but asked again by the next live run.
* Persistent faults (500 or 429 on every request) end in one clear error line, quickly (Retry-After).
* A server that dies mid-run (every request reset) or is not there at all fails the run fast (about one
  request's retries, not one per request) with one error line, keeps every answer it had, and a rerun
  against a healthy server asks only for the rest and ends with the fault-free transcripts.

Per-fault behaviour of the backend alone (every fault kind transient and persistent, bounded concurrency,
request format) is tested in tests/backends/test_openai.py.

The CLI runs in this process (``cli_in_process``; what is checked is the run's outcome and its one error
line, not the process) and the backoff between retries is a tenth of the SDK's (``scaled_retry_backoff``):
with the real one each failing run waited 7.5 s per request's retries. That a failing run stops after about
one request's retries, not one per request, is checked by counting the retries.
"""

from __future__ import annotations

import time
from pathlib import Path

import pytest
from fault_support import cli_in_process, scaled_retry_backoff
from reliability_support import (
    assert_one_line_error,
    cache_answers,
    caption_responder,
    fixture_subset,
    run_file,
    transcripts_of,
)

from extras import needs_openai
from vlmproprio.testing import openai_server
from vlmproprio.testing.openai_server import FakeOpenAIServer

# checked, not imported: collecting this module on every xdist worker must not cost the SDK's ~1 CPU s
pytestmark = needs_openai

MODEL = "openai:fake-vlm"
BACKOFF = 0.1  # of the SDK's and the backend's backoff between retries (Retry-After is still honoured as sent)
RETRIES = 4  # the backend's default max_retries: 5 tries per request


@pytest.fixture(scope="module")
def fixtures(tmp_path_factory) -> Path:
    return fixture_subset(tmp_path_factory.mktemp("server-faults") / "fixtures", ["door_00"])


def run(base_url: str, fixtures: Path, out: Path, *extra: str):
    args = ["run", "--model", MODEL, "--base-url", base_url, "--fixtures", fixtures, "--conditions", "none,both"]
    args += ["--frame-stride", "2", "--no-progress", "--out", out, "--cache-dir", out.parent / f"{out.name}-cache"]
    return cli_in_process([*args, *extra])


@pytest.fixture(scope="module")
def clean(fixtures, tmp_path_factory) -> dict:
    """The fault-free run everything is compared with."""
    out = tmp_path_factory.mktemp("clean") / "run"
    with FakeOpenAIServer(responder=caption_responder) as server:
        proc = run(server.base_url, fixtures, out)
        n = len(server.chat_requests)
    assert proc.returncode == 0, proc.stderr
    return {"transcripts": transcripts_of(out), "answers": cache_answers(out.parent / "run-cache"), "requests": n}


def _retried_same_body(requests) -> bool:
    """Every faulted request was sent again, unchanged, and then answered."""
    for i, r in enumerate(requests):
        if r.fault is not None and not any(s.body == r.body and s.fault is None for s in requests[i + 1 :]):
            return False
    return True


def test_transient_faults_are_retried_and_the_run_completes(fixtures, clean, tmp_path, monkeypatch, figures):
    scaled_retry_backoff(monkeypatch, BACKOFF)
    bad_bodies = {"count": 0}
    real_completion = openai_server._completion

    def sometimes_not_a_completion(body: dict, text: str) -> dict:
        doc = real_completion(body, text)
        if bad_bodies["count"] < 2:  # two 200s whose JSON is no usable completion
            bad_bodies["count"] += 1
            doc["choices"][0]["message"]["content"] = {"text": text} if bad_bodies["count"] == 1 else None
            if bad_bodies["count"] == 2:
                doc["choices"] = None
        return doc

    monkeypatch.setattr(openai_server, "_completion", sometimes_not_a_completion)
    with FakeOpenAIServer(responder=caption_responder, hang_s=5) as server:
        server.inject("429", retry_after=0.6)
        server.inject("500")
        server.inject("reset")
        server.inject("malformed")
        server.inject("hang")
        server.inject("429", times=2, retry_after=0.1)
        t0 = time.monotonic()
        proc = run(server.base_url, fixtures, tmp_path / "run", "--concurrency", "1", "--timeout", "1")
        elapsed = time.monotonic() - t0
        seen = server.chat_requests
    assert proc.returncode == 0, proc.stderr
    faults = [r.fault for r in seen if r.fault is not None]
    assert sorted(faults) == sorted(["429", "500", "reset", "malformed", "hang", "429", "429"])
    assert bad_bodies["count"] == 2
    assert _retried_same_body(seen)
    # Retry-After: 0.6 s is honoured between the first 429 and its retry
    first = next(i for i, r in enumerate(seen) if r.fault == "429")
    assert seen[first + 1].received_at - seen[first].received_at >= 0.55
    assert transcripts_of(tmp_path / "run") == clean["transcripts"]
    assert cache_answers(tmp_path / "run-cache") == clean["answers"]
    figures(
        "server faults: transient",
        faults_injected=len(faults) + bad_bodies["count"],
        faults_survived=len(faults) + bad_bodies["count"],
        requests_sent=len(seen),
        answers_differing_from_fault_free_run=0,
        wall_s=round(elapsed, 1),
    )


def test_answers_no_file_can_hold_are_kept(fixtures, tmp_path):
    def responder(body: dict) -> str:
        return caption_responder(body).replace("gripper", "grip\ud800per")  # a lone surrogate, as JSON allows

    with FakeOpenAIServer(responder=responder) as server:
        proc = run(server.base_url, fixtures, tmp_path / "run")
    assert proc.returncode == 0, proc.stderr
    captions = [f["text"] for t in transcripts_of(tmp_path / "run").values() for f in t["frames"]]
    assert captions and all("grip\ufffdper" in c for c in captions)


def test_empty_answers_are_kept_then_asked_again(fixtures, clean, tmp_path):
    with FakeOpenAIServer(responder=caption_responder) as server:
        server.inject("empty", times=3)
        first = run(server.base_url, fixtures, tmp_path / "run", "--concurrency", "1")
        assert first.returncode == 0, first.stderr
        missing = sum(f["status"] == "missing" for t in transcripts_of(tmp_path / "run").values() for f in t["frames"])
        assert missing > 0  # the empty answers were used as what the model said
        stored = cache_answers(tmp_path / "run-cache")
        assert sum(text == "" for text in stored.values()) == 3  # kept, as empty answers
        before = len(server.chat_requests)
        again = run(server.base_url, fixtures, tmp_path / "run")
        assert again.returncode == 0, again.stderr
        # asked again: the empty ones, and the later requests whose prompts held "(no caption)" for them
        reusable = {k for k, text in stored.items() if text and k in clean["answers"]}
        assert len(server.chat_requests) - before == clean["requests"] - len(reusable) >= 3
    assert transcripts_of(tmp_path / "run") == clean["transcripts"]


@pytest.mark.parametrize(
    ("fault", "message"), [("500", "answered HTTP 500 after 5 tries"), ("429", "HTTP 429 after 5 tries")]
)
def test_persistent_faults_end_in_one_clear_line(fixtures, tmp_path, monkeypatch, fault, message, figures):
    waits = _retry_waits(monkeypatch)
    with FakeOpenAIServer(responder=caption_responder) as server:
        server.inject(fault, times=10_000, retry_after=0.05)
        proc = run(server.base_url, fixtures, tmp_path / "run")
        tries = len(server.chat_requests)
    line = assert_one_line_error(proc, message, "episode door_00", "0 of 8 requests answered")
    assert server.base_url in line
    # quickly, shown by what was decided, not by a clock: every wait was the server's Retry-After (not the SDK's
    # backoff of up to 8 s), and each request asked was tried 5 times, then the run stopped
    assert waits and set(waits) == {0.05}
    assert tries % (1 + RETRIES) == 0 and len(waits) == tries // (1 + RETRIES) * RETRIES
    figures("server faults: persistent", runs=1, one_line_errors=1, tracebacks=0)


def _retry_waits(monkeypatch) -> list[float]:
    """The seconds the SDK decides to wait before each retry (Retry-After, or its own backoff), as decided."""
    import openai._base_client as sdk

    waits, real = [], sdk.SyncAPIClient._calculate_retry_timeout

    def calculated(self, *args, **kwargs) -> float:
        wait = real(self, *args, **kwargs)
        waits.append(wait)  # list.append is atomic: requests retry in several threads at once
        return wait

    monkeypatch.setattr(sdk.SyncAPIClient, "_calculate_retry_timeout", calculated)
    return waits


def _dies_after(n: int):
    """A responder that answers ``n`` requests, then the server resets every connection: it is gone."""
    state = {"answered": 0, "server": None}

    def responder(body: dict) -> str:
        state["answered"] += 1
        if state["answered"] == n:
            state["server"].inject("reset", times=100_000)
        return caption_responder(body)

    return state, responder


def test_a_server_dying_mid_run_fails_fast_and_keeps_every_answer(fixtures, clean, tmp_path, monkeypatch, figures):
    counts = scaled_retry_backoff(monkeypatch, BACKOFF)
    state, responder = _dies_after(10)
    with FakeOpenAIServer(responder=responder, latency_s=0.02) as server:
        state["server"] = server
        t0 = time.monotonic()
        proc = run(server.base_url, fixtures, tmp_path / "run", "--concurrency", "2")
        elapsed = time.monotonic() - t0
        answered = sum(r.fault is None for r in server.chat_requests)
        refused = sum(r.fault == "reset" for r in server.chat_requests)
    assert_one_line_error(proc, "cannot reach", "is the server running")
    # one request's retries, not one per request: the 2 requests in flight when it died, and at most one more
    # each that a worker takes from the queue before the run stops (8 requests were still to be asked)
    assert refused % (1 + RETRIES) == 0 and refused // (1 + RETRIES) <= 2 * 2 < clean["requests"] - answered
    assert counts["retries"] == refused // (1 + RETRIES) * RETRIES
    kept = cache_answers(tmp_path / "run-cache")
    assert len(kept) == answered >= 10  # every answer the server gave is in the cache
    assert kept.items() <= clean["answers"].items()
    assert run_file(tmp_path / "run")["status"] == "running"  # not claimed complete

    with FakeOpenAIServer(responder=caption_responder) as healthy:
        proc = run(healthy.base_url, fixtures, tmp_path / "run")
        asked = len(healthy.chat_requests)
    assert proc.returncode == 0, proc.stderr
    assert asked == clean["requests"] - len(kept)  # only what was missing
    assert transcripts_of(tmp_path / "run") == clean["transcripts"]
    figures(
        "server faults: died mid-run",
        answers_before_death=answered,
        answers_kept=len(kept),
        answers_lost=answered - len(kept),
        asked_again_on_resume=0,
        requests_after_death=refused // (1 + RETRIES),
        failed_after_s=round(elapsed, 1),
    )


def test_a_dead_server_fails_fast(fixtures, tmp_path, monkeypatch, figures):
    counts = scaled_retry_backoff(monkeypatch, BACKOFF)
    dead = FakeOpenAIServer()
    dead.close()  # nothing listens on its port any more
    t0 = time.monotonic()
    proc = run(dead.base_url, fixtures, tmp_path / "run", "--concurrency", "4")
    elapsed = time.monotonic() - t0
    assert_one_line_error(proc, f"cannot reach {dead.base_url}", "0 of 8 requests answered")
    # the 4 requests in flight and at most a few a worker takes from the queue before the run stops, each
    # retried RETRIES times: not all 8 requests of the batch
    assert counts["retries"] % RETRIES == 0 and RETRIES <= counts["retries"] < 8 * RETRIES
    assert cache_answers(tmp_path / "run-cache") == {}
    figures(
        "server faults: dead server",
        runs=1,
        requests_tried=counts["retries"] // RETRIES,
        failed_after_s=round(elapsed, 1),
    )
