"""Write the score tables as one generation of RUN_DIR/scores/, stamped with what they were computed from
(the stamp's digests, and the check that a generation still matches its run, are vlmproprio.run_folder's)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

from vlmproprio.errors import VlmproprioError
from vlmproprio.evaluation.formats import dumps_csv, dumps_json
from vlmproprio.evaluation.tables import ScoreTables
from vlmproprio.io import WriteError, atomic_write_text, atomic_write_texts, writing
from vlmproprio.parallel import map_groups
from vlmproprio.run_folder import (
    STAMP_FILE,
    code_version,
    ground_truth_digest,
    json_digest,
    run_configuration,
    transcripts_digest,
)

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
# scores whose stamp no longer matches the run (``run_folder.check_scores``).

GENERATION_PREFIX = ".scores-"  # .scores-new-*, .scores-old-*: removed by the next score of the run


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
        truth = ground_truth_digest(episode_ids, read_manifest(fixtures))
    except VlmproprioError:  # scored with verify=False on fixtures without a manifest: nothing to check later
        truth = json_digest({})
    parts = {
        "transcripts": transcripts_digest(run_dir, files, documents),
        "run_configuration": json_digest(run_configuration(manifest)),
        "ground_truth": truth,
        "settings": json_digest(settings),
        "lexicons": json_digest(lexicons),
        "code": code_version(),
    }
    return {"stamp": json_digest(parts), "inputs": parts}


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
