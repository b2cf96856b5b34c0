"""Issue 36, item 8: answers with no caption in them.

A server can answer 200 with a valid completion that holds no caption: a refusal (``message.refusal``), a tool
call, ``finish_reason`` content_filter, an answer cut to nothing at the token limit (``length``), a first choice
without a message, everything in the reasoning field (a reasoning parser on a model that does not think), or
an answer from a model other than the one asked for. Each class, end to end against the loopback server:

* the run names it: one warning line with the class and how many requests, and the transcript records the
  class (``problem``), the server's finish reason and the model it says answered, per request (and
  ``vlmproprio show`` prints them below the answer);
* record mode refuses to write a cassette of such answers (one error line naming the class, the count and
  ``--allow-empty-answers``), leaves no cassette behind, and writes it when the flag is given;
* the score's sanity check says so when most of a model's frame captions are missing for such reasons.

Before this, each of these runs exited 0 silently with 100 % of its captions missing, and record mode committed
a cassette of empty answers.
"""

from __future__ import annotations

from pathlib import Path

import pytest
from fault_support import cli_in_process
from reliability_support import assert_one_line_error, caption_responder, fixture_subset, transcripts_of

from extras import needs_openai
from vlmproprio.models import resolve_model
from vlmproprio.testing.openai_server import NO_CAPTION_KINDS, OTHER_MODEL, FakeOpenAIServer

# checked, not imported: collecting this module on every xdist worker must not cost the SDK's ~1 CPU s
pytestmark = needs_openai

MODEL = "openai:fake-vlm"
# the class each of the server's shapes is named by (chat.ANSWER_PROBLEMS); a first choice without a message
# is an empty answer that gives no reason
CLASS_OF = {kind: kind for kind in NO_CAPTION_KINDS} | {"empty_choice": "empty"}
# the finish reason the server sends with each shape
FINISH = {"tool_calls": "tool_calls", "content_filter": "content_filter", "length": "length", "empty_choice": ""}
ALL = 10_000  # more injected answers than any run here sends


@pytest.fixture(scope="module")
def fixtures(tmp_path_factory) -> Path:
    return fixture_subset(tmp_path_factory.mktemp("no-caption") / "fixtures", ["door_00"])


def run(base_url: str, fixtures: Path, out: Path, *extra: str):
    args = ["run", "--model", MODEL, "--base-url", base_url, "--fixtures", fixtures, "--conditions", "none"]
    args += ["--frame-stride", "3", "--no-progress", "--out", out, "--cache-dir", out.parent / f"{out.name}-cache"]
    return cli_in_process([*args, *extra])


def _requests(run_dir: Path) -> list[dict]:
    return [r for t in transcripts_of(run_dir).values() for r in t["requests"]]


def _frames(run_dir: Path) -> list[dict]:
    return [f for t in transcripts_of(run_dir).values() for f in t["frames"]]


@pytest.mark.parametrize("kind", NO_CAPTION_KINDS)
def test_each_class_is_named_and_recorded_in_the_transcript(kind, fixtures, tmp_path, figures):
    with FakeOpenAIServer(responder=caption_responder) as server:
        server.inject(kind, times=ALL)
        proc = run(server.base_url, fixtures, tmp_path / "run")
        sent = len(server.chat_requests)
    assert proc.returncode == 0, proc.stderr
    requests = _requests(tmp_path / "run")
    assert len(requests) == sent > 0
    assert {r["problem"] for r in requests} == {CLASS_OF[kind]}
    assert {r["response_model"] for r in requests} == {OTHER_MODEL if kind == "other_model" else "fake-vlm"}
    assert {r.get("finish_reason", "") for r in requests} == {FINISH.get(kind, "stop")}
    warnings = [line for line in proc.stderr.splitlines() if line.startswith("warning:")]
    assert len(warnings) == 1, proc.stderr
    assert f"{CLASS_OF[kind]} {sent} (" in warnings[0] and f"{sent} of {sent} answers" in warnings[0]
    missing = sum(f["status"] == "missing" for f in _frames(tmp_path / "run"))
    if kind == "other_model":  # another model's captions are there; they are not this model's
        assert missing == 0 and "MOST CAPTIONS ARE MISSING" not in warnings[0]
    else:
        assert missing == len(_frames(tmp_path / "run")) and "MOST CAPTIONS ARE MISSING" in warnings[0]
    figures("no-caption answers: named", classes=1, requests=sent, silent=0)


@pytest.mark.parametrize("kind", NO_CAPTION_KINDS)
def test_record_mode_refuses_a_cassette_of_such_answers(kind, fixtures, tmp_path, figures):
    cassette = fixtures / "responses" / f"{resolve_model(MODEL).slug}.jsonl"
    with FakeOpenAIServer(responder=caption_responder) as server:
        server.inject(kind, times=ALL)
        proc = run(server.base_url, fixtures, tmp_path / "run", "--mode", "record")
        sent = len(server.chat_requests)
    assert_one_line_error(proc, f"{CLASS_OF[kind]} {sent} (", "--allow-empty-answers", f"{sent} of {sent} answers")
    assert not cassette.exists()
    figures("no-caption answers: cassettes refused", classes=1, refused=1, written=0)


def test_a_few_such_answers_are_named_too(fixtures, tmp_path):
    with FakeOpenAIServer(responder=caption_responder) as server:
        server.inject("refusal")  # the first Process 1 group's answer: 5 of the 11 frames
        proc = run(server.base_url, fixtures, tmp_path / "run", "--concurrency", "1")
        sent = len(server.chat_requests)
    assert proc.returncode == 0, proc.stderr
    (warning,) = [line for line in proc.stderr.splitlines() if line.startswith("warning:")]
    assert f"1 of {sent} answers" in warning and "refusal 1 (" in warning and "MOST" not in warning
    assert sum(r.get("problem") == "refusal" for r in _requests(tmp_path / "run")) == 1
    show = cli_in_process(["show", tmp_path / "run", "--episode", "door_00", "--condition", "none"])
    assert show.returncode == 0, show.stderr
    (line,) = [line for line in show.stdout.splitlines() if "answer problem" in line]
    assert "refusal (the model refused" in line and "response model fake-vlm" in line


def test_plain_answers_give_no_warning_and_record(fixtures, tmp_path):
    with FakeOpenAIServer(responder=caption_responder) as server:
        proc = run(server.base_url, fixtures, tmp_path / "run")
    assert proc.returncode == 0, proc.stderr
    assert "warning:" not in proc.stderr
    requests = _requests(tmp_path / "run")
    assert all("problem" not in r and r["finish_reason"] == "stop" for r in requests)


def test_the_flag_records_them_and_the_replay_gives_the_same_transcripts(tmp_path):
    fixtures = fixture_subset(tmp_path / "fixtures", ["door_00"])
    cassette = fixtures / "responses" / f"{resolve_model(MODEL).slug}.jsonl"
    with FakeOpenAIServer(responder=caption_responder) as server:
        server.inject("refusal", times=ALL)
        proc = run(server.base_url, fixtures, tmp_path / "run", "--mode", "record", "--allow-empty-answers")
    assert proc.returncode == 0, proc.stderr
    assert cassette.is_file() and "refusal" in cassette.read_text()
    replay = run("http://127.0.0.1:9/v1", fixtures, tmp_path / "replay", "--mode", "replay")
    assert replay.returncode == 0, replay.stderr
    assert "refusal" in replay.stderr  # a replay of such answers is named as well
    assert transcripts_of(tmp_path / "replay") == transcripts_of(tmp_path / "run")


def test_cassette_export_refuses_them_without_the_flag(fixtures, tmp_path):
    with FakeOpenAIServer(responder=caption_responder) as server:
        server.inject("content_filter", times=ALL)
        assert run(server.base_url, fixtures, tmp_path / "run").returncode == 0
    out = tmp_path / "exported.jsonl"
    export = ["cassette", "export", "--model", MODEL, "--cache-dir", tmp_path / "run-cache", "--out", out]
    proc = cli_in_process([*export, "--no-embed"])
    assert_one_line_error(proc, "content_filter", "--allow-empty-answers")
    assert not out.exists()
    proc = cli_in_process([*export, "--no-embed", "--allow-empty-answers"])
    assert proc.returncode == 0, proc.stderr
    assert out.is_file()
