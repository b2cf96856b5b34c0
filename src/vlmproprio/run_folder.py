"""A run folder read back by the stages after the run: its run.json, the transcripts it must hold, its fixture
folder, and whether its scores/ are still the scores of it.

``vlmproprio.evaluation`` writes RUN_DIR/scores/ as one generation stamped with the digests of what it was
computed from (``stamp.json``: ``run_configuration``, ``transcripts_digest``, ``code_version``); the report and
compare read that generation and refuse it with ``check_scores`` when the run has changed since. Both sides
meet here, before either, so the data flows one way: the scorer writes, the report reads, neither calls the
other.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Sequence
from pathlib import Path

from vlmproprio.errors import VlmproprioError
from vlmproprio.io import load_json, load_required_json, sha256_file
from vlmproprio.locations import recorded_transcripts

# the version of what a scores/ generation holds: a generation scored by another version is stale
SCORES_VERSION = 2


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
    running = [s for s in manifest.get("running_models", []) if isinstance(s, str)]
    unfinished = [p for p in extra if p.parent.name in running]
    if unfinished:  # a run of another model into this folder, still going or stopped: not "another run"
        slug = unfinished[0].parent.name
        raise ScoreRunError(
            f"{run_dir}: model {slug} is still being run into this folder, or its run was stopped (run.json lists "
            f"it under running_models; {len(unfinished)} of its transcripts are there); wait for that run to "
            f"finish, or finish it by running the same `vlmproprio run --model MODEL --out RUN_DIR` command again"
        )
    if extra:
        raise ScoreRunError(
            f"{extra[0]}: not part of the run recorded in {run_dir / 'run.json'} ({len(extra)} such transcript(s), "
            "left by another run); move them out of the run folder, or run into a new --out"
        )
    return expected


# ---------------------------------------------------------------------------------------------- score stamps

STAMP_FILE = "stamp.json"


class StaleScoresError(ScoreRunError):
    """Scores that do not match the run they sit in; the message says how to re-score."""


def json_digest(obj) -> str:
    """The sha256 of ``obj`` as canonical JSON (sorted keys, no spaces): a stamp's digest of each input."""
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
    return json_digest(said)


def ground_truth_digest(episode_ids: Sequence[str], hashes: dict[str, str]) -> str:
    """The stamp's digest of the episodes' ground truth: the sha256 of each ``episodes/<id>/episode.json``
    (``hashes``: fixture path -> sha256, the manifest's when scored, the files' own when checked)."""
    return json_digest({e: hashes.get(f"episodes/{e}/episode.json") for e in episode_ids})


def _episode_ids(documents: Sequence[dict]) -> list[str]:
    return sorted({d["episode_id"] for d in documents if isinstance(d, dict) and isinstance(d.get("episode_id"), str)})


def _check_ground_truth(run_dir: Path, manifest: dict, fixtures, documents: Sequence[dict], recorded) -> None:
    """The fixtures (``fixtures``, else run.json's) hold the ground truth the scores were computed from: a
    changed episode.json, or --fixtures naming another fixture set, makes the scores stale. Not checked when the
    scores were made without a manifest, or when run.json's fixture folder is gone and none is given (the
    report then shows no frames)."""
    if recorded is None or recorded == json_digest({}):
        return
    episode_ids = _episode_ids(documents)
    try:
        root = resolve_fixtures(run_dir, manifest, fixtures)
    except ScoreRunError:
        if fixtures is not None:
            raise
        return
    hashes = {}
    for e in episode_ids:
        path = root / "episodes" / e / "episode.json"
        if path.is_file():
            hashes[f"episodes/{e}/episode.json"] = sha256_file(path)
    if ground_truth_digest(episode_ids, hashes) != recorded:
        given = f" --fixtures {fixtures}" if fixtures is not None else ""
        raise StaleScoresError(
            f"{run_dir / 'scores'}: scores are out of date: the ground truth in {root} (episodes/*/episode.json) "
            f"is not the one they were computed from (the fixtures changed, or are another fixture set); re-score "
            f"the run with these fixtures: `vlmproprio score {run_dir}{given}`"
        )


def _check_files(out: Path, files: dict, names: Sequence[str], fix: str) -> None:
    """Every score file ``names`` (default: every file of the generation) is the one written with the stamp,
    and scores/ holds no file the stamp does not list (one from another run put there by hand)."""
    for name in names or list(files):
        path = out / name
        if name not in files or not path.is_file() or sha256_file(path) != files[name]:
            what = "missing" if name in files and not path.is_file() else "changed or mixed"
            raise StaleScoresError(
                f"{path}: scores are out of date: not the file of this generation of scores ({what}); {fix}"
            )
    unlisted = sorted(
        p.name
        for p in out.iterdir()
        if p.is_file() and not p.name.startswith(".") and p.name not in files and p.name not in UNSTAMPED_FILES
    )
    if unlisted:
        raise StaleScoresError(
            f"{out / unlisted[0]}: scores are out of date: not a file of this generation of scores (from another "
            f"run or an older score; {len(unlisted)} such file(s)); {fix}"
        )


# written with every generation but not listed in its stamp: the stamp itself, and the wall times, which differ
# between repeated scores by nature
UNSTAMPED_FILES = (STAMP_FILE, "timing.json")


def check_scores(run_dir: str | Path, names: Sequence[str] = (), fixtures: str | Path | None = None) -> dict:
    """The stamp of RUN_DIR/scores/ after checking it still matches the run: the same transcripts, run
    configuration, ground truth (in ``fixtures``, default the fixture folder of run.json) and code version, and
    score files ``names`` (default: every file of the generation) as they were written, with no other file
    beside them. StaleScoresError, naming the command that fixes it, otherwise."""
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
    if not isinstance(files, dict):
        raise StaleScoresError(f"{out / STAMP_FILE}: scores are out of date: not a score stamp; {fix}")
    if recorded.get("code") != code_version():
        raise StaleScoresError(
            f"{out}: scores are out of date: scored by {recorded.get('code')}, this is {code_version()}; {fix}"
        )
    manifest = read_run_manifest(run_dir)
    if not (run_dir / "run.json").is_file() and recorded.get("run_configuration") != json_digest(run_configuration({})):
        raise StaleScoresError(
            f"{run_dir / 'run.json'}: missing, though the scores in {out} were made from it (deleted or moved "
            "since); the scores cannot be checked against their run without it: put it back, or run the models "
            "again into this folder and re-score"
        )
    try:
        current = run_transcript_files(run_dir, manifest)
    except ScoreRunError as exc:
        raise StaleScoresError(f"{out}: scores are out of date: the run no longer matches them ({exc})") from None
    if recorded.get("run_configuration") != json_digest(run_configuration(manifest)):
        raise StaleScoresError(
            f"{out}: scores are out of date: run.json records another configuration than the one scored; {fix}"
        )
    documents = [load_json(p, error=ScoreRunError) for p in current]
    if recorded.get("transcripts") != transcripts_digest(run_dir, current, documents):
        raise StaleScoresError(f"{out}: scores are out of date: transcripts changed since the run was scored; {fix}")
    _check_ground_truth(run_dir, manifest, fixtures, documents, recorded.get("ground_truth"))
    _check_files(out, files, names, fix)
    return stamp
