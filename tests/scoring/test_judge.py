"""`vlmproprio score --judge MODEL`: a judge model graded through the response cache and cassettes.

A judge's requests are content-addressed like captioning's, so recording its answers and replaying them
from the cassette gives the same verdicts bit for bit; the report shows rubric vs judge agreement (Cohen's
kappa). Tested with the tiny Qwen2-VL (whose answers are gibberish: every verdict unusable, and identical)
and with the loopback OpenAI-compatible server answering JSON verdicts (kappa defined).
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

from scoring_helpers import door_episode, prefill_embeddings, write_synthetic_run
from vlmproprio.cassettes import read_cassette
from vlmproprio.cli import main
from vlmproprio.embeddings import encoder_spec
from vlmproprio.report.data import load_run_scores
from vlmproprio.report.tables import report_tables, to_markdown
from vlmproprio.scoring import (
    ItemScore,
    ScoringError,
    judge_agreement,
    judge_captions,
    judge_request,
    parse_judge_answer,
    score_caption,
)
from vlmproprio.testing.openai_server import FakeOpenAIServer


def prefilled_cache(run: Path, root: Path) -> Path:
    """A cache root whose embeddings/ holds a vector for every caption of ``run``: scoring with ``--cache-dir
    root`` needs no encoder (a score reads ROOT/embeddings; the judge's answers go to ROOT/cache.db)."""
    prefill_embeddings(run, encoder_spec().key, cache_dir=root / "embeddings")
    return root


@pytest.fixture
def small_run(tmp_path):
    run, fx = tmp_path / "run", tmp_path / "fixtures"
    write_synthetic_run(run, fx, n_door=1, n_per_bin=1, n_frames=8, conditions=("none", "both"))
    return run, fx, prefilled_cache(run, tmp_path / "emb")


def judged(run: Path) -> dict:
    return json.loads((run / "scores" / "judge.json").read_text())


def score(run, cache_root, *extra) -> int:
    return main(["score", str(run), "--cache-dir", str(cache_root), *extra])


@pytest.mark.slow
def test_tiny_judge_live_then_replay_gives_identical_verdicts(small_run, tmp_path, tiny_qwen2vl_dir, capsys):
    run, fx, emb = small_run  # tiny-qwen2-vl: the session's build (tiny_qwen2vl_dir), not one of its own
    cache = prefilled_cache(run, tmp_path / "responses-cache")
    assert score(run, cache, "--judge", "tiny-qwen2-vl", "--judge-mode", "record") == 0
    recorded = judged(run)
    assert "rubric vs judge kappa" in capsys.readouterr().out
    cassette = read_cassette(fx / "responses" / "tiny-qwen2-vl.jsonl")  # the model's cassette, as captioning's
    assert cassette.entries and all(e.tag["stage"] == "judge" for e in cassette.entries.values())
    assert len(recorded["verdicts"]) == 10  # 5 episodes x 2 conditions
    # replay: answers only from the cassette (no cache, no model), the same verdicts bit for bit
    assert score(run, emb, "--judge", "tiny-qwen2-vl", "--judge-mode", "replay") == 0
    assert judged(run) == recorded
    # live again: every answer from the response cache, still the same
    assert score(run, cache, "--judge", "tiny-qwen2-vl", "--judge-mode", "live") == 0
    assert judged(run) == recorded


def _verdict(body: dict) -> str:
    """A rule judge behind the loopback server: trajectory correct only when the caption names a compartment
    side or 'toward'; everything mentioned; for one episode's captions an unusable answer."""
    user = body["messages"][-1]["content"]
    text = user if isinstance(user, str) else " ".join(p.get("text", "") for p in user)
    caption = text.split('"""')[1]
    if "into the far right compartment" in text:  # the instruction of bin1_00
        return "no idea"
    ok = bool(re.search(r"toward|left|right", caption))
    items = {k: {"mentioned": True, "correct": ok or k != "trajectory"} for k in ("object", "action", "trajectory")}
    return "Verdict: " + json.dumps(items)


def test_openai_judge_replays_and_the_report_shows_kappa(small_run, tmp_path, monkeypatch):
    run, _, emb = small_run
    monkeypatch.setenv("OPENAI_API_KEY", "test-key")
    cache = prefilled_cache(run, tmp_path / "responses-cache")
    with FakeOpenAIServer(responder=_verdict) as server:
        args = ["--judge", "openai:rule-judge", "--base-url", server.base_url, "--judge-mode", "record"]
        assert score(run, cache, *args) == 0
        asked = len(server.requests)
    recorded = judged(run)
    assert 0 < asked <= 10 and recorded["agreement"]["n"] == 10
    # the server is gone: replay answers from the cassette alone
    assert score(run, emb, "--judge", "openai:rule-judge", "--judge-mode", "replay") == 0
    assert judged(run) == recorded
    tables = report_tables(load_run_scores(run))
    table = next(t for t in tables if t.anchor == "judge")
    md = to_markdown(table)
    assert "Cohen's κ" in md and "trajectory correct" in md
    kappa = recorded["agreement"]["items"]["object_mentioned"]["kappa"]
    assert kappa is None or isinstance(kappa, float)
    assert recorded["agreement"]["unparsed"] == 2  # bin1_00 under both conditions


# ---------------------------------------------------------------------------------------------- the judge's parts


def test_a_judge_answer_is_read_from_its_first_json_object():
    raw = 'Sure. {"object": {"mentioned": true, "correct": true}, "action": {"mentioned": true, "correct": false},'
    raw += ' "trajectory": {"mentioned": false, "correct": true}} and more {}'
    v = parse_judge_answer(raw)
    assert v.error == "" and v.raw == raw
    assert v.items["object"] == ItemScore(True, True, False)
    assert v.items["action"] == ItemScore(True, False, True)
    assert v.items["trajectory"] == ItemScore(False, False, False)  # correct without a mention is not correct
    assert v.to_dict()["items"]["action"] == {"mentioned": True, "correct": False, "wrong": True}


@pytest.mark.parametrize(
    ("raw", "error"),
    [
        ("no verdict", "no JSON object"),
        ("{not json", "unusable answer (JSONDecodeError"),
        ('{"object": {"mentioned": true, "correct": true}}', "unusable answer (KeyError"),
        ('{"object": {"mentioned": "yes", "correct": true}}', "unusable answer (TypeError: object"),
    ],
)
def test_an_unusable_judge_answer_is_a_verdict_with_an_error(raw, error):
    v = parse_judge_answer(raw)
    assert v.items is None and v.error.startswith(error)


def test_judge_request_states_the_episodes_ground_truth():
    ep = door_episode()
    req = judge_request("It opens the door.", ep, "both")
    assert req.tag.stage == "judge" and req.tag.condition == "both" and req.tag.episode_id == ep.episode_id
    assert req.config.temperature == 0.0 and req.prompt_version.startswith("judge-v")
    user = req.messages[-1].parts[-1].text
    assert "It opens the door." in user and "pull door:" in user


def test_judge_captions_refuses_a_short_answer():
    with pytest.raises(ScoringError, match="judge answered 0 of 1 requests"):
        judge_captions(lambda requests: [], [("It opens the door.", door_episode(), "none")])
    assert judge_captions(lambda requests: [], []) == []


def test_agreement_counts_unparsed_verdicts_and_gives_kappa():
    ep = door_episode()
    rubric = [score_caption(t, ep) for t in ("It opens the door.", "The robot waves.", "It pulls the door.")]
    yes = {"mentioned": True, "correct": True}
    no = {"mentioned": False, "correct": False}
    answers = [{"object": yes, "action": yes, "trajectory": no}, {"object": no, "action": no, "trajectory": no}]
    verdicts = [parse_judge_answer(json.dumps(a)) for a in answers] + [parse_judge_answer("?")]
    out = judge_agreement(rubric, verdicts)
    assert out["n"] == 3 and out["unparsed"] == 1
    assert out["items"]["object_mentioned"] == {"n": 2, "agreement": 1.0, "kappa": 1.0}
    assert out["items"]["trajectory_mentioned"]["kappa"] is None  # one class only: kappa undefined
    with pytest.raises(ValueError, match="3 rubric scores but 2 judge verdicts"):
        judge_agreement(rubric, verdicts[:2])
