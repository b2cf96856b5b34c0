"""The report's tables: one Table type rendered both as Markdown (report.md) and as HTML (the page).

Numbers are formatted by what they measure: rates as percent (differences of rates in percentage
points), F1 and hits per word as fractions, words and segmentation points as means with one decimal.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field

from vlmproprio.report.data import TASK_LABELS, RunScores

BASELINE = "none"

LABELS = {
    "n_episodes": "n",
    "final_object_mentioned": "object mentioned",
    "final_object_correct": "object correct",
    "final_action_mentioned": "action mentioned",
    "final_action_correct": "action correct",
    "final_trajectory_mentioned": "trajectory mentioned",
    "final_trajectory_correct": "trajectory correct",
    "final_all_correct": "all correct",
    "final_words": "words",
    "final_hits_per_word": "hits/word",
    "final_missing": "final missing",
    "frames_missing": "frames missing",
    "seg_gt_boundaries": "true boundaries",
    "seg_points": "points @thr",
    "seg_f1_tol1": "F1 @thr",
    "seg_best_threshold": "best thr",
    "seg_best_f1_tol1": "F1 @best",
    "seg_edit": "edit score",
}
RATE_SUFFIXES = ("_mentioned", "_correct", "_wrong", "_missing")
CAPTION_COLUMNS = (
    "n_episodes",
    "final_object_mentioned",
    "final_object_correct",
    "final_action_mentioned",
    "final_action_correct",
    "final_trajectory_mentioned",
    "final_trajectory_correct",
    "final_all_correct",
    "final_words",
    "final_hits_per_word",
)
SEGMENTATION_COLUMNS = (
    "seg_gt_boundaries",
    "seg_points",
    "seg_f1_tol1",
    "seg_best_threshold",
    "seg_best_f1_tol1",
    "seg_edit",
    "frames_missing",
)


# ---------------------------------------------------------------------------------------------- formatting


def metric_kind(metric: str) -> str:
    """rate | count | f1 | ratio | int: decides how a value and a difference of it are printed."""
    if metric == "n_episodes":
        return "int"
    if metric == "frames_missing" or metric.endswith(("_words", "_points", "_boundaries", "_edit", "words")):
        return "count"
    if metric.endswith("hits_per_word"):
        return "ratio"
    if metric.endswith(RATE_SUFFIXES):
        return "rate"
    return "f1"


def _finite(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def fmt_value(metric: str, v) -> str:
    if not _finite(v):
        return "–"
    kind = metric_kind(metric)
    if kind == "int":
        return str(int(v))
    if kind == "rate":
        return f"{100 * v:.0f}%"
    if kind == "count":
        return f"{v:.1f}"
    if kind == "ratio":
        return f"{v:.3f}"
    return f"{v:.2f}"


def fmt_diff(metric: str, d) -> str:
    if not _finite(d):
        return "–"
    kind = metric_kind(metric)
    if kind == "rate":
        return f"{100 * d:+.0f}"
    if kind in ("count", "int"):
        return f"{d:+.1f}"
    if kind == "ratio":
        return f"{d:+.3f}"
    return f"{d:+.2f}"


def fmt_p(p) -> str:
    if not _finite(p):
        return "–"
    return "<0.001" if p < 0.001 else f"{p:.3f}"


def fmt_paired(metric: str, r: dict) -> str:
    """'+40 pp [+10, +70] p=0.031' (rates in percentage points)."""
    d = r.get("mean_diff")
    if not _finite(d):
        return "–"
    unit = " pp" if metric_kind(metric) == "rate" else ""
    ci = f"[{fmt_diff(metric, r.get('ci_low'))}, {fmt_diff(metric, r.get('ci_high'))}]"
    p = fmt_p(r.get("p_value"))
    return f"{fmt_diff(metric, d)}{unit} {ci} p{'' if p.startswith('<') else '='}{p}"


def label(metric: str) -> str:
    return LABELS.get(metric, metric.removeprefix("final_").replace("_", " "))


# ---------------------------------------------------------------------------------------------- tables


@dataclass
class Table:
    """A titled table of already formatted cells; ``align`` holds 'l' or 'r' per column."""

    title: str
    headers: list[str]
    rows: list[list[str]]
    align: list[str]
    note: str = ""
    anchor: str = ""
    # per row: a CSS class for the HTML page (e.g. the baseline row); Markdown ignores it
    row_classes: list[str] = field(default_factory=list)


def to_markdown(table: Table, level: int = 3) -> str:
    def esc(cell: str) -> str:
        return cell.replace("|", "\\|").replace("\n", " ")

    lines = [f"{'#' * level} {table.title}", ""]
    if table.note:
        lines += [table.note, ""]
    lines.append("| " + " | ".join(esc(h) for h in table.headers) + " |")
    lines.append("|" + "|".join("---:" if a == "r" else ":---" for a in table.align) + "|")
    lines += ["| " + " | ".join(esc(c) for c in row) + " |" for row in table.rows]
    return "\n".join(lines) + "\n"


def _ordered(rows: Iterable[dict], s: RunScores, key: str = "condition") -> list[dict]:
    tasks = s.tasks(with_all=True)
    conds = s.conditions
    return sorted(
        rows,
        key=lambda r: (
            s.models.index(r["model"]) if r["model"] in s.models else len(s.models),
            tasks.index(r["task"]) if r["task"] in tasks else len(tasks),
            conds.index(r[key]) if r.get(key) in conds else len(conds),
        ),
    )


def aggregate_table(s: RunScores, columns: Sequence[str], title: str, note: str, anchor: str) -> Table:
    rows, classes = [], []
    for a in _ordered((a for a in s.aggregate if a["task"] in s.tasks(with_all=True)), s):
        rows.append([a["model"], a["task"], a["condition"], *(fmt_value(c, a.get(c)) for c in columns)])
        classes.append("baseline" if a["condition"] == BASELINE else "")
    return Table(
        title=title,
        headers=["model", "task", "condition", *(label(c) for c in columns)],
        rows=rows,
        align=["l", "l", "l", *("r" for _ in columns)],
        note=note,
        anchor=anchor,
        row_classes=classes,
    )


def caption_table(s: RunScores) -> Table:
    return aggregate_table(
        s,
        CAPTION_COLUMNS,
        "Final captions: success rates per condition",
        "Share of final captions that mention / correctly state the target object, the action and the "
        "trajectory (motion direction, target compartment); 'all correct' needs all three. Means over episodes.",
        "captions",
    )


def segmentation_table(s: RunScores) -> Table:
    thr = s.threshold
    return aggregate_table(
        s,
        SEGMENTATION_COLUMNS,
        "Subtask segmentation",
        f"Segmentation points at the threshold {thr:g} (cosine similarity of consecutive frame captions below it) "
        "and boundary F1 against the true phase changes with a tolerance of ±1 frame, at that threshold and at the "
        "threshold with the best mean F1 of the sweep. Edit score: 0-100 over the segment label sequence.",
        "segmentation",
    )


def paired_table(
    s: RunScores,
    metrics: Sequence[str],
    title: str,
    anchor: str,
    comparisons: Sequence[tuple[str, str]] | None = None,
) -> Table:
    index: dict[tuple, dict] = {}
    order: list[tuple] = []
    for r in s.paired:
        if comparisons is not None and (r["a"], r["b"]) not in comparisons:
            continue
        k = (r["model"], r["task"], r["a"], r["b"])
        if k not in index:
            index[k] = {}
            order.append(k)
        index[k][r["metric"]] = r
    tasks = s.tasks(with_all=True)
    models = s.models
    # vs-baseline comparisons first (the paper's question), then full state against each control
    order.sort(
        key=lambda k: (
            models.index(k[0]) if k[0] in models else len(models),
            tasks.index(k[1]) if k[1] in tasks else len(tasks),
            k[3] != BASELINE,
        )
    )
    rows, classes = [], []
    for k in order:
        by_metric = index[k]
        n = next((r.get("n") for r in by_metric.values()), None)
        rows.append(
            [
                k[0],
                k[1],
                f"{k[2]} − {k[3]}",
                str(n),
                *(fmt_paired(m, by_metric[m]) if m in by_metric else "–" for m in metrics),
            ]
        )
        classes.append("control" if k[3] != BASELINE else "")
    st = s.meta.get("stats", {})
    note = (
        "Mean difference A − B paired by episode (rates in percentage points), its "
        f"{st.get('ci', 'bootstrap 95%')} CI and a {st.get('p_value', 'sign-flip permutation')} p-value."
    )
    return Table(
        title=title,
        headers=["model", "task", "A − B", "n", *(label(m) for m in metrics)],
        rows=rows,
        align=["l", "l", "l", "r", *("r" for _ in metrics)],
        note=note,
        anchor=anchor,
        row_classes=classes,
    )


def judge_table(s: RunScores) -> Table | None:
    """Rubric against the judge model, per item and field: agreement and Cohen's kappa (when a judge ran)."""
    if not s.judge or not isinstance(s.judge.get("agreement"), dict):
        return None
    agr = s.judge["agreement"]
    model = s.judge.get("backend", {}).get("model_id", "?")
    rows = []
    for name, v in agr.get("items", {}).items():
        a, k = v.get("agreement"), v.get("kappa")
        rows.append(
            [
                name.replace("_", " "),
                str(v.get("n", 0)),
                "—" if a is None else f"{a:.2f}",
                "—" if k is None else f"{k:.2f}",
            ]
        )
    return Table(
        title=f"Rubric against the judge model ({model})",
        headers=["item", "captions", "agreement", "Cohen's κ"],
        rows=rows,
        align=["l", "r", "r", "r"],
        note=f"{agr.get('n', 0)} final captions graded, {agr.get('unparsed', 0)} answers unusable (left out). "
        "The rubric stays the reference; κ corrects the agreement for chance (— where it is undefined).",
        anchor="judge",
    )


def report_tables(s: RunScores) -> list[Table]:
    # the metrics scoring paired (evaluation.PAIRED_METRICS, recorded in the scores), not a copy to keep in step
    caption_metrics = [m for m in s.paired_metrics if m.startswith("final_")]
    segmentation_metrics = [m for m in s.paired_metrics if m.startswith("seg_")]
    tables = [
        caption_table(s),
        segmentation_table(s),
        paired_table(s, caption_metrics, "Paired differences: final captions", "paired-captions"),
        paired_table(s, segmentation_metrics, "Paired differences: segmentation", "paired-segmentation"),
    ]
    judged = judge_table(s)
    return [*tables, judged] if judged is not None else tables


HEADLINE_METRICS = ("final_trajectory_correct", "final_all_correct", "final_words", "seg_f1_tol1")
HEADLINE_COMPARISONS = (("both", BASELINE), ("both", "both_shuffled"))


def headline_table(s: RunScores) -> Table:
    """The summary's table: full state against no state and against shuffled state, on the key metrics."""
    t = paired_table(
        s,
        HEADLINE_METRICS,
        "Full state against no state, and against shuffled state",
        "findings",
        comparisons=HEADLINE_COMPARISONS,
    )
    return t


def markdown_report(s: RunScores, tables: Sequence[Table], plots: Sequence[tuple[str, str]] = ()) -> str:
    """report.md: what was run, the plots (relative links) and every table."""
    m = s.manifest
    enc = s.meta.get("encoder", {})
    lines = [
        f"# vlmproprio report: {s.run_dir.name}",
        "",
        f"- models: {', '.join(s.models)}",
        f"- episodes: {len(s.episodes)} ({', '.join(f'{TASK_LABELS.get(t, t)}: {sum(1 for e in s.episodes if s.task_of(e) == t)}' for t in s.tasks())})",
        f"- conditions: {', '.join(s.conditions)}",
        f"- mode: {m.get('mode', '?')}, prompt version: {s.prompt_version or '?'}",
        f"- sentence encoder: {enc.get('name', '?')} ({enc.get('dim', '?')}-d), threshold {s.threshold:g}",
        "",
    ]
    if plots:
        lines += ["## Plots", ""]
        lines += [f"![{alt}]({path})" for path, alt in plots]
        lines.append("")
    lines += ["## Tables", ""]
    lines += [to_markdown(t) for t in tables]
    return "\n".join(lines)
