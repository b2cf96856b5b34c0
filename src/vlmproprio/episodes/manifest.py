"""The fixture manifest: ``<root>/manifest.json`` holds the sha256 of every file under ``<root>``, so a
changed, missing or extra file is an error that names it."""

from __future__ import annotations

import hashlib
import json
import os
from collections.abc import Iterable
from pathlib import Path

from vlmproprio.digests import file_signature, settled
from vlmproprio.episodes.types import FORMAT_VERSION, MANIFEST_NAME, EpisodeError
from vlmproprio.io import (
    JSONLoadError,
    atomic_write_bytes,
    atomic_write_text,
    atomic_write_together,
    load_json,
    sha256_file,
    special_kind,
)


def link_error(path: Path) -> EpisodeError:
    """The one rule for symbolic links inside a fixture folder (manifest, verify and run all apply it): refused,
    since the manifest vouches for the files in the folder, and a link's target can change behind it."""
    return EpisodeError(
        f"{path}: a symbolic link inside the fixture folder; copy what it points to in instead (the manifest "
        "vouches only for files the folder holds)"
    )


def check_no_links(root: Path, path: Path) -> None:
    """EpisodeError when ``path`` or a folder between ``root`` and it is a symbolic link (``root`` itself may be)."""
    for part in (path, *path.parents):
        if part == root or root not in part.parents:
            return
        if part.is_symlink():
            raise link_error(part)


def _fixture_files(root: Path) -> list[str]:
    """The files under ``root`` a manifest lists (not hidden ones, not the manifest), as sorted relative paths;
    a symbolic link anywhere below ``root`` is an EpisodeError (``link_error``)."""
    found = []
    for folder, dirs, names in os.walk(root, onerror=None, followlinks=False):
        here = Path(folder)
        for name in (*dirs, *names):
            if os.path.islink(here / name) and not name.startswith("."):
                raise link_error(here / name)
        for name in names:  # a FIFO or device among the files: named, not taken for a missing file
            kind = special_kind(here / name)
            if kind is not None and not name.startswith("."):
                raise EpisodeError(f"{here / name}: {kind} inside the fixture folder, not a regular file")
        found += [
            (here / n).relative_to(root).as_posix()
            for n in names
            if n != MANIFEST_NAME and not n.startswith(".") and (here / n).is_file()
        ]
    return sorted(found)


def build_manifest(root: Path) -> dict:
    root = Path(root)
    files = {rel: sha256_file(root / rel) for rel in _fixture_files(root)}
    return {"format_version": FORMAT_VERSION, "files": files}


def write_manifest(root: Path) -> Path:
    path = Path(root) / MANIFEST_NAME
    atomic_write_text(path, json.dumps(build_manifest(root), indent=1, sort_keys=True) + "\n")
    return path


def _manifest_text(files: dict[str, str]) -> str:
    doc = {"format_version": FORMAT_VERSION, "files": dict(sorted(files.items()))}
    return json.dumps(doc, indent=1, sort_keys=True) + "\n"


def update_manifest(root: Path, rel_paths: Iterable[str]) -> Path:
    """Re-hash only the named files (dropping those that no longer exist).

    Writing a cassette must not bless unrelated changes elsewhere in the fixtures, which rewriting the
    whole manifest would do."""
    root = Path(root)
    files = dict(read_manifest(root))
    for rel in rel_paths:
        path = root / rel
        if path.is_file():
            files[rel] = sha256_file(path)
        else:
            files.pop(rel, None)
    path = root / MANIFEST_NAME
    atomic_write_text(path, _manifest_text(files))
    return path


def fixture_manifest_of(path: Path) -> Path | None:
    """The manifest of the fixture set whose sub-folder holds ``path`` (``<fixtures>/responses/x`` ->
    ``<fixtures>/manifest.json``), None when the folder above holds none."""
    manifest = Path(path).resolve().parent.parent / MANIFEST_NAME
    return manifest if manifest.is_file() else None


def write_fixture_file(path: Path, data: bytes) -> Path | None:
    """Write ``data`` to ``path`` and, when ``path`` lies in a fixture set's sub-folder (a cassette or sidecar
    in ``<fixtures>/responses/``), its new sha256 into the manifest, together (io.atomic_write_together): a
    failure such as a full disk changes neither, so ``verify`` never finds one without the other. Returns the
    manifest updated, or None. Only this file's entry changes: unrelated edits elsewhere stay unblessed."""
    path = Path(path)
    manifest = fixture_manifest_of(path)
    if manifest is None:
        atomic_write_bytes(path, data)
        return None
    root = manifest.parent
    files = dict(read_manifest(root))
    files[path.resolve().relative_to(root).as_posix()] = hashlib.sha256(data).hexdigest()
    atomic_write_together({path: data, manifest: _manifest_text(files).encode("utf-8")})
    return manifest


def check_fixture_file(path: Path) -> None:
    """A file of a fixture set's sub-folder (a cassette in ``<fixtures>/responses/``) must be the one the
    manifest above it lists: a line edited and re-checksummed is caught before replay uses it. Files outside
    a fixture set (no manifest two levels up) are not checked."""
    path = Path(path).resolve()
    root = path.parent.parent
    if not (root / MANIFEST_NAME).is_file():
        return
    rel = path.relative_to(root).as_posix()
    files = read_manifest(root)
    if rel not in files:
        raise EpisodeError(
            f"{path}: not in {root / MANIFEST_NAME}; a recording registers its cassette there "
            "(`vlmproprio run --model MODEL --mode record` or `vlmproprio cassette export --model MODEL`)"
        )
    if sha256_file(path) != files[rel]:
        raise EpisodeError(
            f"{path}: sha256 differs from {root / MANIFEST_NAME} (changed after it was recorded); restore it "
            f"(`git checkout -- {path}`) or record it again"
        )


def read_manifest(root: Path) -> dict[str, str]:
    path = Path(root) / MANIFEST_NAME
    if not path.is_file():
        raise EpisodeError(
            f"{path}: manifest missing (run `vlmproprio manifest --fixtures {root}` after changing fixtures)"
        )
    try:
        data = load_json(path)
        files = data["files"]
        if not isinstance(files, dict):
            raise TypeError("'files' is not an object")
    except JSONLoadError as exc:
        raise EpisodeError(f"{path}: not a valid manifest ({exc.detail})") from exc
    except (ValueError, KeyError, TypeError) as exc:
        raise EpisodeError(f"{path}: not a valid manifest ({exc})") from exc
    return files


# sha256 of the fixture files hashed in this process, by absolute path, with the stat signature the file had
# (see _file_sha256). A run then a score in one process, or the three loads of a benchmark, hash 50 MB once.
_FILE_DIGESTS: dict[str, tuple[tuple[int, ...], str]] = {}


def _file_sha256(path: Path) -> str:
    """``sha256_file(path)``, hashed again only when the file may have changed since this process hashed it.

    An unchanged signature (vlmproprio.digests.file_signature) means the same bytes; a file that changed just
    before it was hashed is not remembered (digests.settled). Within one process only: the fixtures' bytes are
    checked for corruption under the file system too, which no signature shows."""
    key = os.path.abspath(path)
    sig = file_signature(os.stat(key))
    known = _FILE_DIGESTS.get(key)
    if known is not None and known[0] == sig:
        return known[1]
    digest = sha256_file(key)
    if settled(sig):
        _FILE_DIGESTS[key] = (sig, digest)
    return digest


def verify_files(root: Path, prefix: str = "", manifest: dict[str, str] | None = None) -> int:
    """Check every file under ``root/prefix`` against the manifest; return how many were checked.

    Raises EpisodeError naming the first file that is changed, missing or not in the manifest."""
    if prefix and not prefix.endswith("/"):
        raise ValueError("prefix must end with '/'")
    root = Path(root)
    manifest = read_manifest(root) if manifest is None else manifest
    expected = {k: v for k, v in manifest.items() if k.startswith(prefix)}
    here = root / prefix
    check_no_links(root, here)
    present = {prefix + rel for rel in _fixture_files(here)} if here.is_dir() else set()
    for rel in sorted(present - expected.keys()):
        raise EpisodeError(f"{root / rel}: extra file, not in {root / MANIFEST_NAME}")
    for rel in sorted(expected.keys() - present):
        raise EpisodeError(f"{root / rel}: missing (listed in {root / MANIFEST_NAME})")
    for rel in sorted(expected):
        if _file_sha256(root / rel) != expected[rel]:
            raise EpisodeError(f"{root / rel}: sha256 differs from {root / MANIFEST_NAME} (file changed or corrupt)")
    return len(expected)
