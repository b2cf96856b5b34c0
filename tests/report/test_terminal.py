"""The summary `run`, `score` and `report` print: the scores' own means, one row per condition."""

from __future__ import annotations

from report_helpers import CONDS, make_run
from vlmproprio.report.data import load_run_scores
from vlmproprio.report.tables import fmt_value
from vlmproprio.report.terminal import TERMINAL_METRICS, terminal_summary


def test_one_row_per_condition_with_the_aggregate_means(tmp_path) -> None:
    run, _, _ = make_run(tmp_path)
    s = load_run_scores(run)
    text = terminal_summary(s)
    lines = text.splitlines()
    assert lines[0] == "synthetic (all episodes):"
    for cond in CONDS:
        (row,) = [line.split() for line in lines if line.split()[:1] == [cond]]
        a = s.aggregate_row("synthetic", "all", cond)
        assert row[1:] == [str(a["n_episodes"]), *(fmt_value(m, a[m]) for m in TERMINAL_METRICS)]
    assert "nan" not in text
