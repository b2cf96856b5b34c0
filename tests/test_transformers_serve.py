"""A real OpenAI-compatible server that is not ours: `transformers serve`.

A tiny random LLaVA (the build of `vlmproprio make-tiny-model --family llava`) served by `transformers serve`
must give, through the `openai:` backend, exactly the answers the in-process `hf:` backend gives for the same
checkpoint: every frame, scene and final caption of one Door episode (under ``both``). Needs the `serve`
extra (fastapi, uvicorn); `scripts/setup.sh` installs it with `all`.
"""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
# One condition: the property is per answer, and every request takes the same path on both sides (the openai:
# backend's message building, the server's chat template and generate(); the hf: backend's). ``both`` has every
# message layout ``none`` has (per stage: text, 5 images or the last group's 1 image, 31 in Process 3; text after
# the images) plus the state text, so ``none`` added no layout, only ~12 s of CPU for another 15 answers per side.
EPISODE, CONDITIONS = "door_00", "both"
# A random model never stops early: every answer runs to the token budget (512 for an hf:/openai: model, with
# most of the time in decoding). 64, the registry's tiny models' budget, still makes every answer ~90-260
# characters of input-dependent text, and an exact comparison fails at the first token that differs.
MAX_NEW_TOKENS = "64"

pytestmark = pytest.mark.slow


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def tiny_llava(tiny_model) -> Path:
    # built in this process (the session's build): what is tested is serving it, not building it in a fresh
    # process (tests/backends/test_hf.py checks that, through the CLI); ensure_tiny_model verifies its files on every use
    return tiny_model("llava")


@pytest.fixture(scope="module")
def server(tiny_llava, tmp_path_factory):
    pytest.importorskip("fastapi", reason="transformers serve needs the serve extra: pip install 'vlmproprio[serve]'")
    pytest.importorskip("uvicorn", reason="transformers serve needs the serve extra: pip install 'vlmproprio[serve]'")
    port = _free_port()
    log = tmp_path_factory.mktemp("serve") / "serve.log"
    env = {**os.environ, "HF_HUB_OFFLINE": "1", "OMP_NUM_THREADS": "1", "TOKENIZERS_PARALLELISM": "false"}
    cli = Path(sys.executable).with_name("transformers")
    cmd = [str(cli), "serve", str(tiny_llava), "--host", "127.0.0.1", "--port", str(port), "--device", "cpu"]
    with log.open("w") as out:
        proc = subprocess.Popen(cmd, stdout=out, stderr=subprocess.STDOUT, env=env)
    base = f"http://127.0.0.1:{port}/v1"
    try:
        deadline = time.monotonic() + 180
        while True:
            try:
                with urllib.request.urlopen(f"{base}/models", timeout=2) as r:
                    if r.status == 200:
                        break
            except OSError:
                pass
            if proc.poll() is not None or time.monotonic() > deadline:
                pytest.fail(f"transformers serve did not come up:\n{log.read_text()[-3000:]}")
            time.sleep(0.5)
        yield base
    finally:
        proc.terminate()
        try:
            proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            proc.kill()


def _raw_answers(cache: Path, model: str) -> dict:
    """Every raw answer of ``model`` in the response cache, by (episode, condition, stage, group)."""
    from vlmproprio.cache import ResponseCache
    from vlmproprio.models import resolve_model

    with ResponseCache(cache) as c:
        return {
            (e.tag["episode_id"], e.tag["condition"], e.tag["stage"], e.tag["group"]): e.text
            for e in c.entries(resolve_model(model).slug)
        }


def _captions(run_dir: Path) -> dict:
    from vlmproprio.transcripts import read_transcripts

    return {
        (t.episode_id, t.condition): (
            [f.text for f in t.frames],
            [s.text for s in t.scenes],
            t.final,
            [f.status for f in t.frames],
        )
        for t in read_transcripts(run_dir)
    }


def _run(model: str, out: Path, cache: Path, *extra: str) -> None:
    from vlmproprio.cli import main

    args = ["run", "--model", model, "--fixtures", str(REPO / "fixtures"), "--episodes", EPISODE]
    args += ["--conditions", CONDITIONS, "--mode", "live", "--out", str(out), "--cache-dir", str(cache)]
    args += ["--max-new-tokens", MAX_NEW_TOKENS]
    assert main([*args, "--no-progress", *extra]) == 0


def test_transformers_serve_answers_exactly_as_the_hf_backend(server, tiny_llava, tmp_path, torch_one_thread):
    served_model, local_model = f"openai:{tiny_llava}", f"hf:{tiny_llava}"
    t0 = time.perf_counter()
    _run(served_model, tmp_path / "served", tmp_path / "cache", "--base-url", server, "--concurrency", "2")
    served_s = time.perf_counter() - t0
    _run(local_model, tmp_path / "local", tmp_path / "cache", "--threads", "1", "--dtype", "float32")
    raw_served, raw_local = (
        _raw_answers(tmp_path / "cache", served_model),
        _raw_answers(tmp_path / "cache", local_model),
    )
    stages = {k[2] for k in raw_local}
    assert stages == {"p1", "p2", "p3"} and len(raw_local) >= 10, sorted(raw_local)
    assert any(raw_local.values()), "the local model wrote nothing: nothing would be compared"
    assert len(set(raw_local.values())) > 1  # answers depend on the input, so equality means something
    assert raw_served == raw_local, (
        f"answers differ at {sorted(k for k in raw_local if raw_served.get(k) != raw_local[k])}"
    )
    served, local = _captions(tmp_path / "served"), _captions(tmp_path / "local")
    assert set(served) == set(local) == {(EPISODE, c) for c in CONDITIONS.split(",")}
    assert served == local  # frame, scene and final captions (and their parse statuses)
    print(f"transformers serve: {len(raw_served)} answers identical to hf:, served run {served_s:.1f} s")
