"""The HTML page of a report: a jinja2 template (page.html, autoescaped) filled from the score tables.

Every text that came from a model or a file is escaped by the template engine; highlighted rubric spans
are passed as (text, style, tooltip) pieces, never as pre-built markup. Frames are shown as small JPEG
thumbnails written next to the page (``frames/<sha256 of the PNG>.jpg``), so the folder can be copied
anywhere; only the episode opened first loads its images eagerly, the rest load when opened.
"""

from __future__ import annotations

import hashlib
import io
import json
from collections.abc import Sequence
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path

from vlmproprio.episodes import Episode
from vlmproprio.io import atomic_write_bytes
from vlmproprio.report.data import RunScores, task_label
from vlmproprio.report.plots import Plot
from vlmproprio.report.tables import Table, fmt_value
from vlmproprio.scoring import ITEMS
from vlmproprio.transcripts import FrameCaption, Transcript, cell_key

# atomic writes create private (0600) files; a report is meant to be shared (CI artifact, web server)
THUMB_PX = 128
THUMB_QUALITY = 80
FRAMES_DIR = "frames"
ITEM_SYMBOL = {"correct": "✓", "wrong": "✗", "mentioned": "~", "absent": "–"}
VERDICTS = ("correct", "wrong", "mentioned", "ignored")


# ---------------------------------------------------------------------------------------------- views


@dataclass(frozen=True)
class Span:
    """A piece of caption text; ``style`` is empty for plain text, else CSS classes of a rubric match."""

    text: str
    style: str = ""
    tooltip: str = ""


@dataclass(frozen=True)
class CaptionView:
    spans: tuple[Span, ...]
    status: str  # ok | recovered | missing | absent (not in the transcript)


@dataclass(frozen=True)
class ItemBadge:
    item: str
    state: str  # correct | wrong | mentioned | absent
    symbol: str


@dataclass(frozen=True)
class Spark:
    """An inline SVG sparkline of a similarity trace (coordinates in a 0..W x 0..H box)."""

    width: int
    height: int
    lines: tuple[str, ...]  # polyline point lists; a gap (missing caption) starts a new line
    threshold_y: float
    points: tuple[tuple[float, float], ...]  # predicted boundaries
    truth_x: tuple[float, ...]


@dataclass
class ConditionView:
    name: str
    description: str
    final: CaptionView
    badges: list[ItemBadge]
    metrics: list[tuple[str, str]]
    spark: Spark | None


@dataclass(frozen=True)
class FrameCell:
    caption: CaptionView
    boundary: bool  # a predicted segmentation point between the previous frame and this one
    sim: str  # similarity with the previous frame's caption


@dataclass
class FrameRow:
    index: int
    step: int | None
    thumb: str | None
    phase: str
    direction: str
    new_phase: bool
    cells: list[FrameCell]


@dataclass
class SceneRow:
    group: int
    frames: str
    cells: list[CaptionView]


@dataclass
class EpisodeView:
    model: str
    episode_id: str
    task: str
    anchor: str
    instruction: str
    expectation: str
    conditions: list[ConditionView]
    frames: list[FrameRow]
    scenes: list[SceneRow]
    open: bool = False
    eager: bool = False


@dataclass
class PageContext:
    title: str
    run_name: str
    facts: list[tuple[str, str]]
    notices: list[str]
    findings: Table | None
    plots: list[Plot]
    tables: list[Table]
    episodes: dict[str, list[EpisodeView]]
    condition_help: list[tuple[str, str]]
    metadata: list[tuple[str, str]]
    markdown: str = "report.md"
    legend: list[tuple[str, str, str]] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)  # sanity warnings, shown first
    combined: Table | None = None  # one row per model and combined claim, shown first
    verdicts: Table | None = None  # one row per model and primary hypothesis


# ---------------------------------------------------------------------------------------------- captions


def _tooltip(m: dict) -> str:
    neg = ", negated" if m.get("negated") else ""
    note = f" ({m['note']})" if m.get("note") else ""
    return f"{m.get('entry', '?')} → {m.get('item')} {m.get('verdict')}{neg}{note}"


def highlight(text: str, matches: Sequence[dict]) -> tuple[Span, ...]:
    """Split a caption into plain and matched pieces. Matches whose offsets do not fit the text are dropped
    (an audit from other text), and a match overlapping an earlier one is left out (the earlier one wins)."""
    good = [
        m
        for m in matches
        if isinstance(m.get("start"), int)
        and isinstance(m.get("end"), int)
        and 0 <= m["start"] < m["end"] <= len(text)
        and text[m["start"] : m["end"]] == m.get("text", text[m["start"] : m["end"]])
    ]
    good.sort(key=lambda m: (m["start"], -m["end"]))
    spans: list[Span] = []
    pos = 0
    for m in good:
        if m["start"] < pos:
            continue
        if m["start"] > pos:
            spans.append(Span(text[pos : m["start"]]))
        verdict = m.get("verdict") if m.get("verdict") in VERDICTS else "mentioned"
        style = f"hit v-{verdict}" + (" negated" if m.get("negated") else "")
        spans.append(Span(text[m["start"] : m["end"]], style, _tooltip(m)))
        pos = m["end"]
    if pos < len(text):
        spans.append(Span(text[pos:]))
    return tuple(spans)


def caption_view(text: str | None, status: str, matches: Sequence[dict] = ()) -> CaptionView:
    if text is None:
        return CaptionView((), "absent")
    return CaptionView(highlight(text, matches), status)


def _badges(items: dict) -> list[ItemBadge]:
    out = []
    for item in ITEMS:
        it = items.get(item, {}) if isinstance(items, dict) else {}
        state = (
            "correct"
            if it.get("correct")
            else "wrong"
            if it.get("wrong")
            else "mentioned"
            if it.get("mentioned")
            else "absent"
        )
        out.append(ItemBadge(item, state, ITEM_SYMBOL[state]))
    return out


def expectation_text(exp: dict) -> str:
    parts = [f"object: {exp.get('target_object', '?')}"]
    if exp.get("target_row") or exp.get("target_side"):
        parts.append(f"compartment: {exp.get('target_row') or '?'} {exp.get('target_side') or '?'}")
    for mo in exp.get("motions", []):
        parts.append(f"{mo.get('name')}: {', '.join(mo.get('expected', [])) or '(none expected)'}")
    return " · ".join(parts)


def spark(trace: dict, threshold: float, width: int = 180, height: int = 34) -> Spark | None:
    ys = trace.get("trace") or []
    if not ys:
        return None
    low = min([0.0, *(v for v in ys if v is not None)])
    span = 1.0 - low or 1.0
    step = width / max(1, len(ys) - 1)

    def y(v: float) -> float:
        return round(height - 2 - (v - low) / span * (height - 4), 1)

    lines, cur = [], []
    for j, v in enumerate(ys):
        if v is None:
            if cur:
                lines.append(" ".join(cur))
            cur = []
            continue
        cur.append(f"{round(j * step, 1)},{y(v)}")
    if cur:
        lines.append(" ".join(cur))
    pts = tuple(
        (round(j * step, 1), y(ys[j]))
        for j in trace.get("predicted_boundaries", [])
        if 0 <= j < len(ys) and ys[j] is not None
    )
    truth = tuple(round(j * step, 1) for j in trace.get("true_boundaries", []))
    return Spark(width, height, tuple(lines), y(threshold), pts, truth)


# ---------------------------------------------------------------------------------------------- frames


def write_thumbnail(src: Path, out_dir: Path, size: int = THUMB_PX) -> str:
    """A JPEG thumbnail named by the sha256 of the source file (kept if already there); returns its name."""
    from PIL import Image

    from vlmproprio.episodes.pixels import decode_png_bytes, read_image_file

    data = read_image_file(src)
    name = f"{hashlib.sha256(data).hexdigest()[:24]}.jpg"
    dest = out_dir / name
    if not dest.is_file():
        # decoded with the pixel check's limits (a decompression bomb is one line naming the file)
        with Image.fromarray(decode_png_bytes(src, data), "RGB") as im:
            im.thumbnail((size, size))
            buf = io.BytesIO()
            im.save(buf, format="JPEG", quality=THUMB_QUALITY, optimize=True)
        atomic_write_bytes(dest, buf.getvalue())
    return name


# ---------------------------------------------------------------------------------------------- episodes


def _row_metrics(row: dict | None, threshold: float) -> list[tuple[str, str]]:
    if not row:
        return []
    return [
        ("words", fmt_value("final_words", row.get("final_words"))),
        ("hits/word", fmt_value("final_hits_per_word", row.get("final_hits_per_word"))),
        (f"points @{threshold:g}", str(row.get("seg_points", "–"))),
        ("F1 ±1", fmt_value("seg_f1_tol1", row.get("seg_f1_tol1"))),
    ]


@dataclass
class _EpisodeCells:
    """What the scores hold on one episode of one model, per condition it was run under."""

    rows: dict[str, dict]
    conds: list[str]
    audits: dict[str, dict]
    traces: dict[str, dict]


def _episode_cells(s: RunScores, model: str, episode_id: str) -> _EpisodeCells:
    rows = {r["condition"]: r for r in s.rows if r["model"] == model and r["episode_id"] == episode_id}
    conds = [c for c in s.conditions if c in rows]
    keyed = {c: cell_key(model, episode_id, c) for c in conds}
    audits = {c: s.audit.get(keyed[c], {}) for c in conds}
    traces = {c: s.traces.get(keyed[c], {}) for c in conds}
    return _EpisodeCells(rows, conds, audits, traces)


def _condition_views(cells: _EpisodeCells, descriptions: dict[str, str], thr: float) -> list[ConditionView]:
    cviews = []
    for c in cells.conds:
        fin = cells.audits[c].get("final", {})
        cviews.append(
            ConditionView(
                name=c,
                description=descriptions.get(c, ""),
                final=caption_view(fin.get("text"), fin.get("status", "absent"), fin.get("matches", [])),
                badges=_badges(fin.get("items", {})),
                metrics=_row_metrics(cells.rows.get(c), thr),
                spark=spark(cells.traces[c], thr) if cells.traces[c] else None,
            )
        )
    return cviews


def _frame_cell(f: FrameCaption | None, tr: dict, i: int) -> FrameCell:
    """Frame i of one condition: its caption (status as scored), whether a boundary precedes it, and the
    similarity to the frame before."""
    status = (tr.get("frame_status") or [])[i] if i < len(tr.get("frame_status") or []) else None
    cap = caption_view(f.text, f.status if status is None else status) if f else caption_view(None, "absent")
    sims = tr.get("trace") or []
    sim = sims[i - 1] if 0 < i <= len(sims) else None
    return FrameCell(cap, (i - 1) in tr.get("predicted_boundaries", []), "" if sim is None else f"{sim:.2f}")


def _frame_rows(
    cells: _EpisodeCells, captions: dict[str, dict[int, FrameCaption]], episode: Episode | None, thumbs: dict[int, str]
) -> list[FrameRow]:
    """One row per frame; ``captions[condition]`` maps frame index to the transcript's frame caption."""
    # frames: ground truth from the episode when the fixtures are at hand, else from the trace
    conds, traces = cells.conds, cells.traces
    any_trace = next((traces[c] for c in conds if traces[c]), {})
    phases = list(episode.frame_phases) if episode else list(any_trace.get("true_phases", []))
    n_frames = len(phases) or max((len(traces[c].get("trace", [])) + 1 for c in conds), default=0)
    frame_rows = []
    for i in range(n_frames):
        fr = episode.frames[i] if episode and i < len(episode.frames) else None
        frame_rows.append(
            FrameRow(
                index=i,
                step=fr.step if fr else None,
                thumb=thumbs.get(i),
                phase=phases[i] if i < len(phases) else "",
                direction=fr.direction if fr else "",
                new_phase=0 < i < len(phases) and phases[i] != phases[i - 1],
                cells=[_frame_cell(captions[c].get(i), traces[c], i) for c in conds],
            )
        )
    return frame_rows


def _scene_rows(cells: _EpisodeCells) -> list[SceneRow]:
    groups: dict[int, dict] = {}
    for c in cells.conds:
        for sc in cells.audits[c].get("scenes", []):
            groups.setdefault(sc.get("group", 0), {})[c] = sc
    scene_rows = []
    for g in sorted(groups):
        any_sc = next(iter(groups[g].values()))
        idx = any_sc.get("frame_indices") or []
        scene_rows.append(
            SceneRow(
                group=g,
                frames=f"{idx[0]}–{idx[-1]}" if idx else "?",
                cells=[
                    caption_view(sc.get("text"), sc.get("status", "absent"), sc.get("matches", []))
                    if (sc := groups[g].get(c))
                    else caption_view(None, "absent")
                    for c in cells.conds
                ],
            )
        )
    return scene_rows


def episode_view(
    s: RunScores,
    model: str,
    episode_id: str,
    transcripts: dict[tuple[str, str, str], Transcript],
    episode: Episode | None,
    thumbs: dict[int, str],
    descriptions: dict[str, str],
) -> EpisodeView:
    cells = _episode_cells(s, model, episode_id)
    task = next(iter(cells.rows.values()))["task"] if cells.rows else (episode.task if episode else "")
    captions = {}
    for c in cells.conds:
        t = transcripts.get((model, episode_id, c))
        captions[c] = {f.frame_index: f for f in t.frames} if t else {}
    exp = next((cells.audits[c].get("expectation") for c in cells.conds if cells.audits[c].get("expectation")), {})
    return EpisodeView(
        model=model,
        episode_id=episode_id,
        task=task,
        anchor=f"ep-{model}-{episode_id}",
        instruction=episode.instruction if episode else "",
        expectation=expectation_text(exp) if exp else "",
        conditions=_condition_views(cells, descriptions, s.threshold),
        frames=_frame_rows(cells, captions, episode, thumbs),
        scenes=_scene_rows(cells),
    )


# ---------------------------------------------------------------------------------------------- page


def _json_block(d) -> str:
    return json.dumps(d, indent=1, ensure_ascii=False, sort_keys=False)


def run_facts(s: RunScores) -> list[tuple[str, str]]:
    m = s.manifest
    enc = s.meta.get("encoder", {})
    facts = [
        ("run", str(s.run_dir.name)),
        ("models", ", ".join(s.models)),
        (
            "episodes",
            f"{len(s.episodes)} ("
            + ", ".join(f"{task_label(t)}: {sum(1 for e in s.episodes if s.task_of(e) == t)}" for t in s.tasks())
            + ")",
        ),
        ("conditions", ", ".join(s.conditions)),
        ("transcripts", str(len(s.rows))),
        ("mode", str(m.get("mode", "?"))),
        ("status", str(m.get("status", "?"))),
        ("prompt version", s.prompt_version or "?"),
        ("sentence encoder", f"{enc.get('name', '?')} ({enc.get('dim', '?')}-d)"),
        ("threshold", f"{s.threshold:g}"),
        ("code revision", str(m.get("git_revision") or "?")),
        ("updated", str(m.get("updated", "?"))),
    ]
    for model in s.models:
        ident = s.model_identity(model).get("identity")
        if ident:
            facts.append((f"model {model}", ", ".join(f"{k}={v}" for k, v in ident.items() if v not in ("", None))))
    return [(k, v) for k, v in facts if v not in ("?", "None", "")]


def metadata_blocks(s: RunScores) -> list[tuple[str, str]]:
    out = []
    if s.manifest:
        out.append(("run.json", _json_block(s.manifest)))
    out.append(("scores/meta.json", _json_block(s.meta)))
    return out


LEGEND = [
    ("hit v-correct", "correct", "matches the ground truth"),
    ("hit v-wrong", "wrong", "contradicts the ground truth"),
    ("hit v-mentioned", "mentioned", "a trajectory word not tied to a checked motion"),
    ("hit v-ignored", "ignored", "a neutral term, or a negated wrong one"),
    ("hit v-correct negated", "negated", "(dotted outline) the term is under a negation"),
]


def render_page(ctx: PageContext) -> str:
    import jinja2
    from markupsafe import Markup

    pkg = resources.files("vlmproprio.report")
    env = jinja2.Environment(autoescape=True, undefined=jinja2.StrictUndefined, trim_blocks=True, lstrip_blocks=True)
    template = env.from_string(pkg.joinpath("page.html").read_text(encoding="utf-8"))
    css = Markup(pkg.joinpath("style.css").read_text(encoding="utf-8"))  # package data, not user text
    return template.render(ctx=ctx, css=css)
