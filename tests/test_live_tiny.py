"""The live path of a real transformers model, end to end: the tiny Qwen2-VL run live on one episode gives
exactly the answers its committed cassette holds (and so the transcripts the benchmark replays)."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest

from vlmproprio.cassettes import read_cassette
from vlmproprio.conditions import parse_conditions
from vlmproprio.episodes import load_episode
from vlmproprio.pipeline import calls_per_episode
from vlmproprio.runner import RunPlan, run
from vlmproprio.transcripts import read_transcripts

# checked, not imported: every xdist worker collects this module, and only the one that runs it needs transformers
pytestmark = pytest.mark.skipif(
    importlib.util.find_spec("transformers") is None, reason="the live path needs the [hf] extra"
)

FIXTURES = Path(__file__).resolve().parents[1] / "fixtures"
MODEL = "tiny-qwen2-vl"


@pytest.mark.slow
def test_tiny_model_live_matches_its_cassette(tmp_path: Path, tiny_qwen2vl_dir: Path) -> None:
    from vlmproprio.backends.registry import BackendSettings
    from vlmproprio.backends.tiny import tiny_model_dir

    # the run builds nothing: the registry's tiny-qwen2-vl is the session's build (the build is tested elsewhere)
    assert tiny_qwen2vl_dir == tiny_model_dir("qwen2-vl")

    cassette = read_cassette(FIXTURES / "responses" / f"{MODEL}.jsonl")
    # images + both states, states only: every kind of prompt the model can get. Images only (``none``) is left
    # out: the check is per answer, and ``both`` has every message layout ``none`` has (per stage: text, 5 images
    # or the last group's 1 image, 31 in Process 3; text after the images) plus the state text; its 15 answers,
    # with their 31-image Process 3 prompt, were a third of the test's CPU time and added no code path
    conditions = tuple(parse_conditions("both,state_only"))
    common = dict(models=(MODEL,), conditions=conditions, fixtures=FIXTURES, episode_ids=("door_02",), progress=False)
    [live] = run(
        RunPlan(
            out=tmp_path / "live",
            mode="live",
            cache_dir=tmp_path / "cache",
            backend=BackendSettings.of(threads=1),
            **common,
        )
    )
    n_frames = len(load_episode(FIXTURES, "door_02").frames)
    assert live.stats["misses"] == len(conditions) * calls_per_episode(n_frames, 5)  # all asked of the model
    used = {r.key for t in live.transcripts for r in t.requests}
    assert used <= set(cassette.entries), "a live request has a key the cassette lacks"
    run(RunPlan(out=tmp_path / "replay", mode="replay", **common))
    strip = lambda ts: [t.to_dict() | {"requests": None, "timing": None} for t in ts]  # noqa: E731
    assert strip(read_transcripts(tmp_path / "live")) == strip(read_transcripts(tmp_path / "replay"))
