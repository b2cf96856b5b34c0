"""Where vlmproprio finds its fixtures and keeps its caches, independent of the current folder.

Fixtures: ``--fixtures DIR``, else ``$VLMPROPRIO_FIXTURES``, else the repository the command runs in (the
first folder, from the current one upward, holding ``fixtures/manifest.json``), else the source checkout the
package was installed from (an editable install). Nothing found is a one-line error saying how to point at one.

Caches (model answers in the folder's ``cache.db``, sentence embeddings and the encoder folder's digest in
``embeddings/``, tiny test models in ``models/``, chance baselines in ``chance/``, the report's power analyses in
``power/``): ``--cache-dir DIR`` where a command takes it, else
``$VLMPROPRIO_CACHE``, else the user cache directory (``platformdirs``: ``~/.cache/vlmproprio`` on Linux). One
variable and one option for all of them.

Inside a run folder: ``transcripts/<model slug>/<episode>__<condition>.json``, one file per cell
(``transcript_path``), and which of them the run's ``run.json`` says it must hold (``recorded_transcripts``).
A run, cache or report folder never lies inside the fixtures, nor the fixtures inside it (``refuse_nesting``).
"""

from __future__ import annotations

import os
from pathlib import Path

from vlmproprio.errors import UsageError

FIXTURES_ENV = "VLMPROPRIO_FIXTURES"
CACHE_ENV = "VLMPROPRIO_CACHE"
MANIFEST = "manifest.json"
APP_NAME = "vlmproprio"

# Every environment variable vlmproprio reads, with what it does; the README lists the same (a test checks).
ENVIRONMENT: dict[str, str] = {
    FIXTURES_ENV: "fixture folder when --fixtures is not given",
    CACHE_ENV: (
        "cache folder (answers in cache.db, embeddings/, models/, chance/, power/) when --cache-dir is not given"
    ),
    "OPENAI_API_KEY": "API key of the openai backend (another variable with --api-key-env)",
    "MUJOCO_GL": "headless OpenGL for recording: egl (default) or osmesa",
    "HF_HUB_OFFLINE": "set to 1 unless --allow-download: local weights only",
}


def _source_checkout_fixtures() -> Path | None:
    """The fixtures of the checkout this package runs from (src/vlmproprio -> repo root), if any."""
    root = Path(__file__).resolve().parents[2]
    candidate = root / "fixtures"
    return candidate if (candidate / MANIFEST).is_file() else None


def find_repository_fixtures(start: Path | None = None) -> Path | None:
    """The first ``fixtures/`` holding a manifest, from ``start`` (default: the current folder) upward."""
    here = (start or Path.cwd()).resolve()
    for folder in (here, *here.parents):
        candidate = folder / "fixtures"
        if (candidate / MANIFEST).is_file():
            return candidate
    return None


def _existing_folder(path: Path, given_by: str) -> Path:
    """``path`` when it is a folder; a UsageError naming the flag or variable that gave it otherwise (a typo
    must not read as "no fixtures", nor list models against a folder that is not there)."""
    if not path.is_dir():
        what = "is not a folder" if path.exists() else "does not exist"
        raise UsageError(f"{given_by} {path}: {what}; pass the fixture folder (the one holding {MANIFEST})")
    return path


def resolve_fixtures(explicit: Path | str | None = None, *, must_exist: bool = True, flag: str = "--fixtures") -> Path:
    """The fixture folder to use: explicit, else $VLMPROPRIO_FIXTURES, else the repository's, else the checkout's.

    ``must_exist=False`` is for commands that create fixtures (record, manifest): an explicit or environment
    folder is returned even if it is not there yet; otherwise one that is not a folder is a UsageError naming
    ``flag`` (the option that gave ``explicit``) or the variable.
    """
    if explicit is not None and str(explicit) != "":
        return _existing_folder(Path(explicit), flag) if must_exist else Path(explicit)
    env = os.environ.get(FIXTURES_ENV)
    if env:
        return _existing_folder(Path(env), f"${FIXTURES_ENV}") if must_exist else Path(env)
    found = find_repository_fixtures() or _source_checkout_fixtures()
    if found is not None:
        return found
    if not must_exist:
        return Path.cwd() / "fixtures"
    raise UsageError(
        f"no fixture folder found (no fixtures/{MANIFEST} in {Path.cwd()} or above); "
        f"pass --fixtures DIR or set {FIXTURES_ENV}=DIR"
    )


def cache_root(explicit: Path | str | None = None) -> Path:
    """The cache root: explicit, else $VLMPROPRIO_CACHE, else the user cache directory."""
    if explicit is not None and str(explicit) != "":
        return Path(explicit)
    env = os.environ.get(CACHE_ENV)
    if env:
        return Path(env)
    import platformdirs

    return Path(platformdirs.user_cache_dir(APP_NAME, appauthor=False))


# ---------------------------------------------------------------------------------------------- run folders


def cell_name(episode_id: str, condition: str) -> str:
    """One (episode, condition) cell of a model: the stem of its transcript file."""
    return f"{episode_id}__{condition}"


def transcript_filename(episode_id: str, condition: str) -> str:
    return f"{cell_name(episode_id, condition)}.json"


def transcript_path(run_dir: Path | str, model: str, episode_id: str, condition: str) -> Path:
    return Path(run_dir) / "transcripts" / model / transcript_filename(episode_id, condition)


def recorded_transcripts(run_dir: Path, run_file: dict) -> list[Path] | None:
    """The transcript files the run recorded in run.json must have (model slug x episode x condition), or None
    for a run.json that does not say (written by hand or by another tool)."""
    episodes, conditions = run_file.get("episodes"), run_file.get("conditions")
    models = [m.get("slug") for m in run_file.get("models", []) if isinstance(m, dict)]
    if not (isinstance(episodes, list) and isinstance(conditions, list) and models and all(models)):
        return None
    root = Path(run_dir) / "transcripts"
    return [root / m / transcript_filename(e, c) for m in models for e in episodes for c in conditions]


def is_inside(a: Path, b: Path) -> bool:
    """Whether folder ``a`` is ``b`` or lies below it (both resolved)."""
    a, b = a.resolve(), b.resolve()
    return a == b or b in a.parents


def refuse_nesting(fixtures: Path, folders: dict[str, Path | None]) -> None:
    """Refuse an output or cache folder (``folders``: option name -> folder) inside the fixtures, where the
    manifest would see extra files and every later run fail, and the fixtures inside one of them."""
    fixtures = Path(fixtures)
    for flag, folder in folders.items():
        if folder is None:
            continue
        if is_inside(Path(folder), fixtures):
            raise UsageError(
                f"{flag} {folder} is inside the fixture folder {fixtures}; fixtures hold frozen data only "
                f"(its manifest would see new files): choose a {flag} outside it"
            )
        if is_inside(fixtures, Path(folder)):
            raise UsageError(f"the fixture folder {fixtures} is inside {flag} {folder}; choose a {flag} beside it")
