"""What `run`, `score` and `report` print when they finish: per model, a compact table of the headline
metrics per condition (the means the scores hold), so the numbers are on screen, not only in files."""

from __future__ import annotations

from vlmproprio.evaluation.metrics import headline_metrics
from vlmproprio.report.data import RunScores
from vlmproprio.report.tables import fmt_value, label

TERMINAL_METRICS = headline_metrics()


def _text_table(headers: list[str], rows: list[list[str]]) -> list[str]:
    widths = [max(len(h), *(len(r[i]) for r in rows)) for i, h in enumerate(headers)]
    line = "  ".join(h.ljust(w) if i == 0 else h.rjust(w) for i, (h, w) in enumerate(zip(headers, widths, strict=True)))
    out = [line, "  ".join("-" * w for w in widths)]
    for r in rows:
        out.append(
            "  ".join(c.ljust(w) if i == 0 else c.rjust(w) for i, (c, w) in enumerate(zip(r, widths, strict=True)))
        )
    return out


def model_summary(s: RunScores, model: str) -> list[str]:
    """``model``'s headline means per condition (episodes: the task 'all', or the run's one task)."""
    task = s.pooled_task
    rows = []
    for condition in s.conditions:
        a = s.aggregate_row(model, task, condition)
        if a is not None:
            rows.append([condition, str(a.get("n_episodes", "")), *(fmt_value(m, a.get(m)) for m in TERMINAL_METRICS)])
    if not rows:
        return [f"{model}: no scored cells"]
    headers = ["condition", "episodes", *(label(m) for m in TERMINAL_METRICS)]
    return [f"{model} ({task} episodes):", *("  " + x for x in _text_table(headers, rows))]


def terminal_summary(s: RunScores) -> str:
    lines: list[str] = []
    for model in s.models:
        lines += [*model_summary(s, model), ""]
    return "\n".join(lines)
