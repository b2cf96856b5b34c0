"""Compare two scored runs, or two models inside one run: metric differences B − A, paired by episode.

Rows are matched on (model, task, condition, episode); with ``model_a``/``model_b`` (two models, in one run
or in two) on (task, condition, episode). Each difference comes with the same statistics as the scores'
condition comparisons (vlmproprio.stats: bootstrap 95% CI, sign-flip p-value), over the episodes both sides
have. Metrics that exist only as a per-condition mean (MEAN_ONLY_METRICS; none at present) get no CI.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

from vlmproprio.evaluation.metrics import compare_metrics
from vlmproprio.report.data import ReportError, RunScores, load_run_scores
from vlmproprio.report.tables import Table, fmt_diff, fmt_p, fmt_value, label, metric_kind, to_markdown

# the metric table's default comparison: the paired caption metrics; segmentation also at the fixed threshold,
# which two runs share
COMPARE_METRICS = compare_metrics()
# aggregate-only columns would go here; the in-sample best threshold, the one there was, is no score any more
MEAN_ONLY_METRICS: tuple[str, ...] = ()


@dataclass
class Comparison:
    label_a: str
    label_b: str
    rows: list[dict]
    notes: list[str] = field(default_factory=list)

    def table(self) -> Table:
        show_model = len({r["model"] for r in self.rows}) > 1
        out = []
        for r in self.rows:
            m = r["metric"]
            unit = " pp" if metric_kind(m) == "rate" else ""
            ci = "" if r["ci_low"] is None else f" [{fmt_diff(m, r['ci_low'])}, {fmt_diff(m, r['ci_high'])}]"
            out.append(
                [
                    *([r["model"]] if show_model else []),
                    r["task"],
                    r["condition"],
                    label(m),
                    str(r["n"]) if r["n"] is not None else "–",
                    fmt_value(m, r["a"]),
                    fmt_value(m, r["b"]),
                    f"{fmt_diff(m, r['diff'])}{unit}{ci}",
                    fmt_p(r["p_value"]),
                ]
            )
        return Table(
            title=f"B − A: {self.label_b} − {self.label_a}",
            headers=[
                *(["model"] if show_model else []),
                "task",
                "condition",
                "metric",
                "n",
                "A",
                "B",
                "B − A [95% CI]",
                "p",
            ],
            rows=out,
            align=[*(["l"] if show_model else []), "l", "l", "l", "r", "r", "r", "r", "r"],
            note="A: " + self.label_a + "; B: " + self.label_b + ". Paired by episode; rates in percentage points.",
        )

    def to_markdown(self) -> str:
        lines = [f"# Comparison: {self.label_b} vs {self.label_a}", ""]
        lines += [f"- note: {n}" for n in self.notes]
        if self.notes:
            lines.append("")
        return "\n".join(lines) + to_markdown(self.table(), level=2)


def _settings_notes(a: RunScores, b: RunScores) -> list[str]:
    notes = []
    checks = (
        ("sentence encoder", lambda s: s.meta.get("encoder", {}).get("key")),
        ("lexicons", lambda s: {k: v.get("sha256") for k, v in s.meta.get("lexicons", {}).items()}),
        ("segmentation threshold", lambda s: s.threshold),
        ("prompt version", lambda s: s.prompt_version),
    )
    for what, get in checks:
        va, vb = get(a), get(b)
        if va != vb and va is not None and vb is not None:
            notes.append(f"the runs differ in {what} ({va} vs {vb}): differences are not only the model's")
    return notes


def _pick(s: RunScores, model: str | None, side: str) -> list[dict]:
    if model is None:
        return s.rows
    rows = [r for r in s.rows if r["model"] == model]
    if not rows:
        raise ReportError(f"{s.run_dir}: no model {model!r} (--model-{side}); models there: {', '.join(s.models)}")
    return rows


@dataclass
class _Matched:
    """The rows of both sides by match key (model or "", task, condition, episode), and the keys both have."""

    a: dict[tuple, dict]
    b: dict[tuple, dict]
    common: list[tuple]


def _compare_by_model(sa: RunScores, sb: RunScores, rows_a: list[dict], rows_b: list[dict], notes: list[str]) -> bool:
    """With no model chosen: match rows model by model, or two single-model runs model against model."""
    if {r["model"] for r in rows_a} & {r["model"] for r in rows_b}:
        return True
    if len(sa.models) == 1 and len(sb.models) == 1:
        notes.append(f"no model in common: comparing {sa.models[0]} (A) with {sb.models[0]} (B)")
        return False
    raise ReportError(
        f"no model in common ({', '.join(sa.models)} vs {', '.join(sb.models)}); choose with --model-a/--model-b"
    )


def _match(rows_a: list[dict], rows_b: list[dict], by_model: bool, notes: list[str]) -> _Matched:
    def key(r: dict) -> tuple:
        return (r["model"] if by_model else "", r["task"], r["condition"], r["episode_id"])

    ia = {key(r): r for r in rows_a}
    ib = {key(r): r for r in rows_b}
    common = sorted(set(ia) & set(ib))
    if not common:
        raise ReportError("the two sides share no (task, condition, episode): nothing to compare")
    only_a, only_b = len(set(ia) - set(ib)), len(set(ib) - set(ia))
    if only_a or only_b:
        notes.append(f"{only_a} row(s) only in A and {only_b} only in B are left out")
    return _Matched(ia, ib, common)


def _metrics_to_compare(metrics: Sequence[str] | None, row: dict, notes: list[str]) -> list[str]:
    """The metrics asked for (default: COMPARE_METRICS), checked against a row of the scores."""
    if metrics is None:  # the default set, less what these scores lack (out-of-sample needs 2+ episodes a task)
        metrics = [m for m in COMPARE_METRICS if m in row or m in MEAN_ONLY_METRICS]
        if lacking := [m for m in COMPARE_METRICS if m not in metrics]:
            notes.append(f"not in these scores, left out: {', '.join(lacking)}")
    unknown = [m for m in metrics if m not in row and m not in MEAN_ONLY_METRICS]
    if unknown:
        raise ReportError(f"unknown metric(s) {', '.join(unknown)}; see the columns of scores/rows.csv")
    return list(metrics)


def _layout(sa: RunScores, common: list[tuple], tasks: Sequence[str] | None) -> tuple[list, list, list]:
    """The models, tasks ("all" too when there are several) and conditions of the comparison, in A's order."""
    conds = [c for c in sa.conditions if any(k[2] == c for k in common)]
    conds += sorted({k[2] for k in common} - set(conds))
    models = sorted({k[0] for k in common}, key=lambda m: sa.models.index(m) if m in sa.models else 99)
    present = [t for t in sa.tasks() if any(k[1] == t for k in common)]
    task_list = [*present, "all"] if len(present) > 1 else present
    if tasks:
        task_list = [t for t in task_list if t in tasks]
    return models, task_list, conds


def _difference(matched: _Matched, keys: list[tuple], metric: str, n_boot: int, seed: int) -> dict:
    from vlmproprio.stats import paired_difference

    pairs = [(matched.a[k].get(metric), matched.b[k].get(metric)) for k in keys]
    pairs = [(x, y) for x, y in pairs if _num(x) and _num(y)]
    res = paired_difference([y for _, y in pairs], [x for x, _ in pairs], n_boot=n_boot, seed=seed)
    return {
        "n": res.n,
        "a": res.mean_b,
        "b": res.mean_a,
        "diff": res.mean_diff,
        "ci_low": res.ci_low,
        "ci_high": res.ci_high,
        "p_value": res.p_value,
    }


def compare_runs(
    run_a: str | Path,
    run_b: str | Path | None = None,
    *,
    model_a: str | None = None,
    model_b: str | None = None,
    metrics: Sequence[str] | None = None,
    tasks: Sequence[str] | None = None,
    n_boot: int | None = None,
    seed: int | None = None,
) -> Comparison:
    """Differences B − A per (task, condition, metric). ``run_b`` None compares ``model_a`` with ``model_b``
    inside ``run_a``. With no model given and no model name in common, two single-model runs are compared
    model against model."""
    from vlmproprio.stats import DEFAULT_N_BOOT, DEFAULT_SEED

    if run_b is None and (model_a is None or model_b is None):
        raise ReportError("comparing inside one run needs both --model-a and --model-b")
    sa = load_run_scores(run_a)
    sb = sa if run_b is None else load_run_scores(run_b)
    rows_a, rows_b = _pick(sa, model_a, "a"), _pick(sb, model_b, "b")
    notes = [] if sb is sa else _settings_notes(sa, sb)
    by_model = model_a is None and model_b is None and _compare_by_model(sa, sb, rows_a, rows_b, notes)
    matched = _match(rows_a, rows_b, by_model, notes)
    metrics = _metrics_to_compare(metrics, matched.a[matched.common[0]], notes)
    models, task_list, conds = _layout(sa, matched.common, tasks)
    nb = n_boot or DEFAULT_N_BOOT
    sd = DEFAULT_SEED if seed is None else seed
    out = []
    for model in models:
        for task in task_list:
            for cond in conds:
                keys = [k for k in matched.common if k[0] == model and k[2] == cond and (task == "all" or k[1] == task)]
                if not keys:
                    continue
                for m in metrics:
                    if m in MEAN_ONLY_METRICS:
                        out.append(_mean_only(sa, sb, model_a, model_b, model, task, cond, m))
                    else:
                        cell = {"model": model, "task": task, "condition": cond, "metric": m}
                        out.append(cell | _difference(matched, keys, m, nb, sd))
    la = f"{Path(run_a).name}" + (f" [{model_a}]" if model_a else "")
    lb = f"{Path(run_b if run_b is not None else run_a).name}" + (f" [{model_b}]" if model_b else "")
    return Comparison(la, lb, out, notes)


def _num(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def _mean_only(sa, sb, model_a, model_b, model, task, cond, m) -> dict:
    ra = sa.aggregate_row(model_a or model, task, cond) or {}
    rb = sb.aggregate_row(model_b or model, task, cond) or {}
    a, b = ra.get(m), rb.get(m)
    return {
        "model": model,
        "task": task,
        "condition": cond,
        "metric": m,
        "n": None,
        "a": a,
        "b": b,
        "diff": b - a if _num(a) and _num(b) else None,
        "ci_low": None,
        "ci_high": None,
        "p_value": None,
    }
