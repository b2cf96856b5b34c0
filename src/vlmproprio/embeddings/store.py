"""The embedding cache: (encoder key, text) -> float32 vector in a diskcache store of raw bytes (no pickles)."""

from __future__ import annotations

import hashlib
import json
from collections.abc import Iterable
from pathlib import Path

import numpy as np

from vlmproprio.embeddings.encoder import VECTOR_DTYPE, EmbeddingError


def text_key(encoder_key: str, text: str) -> str:
    return hashlib.sha256(json.dumps([encoder_key, text], ensure_ascii=False).encode("utf-8")).hexdigest()


def default_embedding_dir() -> Path:
    """<cache root>/embeddings (see vlmproprio.cache.cache_root)."""
    from vlmproprio.cache import cache_root

    return cache_root() / "embeddings"


class EmbeddingStore:
    """(encoder key, text) -> float32 vector, on disk, shared safely between processes (diskcache/SQLite).

    The folder is opened (created) on first use, not when the store is made: a score whose sidecars hold every
    vector never asks it, so it runs with a read-only or unwritable cache folder."""

    def __init__(self, directory: str | Path):
        self.directory = Path(directory)
        self._opened = None

    @property
    def _cache(self):
        if self._opened is None:
            from vlmproprio.stores import BYTES_VALUES, open_store

            self._opened = open_store(
                self.directory, BYTES_VALUES, error=EmbeddingError, what="embedding cache", size_limit=2**40
            )
        return self._opened

    def close(self) -> None:
        if self._opened is not None:
            self._opened.close()
            self._opened = None

    def __enter__(self) -> EmbeddingStore:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def get_many(self, encoder_key: str, texts: Iterable[str]) -> dict[str, np.ndarray]:
        out = {}
        for text in texts:
            data = self._cache.get(text_key(encoder_key, text))
            if data is not None:
                if len(data) % VECTOR_DTYPE.itemsize:
                    raise EmbeddingError(f"{self.directory}: corrupt vector for {text[:40]!r}; delete the folder")
                out[text] = np.frombuffer(data, dtype=VECTOR_DTYPE)
        return out

    def put_many(self, encoder_key: str, vectors: dict[str, np.ndarray]) -> None:
        for text, vec in vectors.items():
            if not isinstance(text, str) or not isinstance(vec, np.ndarray) or vec.ndim != 1:
                raise EmbeddingError(f"embedding cache values are 1-d float vectors keyed by text, got {type(vec)}")
        from vlmproprio.io import writing

        with writing(self.directory, "store embeddings in cache"), self._cache.transact():
            for text, vec in vectors.items():
                self._cache.set(text_key(encoder_key, text), np.ascontiguousarray(vec, dtype=VECTOR_DTYPE).tobytes())

    def __len__(self) -> int:
        return len(self._cache)
