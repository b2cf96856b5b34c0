"""Issue 36, classes 4, 5, 6 and one message of 17: scores read back against everything they came from.

Two runs are made and scored once (the real CLI, reference model, one episode each, two conditions); the second
is scored with a judge, so that its scores/ holds a judge.json. Each case then changes a copy of the first
run the way a user could -- the fixtures' ground truth edited after scoring (in place, or another fixture set
given with --fixtures), the other run's judge.json or frames.csv put into its scores/, its frames.csv lost,
its judge.json edited, its run.json deleted -- and `report` and `compare` must refuse in one line saying what
is wrong and to run `vlmproprio score` again (for a lost run.json: that it is missing). A copy of the fixtures
with the same ground truth is accepted.
"""

from __future__ import annotations

import json
import shutil
from collections.abc import Sequence
from pathlib import Path

import pytest
from fast_support import forked_cli
from fault_support import cli_in_process
from reliability_support import assert_one_line_error, cache_env_sharing_embeddings, fixture_subset

from vlmproprio.answering import Answerer
from vlmproprio.backends.base import Backend
from vlmproprio.chat import Answer, AnswerMeta, ChatRequest
from vlmproprio.episodes import write_manifest
from vlmproprio.evaluation import score_run


class AgreeingJudge(Backend):
    """A judge that needs no model: every rubric item of every caption mentioned and correct."""

    max_batch_size = 8

    def identity(self) -> dict[str, str]:
        return {"backend": "agreeing-judge", "model_id": "rule"}

    def generate(self, requests: Sequence[ChatRequest]) -> list[Answer]:
        items = {k: {"mentioned": True, "correct": True} for k in ("object", "action", "trajectory")}
        return [Answer(json.dumps(items), AnswerMeta(backend="agreeing-judge", model_id="rule")) for _ in requests]


RUN_ARGS = ("--model", "reference", "--conditions", "none,both", "--frame-stride", "3")

_LOGS: list[Path] = []


def cli(args, **kw):
    return forked_cli(args, _LOGS[0], **kw)


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    root = tmp_path_factory.mktemp("provenance")
    _LOGS[:] = [root / "logs"]
    fixtures = fixture_subset(root / "fixtures", ["door_00", "door_01"])
    env = cache_env_sharing_embeddings(root, tmp_path_factory)
    cache = {"VLMPROPRIO_CACHE": env["VLMPROPRIO_CACHE"]}
    made = {}
    for name, episode, judge in (("run", "door_00", False), ("judged", "door_01", True)):
        out = root / name
        proc = cli(["run", *RUN_ARGS, "--episodes", episode, "--fixtures", fixtures, "--out", out, "--no-progress"])
        assert proc.returncode == 0, proc.stderr
        if judge:  # in this process, with a judge that needs no model
            score_run(out, embedding_cache=root / "cache" / "embeddings", judge=Answerer(AgreeingJudge(), mode="live"))
        else:
            proc = cli_in_process(["score", out, "--no-progress"], env=cache)  # torch imported once, here
            assert proc.returncode == 0, proc.stderr
        made[name] = out
    assert (made["judged"] / "scores" / "judge.json").is_file()
    return root, fixtures, made, env


def _copy(runs, name: str) -> Path:
    root, _, made, _ = runs
    dest = root / name
    shutil.copytree(made["run"], dest)
    return dest


def _fixtures_with_other_truth(runs, name: str) -> Path:
    """A copy of the fixtures whose door_00 ground truth differs (a phase boundary moved), with its manifest."""
    root, fixtures, _, _ = runs
    other = root / f"fixtures-{name}"
    shutil.copytree(fixtures, other)
    path = other / "episodes" / "door_00" / "episode.json"
    doc = json.loads(path.read_text())
    doc["instruction"] = "Open the door by pulling its handle."
    path.write_text(json.dumps(doc, indent=1) + "\n")
    write_manifest(other)
    return other


def _truth_changed_in_place(runs, run: Path) -> list[str]:
    other = _fixtures_with_other_truth(runs, run.name)  # run.json now names these fixtures: changed in place
    doc = json.loads((run / "run.json").read_text())
    (run / "run.json").write_text(json.dumps({**doc, "fixtures": str(other)}, indent=1) + "\n")
    return []  # no --fixtures: run.json's


def _other_fixtures_given(runs, run: Path) -> list[str]:
    return ["--fixtures", str(_fixtures_with_other_truth(runs, run.name))]


def _judge_of_another_run(runs, run: Path) -> list[str] | None:
    shutil.copy(runs[2]["judged"] / "scores" / "judge.json", run / "scores" / "judge.json")
    return None  # the run's own fixtures, given with --fixtures


def _frames_csv_of_another_run(runs, run: Path) -> list[str] | None:
    shutil.copy(runs[2]["judged"] / "scores" / "frames.csv", run / "scores" / "frames.csv")
    return None  # the run's own fixtures, given with --fixtures


def _frames_csv_lost(runs, run: Path) -> list[str] | None:
    (run / "scores" / "frames.csv").unlink()
    return None  # the run's own fixtures, given with --fixtures


def _run_json_deleted(runs, run: Path) -> list[str] | None:
    (run / "run.json").unlink()
    return None  # the run's own fixtures, given with --fixtures


# case -> (how the copy is changed, what the one error line must say)
CASES = {
    "ground truth changed in place": (_truth_changed_in_place, ["ground truth", "vlmproprio score"]),
    "--fixtures with other ground truth": (_other_fixtures_given, ["ground truth", "vlmproprio score", "--fixtures"]),
    "judge.json of another run": (_judge_of_another_run, ["judge.json", "vlmproprio score"]),
    "frames.csv of another run": (_frames_csv_of_another_run, ["frames.csv", "vlmproprio score"]),
    "frames.csv lost": (_frames_csv_lost, ["frames.csv", "missing", "vlmproprio score"]),
    "run.json deleted": (_run_json_deleted, ["run.json", "missing"]),
}


@pytest.mark.parametrize("case", list(CASES))
def test_report_refuses_scores_that_no_longer_match_what_they_came_from(runs, case, figures):
    _, fixtures, _, env = runs
    run = _copy(runs, "report-" + case.replace(" ", "_").replace("-", ""))
    change, said = CASES[case]
    extra = change(runs, run)
    args = extra if extra is not None else ["--fixtures", str(fixtures)]
    proc = cli(["report", run, *args, "--no-progress"], env=env)
    line = assert_one_line_error(proc, *said)
    assert "another configuration" not in line, line
    assert not (run / "report" / "index.html").exists()
    figures("scores against their inputs: report", attempts=1, refused=1)


@pytest.mark.parametrize("case", ["ground truth changed in place", "judge.json of another run", "frames.csv lost"])
def test_compare_refuses_them_too(runs, case, figures):
    _, _, made, env = runs
    run = _copy(runs, "compare-" + case.replace(" ", "_").replace("-", ""))
    CASES[case][0](runs, run)
    assert_one_line_error(cli(["compare", made["run"], run], env=env), *CASES[case][1])
    figures("scores against their inputs: compare", attempts=1, refused=1)


def test_a_judge_json_edited_after_scoring_is_refused_and_the_judged_run_reports(runs, figures):
    root, fixtures, made, env = runs
    run = root / "judged-edited"
    shutil.copytree(made["judged"], run)
    assert cli(["report", run, "--fixtures", fixtures, "--no-progress"], env=env).returncode == 0
    path = run / "scores" / "judge.json"
    doc = json.loads(path.read_text())
    doc["agreement"]["n"] = 999
    path.write_text(json.dumps(doc))
    assert_one_line_error(cli(["report", run, "--fixtures", fixtures, "--no-progress"], env=env), "judge.json")
    figures("scores against their inputs: report", attempts=1, refused=1)


def test_a_copy_of_the_fixtures_with_the_same_ground_truth_is_accepted(runs):
    root, fixtures, _, env = runs
    run = _copy(runs, "same-truth")
    copy = root / "fixtures-copy"
    shutil.copytree(fixtures, copy)
    proc = cli(["report", run, "--fixtures", copy, "--no-progress"], env=env)
    assert proc.returncode == 0, proc.stderr
