"""Results people can load: run.json and scores/*.json match their shipped JSON Schemas, the per-frame CSV
agrees with the scores, and `vlmproprio show` re-renders exactly the prompts that were sent."""

from __future__ import annotations

import copy
import csv
import json
from pathlib import Path

import pytest

from vlmproprio.cli import main
from vlmproprio.schemas import RUN_FILES, SchemaError, load_schema, schema_names, validate_run

jsonschema = pytest.importorskip("jsonschema", reason="the schema checks need jsonschema (the dev extra)")

REPO = Path(__file__).resolve().parents[1]
EPISODES, CONDITIONS = "door_00,bin0_00", "none,both_shuffled"


@pytest.fixture(scope="module")
def scored_run(tmp_path_factory) -> Path:
    run = tmp_path_factory.mktemp("results") / "run"
    args = ["run", "--model", "reference", "--fixtures", str(REPO / "fixtures"), "--episodes", EPISODES]
    assert main([*args, "--conditions", CONDITIONS, "--out", str(run), "--no-progress"]) == 0
    assert main(["score", str(run), "--no-progress"]) == 0
    return run


def test_every_schema_is_a_valid_versioned_json_schema() -> None:
    assert set(RUN_FILES.values()) == set(schema_names())
    for name in schema_names():
        schema = load_schema(name)
        jsonschema.Draft202012Validator.check_schema(schema)
        assert schema["$id"].endswith(f"/{name}/v{schema['x-schema-version']}.json")


def test_a_scored_run_matches_its_schemas(scored_run: Path) -> None:
    produced = {p.relative_to(scored_run).as_posix() for p in scored_run.glob("scores/*.json")} | {"run.json"}
    assert produced <= set(RUN_FILES), f"files without a schema: {sorted(produced - set(RUN_FILES))}"
    assert sorted(validate_run(scored_run)) == sorted(produced)


@pytest.mark.parametrize(
    ("rel", "damage", "where"),
    [
        ("scores/paired.json", lambda d: d[0].update(p_value=1.5), "0/p_value"),
        ("scores/rows.json", lambda d: d[1].pop("model"), "1"),
        ("scores/traces.json", lambda d: next(iter(d.values()))["trace"].append("x"), "trace"),
        ("run.json", lambda d: d["models"][0].update(mode="fast"), "models/0/mode"),
    ],
)
def test_a_damaged_document_is_refused_naming_the_place(scored_run, tmp_path, rel, damage, where) -> None:
    copy_dir = tmp_path / "run"
    (copy_dir / "scores").mkdir(parents=True)
    doc = copy.deepcopy(json.loads((scored_run / rel).read_text()))
    damage(doc)
    (copy_dir / rel).write_text(json.dumps(doc))
    with pytest.raises(SchemaError, match=where):
        validate_run(copy_dir)


def test_the_per_frame_csv_agrees_with_the_scores(scored_run: Path) -> None:
    with (scored_run / "scores" / "frames.csv").open(newline="") as f:
        rows = list(csv.DictReader(f))
    score_rows = json.loads((scored_run / "scores" / "rows.json").read_text())
    traces = json.loads((scored_run / "scores" / "traces.json").read_text())
    assert len(rows) == sum(r["n_frames"] for r in score_rows)
    assert {"episode_id", "condition", "frame", "phase", "caption", "similarity_next"} <= set(rows[0])
    for r in rows:
        t = traces[f"{r['model']}/{r['episode_id']}__{r['condition']}"]
        j = int(r["frame"])
        assert r["phase"] == t["true_phases"][j]
        assert int(r["boundary_true"]) == (j in t["true_boundaries"])
        assert int(r["boundary_predicted"]) == (j in t["predicted_boundaries"])
        if j < len(t["trace"]) and t["trace"][j] is not None:
            assert float(r["similarity_next"]) == t["trace"][j]
        assert r["scene_trajectory"] in ("correct", "wrong", "mentioned", "none")
    assert any(r["caption"] for r in rows)


def test_show_rerenders_exactly_the_prompts_that_were_sent(scored_run: Path, capsys) -> None:
    assert main(["show", str(scored_run), "--episode", "bin0_00", "--condition", "both_shuffled"]) == 0
    out = capsys.readouterr().out
    transcript = json.loads((scored_run / "transcripts" / "reference" / "bin0_00__both_shuffled.json").read_text())
    n = len(transcript["requests"])
    assert f"{n} requests; {n} match the keys the run recorded, 0 differ" in out
    assert out.count("# Process 1") >= 1 and "# Process 3" in out and "Joint/Pose" in out


def test_show_says_when_the_prompts_no_longer_match(scored_run: Path, tmp_path, capsys) -> None:
    import shutil

    run = tmp_path / "run"
    shutil.copytree(scored_run, run)
    manifest = json.loads((run / "run.json").read_text())
    manifest["models"][0]["pipeline"]["k"] = 4  # as if the run had used other groups
    (run / "run.json").write_text(json.dumps(manifest))
    assert main(["show", str(run), "--episode", "door_00", "--condition", "none"]) == 1
    assert "differ" in capsys.readouterr().out
    assert main(["show", str(run), "--episode", "door_99", "--condition", "none"]) == 2
    assert "no transcript of reference for episode 'door_99'" in capsys.readouterr().err


def test_show_rerenders_a_run_of_the_papers_verbatim_prompts(tmp_path, capsys) -> None:
    """show rebuilds the prompts of the version the run recorded, not the default one."""
    run = tmp_path / "verbatim"
    args = ["run", "--model", "reference", "--fixtures", str(REPO / "fixtures"), "--episodes", "door_00"]
    args += ["--conditions", "both", "--prompt-version", "paper-verbatim", "--no-example", "--out", str(run)]
    assert main([*args, "--no-progress"]) == 0
    capsys.readouterr()
    assert main(["show", str(run), "--episode", "door_00", "--condition", "both"]) == 0
    assert ", 0 differ" in capsys.readouterr().out


def test_show_prints_how_each_recovered_caption_was_read_and_the_reasoning(scored_run: Path, tmp_path, capsys) -> None:
    import shutil

    run = tmp_path / "run"
    shutil.copytree(scored_run, run)
    path = run / "transcripts" / "reference" / "door_00__none.json"
    t = json.loads(path.read_text())
    first = t["frames"][1]
    first.update(status="recovered", span=f"2. **Image 2**: {first['text']}", removed=["label", "emphasis"])
    t["final_status"], t["final_span"], t["final_removed"] = "recovered", f'"{t["final"]}"', ["quotes"]
    next(r for r in t["requests"] if r["stage"] == "p1")["reasoning"] = "the arm is still"
    path.write_text(json.dumps(t, indent=1))
    assert main(["show", str(run), "--episode", "door_00", "--condition", "none"]) == 0
    out = capsys.readouterr().out
    assert ", 0 differ" in out  # the audit changes no prompt
    assert f"--- parsed: frame 1: recovered (label, emphasis removed), from: '2. **Image 2**: {first['text']}'" in out
    assert "--- parsed: final: recovered (quotes removed), from: " in out
    assert "--- parsed: reasoning (16 characters, no part of any caption): the arm is still" in out
    assert out.count("--- parsed:") == 3  # clean captions get no audit line
