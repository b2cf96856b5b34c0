"""Reports of a scored run: Markdown tables, the paper's figures as PNG, one self-contained HTML page,
and the comparison of two runs or models.

    write_report(run_dir) -> RUN_DIR/report/index.html   (plus report.md, *.png, frames/*.jpg)
    compare_runs(run_a, run_b) -> Comparison             (.to_markdown())

matplotlib and jinja2 are imported only when a report is written.
"""

from vlmproprio.report.build import write_report
from vlmproprio.report.compare import Comparison, compare_runs
from vlmproprio.report.data import ReportError, RunScores, load_run_scores, scores_present

__all__ = [
    "Comparison",
    "ReportError",
    "RunScores",
    "compare_runs",
    "load_run_scores",
    "scores_present",
    "write_report",
]
