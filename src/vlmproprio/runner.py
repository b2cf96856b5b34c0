"""A run: models x episodes x conditions through the pipeline, into a run directory.

    RUN_DIR/run.json                                   what was run, with what, by which code
    RUN_DIR/transcripts/<model slug>/<episode>__<condition>.json

Modes (see vlmproprio.cache): ``replay`` answers only from the model's cassette in
``<fixtures>/responses/`` (the reference captioner needs none), ``live`` runs the model and uses and
fills the response cache, ``record`` is live and also writes the answers it used to the cassette;
``auto`` (the CLI's and the benchmark's default) is replay for a model with a cassette, else live, decided per
model (run.json records the mode each model ran in).
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import json
import os
import platform
import subprocess
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field, replace
from importlib import metadata
from pathlib import Path
from urllib.parse import urlsplit, urlunsplit

from vlmproprio.answering import Answerer, open_answerer
from vlmproprio.backends.settings import BackendSettings
from vlmproprio.cache import default_cache_dir
from vlmproprio.cassettes import problem_counts_text
from vlmproprio.conditions import Condition
from vlmproprio.episodes import PIXEL_LEDGER_FILE, Episode, load_episodes, pixel_ledger
from vlmproprio.errors import UsageError, did_you_mean
from vlmproprio.io import atomic_write_text, atomic_write_texts
from vlmproprio.locations import refuse_nesting
from vlmproprio.models import ModelRef, resolve_model
from vlmproprio.parallel import map_groups, resolve_workers
from vlmproprio.pipeline import PipelineSettings, answer_chunk, calls_per_episode, caption_episodes, episode_images
from vlmproprio.transcripts import Transcript, answer_problems, frames_missing_by_problem, transcript_files

RUN_FILE = "run.json"
RUN_VERSION = 1
PACKAGES = ("vlmproprio", "numpy", "torch", "transformers", "sentence-transformers", "openai", "robosuite", "mujoco")


@dataclass(frozen=True)
class RunPlan:
    models: tuple[ModelRef, ...]  # names are resolved when the plan is made
    conditions: tuple[Condition, ...]
    fixtures: Path
    out: Path
    episode_ids: tuple[str, ...] | None = None  # None: every episode in the fixtures
    mode: str = "live"
    cache_dir: Path | None = None  # None: vlmproprio.cache.default_cache_dir()
    pipeline: PipelineSettings = field(default_factory=PipelineSettings)
    backend: BackendSettings | None = None  # None: defaults
    max_new_tokens: int | None = None  # None: each model's registry default (512; tiny models 64)
    thinking: bool | None = None  # a reasoning model's thinking switch; None: its chat template's default
    progress: bool = True
    # processes that caption with a model whose answers are pure (Answerer.pure: the reference captioners, a
    # cassette's replay); None: vlmproprio.parallel's default. The transcripts are the same with any number.
    workers: int | None = None
    allow_empty_answers: bool = False  # record: write answers that hold no caption into the cassette too

    def __post_init__(self) -> None:
        # the one place a run's model names are parsed: an unknown or unsafe name fails before any work
        object.__setattr__(self, "models", tuple(map(resolve_model, self.models)))
        resolve_workers(self.workers)  # a bad number (or $VLMPROPRIO_WORKERS) fails here, whichever models run

    def pipeline_for(self, model: ModelRef) -> PipelineSettings:
        n = self.max_new_tokens or model.max_new_tokens
        thinking = self.thinking if self.thinking is not None else self.pipeline.generation.thinking
        return replace(self.pipeline, generation=replace(self.pipeline.generation, max_new_tokens=n, thinking=thinking))


@dataclass
class ModelRun:
    model: ModelRef
    mode: str
    pipeline: dict
    identity: dict
    stats: dict
    transcripts: list[Transcript]
    cassette: str | None = None

    @property
    def answer_problems(self) -> dict[str, int]:
        """Requests whose answer holds no caption or came from another model, by class (chat.ANSWER_PROBLEMS)."""
        return answer_problems(self.transcripts)

    @property
    def name(self) -> str:
        return self.model.name

    @property
    def slug(self) -> str:
        return self.model.slug


MOST_MISSING_SHARE = 0.5  # frame captions missing, at least this share with answer problems: most are lost


def answer_problem_warning(r: ModelRun) -> str | None:
    """One line naming the answers of ``r`` that hold no caption (or came from another model): how many
    requests of each class and how many frame captions are missing; None when every answer was a plain one."""
    problems = r.answer_problems
    if not problems:
        return None
    requests = sum(len(t.requests) for t in r.transcripts)
    frames = [f for t in r.transcripts for f in t.frames]
    missing = sum(f.status == "missing" for f in frames)
    lost = sum(frames_missing_by_problem(t) for t in r.transcripts)
    lead = "MOST CAPTIONS ARE MISSING: " if frames and lost / len(frames) >= MOST_MISSING_SHARE else ""
    return (
        f"{lead}{r.name}: {sum(problems.values())} of {requests} answers came back without a plain answer "
        f"({problem_counts_text(problems)}); {missing} of {len(frames)} frame captions are missing"
    )


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


def _backend_settings_record(settings: BackendSettings) -> dict:
    d = settings.record()
    d["base_url"] = _public_url(d.get("base_url"))  # and every text written is scrubbed (vlmproprio.io)
    return d


def _model_record(r: ModelRun) -> dict:
    return {
        "name": r.name,
        "slug": r.slug,
        "mode": r.mode,
        "pipeline": r.pipeline,
        "identity": r.identity,
        "stats": r.stats,
        "cassette": r.cassette,
        "transcripts": len(r.transcripts),
        **({"answer_problems": problems} if (problems := r.answer_problems) else {}),
    }


def provenance() -> dict:
    """What code wrote a run: package versions and the git revision (read once per run: ~0.05 s each time)."""
    return {"versions": package_versions(), "git_revision": git_revision(Path(__file__).parent)}


@contextlib.contextmanager
def run_folder_lock(folder: Path) -> Iterator[None]:
    """An exclusive lock on the run folder, held while run.json is read, merged and written: two runs of
    different models into one folder at once each add their model instead of overwriting the other's. The lock
    is on the folder itself (flock on its descriptor), so no lock file is left in it; where the OS has no flock
    (Windows), runs into one folder must not overlap."""
    try:
        import fcntl
    except ImportError:  # pragma: no cover - not on the platforms the suite runs on
        yield
        return
    fd = os.open(folder, os.O_RDONLY)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        yield
    finally:
        os.close(fd)  # closing the descriptor releases the lock


def _write_run_file(plan: RunPlan, episodes: list[Episode], runs: list[ModelRun], settings, written_by: dict) -> None:
    """run.json, merged under the folder's lock with what is there now: the models that earlier runs, and
    runs going on at the same time, put into this folder and this run does not redo stay listed. ``runs``: the
    models this run has finished; the others of ``plan.models`` are listed under ``running_models`` until then
    (and stay there if the run is stopped), and the status is complete once no model is running. Another run
    that started meanwhile with another configuration is refused (check_run_folder), before this run writes.
    ``written_by``: ``provenance()``."""
    path = plan.out / RUN_FILE
    with run_folder_lock(plan.out):
        current = read_run_file(plan.out) or {}
        if current:
            _check_configuration(plan, episodes, current, "another run changed it meanwhile: ")
        done = {r.slug for r in runs}
        planned = {m.slug for m in plan.models}
        models = [m for m in current.get("models", []) if isinstance(m, dict) and m.get("slug") not in done]
        models += [_model_record(r) for r in runs]
        others = [s for s in current.get("running_models", []) if isinstance(s, str) and s not in planned]
        running = sorted(set(others) | (planned - done))
        doc = {
            "run_version": RUN_VERSION,
            "status": "running" if running else "complete",
            "updated": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
            "mode": plan.mode,
            "fixtures": str(plan.fixtures.resolve()),
            "episodes": [e.episode_id for e in episodes],
            "conditions": [c.name for c in plan.conditions],
            "models": models,
            **({"running_models": running} if running else {}),
            "backend_settings": _backend_settings_record(settings),
            "calls_per_episode_condition": {
                e.episode_id: calls_per_episode(len(e.frames), plan.pipeline.k) for e in episodes
            },
            **written_by,
        }
        atomic_write_text(path, json.dumps(doc, indent=1) + "\n")


MIN_EPISODES_PER_WORKER = 4  # a forked worker costs ~0.05 s; fewer episodes each are not worth one
# Episodes captioned together: their frames are read, and their requests built, one block at a time, so a run's
# memory does not grow with the set (the extended set's 216 episodes hold ~490 MB of PNG bytes). The shipped 22
# are one block; a larger set's batches for a model are made within a block (the same blocks every run).
EPISODES_PER_BLOCK = 24


@dataclass
class _Captioned:
    """One episode's transcripts and their files' texts, and on the first episode of each worker's part, the
    answering statistics of that worker (the other episodes' are None)."""

    transcripts: list[Transcript]
    files: dict[Path, str]
    stats: dict[str, int] | None


def caption_and_write(
    model: ModelRef, plan: RunPlan, episodes: list[Episode], peers: list[Episode], answerer: Answerer
) -> list[Transcript]:
    """Every (episode, condition) of ``model`` captioned and written to the run folder, in episode-major order.

    With pure answering (Answerer.pure) and more than one worker, the episodes are dealt out to forked workers
    (vlmproprio.parallel), each captioning its part and rendering its transcripts' text with the same answers one
    process would give. Everything is read and written here: the images before forking (so that the pixel
    ledger learns every frame it checked), the transcripts once every part is done (so that a failed part leaves
    the run folder as one process leaves it). The answerer's statistics are the sums of the workers'; a request
    that two workers' parts both make (none does in a run of distinct episodes) is counted by each. A progress
    bar shows this process's part. Episodes go ``EPISODES_PER_BLOCK`` at a time (images read per block)."""
    pipeline = plan.pipeline_for(model)
    chunk = answer_chunk(answerer.backend.max_batch_size)
    workers = resolve_workers(plan.workers) if answerer.pure else 1
    parent = os.getpid()
    start = dict(answerer.stats)
    blocks = [episodes[i : i + EPISODES_PER_BLOCK] for i in range(0, len(episodes), EPISODES_PER_BLOCK)]

    def caption(part: Sequence[Episode], images: dict, label: str) -> list[_Captioned]:
        before = dict(answerer.stats)
        transcripts = caption_episodes(
            part,
            plan.conditions,
            answerer.answer,
            model.slug,
            pipeline,
            peers=peers,
            chunk=chunk,
            progress=plan.progress and os.getpid() == parent,
            images=images,
            bar_label=label,
        )
        stats = {k: answerer.stats[k] - before[k] for k in before}
        by_episode: dict[str, list[Transcript]] = {}
        for t in transcripts:
            by_episode.setdefault(t.episode_id, []).append(t)
        return [
            _Captioned(
                by_episode.get(e.episode_id, []),
                transcript_files(plan.out, by_episode.get(e.episode_id, [])),
                stats if i == 0 else None,
            )
            for i, e in enumerate(part)
        ]

    done: list[_Captioned] = []
    for b, block in enumerate(blocks):
        images = episode_images(block)  # one block's frames in memory at a time, not the whole set's
        first = b * EPISODES_PER_BLOCK + 1
        label = f", episodes {first}-{first + len(block) - 1} of {len(episodes)}" if len(blocks) > 1 else ""
        done += map_groups(
            lambda part, images=images, label=label: caption(part, images, label),
            block,
            workers,
            lambda e: e.episode_id,
            min_chunk=MIN_EPISODES_PER_WORKER,
            what="episodes",
        )
        del images
    atomic_write_texts({path: text for d in done for path, text in d.files.items()})
    answerer.stats = {k: start[k] + sum(d.stats[k] for d in done if d.stats is not None) for k in start}
    return [t for d in done for t in d.transcripts]


def run_model(
    model: ModelRef, plan: RunPlan, episodes: list[Episode], peers: list[Episode], settings: BackendSettings
) -> ModelRun:
    pipeline = plan.pipeline_for(model)
    with open_answerer(model, plan.mode, settings, plan.cache_dir, allow_empty=plan.allow_empty_answers) as answerer:
        transcripts = caption_and_write(model, plan, episodes, peers, answerer)
    cassette = str(answerer.cassette) if answerer.cassette else None
    stats = dict(answerer.stats)
    return ModelRun(model, answerer.mode, pipeline.to_dict(), dict(answerer.identity), stats, transcripts, cassette)


# ---------------------------------------------------------------------------------------------- run folders


def read_run_file(run_dir: Path) -> dict | None:
    """RUN_DIR/run.json as a dict, None when there is none; a one-line error when it is damaged."""
    from vlmproprio.errors import VlmproprioError
    from vlmproprio.io import load_json

    path = Path(run_dir) / RUN_FILE
    if not path.is_file():
        return None
    data = load_json(path, error=VlmproprioError)
    if not isinstance(data, dict):
        raise VlmproprioError(f"{path}: run.json must be a JSON object")
    return data


def _differences(old: dict, new: dict) -> list[str]:
    keys = sorted(set(old) | set(new))
    return [f"{k} {old.get(k)!r} -> {new.get(k)!r}" for k in keys if old.get(k) != new.get(k)]


def _check_configuration(plan: RunPlan, episodes: list[Episode], old: dict, why: str = "") -> None:
    """Refuse, in one line starting ``why``, a run whose fixtures, episodes, conditions or per-model settings
    differ from those of the run.json ``old`` of its folder."""
    out = Path(plan.out)
    where = out / RUN_FILE
    fix = "choose another --out (nothing in " + str(out) + " is changed)"
    if old.get("fixtures") and Path(old["fixtures"]).resolve() != Path(plan.fixtures).resolve():
        raise UsageError(
            f"{why}{where} is a run on fixtures {old['fixtures']}, not {Path(plan.fixtures).resolve()}; {fix}"
        )
    want = {"episodes": [e.episode_id for e in episodes], "conditions": [c.name for c in plan.conditions]}
    for field_name, value in want.items():
        if field_name in old and old[field_name] != value:
            diff = _differences({"": old[field_name]}, {"": value})[0].strip()
            raise UsageError(f"{why}{where} is a run of other {field_name} ({diff}); {fix}")
    by_slug = {m.get("slug"): m for m in old.get("models", []) if isinstance(m, dict)}
    for model in plan.models:
        m = by_slug.get(model.slug)
        if m is None:
            continue
        if m.get("name") != model.name:
            raise UsageError(
                f"{why}{where}: model {model.name!r} would share the folder transcripts/{model.slug} with model "
                f"{m.get('name')!r} already there; {fix}"
            )
        if isinstance(m.get("pipeline"), dict) and m["pipeline"] != plan.pipeline_for(model).to_dict():
            diff = "; ".join(_differences(m["pipeline"], plan.pipeline_for(model).to_dict()))
            raise UsageError(f"{why}{where}: model {model.name!r} ran there with other settings ({diff}); {fix}")


def check_run_folder(plan: RunPlan, episodes: list[Episode]) -> None:
    """Whether this run may write into ``plan.out``.

    A run folder records its configuration (run.json). Running into it again with the same fixtures, episodes,
    conditions and per-model settings resumes or redoes it; another model with those settings is added to it,
    also by a run going on at the same time (run.json is merged under the folder's lock: _write_run_file).
    Anything else is refused in one line: the folder would otherwise mix transcripts of two configurations."""
    out = Path(plan.out)
    old = read_run_file(out)
    if old is None:
        if any((out / "transcripts").glob("*/*.json")):
            raise UsageError(
                f"{out} holds transcripts but no {RUN_FILE} (their configuration is unknown); choose another "
                f"--out (nothing in {out} is changed)"
            )
        return
    _check_configuration(plan, episodes, old)


def run(plan: RunPlan) -> list[ModelRun]:
    """Caption every (episode, condition) with every model; write transcripts and run.json."""
    slugs: dict[str, str] = {}
    for model in plan.models:
        if slugs.setdefault(model.slug, model.name) != model.name:
            raise UsageError(
                f"models {slugs[model.slug]!r} and {model.name!r} would share the folder transcripts/{model.slug}"
            )
    cache_dir = plan.cache_dir or default_cache_dir()
    refuse_nesting(Path(plan.fixtures), {"--out": plan.out, "--cache-dir": cache_dir})
    settings = replace(plan.backend or BackendSettings(), cassette_dir=Path(plan.fixtures) / "responses")
    peers = load_episodes(plan.fixtures)  # verifies every episode; both_shuffled may borrow from any of them
    if plan.episode_ids is None:
        episodes = peers
    else:
        by_id = {e.episode_id: e for e in peers}
        missing = [eid for eid in plan.episode_ids if eid not in by_id]
        if missing:
            hint = did_you_mean(missing[0], by_id)
            raise UsageError(
                f"unknown episode(s) {', '.join(missing)}{hint} in {plan.fixtures}; known: {', '.join(by_id)}"
            )
        episodes = [by_id[eid] for eid in plan.episode_ids]
    check_run_folder(plan, episodes)
    try:
        plan.out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:  # a file in the way, no permission: the user's --out, not a bug
        raise UsageError(
            f"cannot create run directory {plan.out}: {exc.strerror or exc}; choose another --out"
        ) from exc
    runs: list[ModelRun] = []
    written_by = provenance()
    _write_run_file(plan, episodes, runs, settings, written_by)
    # frames verified by an earlier run with this cache folder are not decoded again (episodes.pixel_ledger)
    with pixel_ledger(cache_dir / PIXEL_LEDGER_FILE):
        for model in plan.models:
            runs.append(run_model(model, plan, episodes, peers, settings))
            _write_run_file(plan, episodes, runs, settings, written_by)
    return runs
