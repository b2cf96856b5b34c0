"""Issue 15, defect 1: reports built from stale or mixed scores.

A run is made and scored once (the real CLI, reference model, one episode, two conditions). Each stale case
then damages a copy of that run the way a user or an interrupted command could -- a transcript edited, added
or removed after scoring, run.json's configuration changed, a score file from another generation, scores from
an older version, a `run` into the folder with other settings -- and `report` and `compare` must refuse in one
line naming `vlmproprio score RUN` (or, for `run`, refuse before anything changes). A `score` killed at every
stage of writing its generation must leave the previous generation whole (or none), and the next `score`
leaves no hidden temporary folder or file behind.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
from fast_support import forked_cli
from fault_support import cli_in_process
from reliability_support import assert_one_line_error, cache_env_sharing_embeddings, fixture_subset

RUN_ARGS = ("--model", "reference", "--episodes", "door_00", "--conditions", "none,both", "--frame-stride", "3")


_LOGS: list[Path] = []


def cli(args, **kw):
    """The CLI, each command its own process, forked from a server that imported it once (fast_support): about
    thirty commands here, a third of them reports, whose imports (matplotlib) cost more than their work."""
    return forked_cli(args, _LOGS[0], **kw)


@pytest.fixture(scope="module")
def scored(tmp_path_factory):
    root = tmp_path_factory.mktemp("generations")
    _LOGS[:] = [root / "logs"]
    fixtures = fixture_subset(root / "fixtures", ["door_00", "door_01"])
    env = cache_env_sharing_embeddings(root, tmp_path_factory)
    run = root / "run"
    proc = cli(["run", *RUN_ARGS, "--fixtures", fixtures, "--out", run, "--no-progress"], env=env)
    assert proc.returncode == 0, proc.stderr
    # in this process: this first score embeds the run's captions, and a subprocess spent most of its CPU
    # importing torch, which the test process imports once
    proc = cli_in_process(["score", run], env={"VLMPROPRIO_CACHE": env["VLMPROPRIO_CACHE"]})
    assert proc.returncode == 0, proc.stderr
    return root, fixtures, run, env


def _copy(scored, name: str) -> Path:
    root, _, run, _ = scored
    dest = root / name
    shutil.copytree(run, dest)
    return dest


def _edit_json(path: Path, change) -> None:
    data = json.loads(path.read_text())
    change(data)
    path.write_text(json.dumps(data, indent=1) + "\n")


def _transcript(run: Path, condition: str = "none") -> Path:
    return run / "transcripts" / "reference" / f"door_00__{condition}.json"


def _edit_final(run: Path) -> None:
    _edit_json(_transcript(run), lambda d: d.update(final="Open the door, now edited after scoring."))


def _add_transcript(run: Path) -> None:
    shutil.copy(_transcript(run), _transcript(run, "ee"))


def _remove_transcript(run: Path) -> None:
    _transcript(run, "both").unlink()


def _other_configuration(run: Path) -> None:
    def change(d):
        d["models"][0]["pipeline"]["k"] = 3

    _edit_json(run / "run.json", change)


def _stale_generation_file(run: Path) -> None:
    _edit_json(run / "scores" / "rows.json", lambda rows: rows[0].update(final_words=999))


def _no_stamp(run: Path) -> None:
    (run / "scores" / "stamp.json").unlink()


def _older_code(run: Path) -> None:
    _edit_json(run / "scores" / "stamp.json", lambda d: d["inputs"]["code"].update(scores_version=0))


STALE = {
    "transcript edited": _edit_final,
    "transcript added": _add_transcript,
    "transcript removed": _remove_transcript,
    "run.json configuration changed": _other_configuration,
    "score file of another generation": _stale_generation_file,
    "scores without a stamp": _no_stamp,
    "scores of an older scoring version": _older_code,
}


# every case through `report`; `compare` reads scores through the same check, so three cases suffice for it
CASES = [(c, "report") for c in STALE] + [
    (c, "compare") for c in ("transcript edited", "run.json configuration changed", "score file of another generation")
]


@pytest.mark.parametrize(("case", "command"), CASES)
def test_stale_or_mixed_scores_are_refused(scored, case, command, figures):
    _, fixtures, current, env = scored
    run = _copy(scored, f"stale-{command}-{case.replace(' ', '_')}")
    STALE[case](run)
    args = ["report", run, "--fixtures", fixtures] if command == "report" else ["compare", current, run]
    proc = cli(args, env=env)
    # a removed transcript is fixed by finishing the run, a stray one by moving it away, the rest by scoring again
    fix = {
        "transcript removed": "the same `vlmproprio run --model MODEL --out RUN_DIR` command",
        "transcript added": "move them out",
    }.get(case, f"`vlmproprio score {run}`")
    assert_one_line_error(proc, "out of date", fix)
    assert not (run / "report" / "index.html").exists()
    figures("stale scores: report/compare", attempts=1, refused=1)


@pytest.mark.parametrize(
    "other", [("--k", "3"), ("--frame-stride", "2"), ("--episodes", "door_01"), ("--conditions", "none")]
)
def test_run_into_a_folder_of_another_configuration_is_refused(scored, other, figures):
    from reliability_support import tree_snapshot

    _, fixtures, _, env = scored
    run = _copy(scored, f"rerun-{other[0].strip('-')}")
    before = tree_snapshot(run)
    args = list(RUN_ARGS)
    if other[0] in args:
        args[args.index(other[0]) + 1] = other[1]
    else:
        args += list(other)
    proc = cli(["run", *args, "--fixtures", fixtures, "--out", run, "--no-progress"], env=env)
    assert_one_line_error(proc, str(run), "choose another --out")
    assert tree_snapshot(run) == before  # refused before anything was written
    proc = cli(["report", run, "--fixtures", fixtures], env=env)
    assert proc.returncode == 0, proc.stderr  # the run and its scores still agree
    figures("stale scores: run of another configuration", attempts=1, refused=1)


def test_the_same_run_again_and_another_model_are_accepted(scored):
    _, fixtures, _, env = scored
    run = _copy(scored, "rerun-same")
    proc = cli(["run", *RUN_ARGS, "--fixtures", fixtures, "--out", run, "--no-progress"], env=env)
    assert proc.returncode == 0, proc.stderr
    assert cli(["report", run, "--fixtures", fixtures], env=env).returncode == 0  # same transcripts: still current


# Where a `score` is killed: after the n-th file of the new generation, or between the two renames of the swap.
KILL_POINTS = [("write", 1), ("write", 7), ("write", 15), ("rename", 1), ("rename", 2)]
KILL_PRELUDE = """
import os, signal, pathlib, vlmproprio.io as io, vlmproprio.evaluation.generations as ev
count = {{"write": 0, "rename": 0}}
def kill_at(kind):
    count[kind] += 1
    if kind == {kind!r} and count[kind] == {n}:
        os.kill(os.getpid(), signal.SIGKILL)
real_write, real_rename = ev.atomic_write_text, pathlib.Path.rename
def write(path, text):
    kill_at("write")
    return real_write(path, text)
def rename(self, target):
    kill_at("rename")
    return real_rename(self, target)
ev.atomic_write_text = io.atomic_write_text = write  # the stamp, and the score files (io.atomic_write_texts)
pathlib.Path.rename = rename
"""


@pytest.mark.parametrize(("kind", "n"), KILL_POINTS)
def test_an_interrupted_score_leaves_one_whole_generation_and_no_leftovers(scored, kind, n, figures):
    _, fixtures, _, env = scored
    run = _copy(scored, f"killed-{kind}-{n}")
    before = {p.name: p.read_bytes() for p in (run / "scores").iterdir()}
    _edit_final(run)  # the new generation differs from the old one
    proc = cli(["score", run], env=env, python_prelude=KILL_PRELUDE.format(kind=kind, n=n))
    assert proc.returncode == -9, proc.stderr
    scores = run / "scores"
    if scores.is_dir():  # the old generation, whole: every file as it was; stale, since a transcript changed
        assert {p.name: p.read_bytes() for p in scores.iterdir()} == before
        assert_one_line_error(cli(["report", run, "--fixtures", fixtures], env=env), f"vlmproprio score {run}")
    else:  # killed between the two renames: no scores at all, which `report` would score first
        assert not (run / "scores").exists()
    proc = cli(["score", run], env=env)
    assert proc.returncode == 0, proc.stderr
    hidden = sorted(p.name for p in run.rglob(".*"))
    assert hidden == [], hidden
    assert cli(["report", run, "--fixtures", fixtures], env=env).returncode == 0
    figures("interrupted score", kills=1, mixed_generations=0, leftovers_after_rescore=len(hidden))
