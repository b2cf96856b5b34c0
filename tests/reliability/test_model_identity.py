"""Issue 15, defect 2: two model names, one folder.

Names whose readable parts sanitise alike (``openai:org/m`` and ``openai:org_m``, two checkpoints both called
``checkpoint-500``, upper and lower case) must get different transcripts folders and cassettes; a model that
would still meet another's folder or cassette is refused naming both; and no error advises a command that
would delete another model's answers (the old advice was ``--replace``).
"""

from __future__ import annotations

import json

import pytest
from fault_support import cli_in_process
from reliability_support import assert_one_line_error, caption_responder, cli, cli_env, fixture_subset

from extras import needs_openai
from vlmproprio.models import resolve_model
from vlmproprio.testing.openai_server import FakeOpenAIServer

# checked, not imported: collecting this module on every xdist worker must not cost the SDK's ~1 CPU s
pytestmark = needs_openai

PAIRS = [
    ("openai:org/m", "openai:org_m"),
    ("hf:/ckpt/run1/checkpoint-500", "hf:/ckpt/run2/checkpoint-500"),
    ("hf:org/name", "hf:org_name"),
    ("openai:GPT-4o", "openai:gpt-4o"),
    ("openai:a b", "openai:a_b"),
    ("openai:org_m-9e955f65", "openai:org/m"),
    ("hf:./tiny", "hf:/x/tiny"),
    ("hf:Qwen/Qwen2-VL-2B-Instruct", "hf:/models/Qwen/Qwen2-VL-2B-Instruct"),
]


@pytest.mark.parametrize(("a", "b"), PAIRS)
def test_names_that_sanitise_alike_get_different_folders(a, b, figures):
    sa, sb = resolve_model(a).slug, resolve_model(b).slug
    assert sa.lower() != sb.lower()  # different even on a case-insensitive disk
    figures("model name collisions", pairs=1, disambiguated=1, refused=0, overwritten=0)


def test_registry_names_keep_their_folders():
    """Shipped cassettes and baselines are named by registry name: those names must not change."""
    assert resolve_model("reference").slug == "reference" and resolve_model("tiny-qwen2-vl").slug == "tiny-qwen2-vl"
    assert resolve_model("openai:gpt-4o").slug == "openai_gpt-4o"


def test_two_colliding_models_recorded_into_one_run_and_fixtures_keep_both(tmp_path, figures):
    fixtures = fixture_subset(tmp_path / "fixtures", ["door_00"])
    env = cli_env(VLMPROPRIO_CACHE=str(tmp_path / "cache"))
    run = tmp_path / "run"
    a, b = "openai:org/m", "openai:org_m"
    with FakeOpenAIServer(responder=lambda body: f"{body['model']}: " + caption_responder(body)) as server:
        for name in (a, b):
            # in this process: each recording embeds its new captions for the cassette's sidecar, and importing
            # torch (which the test process has, or keeps for the next test) was most of a subprocess's CPU
            proc = cli_in_process(
                [
                    *(
                        "run",
                        "--model",
                        name,
                        "--base-url",
                        server.base_url,
                        "--mode",
                        "record",
                        "--fixtures",
                        fixtures,
                    ),
                    *("--episodes", "door_00", "--conditions", "none", "--frame-stride", "3", "--out", run),
                    "--no-progress",
                ],
                env={"VLMPROPRIO_CACHE": env["VLMPROPRIO_CACHE"]},
            )
            assert proc.returncode == 0, proc.stderr
    cassettes = {n: fixtures / "responses" / f"{resolve_model(n).slug}.jsonl" for n in (a, b)}
    assert all(p.is_file() for p in cassettes.values()) and len(set(cassettes.values())) == 2
    for name, path in cassettes.items():  # each cassette holds its own model's answers
        lines = path.read_text().splitlines()
        assert json.loads(lines[0])["model"] == resolve_model(name).slug
        assert all(json.loads(line)["text"].startswith(name.removeprefix("openai:")) for line in lines[1:])
    doc = json.loads((run / "run.json").read_text())
    assert [m["name"] for m in doc["models"]] == [a, b]  # the second run added its model, kept the first
    for name in (a, b):
        t = json.loads((run / "transcripts" / resolve_model(name).slug / "door_00__none.json").read_text())
        assert t["final"].startswith(name.removeprefix("openai:"))

    # exporting one model's answers over the other's cassette: refused, no destructive advice, file unchanged
    before = cassettes[a].read_bytes()
    proc = cli(
        [
            *("cassette", "export", "--model", b),  # the cache: $VLMPROPRIO_CACHE
            *("--out", cassettes[a], "--replace"),
        ],
        env=env,
    )
    line = assert_one_line_error(proc, resolve_model(a).slug, resolve_model(b).slug)
    assert "--replace" not in line and cassettes[a].read_bytes() == before
    figures("model name collisions", pairs=1, disambiguated=1, refused=0, overwritten=0)
    figures("destructive advice", errors=1, advising_replace=0, cassettes_overwritten=0)


def test_a_folder_recorded_for_another_model_is_refused_naming_both(tmp_path, figures):
    fixtures = fixture_subset(tmp_path / "fixtures", ["door_00"])
    env = cli_env(VLMPROPRIO_CACHE=str(tmp_path / "cache"))
    run = tmp_path / "run"
    args = ["run", "--model", "reference", "--episodes", "door_00", "--conditions", "none", "--frame-stride", "3"]
    assert cli([*args, "--fixtures", fixtures, "--out", run, "--no-progress"], env=env).returncode == 0
    doc = json.loads((run / "run.json").read_text())
    doc["models"][0]["name"] = "openai:reference"  # as if another model had written transcripts/reference/
    (run / "run.json").write_text(json.dumps(doc))
    proc = cli([*args, "--fixtures", fixtures, "--out", run, "--no-progress"], env=env)
    assert_one_line_error(proc, "'reference'", "'openai:reference'")
    figures("model name collisions", pairs=1, disambiguated=0, refused=1, overwritten=0)
