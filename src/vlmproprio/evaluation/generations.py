"""Write the score tables as one generation of RUN_DIR/scores/, stamped with what they were computed from, and
check that a generation still matches its run."""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path

from vlmproprio.errors import VlmproprioError
from vlmproprio.evaluation.definitions import SCORES_VERSION
from vlmproprio.evaluation.formats import dumps_csv, dumps_json
from vlmproprio.evaluation.inputs import ScoreRunError, read_run_manifest, run_transcript_files
from vlmproprio.evaluation.tables import ScoreTables
from vlmproprio.io import (
    WriteError,
    atomic_write_text,
    atomic_write_texts,
    load_json,
    load_required_json,
    sha256_file,
    writing,
)
from vlmproprio.parallel import map_groups

# file name -> (table, format), in the order the files are written
SCORE_FILES: dict[str, tuple[str, str]] = {
    "rows.json": ("rows", "json"),
    "rows.csv": ("rows", "csv"),
    "aggregate.json": ("aggregate", "json"),
    "aggregate.csv": ("aggregate", "csv"),
    "sweep.json": ("sweep", "json"),
    "sweep.csv": ("sweep", "csv"),
    "sweep_aggregate.json": ("sweep_aggregate", "json"),
    "sweep_aggregate.csv": ("sweep_aggregate", "csv"),
    "paired.json": ("paired", "json"),
    "paired.csv": ("paired", "csv"),
    "audit.json": ("audit", "json"),
    "traces.json": ("traces", "json"),
    "meta.json": ("meta", "json"),
    "verdicts.json": ("verdicts", "json"),
    "timing.json": ("timing", "json"),
    "judge.json": ("judge", "json"),  # when the run was judged
}
# the costliest to render first (measured on the shipped run: audit.json 4.7 MB, sweep.json 2 MB, sweep.csv
# 0.7 MB, ...): dealt out in this order, two workers get about equal shares
FILES_PER_WORKER = 4  # at least; a fork for one small file costs more than the file
COSTLIEST_FIRST = ("audit.json", "sweep.json", "sweep.csv", "rows.csv", "rows.json", "traces.json")


def score_file_texts(tables: ScoreTables, workers: int = 1) -> dict[str, str]:
    """The text of every score file, by name (judge.json too when the tables have a judge). With ``workers``
    above one, the files are dealt out to forked workers (vlmproprio.parallel): the same texts, ~9 MB of JSON
    and CSV per model written in about half the time on two cores."""
    names = [n for n in SCORE_FILES if n != "judge.json" or tables.judge is not None]
    order = [*COSTLIEST_FIRST, *(n for n in names if n not in COSTLIEST_FIRST)]

    def render(part: Sequence[str]) -> list[str]:
        dumps = {"json": dumps_json, "csv": dumps_csv}
        return [dumps[SCORE_FILES[n][1]](getattr(tables, SCORE_FILES[n][0])) for n in part]

    rendered = map_groups(render, order, workers, lambda name: name, min_chunk=FILES_PER_WORKER, what="score files")
    texts = dict(zip(order, rendered, strict=True))
    return {n: texts[n] for n in names}


def write_score_tables(
    run_dir: str | Path, tables: ScoreTables, inputs: dict | None = None, workers: int = 1
) -> list[Path]:
    """Write the tables as one generation of RUN_DIR/scores/ (see ``swap_in_generation``), stamped with
    ``inputs`` (``score_inputs``: what they were computed from); ``workers``: see ``score_file_texts``."""
    return swap_in_generation(Path(run_dir), score_file_texts(tables, workers), inputs or {})


# ---------------------------------------------------------------------------------------------- score generations
#
# RUN_DIR/scores/ is written as one generation: every file goes into a new hidden folder beside it, with
# stamp.json (the digest of exactly the transcripts, run configuration, fixtures' ground truth, settings and
# code version the scores come from, and the sha256 of each score file); the folder then replaces scores/ by
# rename. A reader sees the old generation, the new one, or none -- never a mix -- and the report refuses
# scores whose stamp no longer matches the run (``check_scores``).

STAMP_FILE = "stamp.json"
GENERATION_PREFIX = ".scores-"  # .scores-new-*, .scores-old-*: removed by the next score of the run


class StaleScoresError(ScoreRunError):
    """Scores that do not match the run they sit in; the message says how to re-score."""


def _digest(obj) -> str:
    import hashlib

    return hashlib.sha256(json.dumps(obj, sort_keys=True, separators=(",", ":")).encode("utf-8")).hexdigest()


def run_configuration(manifest: dict) -> dict:
    """The part of run.json that decides what the transcripts are (not status, times, counts or versions)."""
    models = [
        {k: m.get(k) for k in ("name", "slug", "pipeline")} for m in manifest.get("models", []) if isinstance(m, dict)
    ]
    return {"episodes": manifest.get("episodes"), "conditions": manifest.get("conditions"), "models": models}


def code_version() -> dict:
    from vlmproprio import __version__

    return {"vlmproprio": __version__, "scores_version": SCORES_VERSION}


def transcripts_digest(run_dir: Path, files: Sequence[Path], documents: Sequence[dict] | None = None) -> str:
    """The digest of what the transcripts say, leaving out how it was obtained (``requests``: cache hits and
    latencies; ``timing``), which a resumed or repeated run changes without changing a word. ``documents``:
    the files' JSON as already read (the transcripts a score computed from), instead of reading them again."""
    said = {}
    if documents is not None and len(documents) != len(files):
        raise ValueError(f"{len(documents)} transcript documents for {len(files)} files")
    for i, p in enumerate(files):
        d = documents[i] if documents is not None else load_json(p, error=ScoreRunError)
        said[p.relative_to(run_dir).as_posix()] = (
            {k: v for k, v in d.items() if k not in ("requests", "timing")} if isinstance(d, dict) else d
        )
    return _digest(said)


def score_inputs(
    run_dir: Path,
    manifest: dict,
    files: Sequence[Path],
    fixtures: Path,
    episode_ids,
    settings: dict,
    lexicons: dict,
    documents: Sequence[dict] | None = None,
) -> dict:
    """What a generation of scores is computed from, each part as a digest, and their digest (the stamp).
    ``documents``: the transcript files' JSON as the score read them (``transcripts_digest``)."""
    from vlmproprio.episodes import read_manifest

    try:
        fixture_files = read_manifest(fixtures)
        truth = {e: fixture_files.get(f"episodes/{e}/episode.json") for e in episode_ids}
    except VlmproprioError:  # scored with verify=False on fixtures without a manifest
        truth = {}
    parts = {
        "transcripts": transcripts_digest(run_dir, files, documents),
        "run_configuration": _digest(run_configuration(manifest)),
        "ground_truth": _digest(truth),
        "settings": _digest(settings),
        "lexicons": _digest(lexicons),
        "code": code_version(),
    }
    return {"stamp": _digest(parts), "inputs": parts}


def _remove_leftovers(run_dir: Path) -> None:
    import shutil

    for p in run_dir.glob(GENERATION_PREFIX + "*"):
        shutil.rmtree(p, ignore_errors=True)


def _write_files(folder: Path, files: dict[str, str]) -> dict[str, str]:
    """Each file written atomically into ``folder``, several at a time (``io.atomic_write_texts``); name ->
    sha256. The first failure, in ``files`` order, is raised once every write has finished or failed."""
    digests = atomic_write_texts({folder / name: text for name, text in files.items()})
    return {path.name: digest for path, digest in digests.items()}


def swap_in_generation(run_dir: Path, files: dict[str, str], inputs: dict) -> list[Path]:
    """Write ``files`` (name -> text) and stamp.json into a new folder and swap it in for RUN_DIR/scores/."""
    import os
    import shutil
    import uuid

    _remove_leftovers(run_dir)  # a score killed before its swap left these
    tag = f"{os.getpid()}-{uuid.uuid4().hex[:8]}"
    new, old, out = (
        run_dir / f"{GENERATION_PREFIX}new-{tag}",
        run_dir / f"{GENERATION_PREFIX}old-{tag}",
        run_dir / "scores",
    )
    try:
        with writing(out, "write scores into"):
            new.mkdir(parents=True)
        try:
            written = _write_files(new, files)
        except WriteError as exc:  # name the folder the user knows, not the hidden one
            raise WriteError(str(exc).replace(str(new), str(out))) from exc.__cause__
        # timing.json differs between runs by nature: leaving it out keeps stamp.json byte-identical too
        stamp = {**inputs, "files": {k: v for k, v in sorted(written.items()) if k != "timing.json"}}
        atomic_write_text(new / STAMP_FILE, dumps_json(stamp))
        with writing(out, "replace"):
            if out.exists():
                out.rename(old)
            new.rename(out)
    except BaseException:
        shutil.rmtree(new, ignore_errors=True)
        if old.exists() and not out.exists():
            old.rename(out)  # put the previous generation back
        raise
    shutil.rmtree(old, ignore_errors=True)
    return [out / name for name in files]


def check_scores(run_dir: str | Path, names: Sequence[str] = ()) -> dict:
    """The stamp of RUN_DIR/scores/ after checking it still matches the run: the same transcripts, run
    configuration and code version, and score files ``names`` (default: all) as they were written.
    StaleScoresError, naming the command that fixes it, otherwise."""
    run_dir = Path(run_dir)
    out = run_dir / "scores"
    fix = f"re-score the run: `vlmproprio score {run_dir}`"
    stamp = load_required_json(
        out / STAMP_FILE,
        f"{out}: scores are out of date: no {STAMP_FILE} (scores from an older version or incomplete); {fix}",
        error=StaleScoresError,
    )
    if not isinstance(stamp, dict) or not isinstance(stamp.get("inputs"), dict):
        raise StaleScoresError(f"{out / STAMP_FILE}: scores are out of date: not a score stamp; {fix}")
    recorded, files = stamp["inputs"], stamp.get("files", {})
    if recorded.get("code") != code_version():
        raise StaleScoresError(
            f"{out}: scores are out of date: scored by {recorded.get('code')}, this is {code_version()}; {fix}"
        )
    manifest = read_run_manifest(run_dir)
    try:
        current = run_transcript_files(run_dir, manifest)
    except ScoreRunError as exc:
        raise StaleScoresError(f"{out}: scores are out of date: the run no longer matches them ({exc})") from None
    if recorded.get("run_configuration") != _digest(run_configuration(manifest)):
        raise StaleScoresError(
            f"{out}: scores are out of date: run.json records another configuration than the one scored; {fix}"
        )
    if recorded.get("transcripts") != transcripts_digest(run_dir, current):
        raise StaleScoresError(f"{out}: scores are out of date: transcripts changed since the run was scored; {fix}")
    for name in names or list(files):
        path = out / name
        if name not in files or not path.is_file() or sha256_file(path) != files[name]:
            raise StaleScoresError(
                f"{path}: scores are out of date: not the file of this generation of scores (changed or mixed); {fix}"
            )
    return stamp
