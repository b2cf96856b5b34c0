"""Rewrite the metric table in docs/metrics.md from vlmproprio.evaluation.metrics.METRICS.

    python scripts/metric_table.py          # after adding or changing a MetricSpec

tests/evaluation/test_metrics.py fails while the page and the table differ.
"""

from __future__ import annotations

from pathlib import Path

from vlmproprio.evaluation.metrics import DOC_END, DOC_START, markdown_table

DOC = Path(__file__).resolve().parents[1] / "docs" / "metrics.md"


def with_table(text: str) -> str:
    """The page with the block between DOC_START and DOC_END replaced by the table of today's METRICS."""
    head, start, rest = text.partition(DOC_START)
    _, end, tail = rest.partition(DOC_END)
    if not start or not end:
        raise SystemExit(f"{DOC}: the markers {DOC_START!r} and {DOC_END!r} are missing")
    return f"{head}{DOC_START}\n\n{markdown_table()}\n{DOC_END}{tail}"


if __name__ == "__main__":
    DOC.write_text(with_table(DOC.read_text(encoding="utf-8")), encoding="utf-8")
