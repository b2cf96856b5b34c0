"""The report's tables: one Table type rendered both as Markdown (report.md) and as HTML (the page).

Numbers are formatted by what they measure: rates as percent (differences of rates in percentage
points), F1 and hits per word as fractions, words and segmentation points as means with one decimal.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field

from vlmproprio.conditions import BASELINE
from vlmproprio.evaluation.metrics import BY_NAME, headline_metrics, report_columns
from vlmproprio.report.data import RunScores, task_label

RATE_SUFFIXES = ("_mentioned", "_correct", "_wrong", "_missing")
# the aggregate tables' columns and their labels come from the metric table (vlmproprio.evaluation.metrics)
CAPTION_COLUMNS = report_columns("captions")
SEGMENTATION_COLUMNS = report_columns("segmentation")


# ---------------------------------------------------------------------------------------------- formatting


def metric_kind(metric: str) -> str:
    """rate | count | f1 | ratio | int: decides how a value and a difference of it are printed (the metric
    table's unit; a column outside the table, e.g. asked for by `compare --metric`, by its name)."""
    if metric in BY_NAME:
        return BY_NAME[metric].unit
    if metric.endswith(("_words", "_points", "_boundaries", "_edit", "words")):
        return "count"
    if "_edit_" in metric:  # edit score chance / lift / even: 0-100 like the score
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
    """'+40 pp [+10, +70] p=0.031 q=0.20' (rates in percentage points); a primary test shows its Holm-adjusted
    p ('Holm p=') and a star, an exploratory one its Benjamini-Hochberg q-value."""
    d = r.get("mean_diff")
    if not _finite(d):
        return "–"
    unit = " pp" if metric_kind(metric) == "rate" else ""
    ci = f"[{fmt_diff(metric, r.get('ci_low'))}, {fmt_diff(metric, r.get('ci_high'))}]"
    p = fmt_p(r.get("p_value"))
    text = f"{fmt_diff(metric, d)}{unit} {ci} p{'' if p.startswith('<') else '='}{p}"
    if r.get("family") == "primary":
        h = fmt_p(r.get("p_holm"))
        return f"★ {text} Holm p{'' if h.startswith('<') else '='}{h}"
    if r.get("family") == "exploratory":
        q = fmt_p(r.get("q_bh"))
        return f"{text} q{'' if q.startswith('<') else '='}{q}"
    return text


def label(metric: str) -> str:
    spec = BY_NAME.get(metric)
    return spec.label if spec is not None else metric.removeprefix("final_").replace("_", " ")


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
        f"Segmentation points at the paper's threshold {thr:g} (cosine similarity of consecutive frame captions "
        "below it) and at a threshold chosen out of sample (LOO: the best mean boundary F1 on the other episodes "
        "of the task). F1: boundary F1 against the true phase changes, ±1 frame. Chance: the expected F1 of the "
        "same number of points placed at random; even: evenly spaced; lift = F1 − chance; group-edge F1: points "
        "at the edges of the frame groups. Edit: MS-TCN's segmental edit score (0–100), F1@25: segmental F1 at "
        "IoU 0.25, both on majority-labelled segments (docs/metrics.md). The in-sample best threshold is only "
        "in the sweep plot, as an optimistic upper bound.",
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
        f"{st.get('ci', 'bootstrap 95%')} CI and a {st.get('p_value', 'sign-flip permutation')} p-value. "
        "★ marks a pre-registered primary hypothesis (its Holm-adjusted p decides); every other test is "
        "exploratory and shows its Benjamini–Hochberg q-value: read it as a lead, not a finding. Segmentation "
        "uses the out-of-sample (leave-one-episode-out) threshold; a lift is the score minus random chance."
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


def combined_table(s: RunScores) -> Table:
    """One row per model and combined claim (the question a reader asks): its verdict and why."""
    from vlmproprio.verdicts import COMBINED_RULE

    rows, classes = [], []
    for c in s.verdicts.get("combined", []):
        rows.append(
            [c["model"], c["description"], " and ".join(c["all_of"]), c["verdict"], c["because"], fmt_p(c.get("p"))]
        )
        classes.append(f"verdict-{c['verdict'].replace(' ', '-')}")
    return Table(
        title="Claims: does the state's content help?",
        headers=["model", "claim", "hypotheses", "verdict", "because", "p"],
        rows=rows,
        align=["l", "l", "l", "l", "l", "r"],
        note=f"A claim combines the hypotheses under it by {COMBINED_RULE}. Beating no state alone can be won by a "
        "captioner that only notices that numbers are present; beating another episode's states as well needs their "
        "content.",
        anchor="claims",
        row_classes=classes,
    )


def verdict_table(s: RunScores) -> Table:
    """One row per model and pre-registered primary hypothesis: the verdict, effect with 95 % CI, corrected p."""
    from vlmproprio.verdicts import BOUND_RULE, VERDICT_RULES

    rows = []
    for v in s.verdicts.get("verdicts", []):
        rows.append(
            [
                v["model"],
                f"{v['a']} > {v['b']}",
                label(v["metric"]),
                v["task"],
                v["verdict"] + (f": {v['bound_text']}" if v.get("bound_text") else ""),
                fmt_paired(v["metric"], {**v, "family": None}) if v.get("mean_diff") is not None else "–",
                fmt_p(v.get("p_holm")),
            ]
        )
    claims = s.verdicts.get("claims", {})
    return Table(
        title="Verdicts on the pre-registered hypotheses",
        headers=["model", "hypothesis", "metric", "task", "verdict", "effect [95% CI] p", "Holm p"],
        rows=rows,
        align=["l", "l", "l", "l", "l", "r", "r"],
        note=f"Primary hypotheses from {claims.get('source', 'claims.yml')} (alpha {claims.get('alpha', 0.05)}), "
        "corrected with Holm's procedure per model. "
        + " ".join(f"{k.capitalize()}: {VERDICT_RULES[k]}." for k in ("supported", "not supported", "inconclusive"))
        + f" The stated bound is {BOUND_RULE}.",
        anchor="verdicts",
        row_classes=[f"verdict-{v['verdict'].replace(' ', '-')}" for v in s.verdicts.get("verdicts", [])],
    )


def verdict_lines(s: RunScores) -> list[str]:
    """The report's first lines: every sanity warning, the combined claims, then each primary hypothesis."""
    from vlmproprio.verdicts import verdict_doc_lines

    return verdict_doc_lines(s.verdicts)


CORRELATION_DIMS = ("gripper", "x", "y", "z", "roll", "pitch", "yaw")


def controls_table(s: RunScores) -> Table:
    """How much each condition's numbers still tell about the episode: mean Pearson r with the true states."""
    from vlmproprio.conditions import CONDITIONS, STATE_DIMENSIONS

    rows = []
    for cond, by_task in s.meta.get("controls", {}).items():
        if cond != "both" and not (cond in CONDITIONS and CONDITIONS[cond].control):
            continue  # the paper's own-state conditions show the true numbers (r = 1); "both" stands for them
        for task in s.tasks():
            dims = by_task.get(task)
            if not dims:
                continue
            joints = [dims[d]["mean_r"] for d in STATE_DIMENSIONS[:7] if d in dims]
            cells = [f"{sum(joints) / len(joints):+.2f}" if joints else "–"]
            cells += [f"{dims[d]['mean_r']:+.2f}" if d in dims else "–" for d in CORRELATION_DIMS]
            top = max((max(abs(v["max_r"]), abs(v["min_r"])) for v in dims.values()), default=None)
            rows.append([cond, task, *cells, f"{top:.2f}" if top is not None else "–"])
    return Table(
        title="How much each condition's state still tells: correlation with the true states",
        headers=["condition", "task", "joints 1–7", *CORRELATION_DIMS, "max |r|"],
        rows=rows,
        align=["l", "l", *("r" for _ in range(len(CORRELATION_DIMS) + 2))],
        note="Mean over episodes of the Pearson r, per state dimension, between the numbers a condition's prompts "
        "showed and the episode's true states (joints: mean of the seven joints; max |r|: the largest |r| of any "
        "episode and dimension; all conditions, per dimension and over both tasks, are in scores/meta.json). A control near 0 carries no information about the episode's timeline; one near "
        "1 is weak (reversed pick-and-place still resembles the original).",
        anchor="controls",
    )


def parsing_table(s: RunScores) -> Table | None:
    """Per model: how its answers were parsed (meta.json "parsing"; None for scores made before it was kept)."""
    from vlmproprio.sanity import MIN_HEAVY_RECOVERY_SHARE

    parsing = s.meta.get("parsing")
    if not isinstance(parsing, dict) or not isinstance(parsing.get("models"), dict):
        return None
    rows = []
    for model, p in parsing["models"].items():
        f = p["frames"]
        present = f["captions"] - f["missing"]
        heavy = f"{f['heavy']} ({100 * f['heavy'] / present:.0f}%)" if present else "0"
        classes = "; ".join(
            f"{cls} {n['frames']}/{n['scenes']}/{n['final']}" for cls, n in p.get("recoveries", {}).items()
        )
        reasoning = f"{p['answers_with_reasoning']} ({p['reasoning_chars']} chars)"
        rows.append(
            [model, str(p["answers"]), reasoning, str(f["recovered"]), str(f["missing"]), heavy, classes or "–"]
        )
    return Table(
        title="Parsing recoveries",
        headers=["model", "answers", "with reasoning", "frames recovered", "frames missing", "heavy", "recoveries"],
        rows=rows,
        align=["l", "r", "r", "r", "r", "r", "l"],
        note="How the parser got each model's captions. Recoveries: per recovery class, the present frame/scene/final "
        "captions it was applied to. Heavy: present frame captions placed by position rather than read from a frame "
        f"label ({', '.join(parsing.get('heavy_classes', []))}); a sanity warning fires at "
        f"{100 * MIN_HEAVY_RECOVERY_SHARE:g}%. Reasoning blocks are "
        "kept apart in the transcripts and never scored.",
        anchor="parsing",
    )


def report_tables(s: RunScores) -> list[Table]:
    # the metrics scoring paired (evaluation.PAIRED_METRICS, recorded in the scores), not a copy to keep in step
    caption_metrics = [m for m in s.paired_metrics if m.startswith("final_")]
    segmentation_metrics = [m for m in s.paired_metrics if m.startswith("seg_")]
    tables = [
        verdict_table(s),
        caption_table(s),
        segmentation_table(s),
        controls_table(s),
        paired_table(s, caption_metrics, "Paired differences: final captions", "paired-captions"),
        paired_table(s, segmentation_metrics, "Paired differences: segmentation", "paired-segmentation"),
    ]
    parsed = parsing_table(s)
    if parsed is not None:
        tables.append(parsed)
    judged = judge_table(s)
    return [*tables, judged] if judged is not None else tables


HEADLINE_METRICS = headline_metrics()
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
        "## Verdicts",
        "",
        *(f"- {line}" for line in verdict_lines(s)),
        "",
        f"- models: {', '.join(s.models)}",
        f"- episodes: {len(s.episodes)} ({', '.join(f'{task_label(t)}: {sum(1 for e in s.episodes if s.task_of(e) == t)}' for t in s.tasks())})",
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
