"""Issue 36, class 1: two `run`s into one run folder at once.

Two real `vlmproprio run` processes (forked from the import-once server: fast_support) are held behind a gate
right after each has checked the folder (both find it empty), then let go together: the worst case, where
each has decided it may write before either has written. Two different models with the same configuration
must both end up in run.json (merged under the folder's lock), and `score` takes every transcript of both;
two runs of other configurations (other episodes) must not both succeed: the second to write refuses in one
line before it writes a transcript, and the folder holds the first run only.
"""

from __future__ import annotations

import json
from pathlib import Path

from fast_support import CliProcess
from fault_support import cli_in_process
from reliability_support import ERROR_PREFIX, cli_env, fixture_subset

GATE_PRELUDE = """
import os, pathlib, time
import vlmproprio.runner as runner
_check = runner.check_run_folder
def check_run_folder(*a, **k):
    result = _check(*a, **k)
    gate = pathlib.Path(os.environ["VP_GATE"])
    (gate / str(os.getpid())).touch()
    deadline = time.monotonic() + 60
    while len(list(gate.iterdir())) < 2 and time.monotonic() < deadline:
        time.sleep(0.02)
    return result
runner.check_run_folder = check_run_folder
"""

COMMON = ("--conditions", "none,both", "--frame-stride", "3", "--mode", "live", "--no-progress")


def _two_runs_at_once(tmp_path: Path, first: list[str], second: list[str]) -> tuple[Path, list[CliProcess]]:
    fixtures = fixture_subset(tmp_path / "fixtures", ["door_00", "door_01"])
    gate, out = tmp_path / "gate", tmp_path / "run"
    gate.mkdir()
    env = cli_env(VLMPROPRIO_CACHE=str(tmp_path / "cache"), VP_GATE=str(gate))
    procs = [
        CliProcess(
            ["run", *args, *COMMON, "--fixtures", fixtures, "--out", out],
            tmp_path / "logs",
            env=env,
            python_prelude=GATE_PRELUDE,
        )
        for args in (first, second)
    ]
    for p in procs:
        p.wait(120)
    assert len(list(gate.iterdir())) == 2  # both had checked the folder before either wrote run.json
    return out, procs


def test_two_models_run_into_one_folder_at_once_are_both_recorded(tmp_path, figures):
    out, procs = _two_runs_at_once(
        tmp_path,
        ["--model", "reference", "--episodes", "door_00"],
        ["--model", "reference-state", "--episodes", "door_00"],
    )
    assert [p.returncode for p in procs] == [0, 0], [p.stderr() for p in procs]
    run = json.loads((out / "run.json").read_text())
    assert sorted(m["name"] for m in run["models"]) == ["reference", "reference-state"], run["models"]
    assert run["status"] == "complete" and "running_models" not in run
    proc = cli_in_process(["score", out, "--no-progress"], env={"VLMPROPRIO_CACHE": str(tmp_path / "cache")})
    assert proc.returncode == 0, proc.stderr
    assert "scored 4 transcripts" in proc.stdout, proc.stdout
    figures("two runs into one folder at once", attempts=1, models_lost=0)


def test_two_runs_of_other_episodes_into_one_folder_at_once_do_not_both_write(tmp_path, figures):
    out, procs = _two_runs_at_once(
        tmp_path,
        ["--model", "reference", "--episodes", "door_00"],
        ["--model", "reference-state", "--episodes", "door_01"],
    )
    codes = sorted(p.returncode for p in procs)
    assert codes == [0, 2], [p.stderr() for p in procs]
    refused = next(p for p in procs if p.returncode == 2)
    errors = [line for line in refused.stderr().splitlines() if line.startswith(ERROR_PREFIX)]
    assert len(errors) == 1 and "another run changed it meanwhile" in errors[0], refused.stderr()
    assert "Traceback" not in refused.stderr()
    kept = next(p for p in procs if p.returncode == 0)
    model = kept.args[kept.args.index("--model") + 1]
    run = json.loads((out / "run.json").read_text())
    assert [m["name"] for m in run["models"]] == [model]
    assert sorted(p.parent.name for p in (out / "transcripts").glob("*/*.json")) == [model, model]
    figures("two runs into one folder at once", attempts=1, mixed_configurations=0)


def test_score_names_a_model_still_being_run_into_the_folder(tmp_path):
    """The transcripts of a model whose run is going on (or was stopped) are named as that, not as strays."""
    fixtures = fixture_subset(tmp_path / "fixtures", ["door_00"])
    out, cache = tmp_path / "run", {"VLMPROPRIO_CACHE": str(tmp_path / "cache")}
    args = ["run", "--model", "reference", *COMMON, "--fixtures", fixtures, "--out", out]
    assert cli_in_process(args, env=cache).returncode == 0
    doc = json.loads((out / "run.json").read_text())  # as a run of reference-state writes it while it runs
    (out / "run.json").write_text(json.dumps({**doc, "status": "running", "running_models": ["reference-state"]}))
    (out / "transcripts" / "reference-state").mkdir()
    for p in (out / "transcripts" / "reference").glob("*.json"):
        (out / "transcripts" / "reference-state" / p.name).write_bytes(p.read_bytes())
    proc = cli_in_process(["score", out, "--no-progress"], env=cache)
    assert proc.returncode == 2
    assert "model reference-state is still being run into this folder" in proc.stderr, proc.stderr
    assert "left by another run" not in proc.stderr
