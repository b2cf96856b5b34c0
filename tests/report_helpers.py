"""A small scored synthetic run for the report tests, with captions that test escaping and highlighting.

Captions come from the template writer in scoring_helpers (no model); a few are then edited on purpose:
markup in a final and a frame caption, a negated expected action, a recovered scene and a missing frame.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest

from scoring_helpers import fake_spec, prefill_embeddings, write_synthetic_run
from vlmproprio.locations import transcript_filename
from vlmproprio.transcripts import FrameCaption, SceneCaption, read_transcript, write_transcript

CONDS = ("none", "ee", "both", "both_shuffled")
# would change the page's title if a browser ran it
EVIL = '<script>document.title="pwned"</script><img src=x onerror="document.title=1">'
NEGATED_FINAL = "The robot does not open the door. "


def edit_transcript(run: Path, model: str, episode_id: str, condition: str, **changes) -> None:
    path = run / "transcripts" / model / transcript_filename(episode_id, condition)
    t = read_transcript(path)
    for k, v in changes.items():
        setattr(t, k, v)
    write_transcript(run, t)


def make_run(base: Path, model: str = "synthetic", score: bool = True) -> tuple[Path, Path, list[str]]:
    """3 Door and 4 bin episodes of 14 frames under CONDS; scored with fake embeddings unless score=False."""
    run, fx = base / "run", base / "fixtures"
    ids = write_synthetic_run(
        run, fx, model=model, n_door=3, n_per_bin=1, n_frames=14, conditions=CONDS, missing={("door_00", "both"): [3]}
    )
    t = read_transcript(run / "transcripts" / model / transcript_filename("door_00", "none"))
    frames = list(t.frames)
    frames[2] = FrameCaption(2, frames[2].step, f"The arm waits {EVIL}", "recovered")
    scenes = list(t.scenes)
    scenes[1] = SceneCaption(1, scenes[1].frame_indices, scenes[1].text, "recovered")
    edit_transcript(run, model, "door_00", "none", frames=frames, scenes=scenes)
    edit_transcript(run, model, "door_01", "ee", final=NEGATED_FINAL + EVIL)
    if score:
        score_synthetic(run)
    return run, fx, ids


def score_synthetic(run: Path) -> None:
    from vlmproprio.evaluation import score_run

    prefill_embeddings(run, fake_spec().key)
    score_run(run, encoder=fake_spec())


def add_model(run: Path, source: str, model: str, final_of: dict[str, str]) -> None:
    """Copy model ``source``'s transcripts as ``model``, with the final captions of some conditions replaced
    by those of another condition (e.g. {'both': 'none'}: 'both' gets the no-state final)."""
    for p in sorted((run / "transcripts" / source).glob("*.json")):
        t = read_transcript(p)
        t.model = model
        if t.condition in final_of:
            other = read_transcript(p.with_name(transcript_filename(t.episode_id, final_of[t.condition])))
            t.final = other.final
        write_transcript(run, t)
    manifest = json.loads((run / "run.json").read_text())
    manifest["models"] = [*manifest["models"], {"name": model, "slug": model, "pipeline": {"prompt_version": "test"}}]
    (run / "run.json").write_text(json.dumps(manifest, indent=1) + "\n")


def shared_report(tmp_path_factory: pytest.TempPathFactory) -> tuple[tuple[Path, Path, list[str]], Path]:
    """make_run's run with its report written, and the report's index.html: built once per test session, as
    tests/report/test_report.py and tests/report/test_browser.py both only read it (a test that changes a run copies it first).
    Under xdist (``--dist loadscope``) the two modules may run on different workers: the first builds it in the
    folder the workers share, holding a lock; the other waits for the lock and reuses it."""
    from vlmproprio.io import text_computed_once
    from vlmproprio.report import write_report

    def build() -> str:
        run, fx, ids = make_run(root / "shared-report")
        write_report(run)
        return json.dumps([str(run), str(fx), ids])

    root = tmp_path_factory.getbasetemp()
    if os.environ.get("PYTEST_XDIST_WORKER"):
        root = root.parent  # the session's folder, above each worker's own
    run, fx, ids = json.loads(text_computed_once(root / "shared-report.lock", root / "shared-report.json", build))
    return (Path(run), Path(fx), ids), Path(run) / "report" / "index.html"
