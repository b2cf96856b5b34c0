"""Every file vlmproprio writes, and every JSON document it reads, goes through here.

* ``atomic_write_bytes`` / ``atomic_write_text``: a temp file in the same folder, fsync, rename, so a reader
  never sees half a file; texts pass the secret scrubber first (``vlmproprio.secrets``).
* ``atomic_write_together``: files that must change together, all written before any is renamed into place.
* ``writing(path)``: turns an OSError (read-only folder, no permission, disk full) or an SQLite write error
  ("database or disk is full", "attempt to write a readonly database") into one ``WriteError`` line naming
  the path and the cause. Nothing half-written stays behind: the temp file is removed.
* ``load_json`` / ``loads_json``: size and nesting-depth limits, one ``JSONLoadError`` line naming the file
  (never a ``RecursionError`` from ``[`` x 100 000).
"""

from __future__ import annotations

import contextlib
import errno
import hashlib
import json
import os
import sqlite3
import tempfile
from collections.abc import Callable, Iterator, Mapping
from pathlib import Path

from vlmproprio.errors import VlmproprioError

# A fixture's episode.json is ~100 KB, scores/sweep.json a few MB, a cassette line a few KB: 256 MiB is
# far above anything the suite writes and far below what would exhaust memory.
MAX_JSON_BYTES = 256 * 1024 * 1024
# The deepest document the suite writes is ~6 levels (audit.json); 64 leaves room and stays far from
# Python's recursion limit in any code that walks a document.
MAX_JSON_DEPTH = 64

_SQLITE_WRITE_ERRORS = ("disk is full", "readonly", "read-only", "disk i/o error", "unable to open")


class WriteError(VlmproprioError):
    """A file or database that cannot be written (read-only folder, no space, ...); names path and cause."""


class JSONLoadError(VlmproprioError):
    """A JSON document that cannot be read: malformed, too large or nested too deeply; names the file."""


# ---------------------------------------------------------------------------------------------- write errors


def _cause(exc: BaseException) -> str:
    if isinstance(exc, OSError):
        name = errno.errorcode.get(exc.errno or -1, "")
        text = exc.strerror or str(exc)
        return f"{text} ({name})" if name else text
    return str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__


def is_write_failure(exc: BaseException) -> bool:
    """True for the OS and SQLite errors that mean "cannot write here" rather than a bug."""
    if isinstance(exc, sqlite3.OperationalError | sqlite3.DatabaseError):
        return any(s in str(exc).lower() for s in _SQLITE_WRITE_ERRORS)
    return isinstance(exc, OSError)


def write_error(path: Path | str, exc: BaseException, what: str = "write") -> WriteError:
    """The one-line error for a failed write of ``path``."""
    return WriteError(f"cannot {what} {path}: {_cause(exc)}")


@contextlib.contextmanager
def writing(path: Path | str, what: str = "write") -> Iterator[None]:
    """Turn OS and SQLite write errors raised inside the block into a one-line WriteError naming ``path``."""
    try:
        yield
    except VlmproprioError:
        raise
    except (OSError, sqlite3.Error) as exc:
        if not is_write_failure(exc):
            raise
        raise write_error(path, exc, what) from exc


def make_dirs(path: Path | str) -> Path:
    path = Path(path)
    with writing(path, "create folder"):
        path.mkdir(parents=True, exist_ok=True)
    return path


# ---------------------------------------------------------------------------------------------- atomic writes


def atomic_write_bytes(path: Path | str, data: bytes) -> str:
    """Write via a temp file in the same folder and rename; returns the sha256 of what was written.

    A failure (read-only folder, full disk) is a WriteError and leaves neither the temp file nor a
    half-written target; an existing target keeps its old content."""
    path = Path(path)
    tmp: str | None = None
    try:
        with writing(path):
            path.parent.mkdir(parents=True, exist_ok=True)
            fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
            with os.fdopen(fd, "wb") as f:
                f.write(data)
                f.flush()
                os.fsync(f.fileno())
            os.chmod(tmp, 0o644)  # mkstemp makes owner-only files; results are meant to be shared
            os.replace(tmp, path)
            tmp = None
    finally:
        if tmp is not None:
            Path(tmp).unlink(missing_ok=True)
    return hashlib.sha256(data).hexdigest()


def atomic_write_together(files: Mapping[Path, bytes]) -> dict[Path, str]:
    """Write several files that must change together (a cassette and the manifest entry that blesses it):
    every one goes to a temp file beside its target first (fsynced), and only once all are written are they
    renamed over their targets. A failure while writing (a full disk) is a WriteError naming the file and
    leaves every target as it was and no temp file behind; path -> sha256 of the bytes written.

    The renames are not one atomic step: a kill between two of them (microseconds, after every byte is on
    disk) can still leave the first target new and the next old."""
    temps: dict[Path, str] = {}
    try:
        for path, data in files.items():
            with writing(path):
                path.parent.mkdir(parents=True, exist_ok=True)
                fd, temps[path] = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
                with os.fdopen(fd, "wb") as f:
                    f.write(data)
                    f.flush()
                    os.fsync(f.fileno())
                os.chmod(temps[path], 0o644)
        for path in list(temps):
            with writing(path):
                os.replace(temps[path], path)
            del temps[path]
    finally:
        for tmp in temps.values():
            Path(tmp).unlink(missing_ok=True)
    return {path: hashlib.sha256(data).hexdigest() for path, data in files.items()}


def atomic_write_text(path: Path | str, text: str) -> str:
    """Scrub secrets from ``text``, write it as UTF-8 atomically; returns the sha256 of the bytes written."""
    from vlmproprio.secrets import scrub

    return atomic_write_bytes(path, scrub(text).encode("utf-8"))


WRITERS = 4  # threads writing files at once: creating and fsyncing files waits on the disk, not the interpreter


def atomic_write_texts(files: Mapping[Path, str]) -> dict[Path, str]:
    """``atomic_write_text`` for each path -> text, several at a time (a run's ~200 transcripts or a score's 16
    files are ~2 ms of file creation and fsync each, which threads overlap); path -> sha256 of the bytes written.
    Each file is still written atomically on its own; the first failure, in ``files`` order, is raised once
    every write has finished or failed."""
    if len(files) < 2:
        return {path: atomic_write_text(path, text) for path, text in files.items()}
    from concurrent.futures import ThreadPoolExecutor

    with ThreadPoolExecutor(max_workers=WRITERS, thread_name_prefix="writers") as pool:
        futures = {path: pool.submit(atomic_write_text, path, text) for path, text in files.items()}
    return {path: f.result() for path, f in futures.items()}


def text_computed_once(lock: Path, done: Path, compute: Callable[[], str]) -> str:
    """The text ``compute()`` returns, computed by the first process to take an exclusive lock on ``lock`` and
    kept in ``done``; a process that comes later waits for the lock and reads ``done``. For work several
    processes of one session (pytest-xdist workers) need once. A failure writes nothing: the next process tries
    again and fails the same way."""
    from filelock import FileLock

    with FileLock(lock):
        if not done.is_file():
            atomic_write_text(done, compute())
        return done.read_text(encoding="utf-8")


def sha256_file(path: Path | str) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


# ---------------------------------------------------------------------------------------------- bounded JSON


def _too_deep(obj: object, limit: int) -> bool:
    """Iteratively (no recursion) whether ``obj`` nests containers deeper than ``limit``."""
    stack: list[tuple[object, int]] = [(obj, 1)]
    while stack:
        node, depth = stack.pop()
        if depth > limit:
            return True
        if isinstance(node, dict):
            stack.extend((v, depth + 1) for v in node.values() if isinstance(v, dict | list))
        elif isinstance(node, list):
            stack.extend((v, depth + 1) for v in node if isinstance(v, dict | list))
    return False


def loads_json(
    text: str | bytes,
    where: str | Path,
    *,
    max_bytes: int = MAX_JSON_BYTES,
    max_depth: int = MAX_JSON_DEPTH,
    error: type[VlmproprioError] = JSONLoadError,
):
    """Parse one JSON document; ``error`` (one line naming ``where``) when malformed, too big or too deep.

    The error's ``detail`` attribute holds the message without ``where``, for callers that phrase their own."""

    def fail(detail: str) -> VlmproprioError:
        exc = error(f"{where}: {detail}")
        exc.detail = detail  # type: ignore[attr-defined]
        return exc

    if len(text) > max_bytes:
        raise fail(f"{len(text):,} bytes of JSON, more than the {max_bytes:,} allowed")
    try:
        if isinstance(text, bytes):
            text = text.decode("utf-8")
        obj = json.loads(text)
    except RecursionError:
        raise fail(f"JSON nested too deeply (limit {max_depth} levels); the file is damaged") from None
    except (UnicodeDecodeError, ValueError) as exc:
        raise fail(f"not valid JSON ({exc})") from exc
    # a document cannot nest deeper than it has opening brackets (a cassette line has a handful): walk it only then
    if isinstance(obj, dict | list) and text.count("[") + text.count("{") > max_depth and _too_deep(obj, max_depth):
        raise fail(f"JSON nested too deeply (limit {max_depth} levels); the file is damaged")
    return obj


def load_json(
    path: Path | str,
    *,
    max_bytes: int = MAX_JSON_BYTES,
    max_depth: int = MAX_JSON_DEPTH,
    error: type[VlmproprioError] = JSONLoadError,
):
    """Read and parse a JSON file with the limits of ``loads_json``; FileNotFoundError passes through."""
    path = Path(path)
    try:
        size = path.stat().st_size
        if size > max_bytes:
            raise error(f"{path}: {size:,} bytes of JSON, more than the {max_bytes:,} allowed")
        data = path.read_bytes()
    except FileNotFoundError:
        raise
    except OSError as exc:
        raise error(f"{path}: cannot read ({_cause(exc)})") from exc
    return loads_json(data, path, max_bytes=max_bytes, max_depth=max_depth, error=error)


def load_required_json(path: Path | str, missing: str, *, error: type[VlmproprioError] = JSONLoadError):
    """``load_json`` of a file that must be there: a missing file is ``error`` too, with the message ``missing``
    (which says what the file is and what to do), not a FileNotFoundError."""
    try:
        return load_json(path, error=error)
    except FileNotFoundError:
        raise error(missing) from None
