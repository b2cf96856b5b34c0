"""Texts to vectors: a cassette's sidecar first, then the cache, then the encoder (loaded only for what is
missing); which encoder a torch-free install scores with."""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from vlmproprio.embeddings.encoder import (
    BATCHING_SCHEME,
    DEFAULT_BATCH_SIZE,
    DEFAULT_ENCODER_NAME,
    DEFAULT_ENCODER_PACKAGE,
    DEFAULT_THREADS,
    EmbeddingError,
    EncoderSpec,
    SentenceEncoder,
    default_encoder_installed,
    encoder_spec,
)
from vlmproprio.embeddings.sidecar import Sidecar, text_digest
from vlmproprio.embeddings.store import EmbeddingStore


def resolve_encoder(
    sidecars: Sequence[Sidecar] = (),
    *,
    batch_size: int = DEFAULT_BATCH_SIZE,
    threads: int = DEFAULT_THREADS,
    memo_dir: Path | None = None,
) -> EncoderSpec:
    """The default encoder: from its package when installed (its digest remembered in ``memo_dir``, see
    folder_revision), else as the sidecars record it.

    A torch-free install (the ``bench`` extra) has neither the encoder nor torch; the sidecars name the
    encoder their vectors came from, so scores keep the same encoder key and bits. Any text they lack then
    fails with a message saying how to get it, instead of silently using another encoder."""
    if default_encoder_installed():
        return encoder_spec(batch_size=batch_size, threads=threads, memo_dir=memo_dir)
    recorded = {
        sec.key: sec.encoder
        for sc in sidecars
        for sec in sc.sections.values()
        if sec.encoder["name"] == DEFAULT_ENCODER_NAME
        and sec.encoder["batch_size"] == batch_size
        and sec.encoder["batching"] == BATCHING_SCHEME
    }
    if len(recorded) == 1:
        enc = next(iter(recorded.values()))
        return EncoderSpec(name=enc["name"], path="", revision=enc["revision"], batch_size=batch_size, threads=threads)
    if recorded:
        raise EmbeddingError(
            f"the sidecars hold several revisions of {DEFAULT_ENCODER_NAME} ({', '.join(sorted(recorded))}); "
            f"install {DEFAULT_ENCODER_PACKAGE} (pip install 'vlmproprio[embed]') to choose"
        )
    return encoder_spec(batch_size=batch_size, threads=threads)  # raises, saying how to install it


@dataclass
class EmbedStats:
    requested: int = 0
    sidecar: int = 0  # found in a cassette's sidecar
    cached: int = 0  # found in the embedding cache
    computed: int = 0
    load_s: float = 0.0
    encode_s: float = 0.0
    torch_loaded: bool = False

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass
class CachedEmbedder:
    """Embeds texts through the store, loading the encoder only for texts not cached yet."""

    spec: EncoderSpec
    store: EmbeddingStore
    stats: EmbedStats = field(default_factory=EmbedStats)
    _encoder: SentenceEncoder | None = None
    sidecar: Mapping[str, np.ndarray] = field(default_factory=dict)  # {text digest: vector} for spec.key

    def embed(self, texts: Iterable[str]) -> dict[str, np.ndarray]:
        unique = list(dict.fromkeys(texts))
        found: dict[str, np.ndarray] = {}
        if self.sidecar:
            for t in unique:
                vec = self.sidecar.get(text_digest(t))
                if vec is not None:
                    found[t] = vec
        rest = [t for t in unique if t not in found]
        stored = self.store.get_many(self.spec.key, rest) if rest else {}
        found.update(stored)
        missing = [t for t in rest if t not in stored]
        self.stats.requested += len(unique)
        self.stats.sidecar += len(unique) - len(rest)
        self.stats.cached += len(stored)
        if missing:
            if not self.spec.path:  # an encoder known only from a sidecar (torch-free install)
                raise EmbeddingError(
                    f"{len(missing)} caption(s) have no stored embedding (first: {missing[0][:60]!r}) and the "
                    f"encoder {self.spec.name} is not installed: pip install 'vlmproprio[embed]', or rebuild the "
                    "model's sidecar where it is (`vlmproprio cassette embed --model MODEL`)"
                )
            if self._encoder is None:
                self._encoder = SentenceEncoder(self.spec)
            vecs = self._encoder.encode(missing)
            new = {t: vecs[i] for i, t in enumerate(missing)}
            self.store.put_many(self.spec.key, new)
            found.update(new)
            self.stats.computed += len(missing)
            self.stats.load_s = self._encoder.load_s
            self.stats.encode_s = self._encoder.encode_s
            self.stats.torch_loaded = True
        dims = {v.shape[0] for v in found.values()}
        if len(dims) > 1:
            raise EmbeddingError(f"{self.store.directory}: vectors of several sizes {sorted(dims)} for {self.spec.key}")
        return found
