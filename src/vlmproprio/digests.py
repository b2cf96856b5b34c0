"""The sha256 of a folder's files, remembered across processes for files that have not changed.

The sentence encoder's revision is the digest of its folder (all-MiniLM-L6-v2's weights): hashing it again in
every process that scores a run would be a noticeable share of a warm score (perf/machinery.py); a local model
folder's revision (vlmproprio.backends.hf_files) covers gigabytes of weights. So a digest is remembered in
``folder-digests.json`` in a folder the caller names (scoring: the embedding cache, whose keys the digest is part
of; a model's revision: the cache's models/ folder, under its own name and in its own layout, ``hasher``)
together with the identity of every file it covers (``file_signature``: device, inode, size,
mtime and ctime in nanoseconds). Writing a file's bytes changes its ctime, which no program can set back
(``touch``/``os.utime`` set mtime and change the ctime too), and replacing a file changes its inode; so any change
to a file is another signature, and its folder is hashed again. What this does not see is bytes changed under the
file system (a disk's bit rot): fixtures, whose bytes are checked for exactly that, are trusted within one process
only (vlmproprio.episodes.manifest).

As with git's index, a file changed within the same clock tick as its listing could keep its signature: a
listing with a file changed less than ``SETTLED_NS`` before it is never remembered on disk. A missing,
damaged or unwritable memo only means hashing; it never changes a digest.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import time
from collections.abc import Callable
from functools import lru_cache
from pathlib import Path

from vlmproprio.errors import VlmproprioError
from vlmproprio.io import WriteError, atomic_write_text, load_json

MEMO_FILE = "folder-digests.json"
MEMO_VERSION = 1
MAX_FOLDERS = 32  # remembered at once; the oldest is forgotten first
SETTLED_NS = 2_000_000_000  # a file changed less than this before it was listed is not remembered

Signature = tuple[int, int, int, int, int]  # device, inode, size, mtime_ns, ctime_ns
Listing = tuple[tuple, ...]  # (relative name, *Signature) per file
Hasher = Callable[[Path, Listing], str]  # the digest of a folder's listed files


def file_signature(st: os.stat_result) -> Signature:
    """What identifies a file's bytes without reading them: any write, truncation, rename onto or metadata change
    sets its ctime to the current time, which no program can set back."""
    return (st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns, st.st_ctime_ns)


def settled(signature: Signature, now_ns: int | None = None) -> bool:
    """Whether the file last changed SETTLED_NS or more ago: one changed within the timestamps' granularity of
    its listing could change again unseen, so it is not remembered."""
    now = time.time_ns() if now_ns is None else now_ns
    return now - max(signature[3], signature[4]) >= SETTLED_NS


def folder_listing(root: Path, files: list[Path]) -> Listing:
    """The name and signature of every file in ``files`` (paths under ``root``), in their order."""
    return tuple((p.relative_to(root).as_posix(), *file_signature(p.stat())) for p in files)


def hash_files(root: Path, listing: Listing) -> str:
    """sha256 over the relative name and bytes of each listed file, in order."""
    h = hashlib.sha256()
    for rel, *_ in listing:
        h.update(rel.encode() + b"\0")
        with open(root / rel, "rb") as f:
            for chunk in iter(lambda f=f: f.read(1 << 22), b""):
                h.update(chunk)
        h.update(b"\0")
    return h.hexdigest()


def _read_memo(path: Path) -> dict[str, dict]:
    try:
        data = load_json(path)
    except (OSError, VlmproprioError):
        return {}
    if not isinstance(data, dict) or data.get("version") != MEMO_VERSION or not isinstance(data.get("folders"), dict):
        return {}
    return data["folders"]


def _remembered(folders: dict[str, dict], key: str, listing: Listing) -> str | None:
    entry = folders.get(key)
    if not isinstance(entry, dict) or not isinstance(entry.get("digest"), str):
        return None
    stored = entry.get("listing")
    if not isinstance(stored, list) or [tuple(row) for row in stored if isinstance(row, list)] != list(listing):
        return None
    return entry["digest"]


def _remember(path: Path, key: str, listing: Listing, digest: str) -> None:
    folders = _read_memo(path)
    folders.pop(key, None)
    folders[key] = {"listing": [list(row) for row in listing], "digest": digest}
    while len(folders) > MAX_FOLDERS:
        folders.pop(next(iter(folders)))
    with contextlib.suppress(OSError, WriteError):  # a read-only cache: the digest is right, only not remembered
        atomic_write_text(path, json.dumps({"version": MEMO_VERSION, "folders": folders}) + "\n")


@lru_cache(maxsize=16)
def _digest(root: str, listing: Listing, memo: str | None, hasher: Hasher, name: str) -> str:
    key = os.path.realpath(root) + (f"#{name}" if name else "")  # one folder, several kinds of digest
    path = Path(memo) / MEMO_FILE if memo is not None else None
    digest = _remembered(_read_memo(path), key, listing) if path is not None else None
    if digest is None:
        digest = hasher(Path(root), listing)
        now = time.time_ns()
        if path is not None and all(settled(row[1:], now) for row in listing):
            _remember(path, key, listing, digest)
    return digest


def folder_digest(
    root: Path, files: list[Path], memo: Path | None = None, *, hasher: Hasher | None = None, name: str = ""
) -> str:
    """sha256 over the relative names and bytes of ``files`` (under ``root``, in order), or what ``hasher`` makes
    of their listing (a digest of another layout, remembered under ``name``). Hashed once per process for the
    same file signatures; with ``memo`` (a folder), once for all processes that name it."""
    memo_dir = str(memo) if memo is not None else None
    return _digest(str(root), folder_listing(root, files), memo_dir, hasher or hash_files, name)
