"""The inputs of a score: run.json, exactly the run's transcripts, and the ground truth of their episodes."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

from vlmproprio.conditions import CONTROLS, PAPER_CONDITIONS
from vlmproprio.episodes import Episode, load_episodes
from vlmproprio.errors import VlmproprioError
from vlmproprio.io import load_json
from vlmproprio.segmentation import caption_present
from vlmproprio.transcripts import Transcript, read_transcript_document

DEFAULT_GROUP_SIZE = 5


class ScoreRunError(VlmproprioError):
    """A run directory that cannot be scored; the message names the file and what to do."""


def read_run_manifest(run_dir: Path) -> dict:
    path = run_dir / "run.json"
    if not path.is_file():
        return {}
    data = load_json(path, error=ScoreRunError)
    if not isinstance(data, dict):
        raise ScoreRunError(f"{path}: run manifest must be a JSON object")
    return data


def resolve_fixtures(run_dir: Path, manifest: dict, fixtures: str | Path | None) -> Path:
    if fixtures is not None:
        root = Path(fixtures)
    elif manifest.get("fixtures"):
        root = Path(manifest["fixtures"])
        if not root.is_absolute() and not root.is_dir() and (run_dir / root).is_dir():
            root = run_dir / root
    else:
        raise ScoreRunError(f"{run_dir / 'run.json'}: no 'fixtures' entry; pass the fixture folder (--fixtures)")
    if not root.is_dir():
        raise ScoreRunError(f"fixture folder {root} not found (from {run_dir / 'run.json'}); pass --fixtures")
    return root


def run_transcript_files(run_dir: Path, manifest: dict) -> list[Path]:
    """Exactly the transcripts of the configuration recorded in run.json; a one-line error when some are
    missing (an unfinished run) or when others lie there (left by an older run). Without run.json, or with one
    that lists no models: every transcript in the folder."""
    from vlmproprio.runner import recorded_transcripts

    root = run_dir / "transcripts"
    on_disk = sorted(root.glob("*/*.json"))
    expected = recorded_transcripts(run_dir, manifest)
    if expected is None:
        return on_disk
    missing = [p for p in expected if not p.is_file()]
    if missing:
        raise ScoreRunError(
            f"{run_dir}: the run recorded in run.json is not finished ({len(missing)} of {len(expected)} "
            f"transcripts missing, e.g. {missing[0].relative_to(run_dir)}); finish it by running the same "
            "`vlmproprio run --model MODEL --out RUN_DIR` command again (answers already made are cached)"
        )
    extra = sorted(set(on_disk) - set(expected))
    if extra:
        raise ScoreRunError(
            f"{extra[0]}: not part of the run recorded in {run_dir / 'run.json'} ({len(extra)} such transcript(s), "
            "left by another run); move them out of the run folder, or run into a new --out"
        )
    return expected


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
