"""Where vlmproprio finds its fixtures and keeps its caches, independent of the current folder.

Fixtures: ``--fixtures DIR``, else ``$VLMPROPRIO_FIXTURES``, else the repository the command runs in (the
first folder, from the current one upward, holding ``fixtures/manifest.json``), else the source checkout the
package was installed from (an editable install). Nothing found is a one-line error saying how to point at one.

Caches (model answers in the folder's ``cache.db``, sentence embeddings and the encoder folder's digest in
``embeddings/``, tiny test models in ``models/``, chance baselines in ``chance/``, the report's power analyses in
``power/``): ``--cache-dir DIR`` where a command takes it, else
``$VLMPROPRIO_CACHE``, else the user cache directory (``platformdirs``: ``~/.cache/vlmproprio`` on Linux). One
variable and one option for all of them.
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


def resolve_fixtures(explicit: Path | str | None = None, *, must_exist: bool = True) -> Path:
    """The fixture folder to use: explicit, else $VLMPROPRIO_FIXTURES, else the repository's, else the checkout's.

    ``must_exist=False`` is for commands that create fixtures (record, manifest): an explicit or environment
    folder is returned even if it is not there yet.
    """
    if explicit is not None and str(explicit) != "":
        return Path(explicit)
    env = os.environ.get(FIXTURES_ENV)
    if env:
        return Path(env)
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
