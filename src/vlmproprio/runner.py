"""A run: models x episodes x conditions through the pipeline, into a run directory.

    RUN_DIR/run.json                                   what was run, with what, by which code
    RUN_DIR/transcripts/<model slug>/<episode>__<condition>.json

Modes (see vlmproprio.cache): ``replay`` answers only from the model's cassette in
``<fixtures>/responses/`` (the reference captioner needs none), ``live`` runs the model and uses and
fills the response cache, ``record`` is live and also writes the answers it used to the cassette.
"""

from __future__ import annotations

import datetime as _dt
import json
import platform
import subprocess
from dataclasses import asdict, dataclass, field, replace
from importlib import metadata
from pathlib import Path
from urllib.parse import urlsplit, urlunsplit

from vlmproprio.conditions import Condition
from vlmproprio.episodes import Episode, load_episodes, register_fixture_file
from vlmproprio.errors import UsageError
from vlmproprio.io import atomic_write_text
from vlmproprio.pipeline import PipelineSettings, answer_chunk, calls_per_episode, caption_episodes
from vlmproprio.transcripts import Transcript, write_transcript

RUN_FILE = "run.json"
RUN_VERSION = 1
PACKAGES = ("vlmproprio", "numpy", "torch", "transformers", "sentence-transformers", "openai", "robosuite", "mujoco")


@dataclass(frozen=True)
class RunPlan:
    models: tuple[str, ...]
    conditions: tuple[Condition, ...]
    fixtures: Path
    out: Path
    episode_ids: tuple[str, ...] | None = None  # None: every episode in the fixtures
    mode: str = "live"
    cache_dir: Path | None = None  # None: vlmproprio.cache.default_cache_dir()
    pipeline: PipelineSettings = field(default_factory=PipelineSettings)
    backend: object = None  # vlmproprio.backends.registry.BackendSettings; None: defaults
    max_new_tokens: int | None = None  # None: each model's registry default (512; tiny models 64)
    progress: bool = True

    def pipeline_for(self, model: str) -> PipelineSettings:
        from vlmproprio.backends.registry import parse_model_name

        n = self.max_new_tokens or parse_model_name(model).max_new_tokens
        return replace(self.pipeline, generation=replace(self.pipeline.generation, max_new_tokens=n))


@dataclass
class ModelRun:
    name: str
    slug: str
    mode: str
    pipeline: dict
    identity: dict
    stats: dict
    transcripts: list[Transcript]
    cassette: str | None = None


def package_versions() -> dict[str, str]:
    """Installed versions, read from package metadata (nothing is imported)."""
    out = {"python": platform.python_version()}
    for name in PACKAGES:
        try:
            out[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            continue
    return out


def git_revision(path: Path) -> str | None:
    try:
        res = subprocess.run(
            ["git", "-C", str(path), "rev-parse", "HEAD"], capture_output=True, text=True, timeout=5, check=False
        )
    except (OSError, subprocess.SubprocessError):
        return None
    return res.stdout.strip() or None


def _public_url(url: str | None) -> str | None:
    """A base URL without user:password@ or query (they can carry credentials)."""
    if not url:
        return url
    parts = urlsplit(url)
    host = parts.hostname or ""
    if parts.port:
        host += f":{parts.port}"
    return urlunsplit((parts.scheme, host, parts.path, "", ""))


def _backend_settings_record(settings) -> dict:
    d = {k: v for k, v in asdict(settings).items() if k not in ("extra", "home", "cassette_dir")}
    d["base_url"] = _public_url(d.get("base_url"))
    return {k: (str(v) if isinstance(v, Path) else v) for k, v in d.items()}


def _write_run_file(plan: RunPlan, episodes: list[Episode], runs: list[ModelRun], status: str, settings) -> None:
    doc = {
        "run_version": RUN_VERSION,
        "status": status,
        "updated": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
        "mode": plan.mode,
        "fixtures": str(plan.fixtures.resolve()),
        "episodes": [e.episode_id for e in episodes],
        "conditions": [c.name for c in plan.conditions],
        "models": [
            {
                "name": r.name,
                "slug": r.slug,
                "mode": r.mode,
                "pipeline": r.pipeline,
                "identity": r.identity,
                "stats": r.stats,
                "cassette": r.cassette,
                "transcripts": len(r.transcripts),
            }
            for r in runs
        ],
        "backend_settings": _backend_settings_record(settings),
        "calls_per_episode_condition": {
            e.episode_id: calls_per_episode(len(e.frames), plan.pipeline.k) for e in episodes
        },
        "versions": package_versions(),
        "git_revision": git_revision(Path(__file__).parent),
    }
    atomic_write_text(plan.out / RUN_FILE, json.dumps(doc, indent=1) + "\n")


def run_model(name: str, plan: RunPlan, episodes: list[Episode], peers: list[Episode], settings) -> ModelRun:
    from vlmproprio.backends.registry import cassette_path, create_backend, model_slug
    from vlmproprio.cache import CachedBackend, ResponseCache, default_cache_dir

    slug = model_slug(name)
    backend = create_backend(name, plan.mode, settings)
    # replay answers strictly from the committed cassette: a stale local cache must not mask a missing answer
    cache = None if plan.mode == "replay" else ResponseCache(plan.cache_dir or default_cache_dir())
    try:
        cached = CachedBackend(backend, mode=plan.mode, cache=cache, model=slug)
        pipeline = plan.pipeline_for(name)
        transcripts = caption_episodes(
            episodes,
            plan.conditions,
            cached.answer,
            slug,
            pipeline,
            peers=peers,
            chunk=answer_chunk(backend.max_batch_size),
            progress=plan.progress,
        )
        for t in transcripts:
            write_transcript(plan.out, t)
        cassette = None
        if plan.mode == "record":
            path = cassette_path(name, settings.cassette_dir)
            cached.export_cassette(path)
            cassette = str(path)
            register_fixture_file(path)
        return ModelRun(
            name, slug, plan.mode, pipeline.to_dict(), dict(cached.identity), dict(cached.stats), transcripts, cassette
        )
    finally:
        backend.close()
        if cache is not None:
            cache.close()


def run(plan: RunPlan) -> list[ModelRun]:
    """Caption every (episode, condition) with every model; write transcripts and run.json."""
    from vlmproprio.backends.registry import BackendSettings, model_slug

    for name in plan.models:
        model_slug(name)  # refuse unsafe or unknown names before any work
    settings = plan.backend or BackendSettings()
    settings = BackendSettings(**{**asdict(settings), "cassette_dir": Path(plan.fixtures) / "responses"})
    peers = load_episodes(plan.fixtures)  # verifies every episode; both_shuffled may borrow from any of them
    if plan.episode_ids is None:
        episodes = peers
    else:
        by_id = {e.episode_id: e for e in peers}
        missing = [eid for eid in plan.episode_ids if eid not in by_id]
        if missing:
            raise UsageError(f"unknown episode(s) {', '.join(missing)} in {plan.fixtures}; known: {', '.join(by_id)}")
        episodes = [by_id[eid] for eid in plan.episode_ids]
    try:
        plan.out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:  # a file in the way, no permission: the user's --out, not a bug
        raise UsageError(
            f"cannot create run directory {plan.out}: {exc.strerror or exc}; choose another --out"
        ) from exc
    runs: list[ModelRun] = []
    _write_run_file(plan, episodes, runs, "running", settings)
    for name in plan.models:
        runs.append(run_model(name, plan, episodes, peers, settings))
        _write_run_file(plan, episodes, runs, "running", settings)
    _write_run_file(plan, episodes, runs, "complete", settings)
    return runs
