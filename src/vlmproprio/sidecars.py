"""A model's caption embeddings beside its cassette: which captions, embedded by which encoder, written where.

A cassette's answers are fixed, so the frame captions scoring embeds are fixed too, and so are their
vectors. ``build_sidecar`` stores them in ``<fixtures>/responses/<model slug>.embeddings.npz`` (format:
``vlmproprio.embeddings.write_sidecar``) and updates the fixtures' manifest; ``score_run`` reads the sidecars
of a run's models before it looks for an encoder, so replaying and scoring the benchmark needs no torch.

Which captions: those of a replay run of the model over every episode and condition of the fixtures with the
benchmark's settings (what ``pytest benchmark/`` and ``vlmproprio run --model MODEL --mode replay`` score), or those of
given run folders. The ``reference`` captioner has no cassette (it is computed, deterministically, from the
states), but its captions are as fixed as a cassette's, so it gets a sidecar the same way.

After a run that recorded answers, ``embed_recorded`` adds their new captions to each recorded model's sidecar
(what ``vlmproprio run --model MODEL --mode record`` does once the run is written).
"""

from __future__ import annotations

import logging
import tempfile
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from vlmproprio.embeddings import (
    CachedEmbedder,
    EmbeddingError,
    EmbeddingStore,
    EncoderSpec,
    default_embedding_dir,
    default_encoder_installed,
    encoder_spec,
    merge_sections,
    read_sidecar,
    sidecar_path,
    sidecar_section,
    write_sidecar,
)
from vlmproprio.episodes import fixture_manifest_of, load_episodes, sha256_file
from vlmproprio.errors import VlmproprioError
from vlmproprio.evaluation import frame_texts
from vlmproprio.models import ModelRef, resolve_model
from vlmproprio.transcripts import read_transcripts, transcript_path

if TYPE_CHECKING:
    from vlmproprio.runner import ModelRun

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class SidecarBuild:
    path: Path
    texts: int  # captions in this encoder's section now
    computed: int  # of which the encoder computed now (the rest came from the embedding cache)
    manifest: Path | None  # the manifest updated, if the folder above holds one


def run_caption_texts(run_dir: str | Path, fixtures: str | Path, slug: str) -> set[str]:
    """The frame captions of ``slug`` in a run folder that scoring embeds (present ones, as score_run reads them)."""
    run_dir = Path(run_dir)
    transcripts = read_transcripts(run_dir, slug)
    if not transcripts:
        raise VlmproprioError(f"{run_dir / 'transcripts' / slug}: no transcripts of model {slug}")
    ids = sorted({t.episode_id for t in transcripts})
    frames = {e.episode_id: len(e.frames) for e in load_episodes(fixtures, ids, verify=False)}
    texts: set[str] = set()
    for t in transcripts:
        where = str(transcript_path(run_dir, t.model, t.episode_id, t.condition))
        captions, statuses = frame_texts(t, frames[t.episode_id], where)
        texts.update(x for x, s in zip(captions, statuses, strict=True) if s != "missing")
    return texts


def benchmark_caption_texts(model: str | ModelRef, fixtures: str | Path, *, progress: bool = False) -> set[str]:
    """The frame captions of a replay of ``model`` over every episode and condition of ``fixtures``."""
    from vlmproprio.backends.settings import BackendSettings
    from vlmproprio.conditions import parse_conditions
    from vlmproprio.runner import RunPlan, run

    ref = resolve_model(model)

    with tempfile.TemporaryDirectory(prefix="vlmproprio-embed-") as tmp:
        out = Path(tmp) / "run"
        plan = RunPlan(
            models=(ref,),
            conditions=tuple(parse_conditions("all")),
            fixtures=Path(fixtures),
            out=out,
            mode="replay",
            backend=BackendSettings.of(threads=1),  # as the benchmark runs it
            progress=progress,
        )
        run(plan)
        return run_caption_texts(out, fixtures, ref.slug)


def _existing_sections(path: Path, merge: bool) -> dict:
    if not path.is_file():
        return {}
    try:
        return dict(read_sidecar(path).sections)
    except EmbeddingError:
        if merge:
            raise
        log.warning("%s is damaged: rebuilding it from scratch (other encoders' vectors in it are lost)", path)
        return {}


def build_sidecar(
    model: str | ModelRef,
    fixtures: str | Path,
    spec: EncoderSpec,
    texts: Iterable[str],
    *,
    merge: bool = False,
    embedding_cache: str | Path | None = None,
) -> SidecarBuild:
    """Embed ``texts`` with ``spec`` and store them in the model's sidecar, keeping other encoders' sections.

    ``merge=False`` replaces this encoder's section (a rebuild: vectors of captions the cassette no longer
    produces go); ``merge=True`` adds to it (after recording part of the benchmark)."""
    ref = resolve_model(model)
    slug = ref.slug
    responses = Path(fixtures) / "responses"
    path = sidecar_path(responses, slug)
    cache_dir = Path(embedding_cache) if embedding_cache is not None else default_embedding_dir()
    with EmbeddingStore(cache_dir) as store:
        embedder = CachedEmbedder(spec, store)
        vectors = embedder.embed(sorted(set(texts)))
    section = sidecar_section(spec, vectors)
    sections = _existing_sections(path, merge)
    if merge and section.key in sections:
        section = merge_sections(sections[section.key], section)
    sections[section.key] = section
    cassette = ref.cassette(responses)
    source = {"model": ref.name, "cassette_sha256": sha256_file(cassette) if cassette.is_file() else None}
    write_sidecar(path, slug, sections.values(), source)
    manifest = fixture_manifest_of(path)  # written with the sidecar (write_sidecar)
    return SidecarBuild(path, len(section.digests), embedder.stats.computed, manifest)


def embed_recorded(
    runs: Iterable[ModelRun], run_dir: Path, fixtures: Path
) -> Iterator[tuple[str, SidecarBuild | None]]:
    """After a run that recorded answers: add each recorded model's new captions to its sidecar, yielding (model
    name, build) as each is done; the build is None when the encoder is not installed (the sidecar is left as it
    was). Models that replayed or ran live are skipped: their cassette did not change."""
    for r in runs:
        if r.mode != "record":
            continue
        if not default_encoder_installed():
            yield r.name, None
            continue
        texts = run_caption_texts(run_dir, fixtures, r.slug)
        yield r.name, build_sidecar(r.name, fixtures, encoder_spec(), texts, merge=True)
