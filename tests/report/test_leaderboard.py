"""The leaderboard: any number of scored runs, one entry per (run, model), numbers exactly as the scores hold them."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from report_helpers import make_run
from vlmproprio.cli import main
from vlmproprio.report.data import ReportError
from vlmproprio.report.leaderboard import LEADERBOARD_METRICS, build_leaderboard, write_leaderboard


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> list[Path]:
    return [make_run(tmp_path_factory.mktemp(name))[0] for name in ("a", "b")]


def _paired(run: Path, model: str, metric: str, task: str = "all") -> dict:
    rows = json.loads((run / "scores" / "paired.json").read_text())
    (row,) = [
        r for r in rows if (r["model"], r["task"], r["metric"], r["a"], r["b"]) == (model, task, metric, "both", "none")
    ]
    return row


def test_each_run_and_model_is_an_entry_with_the_scores_own_numbers(runs) -> None:
    board = build_leaderboard(runs)
    assert [e.run_dir for e in board.entries] == runs
    assert len({e.name for e in board.entries}) == 2  # the same model in two runs: told apart by the run
    for e in board.entries:
        for m in LEADERBOARD_METRICS:
            assert e.cells[m].row == _paired(e.run_dir, e.model, m)
    table = board.table()
    assert len(table.rows) == 2 and len(table.headers) == len(LEADERBOARD_METRICS) + 2


def test_a_cell_that_cannot_be_filled_says_why(runs) -> None:
    board = build_leaderboard(runs[:1], a="both", b="state_only")
    cell = board.entries[0].cells[LEADERBOARD_METRICS[0]]
    assert cell.row is None and cell.why == "condition state_only not run"
    assert "state_only not run" in board.to_markdown() and "nan" not in board.to_markdown()


def test_written_files_and_the_command(runs, tmp_path, capsys) -> None:
    paths = write_leaderboard(build_leaderboard(runs), tmp_path / "lb")
    assert paths["plot"].read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    html = paths["html"].read_text()
    assert 'src="leaderboard.png"' in html and html.count("<tr>") == 3
    doc = json.loads(paths["json"].read_text())
    assert [e["model"] for e in doc["entries"]] == ["synthetic", "synthetic"]
    out = tmp_path / "cli"
    assert main(["leaderboard", *map(str, runs), "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert printed.startswith("## Leaderboard: both vs none") and (out / "index.html").is_file()


def test_no_runs_or_an_unscored_run_is_one_clear_error(tmp_path) -> None:
    with pytest.raises(ReportError, match="at least one"):
        build_leaderboard([])
    with pytest.raises(ReportError, match="not found"):
        build_leaderboard([tmp_path / "nowhere"])
