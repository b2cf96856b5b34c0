"""Issue 15, defect 5: deeply nested JSON read from disk is one line naming the file, never a RecursionError.

Every kind of JSON document the suite reads -- the fixtures' manifest, an episode.json, a cassette line, a
transcript, run.json, the score tables and their stamp -- is replaced by ``[`` x 100 000 (and, for the depth
limit below Python's recursion limit, by 100 nested lists), and the command that reads it must fail with one
``vlmproprio: error:`` line naming that file. Where the manifest guards a file, it is rewritten first, so the
nesting is what the reader meets.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest
from fast_support import forked_cli
from fault_support import cli_in_process
from reliability_support import assert_one_line_error, cache_env_sharing_embeddings, fixture_subset

from vlmproprio.episodes import write_manifest

RUN_ARGS = ("--model", "reference", "--episodes", "door_00", "--conditions", "none", "--frame-stride", "3")
DEEP = "[" * 100_000
NESTED_100 = "[" * 100 + "]" * 100


@pytest.fixture(scope="module")
def base(tmp_path_factory):
    """A recorded and scored run to damage. Made through the CLI in this process: only the commands that meet
    the damage are what is checked (they stay processes of their own, whose stack is the CLI's alone), and
    scoring in a subprocess imported torch and the encoder again (~10 CPU s)."""
    root = tmp_path_factory.mktemp("nested")
    fixtures = fixture_subset(root / "fixtures", ["door_00"])
    env = cache_env_sharing_embeddings(root, tmp_path_factory)
    run = root / "run"
    for args in (
        ["run", *RUN_ARGS, "--fixtures", fixtures, "--out", run, "--no-progress", "--mode", "record"],
        ["score", run],
    ):
        proc = cli_in_process(args, env={"VLMPROPRIO_CACHE": env["VLMPROPRIO_CACHE"]})
        assert proc.returncode == 0, proc.stderr
    return root, fixtures, run, env


def _cassette_line(fixtures: Path, text: str) -> Path:
    path = fixtures / "responses" / "reference.jsonl"
    lines = path.read_text().splitlines()
    lines[1] = text
    path.write_text("\n".join(lines) + "\n")
    return path


# name -> (file to damage, relative to the case folder, or a function doing it; the command that reads it)
CASES = {
    "manifest": (
        lambda w, t: _write(w / "fixtures" / "manifest.json", t),
        lambda w: ["verify", "--fixtures", w / "fixtures"],
    ),
    "episode.json": (
        lambda w, t: _write(w / "fixtures" / "episodes" / "door_00" / "episode.json", t, manifest=w / "fixtures"),
        lambda w: ["verify", "--fixtures", w / "fixtures"],
    ),
    "cassette line": (
        lambda w, t: _cassette_line(w / "fixtures", t),
        lambda w: ["cassette", "import", w / "fixtures" / "responses" / "reference.jsonl", "--cache", w / "c2"],
    ),
    "transcript": (
        lambda w, t: _write(w / "run" / "transcripts" / "reference" / "door_00__none.json", t),
        lambda w: ["score", w / "run"],
    ),
    "run.json (score)": (lambda w, t: _write(w / "run" / "run.json", t), lambda w: ["score", w / "run"]),
    "run.json (run)": (
        lambda w, t: _write(w / "run" / "run.json", t),
        lambda w: ["run", *RUN_ARGS, "--fixtures", w / "fixtures", "--out", w / "run", "--no-progress"],
    ),
    "run.json (show)": (
        lambda w, t: _write(w / "run" / "run.json", t),
        lambda w: ["show", w / "run", "--episode", "door_00", "--condition", "none"],
    ),
    "run.json (score --judge)": (
        lambda w, t: _write(w / "run" / "run.json", t),
        lambda w: ["score", w / "run", "--judge", "reference", "--no-progress"],
    ),
    "scores/meta.json": (lambda w, t: _write(w / "run" / "scores" / "meta.json", t), lambda w: ["report", w / "run"]),
    "scores/stamp.json": (lambda w, t: _write(w / "run" / "scores" / "stamp.json", t), lambda w: ["report", w / "run"]),
}


def _write(path: Path, text: str, manifest: Path | None = None) -> Path:
    path.write_text(text)
    if manifest is not None:
        write_manifest(manifest)  # the checksum passes: the reader itself must cope
    return path


@pytest.mark.parametrize("depth", ["100000", "100"])
@pytest.mark.parametrize("case", list(CASES))
def test_nested_json_is_one_line_naming_the_file(base, case, depth, figures):
    root, fixtures, run, env = base
    work = root / f"{case.replace('/', '_').replace(' ', '_')}-{depth}"
    shutil.copytree(fixtures, work / "fixtures")
    shutil.copytree(run, work / "run")
    damage, command = CASES[case]
    damaged = damage(work, DEEP if depth == "100000" else NESTED_100)
    # forked from the import-once server (fast_support): its own process, environment and folder, as
    # `python -m vlmproprio.cli` would be, without ~0.6 CPU s of imports in each of the 20 cases
    env = {**env, "VLMPROPRIO_FIXTURES": str(work / "fixtures")}
    proc = forked_cli(command(work), root / "logs", cwd=work, env=env)
    assert "RecursionError" not in proc.stderr
    line = assert_one_line_error(proc, damaged.name)
    assert len(line) < 600, line
    figures("nested JSON", files=1, refused_in_one_line=1, recursion_errors=0)
