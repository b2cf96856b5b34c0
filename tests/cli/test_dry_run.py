"""`run --dry-run`: the run's own requests counted, the cache asked, no model called, nothing written;
`run --limit N`: the first N episodes."""

from __future__ import annotations

import json
import re
from pathlib import Path

from vlmproprio.cli import main
from vlmproprio.episodes import load_episodes
from vlmproprio.testing.openai_server import FakeOpenAIServer

ROOT = Path(__file__).resolve().parents[2]
CELLS = ["--episodes", "door_00,bin0_00", "--conditions", "none,both", "--frame-stride", "3", "--no-progress"]


def _totals(text: str) -> list[tuple[int, int, str, str]]:
    return [
        (int(a), int(b), c, d) for a, b, c, d in re.findall(r"^  total\s+(\d+)\s+(\d+)\s+(\S+)\s+(\S+)$", text, re.M)
    ]


def test_dry_run_counts_the_runs_requests_and_asks_the_cache_only(tmp_path, monkeypatch, capsys) -> None:
    monkeypatch.setenv("VLMPROPRIO_CACHE", str(tmp_path / "cache"))
    monkeypatch.setenv("OPENAI_API_KEY", "sk-test")
    out = tmp_path / "run"
    with FakeOpenAIServer() as server:
        args = ["run", "--model", "openai:m", "--base-url", server.base_url, "--out", str(out), *CELLS]
        assert main([*args, "--dry-run"]) == 0
        [(requests, images, cached, to_compute)] = _totals(capsys.readouterr().out)
        assert (cached, to_compute) == ("0", str(requests)) and not server.requests and not out.exists()
        assert main([*args, "--mode", "live"]) == 0  # the real run: exactly the requests counted
        capsys.readouterr()
        sent = [r for r in server.requests if r.path.endswith("/chat/completions")]
        assert len(sent) == requests
        assert images == sum(
            sum(p.get("type") == "image_url" for m in r.body["messages"] for p in m["content"] if isinstance(p, dict))
            for r in sent
        )
        assert main([*args, "--dry-run"]) == 0  # now every answer, Processes 2 and 3 included, is cached
        assert _totals(capsys.readouterr().out) == [(requests, images, str(requests), "0")]
        assert len(server.requests) == len(sent)  # the dry runs sent nothing


def test_dry_run_of_a_model_that_cannot_run_still_counts(tmp_path, monkeypatch, capsys) -> None:
    monkeypatch.delenv("OPENAI_API_KEY", raising=False)
    monkeypatch.delenv("OPENAI_BASE_URL", raising=False)
    assert main(["run", "--model", "gpt-4o", "--out", str(tmp_path / "r"), *CELLS, "--dry-run"]) == 0
    text = capsys.readouterr().out
    [(requests, _, cached, _)] = _totals(text)
    assert requests > 0 and cached == "?" and "cached answers unknown" in text


def test_limit_runs_the_first_episodes(tmp_path, monkeypatch) -> None:
    monkeypatch.setenv("VLMPROPRIO_CACHE", str(tmp_path / "cache"))
    out = tmp_path / "run"
    assert main(["run", "--model", "reference", "--out", str(out), "--limit", "3", "--no-progress"]) == 0
    first = [e.episode_id for e in load_episodes(ROOT / "fixtures")][:3]
    assert json.loads((out / "run.json").read_text())["episodes"] == first
    assert main(["run", "--model", "reference", "--out", str(out), "--limit", "0"]) == 2  # one line, named
