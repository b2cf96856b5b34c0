"""`write_report`: the score tables of a run -> RUN_DIR/report/ (report.md, PNG plots, index.html, thumbnails)."""

from __future__ import annotations

import re
from collections.abc import Sequence
from pathlib import Path

from vlmproprio.episodes import Episode
from vlmproprio.io import atomic_write_text, make_dirs
from vlmproprio.report.data import ReportError, RunScores, load_run_scores, paper_figure, task_label
from vlmproprio.report.page import (
    FRAMES_DIR,
    LEGEND,
    PageContext,
    episode_view,
    metadata_blocks,
    render_page,
    run_facts,
    write_thumbnail,
)
from vlmproprio.report.plots import Plot, save_figure, success_rates_figure, sweep_figure, trace_figure
from vlmproprio.report.power_section import power_cache, power_outputs
from vlmproprio.report.tables import (
    combined_table,
    headline_table,
    markdown_report,
    report_tables,
    verdict_table,
)
from vlmproprio.transcripts import Transcript, read_transcripts

REPORT_DIR = "report"
INDEX = "index.html"
MARKDOWN = "report.md"
# files this module writes into the report folder; anything else there is left alone
OWNED = re.compile(r"^(fig5_success|fig6_points|f1_threshold|fig7_trace|fig8_trace)[^/]*\.png$")


# C0 controls other than tab, newline and carriage return (NUL above all) are not allowed in HTML text; a
# model's answer can hold them. HTML parsers turn NUL into U+FFFD anyway: do it here, so the file is valid.
_HTML_CONTROLS = re.compile(r"[\x00-\x08\x0b\x0c\x0e-\x1f\x7f]")


def html_text(page: str) -> str:
    return _HTML_CONTROLS.sub("\ufffd", page)


def _safe(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9._-]+", "_", name)


def _descriptions(conditions: Sequence[str]) -> dict[str, str]:
    from vlmproprio.conditions import CONDITIONS

    return {c: CONDITIONS[c].description if c in CONDITIONS else "" for c in conditions}


def trace_conditions(s: RunScores, requested: Sequence[str] | None = None) -> list[str]:
    """The conditions of Figs. 7-8: as requested, else one without state ('none') and one with ('both'),
    as in the paper, falling back to the first condition of each kind the run has."""
    from vlmproprio.conditions import CONDITIONS

    if requested:
        unknown = [c for c in requested if c not in s.conditions]
        if unknown:
            raise ReportError(f"trace condition(s) {', '.join(unknown)} not in this run ({', '.join(s.conditions)})")
        return list(requested)

    def pick(preferred: str, want_state: bool) -> str | None:
        if preferred in s.conditions:
            return preferred
        return next(
            (
                c
                for c in s.conditions
                if c in CONDITIONS and CONDITIONS[c].has_state == want_state and not CONDITIONS[c].control
            ),
            None,
        )

    return [c for c in (pick("none", False), pick("both", True)) if c] or s.conditions[:2]


def example_episodes(s: RunScores, requested: Sequence[str] | None = None) -> list[str]:
    """The episodes of Figs. 7-8: as requested, else the first episode of each task in run order."""
    if requested:
        unknown = [e for e in requested if e not in s.episodes]
        if unknown:
            raise ReportError(f"example episode(s) {', '.join(unknown)} not in this run")
        return list(requested)
    out = []
    for task in s.tasks():
        first = next((e for e in s.episodes if s.task_of(e) == task), None)
        if first:
            out.append(first)
    return out


def _frame_texts(t: Transcript) -> list[str]:
    """Frame caption texts by frame index (a frame absent from the transcript is an empty text)."""
    texts = [""] * (max((f.frame_index for f in t.frames), default=-1) + 1)
    for f in t.frames:
        if f.frame_index >= 0:
            texts[f.frame_index] = f.text
    return texts


def write_plots(
    s: RunScores,
    out: Path,
    transcripts: dict[tuple[str, str, str], Transcript],
    examples: Sequence[str] | None = None,
    conditions: Sequence[str] | None = None,
) -> list[Plot]:
    thr = s.threshold
    plots: list[Plot] = []
    trace_conds = trace_conditions(s, conditions)
    for model in s.models:
        m = _safe(model)
        f = f"fig5_success__{m}.png"
        save_figure(success_rates_figure(s, model), out / f)
        plots.append(
            Plot(
                model,
                "fig5",
                f,
                f"Fig. 5 — caption success rates ({model})",
                "Share of final captions that mention (light) and correctly state (solid) the target object, "
                "the action and the trajectory, per condition and task.",
            )
        )
        f = f"fig6_points__{m}.png"
        fig = sweep_figure(
            s, model, "points", "segmentation points (mean per episode)", f"Segmentation points vs threshold — {model}"
        )
        save_figure(fig, out / f)
        plots.append(
            Plot(
                model,
                "fig6",
                f,
                f"Fig. 6 — segmentation points vs threshold ({model})",
                "Mean number of segmentation points per episode (consecutive frame captions whose cosine "
                f"similarity is below the threshold); dotted line: the default threshold {thr:g}.",
            )
        )
        f = f"f1_threshold__{m}.png"
        fig = sweep_figure(
            s,
            model,
            "f1_tol1",
            "boundary F1 (±1 frame)",
            f"Boundary F1 vs threshold — {model} (★ in-sample best: optimistic upper bound)",
            mark_best=True,
        )
        save_figure(fig, out / f)
        plots.append(
            Plot(
                model,
                "f1",
                f,
                f"Boundary F1 vs threshold ({model})",
                "Mean boundary F1 of the segmentation points against the true phase changes, with a tolerance "
                "of ±1 frame, per condition and task. ★: the threshold with the best mean F1, chosen on the same "
                "episodes it is shown on — an optimistic upper bound, not a score; the tables report the paper's "
                "fixed threshold and a leave-one-episode-out threshold instead.",
            )
        )
        for eid in example_episodes(s, examples):
            task = s.task_of(eid)
            num = paper_figure(task)  # the paper's figure for its two tasks; any other task's is unnumbered
            captions = {c: _frame_texts(t) for c in trace_conds if (t := transcripts.get((model, eid, c)))}
            f = f"fig{num if num else ''}_trace_{_safe(eid)}__{m}.png"
            save_figure(trace_figure(s, model, eid, trace_conds, captions), out / f)
            plots.append(
                Plot(
                    model,
                    "trace",
                    f,
                    f"{f'Fig. {num} — s' if num else 'S'}egmentation of {eid} ({task_label(task)}, {model})",
                    f"Cosine similarity of consecutive frame captions under {' and '.join(trace_conds)}; dashed: "
                    f"the threshold {thr:g}; red points: segmentation points, each labelled with the caption that "
                    "starts there; grey bands: true phase changes.",
                )
            )
    return plots


def _load_episodes(s: RunScores, fixtures: str | Path | None, notices: list[str]) -> dict[str, Episode]:
    from vlmproprio.episodes import load_episodes
    from vlmproprio.run_folder import ScoreRunError, resolve_fixtures

    try:
        root = resolve_fixtures(s.run_dir, s.manifest, fixtures)
    except ScoreRunError as exc:
        if fixtures is not None:
            raise ReportError(str(exc)) from exc
        notices.append(f"Frames are not shown: {exc}.")
        return {}
    return {e.episode_id: e for e in load_episodes(root, s.episodes)}


def require_report_packages() -> None:
    """matplotlib and jinja2 come with the [report] extra; say so instead of failing deep inside."""
    import importlib.util

    missing = [m for m in ("matplotlib", "jinja2") if importlib.util.find_spec(m) is None]
    if missing:
        raise ReportError(f"writing a report needs {' and '.join(missing)}: pip install 'vlmproprio[report]'")


def _episode_order(s: RunScores) -> list[str]:
    """Door before bins (the paper's order), run order inside a task."""
    tasks = s.tasks()
    return sorted(s.episodes, key=lambda e: tasks.index(s.task_of(e)) if s.task_of(e) in tasks else len(tasks))


def _remove_stale(out: Path, keep: set[str]) -> None:
    for p in out.glob("*.png"):
        if OWNED.match(p.name) and p.name not in keep:
            p.unlink()
    frames = out / FRAMES_DIR
    if frames.is_dir():
        for p in frames.glob("*.jpg"):
            if f"{FRAMES_DIR}/{p.name}" not in keep:
                p.unlink()


def write_report(
    run_dir: str | Path,
    fixtures: str | Path | None = None,
    *,
    out: str | Path | None = None,
    examples: Sequence[str] | None = None,
    trace_conditions: Sequence[str] | None = None,
    cache_dir: str | Path | None = None,
) -> Path:
    """Write the report of a scored run into ``out`` (default RUN_DIR/report/); returns the HTML page's path.

    The run must be scored (RUN_DIR/scores/, `vlmproprio score RUN_DIR`). Frames come from the fixture folder
    (``fixtures``, default the one named in run.json); without it the page says so and shows no frames.
    ``cache_dir``: the cache root whose ``power/`` keeps power analyses (default: vlmproprio.locations)."""
    require_report_packages()
    s = load_run_scores(run_dir, fixtures)  # scores computed from the ground truth in these fixtures
    out = Path(out) if out is not None else Path(run_dir) / REPORT_DIR
    root = fixtures if fixtures is not None else s.manifest.get("fixtures")
    if root and Path(root).is_dir():
        from vlmproprio.locations import refuse_nesting

        refuse_nesting(Path(root), {"--out": out})
    make_dirs(out)
    notices: list[str] = []
    if s.manifest.get("status") not in (None, "complete"):
        notices.append(f"The run is not complete (status {s.manifest.get('status')!r}): numbers cover what was done.")
    episodes = _load_episodes(s, fixtures, notices)
    transcripts = {(t.model, t.episode_id, t.condition): t for t in read_transcripts(Path(run_dir))}
    if not transcripts:
        notices.append("No transcripts found: frame captions are not shown.")

    plots = write_plots(s, out, transcripts, examples, trace_conditions)
    tables = report_tables(s)
    if s.rows:
        power_plot, power_tab = power_outputs(s, out, power_cache(cache_dir, root))
        plots.append(power_plot)
        tables.append(power_tab)
    atomic_write_text(out / MARKDOWN, markdown_report(s, tables, [(p.file, p.title) for p in plots]))

    keep = {p.file for p in plots}
    descriptions = _descriptions(s.conditions)
    views: dict[str, list] = {}
    for model in s.models:
        views[model] = []
        for eid in _episode_order(s):
            if not any(r["model"] == model and r["episode_id"] == eid for r in s.rows):
                continue
            ep = episodes.get(eid)
            thumbs = {}
            if ep is not None:
                for fr in ep.frames:
                    thumbs[fr.index] = f"{FRAMES_DIR}/{write_thumbnail(fr.image_path, out / FRAMES_DIR)}"
                keep.update(thumbs.values())
            views[model].append(episode_view(s, model, eid, transcripts, ep, thumbs, descriptions))
    first = next((v for vs in views.values() for v in vs), None)
    if first is not None:
        first.open = first.eager = True

    findings = headline_table(s)
    ctx = PageContext(
        title=f"vlmproprio report — {s.run_dir.name}",
        run_name=s.run_dir.name,
        facts=run_facts(s),
        notices=notices,
        findings=findings if findings.rows else None,
        plots=plots,
        tables=tables,
        episodes=views,
        condition_help=list(descriptions.items()),
        metadata=metadata_blocks(s),
        markdown=MARKDOWN,
        legend=LEGEND,
        warnings=[f"{w['model']}: {w['message']}" for w in s.verdicts.get("warnings", [])],
        combined=combined_table(s) if s.verdicts.get("combined") else None,
        verdicts=verdict_table(s) if s.verdicts.get("verdicts") else None,
    )
    index = out / INDEX
    atomic_write_text(index, html_text(render_page(ctx)))
    _remove_stale(out, keep)
    return index
