"""The frame captions of a run, aligned with their episodes' frames and embedded (sidecars, then the cache, then
the encoder)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from vlmproprio.embeddings import default_embedding_dir
from vlmproprio.evaluation.inputs import RunInputs, ScoreRunError, frame_texts
from vlmproprio.transcripts import transcript_path

Cell = tuple[str, str, str]  # (model, episode id, condition)


@dataclass
class EmbeddedCaptions:
    """Per cell the frame texts and statuses aligned with frames 0..n-1, and the vector of every present text."""

    frames: dict[Cell, tuple[list[str], list[str]]]
    vectors: dict[str, np.ndarray]
    encoder: dict  # the encoder spec (embeddings.EncoderSpec.to_dict)
    embedding_stats: dict  # where the vectors came from (embeddings.EmbedStats.to_dict)
    cache_dir: Path  # the embedding cache; the chance cache defaults to a folder beside it


def align_frames(inputs: RunInputs) -> dict[Cell, tuple[list[str], list[str]]]:
    """Every transcript's frame captions by frame index; a one-line error for a transcript of another task."""
    aligned = {}
    for t in inputs.transcripts:
        where = str(transcript_path(inputs.run_dir, t.model, t.episode_id, t.condition))
        ep = inputs.episodes[t.episode_id]
        if t.task != ep.task:
            raise ScoreRunError(f"{where}: task {t.task!r} but episode {ep.episode_id} is {ep.task!r}")
        aligned[(t.model, t.episode_id, t.condition)] = frame_texts(t, len(ep.frames), where)
    return aligned


def embed_captions(
    inputs: RunInputs,
    encoder,
    embedding_cache: str | Path | None,
    sidecars: Sequence[str | Path] | None,
) -> EmbeddedCaptions:
    """Embed every distinct present frame caption of the run once (see score_run for the arguments)."""
    from vlmproprio.embeddings import (
        CachedEmbedder,
        EmbeddingStore,
        load_sidecars,
        read_sidecar,
        resolve_encoder,
        sidecar_vectors,
    )
    from vlmproprio.locations import refuse_nesting

    if sidecars is None:
        stored = load_sidecars(inputs.fixtures / "responses", {t.model for t in inputs.transcripts})
    else:
        stored = [read_sidecar(p) for p in sidecars]
    cache_dir = Path(embedding_cache) if embedding_cache is not None else default_embedding_dir()
    refuse_nesting(inputs.fixtures, {"RUN_DIR": inputs.run_dir, "--embedding-cache": cache_dir})
    spec = encoder if encoder is not None else resolve_encoder(stored, memo_dir=cache_dir)
    aligned = align_frames(inputs)
    all_texts = sorted({x for texts, st in aligned.values() for x, s in zip(texts, st, strict=True) if s != "missing"})
    with EmbeddingStore(cache_dir) as store:
        embedder = CachedEmbedder(spec, store, sidecar=sidecar_vectors(stored, spec.key))
        vectors = embedder.embed(all_texts)
    return EmbeddedCaptions(aligned, vectors, spec.to_dict(), embedder.stats.to_dict(), cache_dir)
