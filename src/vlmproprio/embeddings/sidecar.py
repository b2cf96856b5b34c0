"""A cassette's caption vectors beside it: ``<model>.embeddings.npz``, per encoder key the sha256 of every
caption and its float32 vector, written with fixed zip dates and order so the same vectors give the same bytes."""

from __future__ import annotations

import hashlib
import io
import itertools
import json
import zipfile
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from vlmproprio.embeddings.encoder import VECTOR_DTYPE, EmbeddingError, EncoderSpec
from vlmproprio.io import ReadError, read_npz

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
    """Write (atomically, with its fixture manifest entry: episodes.write_fixture_file) an .npz that ``np.load(path, allow_pickle=False)`` reads: a JSON header (a 0-d
    unicode array) and per encoder ``digests_<i>`` (<U64) and ``vectors_<i>`` (<f4), sections in key order."""
    from vlmproprio.episodes import write_fixture_file

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
    # with its manifest entry when it lies in a fixture set: a full disk leaves both as they were
    write_fixture_file(Path(path), buf.getvalue())
    return Path(path)


def read_sidecar(path: str | Path) -> Sidecar:
    """Load and verify a sidecar; anything wrong is an EmbeddingError naming the file. Never unpickles."""
    path = Path(path)

    def bad(why: str) -> EmbeddingError:
        return EmbeddingError(f"{path}: {why}; rebuild it with `vlmproprio cassette embed --model MODEL`")

    try:
        arrays = read_npz(path)
    except FileNotFoundError as exc:
        raise EmbeddingError(f"{path}: embeddings sidecar not found") from exc
    except ReadError as exc:
        raise bad(f"not a readable embeddings sidecar ({exc.detail})") from exc
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
