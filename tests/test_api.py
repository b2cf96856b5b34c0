"""Your own model from Python: vlmproprio.evaluate with a callable, its cassette replayed to the same scores,
and the same model named py:package.module:factory on the command line."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

import vlmproprio
from vlmproprio.chat import ChatRequest
from vlmproprio.episodes.manifest import write_manifest
from vlmproprio.errors import UsageError

ROOT = Path(__file__).resolve().parents[1]
EPISODES = ("door_00", "bin0_00")
CONDITIONS = "none,both"
WORDS = ("moves forward", "closes the gripper", "turns the handle down", "lifts the box up", "moves left")

# a deterministic toy VLM: its captions depend on the images and the process, as a real model's would
TOY = f"""
import hashlib

WORDS = {WORDS!r}


def answer(request):
    text = "".join(m.text for m in request.messages)
    images = request.images
    if "Summaries of the task:" in text:
        return "Open the door by pulling the handle." if "door" in text.lower() else "Pick up the box and place it."
    if "Described robot arm actions:" in text:
        return "The robot arm " + WORDS[len(images) % len(WORDS)] + "."
    pick = [int(hashlib.sha256(i.data).hexdigest()[:6], 16) % len(WORDS) for i in images]
    return "\\n".join(f"Frame {{n + 1}}: The arm {{WORDS[p]}}." for n, p in enumerate(pick))


def factory():
    return answer
"""


@pytest.fixture
def toy_module(tmp_path, monkeypatch):
    pkg = tmp_path / "pkgs"
    pkg.mkdir()
    (pkg / "toyvlm.py").write_text(TOY)
    monkeypatch.syspath_prepend(str(pkg))
    import importlib

    return importlib.import_module("toyvlm"), pkg


@pytest.fixture
def fixtures(tmp_path) -> Path:
    dest = tmp_path / "fixtures"
    for eid in EPISODES:
        shutil.copytree(ROOT / "fixtures" / "episodes" / eid, dest / "episodes" / eid)
    write_manifest(dest)
    return dest


def _same(a, b) -> bool:
    """Equal, NaN included (json writes NaN as NaN on both sides)."""
    return json.dumps(a, sort_keys=True) == json.dumps(b, sort_keys=True)


def _scores(rows: list[dict]) -> list[dict]:
    drop = {"model"}
    return [{k: v for k, v in r.items() if k not in drop} for r in rows]


def test_a_callable_records_and_its_cassette_replays_to_the_same_scores(toy_module, fixtures, tmp_path) -> None:
    toy, _ = toy_module
    cache = tmp_path / "cache"
    live = vlmproprio.evaluate(
        toy.answer,
        EPISODES,
        CONDITIONS,
        tmp_path / "live",
        name="toy",
        revision="1",
        fixtures=fixtures,
        mode="record",
        cache_dir=cache,
        progress=False,
    )
    assert live.mode == "record" and live.cassette is not None and live.cassette.is_file()
    assert any(r["final_words"] for r in live.rows) and len(live.rows) == 4
    replayed = vlmproprio.evaluate(
        "py:toy",
        EPISODES,
        CONDITIONS,
        tmp_path / "replay",
        fixtures=fixtures,
        mode="replay",
        cache_dir=tmp_path / "other-cache",
        progress=False,
    )
    assert replayed.mode == "replay"
    assert _same(_scores(replayed.rows), _scores(live.rows))
    assert _same(replayed.paired, live.paired)


def test_identity_is_part_of_the_cache_key(toy_module, fixtures, tmp_path) -> None:
    toy, _ = toy_module
    calls = []

    def counting(request: ChatRequest) -> str:
        calls.append(1)
        return toy.answer(request)

    kw = dict(episodes=EPISODES[:1], conditions="none", fixtures=fixtures, mode="live", cache_dir=tmp_path / "c")
    vlmproprio.evaluate(counting, out=tmp_path / "a", name="toy2", revision="1", progress=False, **kw)
    first = len(calls)
    vlmproprio.evaluate(counting, out=tmp_path / "b", name="toy2", revision="1", progress=False, **kw)
    assert len(calls) == first  # the same identity: every answer from the cache
    vlmproprio.evaluate(counting, out=tmp_path / "c2", name="toy2", revision="2", progress=False, **kw)
    assert len(calls) == 2 * first  # a new revision: asked again


def test_model_objects_need_a_name_and_bad_models_are_named(fixtures, tmp_path) -> None:
    with pytest.raises(UsageError, match="needs name="):
        vlmproprio.evaluate(lambda r: "x", fixtures=fixtures, out=tmp_path / "r")

    def broken(request):
        raise RuntimeError("out of memory")

    from vlmproprio.errors import VlmproprioError

    with pytest.raises(VlmproprioError, match="py:broken: the model raised RuntimeError: out of memory"):
        vlmproprio.evaluate(
            broken,
            EPISODES[:1],
            "none",
            tmp_path / "r",
            name="broken",
            fixtures=fixtures,
            mode="live",
            cache_dir=tmp_path / "c",
            progress=False,
        )


def test_the_cli_runs_a_factory_named_py(toy_module, fixtures, tmp_path) -> None:
    _, pkg = toy_module
    env = {"PYTHONPATH": f"{pkg}:{ROOT / 'src'}", "VLMPROPRIO_CACHE": str(tmp_path / "cache"), "PATH": "/usr/bin:/bin"}
    cmd = [sys.executable, "-m", "vlmproprio.cli", "run", "--model", "py:toyvlm:factory", "--fixtures", str(fixtures)]
    cmd += ["--episodes", EPISODES[0], "--conditions", "none", "--out", str(tmp_path / "run"), "--no-progress"]
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=300, check=False)
    assert proc.returncode == 0, proc.stderr
    assert "py:toyvlm:factory: 1 transcripts" in proc.stdout
    missing = subprocess.run(
        [*cmd[:5], "py:nowhere.mod:factory", *cmd[6:]],
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
    )
    assert missing.returncode == 2 and "cannot import nowhere.mod" in missing.stderr
    assert "Traceback" not in missing.stderr
