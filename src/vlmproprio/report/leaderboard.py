"""Many models side by side: one table and one plot of models x headline metrics over any number of scored runs.

Each (run, model) is one entry. Per headline metric it shows the mean under A and B (default ``both`` and
``none``) and the paired difference A − B with its 95 % CI, exactly as the run's scores hold them
(``scores/paired.json``; nothing is recomputed), then the model's verdicts and sanity warnings. A cell that
cannot be filled says why (a condition not run, a task not in the run) instead of showing a number.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

from vlmproprio.evaluation.metrics import headline_metrics
from vlmproprio.json_text import dumps_indented
from vlmproprio.report.data import ReportError, RunScores, load_run_scores
from vlmproprio.report.tables import Table, fmt_diff, fmt_value, label, to_markdown

LEADERBOARD_METRICS = headline_metrics()
FILES = {"html": "index.html", "markdown": "leaderboard.md", "plot": "leaderboard.png", "json": "leaderboard.json"}


@dataclass(frozen=True)
class Cell:
    """One metric of one entry: the paired row, or why there is none."""

    row: dict | None
    why: str = ""

    def text(self, metric: str) -> str:
        if self.row is None:
            return f"– ({self.why})"
        r = self.row
        diff = f"{fmt_diff(metric, r['mean_diff'])} [{fmt_diff(metric, r['ci_low'])}, {fmt_diff(metric, r['ci_high'])}]"
        return f"{fmt_value(metric, r['mean_a'])} vs {fmt_value(metric, r['mean_b'])}: {diff}"


@dataclass
class Entry:
    name: str
    model: str
    run_dir: Path
    cells: dict[str, Cell]
    verdicts: list[dict]
    warnings: list[str]

    def verdict_summary(self) -> str:
        if not self.verdicts:
            return "no verdicts (needs every episode and the claims' conditions)"
        supported = [v["hypothesis"] for v in self.verdicts if v.get("verdict") == "supported"]
        return f"{len(supported)} of {len(self.verdicts)} supported" + (
            f": {', '.join(supported)}" if supported else ""
        )


@dataclass
class Leaderboard:
    metrics: tuple[str, ...]
    a: str
    b: str
    task: str
    entries: list[Entry] = field(default_factory=list)

    def table(self) -> Table:
        rows = [[e.name, *(e.cells[m].text(m) for m in self.metrics), e.verdict_summary()] for e in self.entries]
        return Table(
            title=f"Leaderboard: {self.a} vs {self.b}, task {self.task}",
            headers=["model", *(label(m) for m in self.metrics), "verdicts"],
            rows=rows,
            align=["l", *("r" for _ in self.metrics), "l"],
            note=f"Each metric: mean under {self.a} vs under {self.b}: the paired difference {self.a} − {self.b} "
            "[bootstrap 95 % CI] over the episodes both conditions ran (rates in percentage points).",
            anchor="leaderboard",
        )

    def verdict_lines(self) -> list[str]:
        from vlmproprio.verdicts import format_verdict

        out = []
        for e in self.entries:
            out += [f"⚠ {e.name}: {w}" for w in e.warnings]
            out += [f"{e.name} — {format_verdict(v)}" for v in e.verdicts]
        return out

    def to_markdown(self) -> str:
        lines = self.verdict_lines()
        return to_markdown(self.table(), level=2) + ("\n" + "\n".join(f"- {x}" for x in lines) + "\n" if lines else "")

    def to_json(self) -> dict:
        return {
            "a": self.a,
            "b": self.b,
            "task": self.task,
            "metrics": list(self.metrics),
            "entries": [
                {
                    "name": e.name,
                    "model": e.model,
                    "run_dir": str(e.run_dir),
                    "cells": {m: c.row if c.row is not None else {"missing": c.why} for m, c in e.cells.items()},
                    "verdicts": e.verdicts,
                    "warnings": e.warnings,
                }
                for e in self.entries
            ],
        }


def _cell(s: RunScores, model: str, metric: str, a: str, b: str, task: str) -> Cell:
    for r in s.paired:
        if (r["model"], r["task"], r["metric"], r["a"], r["b"]) == (model, task, metric, a, b):
            return Cell(r)
    missing = [c for c in (a, b) if c not in s.conditions]
    if missing:
        return Cell(None, f"condition {', '.join(missing)} not run")
    if task not in s.tasks(with_all=True):
        return Cell(None, f"no {task} episodes")
    return Cell(None, f"{label(metric)} not scored")


def build_leaderboard(
    run_dirs: Sequence[str | Path],
    metrics: Sequence[str] = LEADERBOARD_METRICS,
    a: str = "both",
    b: str = "none",
    task: str = "all",
) -> Leaderboard:
    if not run_dirs:
        raise ReportError("leaderboard: name at least one scored run directory")
    board = Leaderboard(tuple(metrics), a, b, task)
    runs = [load_run_scores(d) for d in run_dirs]
    names = [m for s in runs for m in s.models]
    for s in runs:
        t = s.pooled_task if task == "all" else task
        for model in s.models:
            name = model if names.count(model) == 1 else f"{model} ({s.run_dir})"
            verdicts = [v for v in s.verdicts.get("verdicts", []) if v.get("model") == model]
            warnings = [w["message"] for w in s.verdicts.get("warnings", []) if w.get("model") == model]
            cells = {m: _cell(s, model, m, a, b, t) for m in metrics}
            board.entries.append(Entry(name, model, s.run_dir, cells, verdicts, warnings))
    return board


def leaderboard_figure(board: Leaderboard):
    """One panel per metric: each entry's paired difference A − B with its 95 % CI; 0 marks no effect."""
    from vlmproprio.report.plots import _figure

    n = len(board.entries)
    fig = _figure(3.2 * len(board.metrics), 0.5 + 0.4 * n)
    axes = fig.subplots(1, len(board.metrics), sharey=True, squeeze=False)[0]
    ys = list(range(n))[::-1]
    for ax, metric in zip(axes, board.metrics, strict=True):
        for y, e in zip(ys, board.entries, strict=True):
            r = e.cells[metric].row
            if r is None or not all(math.isfinite(float(r[k])) for k in ("mean_diff", "ci_low", "ci_high")):
                ax.text(0, y, "not tested", ha="center", va="center", fontsize=7, color="0.4")
                continue
            d, lo, hi = r["mean_diff"], r["ci_low"], r["ci_high"]
            ax.errorbar([d], [y], xerr=[[d - lo], [hi - d]], fmt="o", color="C0", capsize=3)
        ax.axvline(0, color="0.5", lw=0.8, ls="--")
        ax.set_title(label(metric), fontsize=9)
        ax.set_xlabel(f"{board.a} − {board.b}", fontsize=8)
    axes[0].set_yticks(ys, [e.name for e in board.entries], fontsize=8)
    axes[0].set_ylim(-0.7, n - 0.3)
    return fig


def write_leaderboard(board: Leaderboard, out: str | Path) -> dict[str, Path]:
    """index.html (the table, the plot and the verdicts), leaderboard.md, leaderboard.png and leaderboard.json."""
    import jinja2

    from vlmproprio.io import atomic_write_text
    from vlmproprio.report.plots import save_figure

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    paths = {k: out / v for k, v in FILES.items()}
    save_figure(leaderboard_figure(board), paths["plot"])
    atomic_write_text(paths["markdown"], board.to_markdown())
    atomic_write_text(paths["json"], dumps_indented(board.to_json(), nan_as_null=True) + "\n")
    template = (Path(__file__).parent / "leaderboard.html").read_text(encoding="utf-8")
    env = jinja2.Environment(autoescape=True, undefined=jinja2.StrictUndefined, trim_blocks=True, lstrip_blocks=True)
    html = env.from_string(template).render(
        table=board.table(), plot=paths["plot"].name, lines=board.verdict_lines(), css=_css()
    )
    atomic_write_text(paths["html"], html)
    return paths


def _css() -> str:
    return (Path(__file__).parent / "style.css").read_text(encoding="utf-8")
