"""The report's figures (PNG, matplotlib Agg, no display), mirroring the paper's Figs. 5-8.

* Fig. 5: share of final captions that mention / correctly state object, action and trajectory, per condition and task;
* Fig. 6: mean number of segmentation points against the similarity threshold, per condition and task;
* Figs. 7-8: the similarity trace of one Door and one bin episode under a condition without state and one
  with, the threshold line, the true phase changes, and the caption at each segmentation point;
* boundary F1 (±1 frame) against the threshold, per condition and task.

Figures are built on ``matplotlib.figure.Figure`` directly (not pyplot), so nothing global is touched and
every figure is freed when it goes out of scope.
"""

from __future__ import annotations

import math
import textwrap
import unicodedata
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from vlmproprio.report.data import RunScores, task_label
from vlmproprio.scoring import ITEMS
from vlmproprio.transcripts import cell_key

DPI = 110
# one colour per condition in every figure; controls also get a hatch (bars) and a dashed line
CONDITION_STYLE = {
    "none": ("#7f7f7f", ""),
    "ee": ("#1f77b4", ""),
    "joint": ("#ff7f0e", ""),
    "both": ("#2ca02c", ""),
    "both_shuffled": ("#9467bd", "//"),
    "both_permuted": ("#d62728", "--"),
    "both_noisy": ("#8c564b", "\\\\"),
    "state_only": ("#e377c2", ".."),
    "primitives": ("#bcbd22", "xx"),
}
EXTRA_COLOURS = ("#17becf", "#d62728", "#393b79", "#637939", "#8c6d31", "#843c39")
MAX_ANNOTATIONS = 10
CAPTION_CHARS = 90


@dataclass(frozen=True)
class Plot:
    """A written figure: its file (relative to the report folder), title and what it shows."""

    model: str
    kind: str  # fig5 | fig6 | f1 | trace
    file: str
    title: str
    caption: str


def condition_style(condition: str, conditions: Sequence[str]) -> tuple[str, str, str]:
    """(colour, bar hatch, line style) of a condition."""
    if condition in CONDITION_STYLE:
        colour, hatch = CONDITION_STYLE[condition]
    else:
        extra = [c for c in conditions if c not in CONDITION_STYLE]
        colour, hatch = EXTRA_COLOURS[extra.index(condition) % len(EXTRA_COLOURS)], "++"
    return colour, hatch, "--" if hatch else "-"


def _figure(width: float, height: float):
    from matplotlib.figure import Figure

    return Figure(figsize=(width, height), dpi=DPI, layout="constrained")


def save_figure(fig, path: Path) -> None:
    import io as _io

    from vlmproprio.io import atomic_write_bytes

    buf = _io.BytesIO()
    # no software/date metadata: the same scores give the same bytes
    fig.savefig(buf, format="png", dpi=DPI, metadata={"Software": None})
    atomic_write_bytes(path, buf.getvalue())  # one-line error on a read-only or full folder, no temp left


def _n_episodes(s: RunScores, model: str, task: str) -> int:
    return len({r["episode_id"] for r in s.rows if r["model"] == model and (task == "all" or r["task"] == task)})


def success_rates_figure(s: RunScores, model: str):
    """Fig. 5: for each task, bars per item and condition; light = mentioned, solid = correct."""
    from matplotlib.patches import Patch

    tasks = s.tasks()
    conds = s.conditions
    fig = _figure(1.2 + 4.6 * len(tasks), 3.8)
    axes = fig.subplots(1, len(tasks), sharey=True, squeeze=False)[0]
    width = 0.84 / max(1, len(conds))
    for ax, task in zip(axes, tasks, strict=True):
        for i, c in enumerate(conds):
            a = s.aggregate_row(model, task, c) or {}
            colour, hatch, _ = condition_style(c, conds)
            xs = [k + (i - (len(conds) - 1) / 2) * width for k in range(len(ITEMS))]
            mentioned = [100 * (a.get(f"final_{it}_mentioned") or 0.0) for it in ITEMS]
            correct = [100 * (a.get(f"final_{it}_correct") or 0.0) for it in ITEMS]
            ax.bar(xs, mentioned, width, color=colour, alpha=0.3, hatch=hatch, edgecolor=colour, linewidth=0.5)
            ax.bar(xs, correct, width, color=colour, hatch=hatch, edgecolor="white", linewidth=0.5)
        ax.set_xticks(range(len(ITEMS)), ITEMS)
        ax.set_ylim(0, 105)
        ax.set_title(f"{task_label(task)} (n={_n_episodes(s, model, task)})", fontsize=10)
        ax.grid(axis="y", alpha=0.3)
        ax.set_axisbelow(True)
    axes[0].set_ylabel("final captions (%)")
    handles = [
        Patch(facecolor=condition_style(c, conds)[0], hatch=condition_style(c, conds)[1], edgecolor="white", label=c)
        for c in conds
    ]
    handles += [
        Patch(facecolor="#555555", alpha=0.3, label="mentioned (light)"),
        Patch(facecolor="#555555", label="correct (solid)"),
    ]
    fig.legend(handles=handles, loc="outside right upper", fontsize=8, frameon=False)
    fig.suptitle(f"Caption success rates per condition — {model}", fontsize=11)
    return fig


def sweep_figure(s: RunScores, model: str, metric: str, ylabel: str, title: str, mark_best: bool = False):
    """Fig. 6 (metric 'points') or boundary F1 ('f1_tol1') against the threshold, one line per condition;
    ``mark_best`` stars each line's in-sample best point (an optimistic upper bound, see the caption)."""
    tasks = s.tasks()
    conds = s.conditions
    fig = _figure(1.2 + 4.6 * len(tasks), 3.6)
    axes = fig.subplots(1, len(tasks), sharey=True, squeeze=False)[0]
    for ax, task in zip(axes, tasks, strict=True):
        for c in conds:
            pts = sorted(
                (r["threshold"], r.get(metric))
                for r in s.sweep_aggregate
                if (r["model"], r["task"], r["condition"]) == (model, task, c) and r.get(metric) is not None
            )
            if not pts:
                continue
            colour, _, ls = condition_style(c, conds)
            ax.plot([p[0] for p in pts], [p[1] for p in pts], ls, color=colour, marker="o", ms=2.5, lw=1.3, label=c)
            if mark_best:
                best = max(pts, key=lambda p: (p[1], -p[0]))  # ties: the lowest threshold, as LOO picks
                ax.plot([best[0]], [best[1]], "*", color=colour, ms=9, mec="black", mew=0.5)
        ax.axvline(s.threshold, color="black", ls=":", lw=1)
        ax.set_xlabel("cosine similarity threshold")
        ax.set_xlim(0, 1)
        ax.set_title(f"{task_label(task)} (n={_n_episodes(s, model, task)})", fontsize=10)
        ax.grid(alpha=0.3)
    axes[0].set_ylabel(ylabel)
    fig.legend(*axes[0].get_legend_handles_labels(), loc="outside right upper", fontsize=8, frameon=False)
    fig.suptitle(title, fontsize=11)
    return fig


def _printable(text: str) -> str:
    """Model text can hold control characters (a random model writes any byte); fonts have no glyph for
    them, so they are shown as the replacement character instead."""
    return "".join("\ufffd" if unicodedata.category(ch) in ("Cc", "Cf", "Cs", "Co", "Cn") else ch for ch in text)


def _short(text: str) -> str:
    one = textwrap.shorten(" ".join(_printable(text).split()), CAPTION_CHARS, placeholder=" …")
    return textwrap.fill(one, 34)


def trace_figure(s: RunScores, model: str, episode_id: str, conditions: Sequence[str], captions: dict):
    """Figs. 7-8: similarity traces of one episode, one panel per condition, with the caption at each point.

    ``captions[(condition)]`` is the list of frame caption texts (may be empty: then no text is drawn).
    A point j means the caption of frame j+1 differs from that of frame j, so the text drawn is caption j+1."""
    thr = s.threshold
    task = s.task_of(episode_id) or ""
    fig = _figure(11, 2.9 * len(conditions) + 0.6)
    axes = fig.subplots(len(conditions), 1, sharex=True, squeeze=False)[:, 0]
    for ax, c in zip(axes, conditions, strict=True):
        tr = s.traces.get(cell_key(model, episode_id, c))
        if tr is None:
            ax.text(0.5, 0.5, f"no trace for {c}", ha="center", va="center", transform=ax.transAxes)
            continue
        ys = [math.nan if v is None else float(v) for v in tr["trace"]]
        xs = list(range(len(ys)))
        colour, _, _ = condition_style(c, s.conditions)
        for j in tr.get("true_boundaries", []):
            ax.axvline(j, color="#999999", lw=6, alpha=0.25, zorder=0)
        ax.plot(xs, ys, "-", color=colour, marker="o", ms=3, lw=1.3, zorder=2)
        ax.axhline(thr, color="black", ls="--", lw=1, zorder=1)
        pred = [j for j in tr.get("predicted_boundaries", []) if 0 <= j < len(ys)]
        ax.plot(pred, [ys[j] for j in pred], "o", color="#d62728", ms=6, zorder=3)
        fin = [y for y in ys if math.isfinite(y)]
        low = min([0.0, *fin]) - 0.05
        ax.set_ylim(low, 1.05)
        texts = captions.get(c) or []
        shown = sorted(sorted(pred, key=lambda j: ys[j])[:MAX_ANNOTATIONS])
        levels = (0.08, 0.36)
        for n, j in enumerate(shown):
            if j + 1 >= len(texts) or not texts[j + 1].strip():
                continue
            ax.annotate(
                _short(texts[j + 1]),
                xy=(j, ys[j]),
                xytext=(j, low + (1.05 - low) * levels[n % 2]),
                fontsize=6,
                ha="center" if 2 < j < len(ys) - 3 else ("left" if j <= 2 else "right"),
                va="bottom",
                color="#b0171f",
                bbox={"boxstyle": "round,pad=0.2", "fc": "white", "ec": "#d62728", "lw": 0.5, "alpha": 0.85},
                arrowprops={"arrowstyle": "-", "color": "#d62728", "lw": 0.5},
                zorder=4,
            )
        more = f", {len(shown)} of {len(pred)} annotated" if len(shown) < len(pred) else ""
        ax.set_title(f"{c}: {len(pred)} segmentation point(s) at {thr:g}{more}", fontsize=9, loc="left")
        ax.set_ylabel("cos sim")
        ax.grid(alpha=0.3)
    axes[-1].set_xlabel("caption pair j (frame j vs frame j+1); grey bands: true phase changes")
    fig.suptitle(f"{task_label(task)}: {episode_id} — {model}", fontsize=11)
    return fig
