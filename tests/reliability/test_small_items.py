"""Issue 15, item 9: the smaller defects, one test each (the interrupted score's hidden temp files are in
test_score_generations.py)."""

from __future__ import annotations

import shutil
import subprocess
import sys

import pytest
from fast_support import forked_cli
from reliability_support import REPO, assert_one_line_error, cli_env, fixture_subset

RUN_ARGS = ("--episodes", "door_00", "--conditions", "none", "--frame-stride", "3", "--no-progress")


@pytest.mark.parametrize(
    ("key", "said"),
    [("sk-abcdefgh12345678\n", "a newline"), ("sk-abcdéfgh12345678", "non-ASCII"), ("sk-abc\r\ndef", "carriage")],
)
def test_a_bad_character_in_the_api_key_is_a_clear_error(tmp_path, key, said, figures):
    pytest.importorskip("openai")
    fixtures = fixture_subset(tmp_path / "fixtures", ["door_00"])
    env = cli_env(OPENAI_API_KEY=key, VLMPROPRIO_CACHE=str(tmp_path / "cache"))
    # forked from the import-once server (fast_support): a process of its own with this environment, without
    # ~1.5 CPU s of imports (the openai SDK's among them) that say nothing about the key
    proc = forked_cli(
        ["run", "--model", "openai:m", "--fixtures", fixtures, *RUN_ARGS, "--out", tmp_path / "run"],
        tmp_path / "logs",
        env=env,
    )
    line = assert_one_line_error(proc, "OPENAI_API_KEY", said)
    assert "reach" not in line and "UnicodeEncodeError" not in proc.stderr
    assert key.strip() not in proc.stderr  # the key itself is never shown
    figures("small items", cases=1, fixed=1)


@pytest.mark.parametrize("sep", ["\u2028", "\u2029", "\u0085"])
def test_a_line_separator_in_a_model_name_is_refused_in_one_line(tmp_path, sep, figures):
    fixtures = fixture_subset(tmp_path / "fixtures", ["door_00"])
    argv = ["run", "--model", f"openai:gpt{sep}4o", "--fixtures", fixtures, *RUN_ARGS, "--out", tmp_path / "r"]
    proc = forked_cli(argv, tmp_path / "logs")  # a process of its own, forked from the import-once server
    assert_one_line_error(proc, "model name")
    assert len(proc.stderr.splitlines()) == 1 and sep not in proc.stderr
    figures("small items", cases=1, fixed=1)


def test_nul_in_answers_does_not_reach_index_html(tmp_path, figures):
    sys.path.insert(0, str(REPO / "tests"))
    from report_helpers import edit_transcript, make_run, score_synthetic
    from vlmproprio.report import write_report

    run, fixtures, _ = make_run(tmp_path, score=False)
    edit_transcript(run, "synthetic", "door_00", "none", final="Open the door\x00 then\x07 stop\x1b[31m.")
    score_synthetic(run)
    index = write_report(run, fixtures=fixtures)
    data = index.read_bytes()
    assert "\ufffd stop\ufffd[31m.".encode() in data  # the answer is shown, its controls as U+FFFD
    assert not any(bytes([c]) in data for c in (*range(0, 9), 11, 12, *range(14, 32), 127))
    figures("small items", cases=1, fixed=1)


def _pytest(tmp_path, *args: str) -> subprocess.CompletedProcess:
    # --basetemp: the inner session's temporary folders in this test's own; by default it would also sweep the
    # shared /tmp/pytest-of-USER of old sessions at its end (seconds, with many sessions there)
    basetemp = tmp_path / f"basetemp-{len(list(tmp_path.glob('basetemp-*')))}"
    return subprocess.run(
        [sys.executable, "-m", "pytest", "benchmark/", "-q", "-p", "no:cacheprovider", "--basetemp", basetemp, *args],
        cwd=REPO,
        env=cli_env(),
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
    )


def test_plugin_empty_episodes_is_a_usage_error(tmp_path, figures):
    proc = _pytest(tmp_path, "--episodes", "", "--model", "reference")
    assert proc.returncode == 4, proc.stdout[-2000:] + proc.stderr[-2000:]
    assert "--episodes" in proc.stderr and "Traceback" not in proc.stderr
    figures("small items", cases=1, fixed=1)


def test_plugin_fails_a_named_model_that_cannot_run(tmp_path, figures):
    proc = _pytest(tmp_path, "--model", "gpt-4o")
    assert proc.returncode == 4, proc.stdout[-2000:]  # a usage error, not 0 with "all skipped"
    output = proc.stdout + proc.stderr
    assert output.count("gpt-4o cannot run in") == 1, output[-3000:]  # once, not once per cell
    assert len(output.splitlines()) <= 3 and "Traceback" not in output
    figures("small items", cases=1, fixed=1)


@pytest.mark.parametrize(
    "damage",
    [
        lambda t: t[: len(t) // 2] + '"unclosed\n1,2',  # a truncated file with a broken quote
        lambda t: "\x00\x01garbage\xff" * 40,
        lambda t: t.replace(",", ";"),
        lambda t: t.replace("0.", "zero."),
    ],
    ids=["truncated", "binary", "separator", "non-numeric"],
)
def test_a_damaged_baseline_csv_is_one_line_naming_the_file(tmp_path, damage, figures):
    sys.path.insert(0, str(REPO))
    from benchmark.metrics import baseline_problem

    src = REPO / "benchmark" / "baselines" / "reference" / "door_00" / "both.rates.csv"
    path = tmp_path / "both.rates.csv"
    shutil.copy(src, path)
    import pandas as pd

    columns = list(pd.read_csv(src, index_col=0).columns)
    assert baseline_problem(path, columns) is None  # the shipped one is fine
    path.write_text(damage(src.read_text()))
    problem = baseline_problem(path, columns)
    assert problem is not None and "\n" not in problem and str(path) in problem and "--force-regen" in problem
    figures("small items", cases=1, fixed=1)


def test_plugin_keeps_runs_of_other_selections_apart(tmp_path, figures):
    """`--run-dir` keeps runs: a second session selecting other cells must neither be refused nor mix its
    transcripts into the first session's run folder."""
    runs = tmp_path / "bench"
    for k in ("door_00 and none", "door_01 and none"):
        proc = _pytest(tmp_path, "--model", "reference", "--run-dir", str(runs), "-k", k)
        assert proc.returncode == 0, proc.stdout[-2000:]
    folders = sorted(p.name for p in runs.iterdir())
    assert len(folders) == 2 and folders[0] == "reference", folders
    for f in folders:
        names = sorted(p.name for p in (runs / f / "transcripts" / "reference").iterdir())
        assert len(names) == 1 and names[0].endswith("__none.json"), names
    figures("small items", cases=1, fixed=1)
