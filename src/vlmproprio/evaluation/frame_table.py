"""A flat per-frame table of a scored run, for pandas, R or a spreadsheet: RUN_DIR/scores/frames.csv.

One row per (model, episode, condition, frame): the frame's true phase, its caption and parse status, the
similarity of its caption to the next frame's (the segmentation trace), whether a boundary is predicted there at
the run's threshold and whether there truly is one, and the rubric verdicts of the scene caption covering the
frame and of the episode's final caption (``correct``, ``wrong``, ``mentioned`` or ``none`` per item).
Columns are listed in ``COLUMNS``; the schema is documented in docs/results.md. ``score_run`` writes it into
the generation of scores it stamps, so every caller of score_run gets it.
"""

from __future__ import annotations

import csv
import io
from collections.abc import Iterable

from vlmproprio.evaluation.tables import ScoreTables
from vlmproprio.scoring import ITEMS
from vlmproprio.transcripts import Transcript, cell_key

FRAMES_CSV = "frames.csv"
COLUMNS: tuple[str, ...] = (
    "model",
    "episode_id",
    "condition",
    "frame",
    "step",
    "phase",
    "caption",
    "caption_status",
    "similarity_next",
    "boundary_predicted",
    "boundary_true",
    "scene_group",
    *(f"scene_{item}" for item in ITEMS),
    *(f"final_{item}" for item in ITEMS),
    "final_all_correct",
)


def verdict(items: dict, item: str) -> str:
    """One word for a rubric item: correct, wrong, mentioned (named, neither right nor wrong) or none."""
    v = items.get(item) or {}
    if v.get("correct"):
        return "correct"
    if v.get("wrong"):
        return "wrong"
    return "mentioned" if v.get("mentioned") else "none"


def frame_rows(tables: ScoreTables, transcripts: Iterable[Transcript]) -> list[dict]:
    """The rows of the table, in the order of the score rows (model, episode, condition) then frame;
    ``transcripts``: the run's, as scored."""
    transcripts = {(t.model, t.episode_id, t.condition): t for t in transcripts}
    out: list[dict] = []
    for row in tables.rows:
        key = (row["model"], row["episode_id"], row["condition"])
        name = cell_key(*key)
        t, trace, audit = transcripts.get(key), tables.traces.get(name), tables.audit.get(name)
        if t is None or trace is None or audit is None:
            continue
        captions = {f.frame_index: f for f in t.frames}
        group_of = {i: s for s in audit["scenes"] for i in s["frame_indices"]}
        predicted, true = set(trace["predicted_boundaries"]), set(trace["true_boundaries"])
        final_items = audit["final"]["items"]
        for j, phase in enumerate(trace["true_phases"]):
            f = captions.get(j)
            scene = group_of.get(j)
            sim = trace["trace"][j] if j < len(trace["trace"]) else None
            out.append(
                {
                    "model": key[0],
                    "episode_id": key[1],
                    "condition": key[2],
                    "frame": j,
                    "step": f.step if f else "",
                    "phase": phase,
                    "caption": f.text if f else "",
                    "caption_status": trace["frame_status"][j],
                    "similarity_next": "" if sim is None else repr(float(sim)),
                    "boundary_predicted": int(j in predicted),
                    "boundary_true": int(j in true),
                    "scene_group": scene["group"] if scene else "",
                    **{f"scene_{i}": verdict(scene["items"], i) if scene else "none" for i in ITEMS},
                    **{f"final_{i}": verdict(final_items, i) for i in ITEMS},
                    "final_all_correct": int(bool(final_items.get("all_correct"))),
                }
            )
    return out


def frame_table_text(tables: ScoreTables, transcripts: Iterable[Transcript]) -> str:
    """The text of scores/frames.csv."""
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=COLUMNS, lineterminator="\n")
    w.writeheader()
    w.writerows(frame_rows(tables, transcripts))
    return buf.getvalue()
