"""The inputs of a score: run.json, exactly the run's transcripts, and the ground truth of their episodes."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

from vlmproprio.conditions import CONTROLS, PAPER_CONDITIONS
from vlmproprio.episodes import Episode, load_episodes
from vlmproprio.run_folder import ScoreRunError, read_run_manifest, resolve_fixtures, run_transcript_files
from vlmproprio.segmentation import caption_present
from vlmproprio.transcripts import Transcript, read_transcript_document

DEFAULT_GROUP_SIZE = 5


def condition_order(conditions: Sequence[str]) -> list[str]:
    known = [*PAPER_CONDITIONS, *CONTROLS]
    return sorted(set(conditions), key=lambda c: (known.index(c) if c in known else len(known), c))


def frame_texts(t: Transcript, n_frames: int, where: str) -> tuple[list[str], list[str]]:
    """Texts and statuses aligned with frame indices 0..n-1; absent frames are 'missing'."""
    texts = [""] * n_frames
    statuses = ["missing"] * n_frames
    for f in t.frames:
        if not 0 <= f.frame_index < n_frames:
            raise ScoreRunError(f"{where}: frame_index {f.frame_index} outside the episode's {n_frames} frames")
        texts[f.frame_index] = f.text or ""
        statuses[f.frame_index] = f.status if caption_present(f.text, f.status) else "missing"
    return texts, statuses


def frame_group_size(manifest: dict) -> int:
    """The pipeline's frame-group size k from run.json (every model of a run must agree; default 5)."""
    sizes = {
        m.get("pipeline", {}).get("k")
        for m in manifest.get("models", [])
        if isinstance(m, dict) and isinstance(m.get("pipeline"), dict)
    }
    sizes.discard(None)
    if len(sizes) > 1:
        raise ScoreRunError(f"run.json: models use different frame-group sizes {sorted(sizes)}; score them apart")
    return int(next(iter(sizes))) if sizes else DEFAULT_GROUP_SIZE


@dataclass
class RunInputs:
    """A run to score: its folder and manifest, its transcripts (and their files, for the stamp), the fixtures and
    the episodes the transcripts are about, in the run's order."""

    run_dir: Path
    manifest: dict
    transcript_files: list[Path]
    transcripts: list[Transcript]
    fixtures: Path
    episodes: dict[str, Episode]
    episode_order: dict[str, int]  # episode id -> its place in run.json (others after, by id)
    conditions: list[str]  # the transcripts' conditions, in condition_order
    # the JSON objects the transcripts were read from, one per file: the stamp digests exactly what was scored
    transcript_documents: list[dict] = field(default_factory=list)

    @property
    def episode_ids(self) -> list[str]:
        return sorted({t.episode_id for t in self.transcripts})

    @property
    def models(self) -> list[str]:
        return sorted({t.model for t in self.transcripts})


def load_run_inputs(run_dir: Path, fixtures: str | Path | None, verify: bool) -> RunInputs:
    """Read run.json and the run's transcripts, and load (by default: verify) their episodes."""
    if not run_dir.is_dir():
        raise ScoreRunError(f"{run_dir}: run directory not found")
    manifest = read_run_manifest(run_dir)
    transcript_files = run_transcript_files(run_dir, manifest)
    read = [read_transcript_document(p) for p in transcript_files]
    transcripts = [t for t, _ in read]
    if not transcripts:
        raise ScoreRunError(
            f"{run_dir / 'transcripts'}: no transcripts (run `vlmproprio run --model NAME --out {run_dir}` first)"
        )
    root = resolve_fixtures(run_dir, manifest, fixtures)
    ids = sorted({t.episode_id for t in transcripts})
    episodes: dict[str, Episode] = {e.episode_id: e for e in load_episodes(root, ids, verify=verify)}
    run_order = [e for e in manifest.get("episodes", []) if isinstance(e, str)]
    episode_order = {e: i for i, e in enumerate([*run_order, *[i for i in ids if i not in run_order]])}
    conds = condition_order([t.condition for t in transcripts])
    documents = [d for _, d in read]
    return RunInputs(run_dir, manifest, transcript_files, transcripts, root, episodes, episode_order, conds, documents)
