"""Every file vlmproprio writes, and every JSON document it reads, goes through here.

* ``atomic_write_bytes`` / ``atomic_write_text``: a temp file in the same folder, fsync, rename, so a reader
  never sees half a file; texts pass the secret scrubber first (``vlmproprio.secrets``).
* ``atomic_write_together``: files that must change together, all written before any is renamed into place.
* ``writing(path)``: turns an OSError (read-only folder, no permission, disk full) or an SQLite write error
  ("database or disk is full", "attempt to write a readonly database") into one ``WriteError`` line naming
  the path and the cause. Nothing half-written stays behind: the temp file is removed.
* ``read_limited``: every file read by a path a user gave (fixtures, cassettes, run folders, sidecars) is read
  through it: a regular file (never a device, FIFO or folder: ``/dev/zero`` would never end) of at most
  ``MAX_READ_BYTES``, else one line naming the file. ``atomic_write_bytes`` likewise refuses a target that
  exists and is not a regular file (``--out /dev/full``).
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
import stat
import tempfile
from collections.abc import Callable, Iterator, Mapping
from pathlib import Path

from vlmproprio.errors import VlmproprioError

# A fixture's episode.json is ~100 KB, scores/sweep.json a few MB, a cassette line a few KB: 256 MiB is
# far above anything the suite writes and far below what would exhaust memory.
MAX_JSON_BYTES = 256 * 1024 * 1024
# One limit for every file read whole (a PNG frame is ~50 KB, a steps.npz ~1 MB, a cassette a few MB).
MAX_READ_BYTES = MAX_JSON_BYTES
# The deepest document the suite writes is ~6 levels (audit.json); 64 leaves room and stays far from
# Python's recursion limit in any code that walks a document.
MAX_JSON_DEPTH = 64

_SQLITE_WRITE_ERRORS = ("disk is full", "readonly", "read-only", "disk i/o error", "unable to open")


class WriteError(VlmproprioError):
    """A file or database that cannot be written (read-only folder, no space, ...); names path and cause."""


class JSONLoadError(VlmproprioError):
    """A JSON document that cannot be read: malformed, too large or nested too deeply; names the file."""


class ReadError(VlmproprioError):
    """A file that cannot be read whole: not a regular file, too large, or an OS error; names the file.

    ``detail`` holds the message without the path, for callers that phrase their own."""


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
    kind = special_kind(path)
    if kind is not None:  # renaming over /dev/full would replace the device; a FIFO is not a file to keep
        raise WriteError(f"cannot write {path}: {kind}, not a regular file")
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
    """The sha256 of a regular file's bytes; ``ReadError`` for a device, FIFO or folder (``/dev/zero`` never
    ends), FileNotFoundError passes through."""
    h = hashlib.sha256()
    with _open_regular(Path(path), ReadError) as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


# ---------------------------------------------------------------------------------------------- bounded reads

_KINDS = (
    (stat.S_ISDIR, "a folder"),
    (stat.S_ISCHR, "a character device"),
    (stat.S_ISBLK, "a block device"),
    (stat.S_ISFIFO, "a FIFO (named pipe)"),
    (stat.S_ISSOCK, "a socket"),
)


def _kind_of(mode: int) -> str | None:
    """What a file of this mode is, when it is not a regular file."""
    if stat.S_ISREG(mode):
        return None
    return next((name for test, name in _KINDS if test(mode)), "not a plain file")


def special_kind(path: Path | str) -> str | None:
    """``"a folder"``, ``"a character device"``, ... when ``path`` exists (links followed) and is not a regular
    file; None when it is one or does not exist."""
    try:
        return _kind_of(os.stat(path).st_mode)
    except OSError:
        return None


def detailed(error: type[VlmproprioError], where: Path | str, detail: str) -> VlmproprioError:
    """``error("WHERE: DETAIL")`` with ``detail`` kept as an attribute, for callers that phrase their own line."""
    exc = error(f"{where}: {detail}")
    exc.detail = detail  # type: ignore[attr-defined]
    return exc


@contextlib.contextmanager
def _open_regular(path: Path, error: type[VlmproprioError], max_bytes: int | None = None):
    """An open binary file that is regular (checked on the open descriptor too, so a FIFO swapped in after the
    check neither blocks, thanks to O_NONBLOCK, nor is read) and, with ``max_bytes``, no larger than that."""
    kind = special_kind(path)
    if kind is not None:  # checked before opening: opening a FIFO for reading blocks until a writer comes
        raise detailed(error, path, f"{kind}, not a regular file")
    try:
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_NOCTTY", 0))
    except FileNotFoundError:
        raise
    except OSError as exc:
        raise detailed(error, path, f"cannot read ({_cause(exc)})") from exc
    with os.fdopen(fd, "rb") as f:
        st = os.fstat(fd)
        kind = _kind_of(st.st_mode)
        if kind is not None:
            raise detailed(error, path, f"{kind}, not a regular file")
        if max_bytes is not None and st.st_size > max_bytes:
            raise detailed(error, path, f"{st.st_size:,} bytes, more than the {max_bytes:,} allowed")
        try:
            yield f
        except OSError as exc:
            raise detailed(error, path, f"cannot read ({_cause(exc)})") from exc


def read_limited(
    path: Path | str, *, max_bytes: int = MAX_READ_BYTES, error: type[VlmproprioError] = ReadError
) -> bytes:
    """The bytes of a regular file of at most ``max_bytes``; ``error`` (one line naming the file, with
    ``detail``) for a device, FIFO, folder, a larger file or an OS error. FileNotFoundError passes through."""
    path = Path(path)
    with _open_regular(path, error, max_bytes) as f:
        data = f.read(max_bytes + 1)  # a file that grew after the size check is still cut off here
    if len(data) > max_bytes:
        raise detailed(error, path, f"more than the {max_bytes:,} bytes allowed")
    return data


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
        return detailed(error, where, detail)

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
    """Read (``read_limited``) and parse a JSON file with the limits of ``loads_json``; every error but
    FileNotFoundError, which passes through, is ``error`` with ``detail``."""
    path = Path(path)
    data = read_limited(path, max_bytes=max_bytes, error=error)
    return loads_json(data, path, max_bytes=max_bytes, max_depth=max_depth, error=error)


def load_required_json(path: Path | str, missing: str, *, error: type[VlmproprioError] = JSONLoadError):
    """``load_json`` of a file that must be there: a missing file is ``error`` too, with the message ``missing``
    (which says what the file is and what to do), not a FileNotFoundError; it has ``detail`` (that message) too."""
    try:
        return load_json(path, error=error)
    except FileNotFoundError:
        exc = error(missing)
        exc.detail = missing  # type: ignore[attr-defined]  # as every error of the reader has
        raise exc from None


def read_npz(
    path: Path | str, *, max_bytes: int = MAX_READ_BYTES, error: type[VlmproprioError] = ReadError
) -> dict[str, object]:
    """Every array of an ``.npz`` file, by name without ``.npy``; never unpickles. The file is read with
    ``read_limited`` and its members may not inflate past ``max_bytes`` in all (a small zip can hold a huge
    array); anything unreadable is ``error`` naming the file (not the member inside it), with ``detail``.
    FileNotFoundError passes through."""
    import io as _io
    import zipfile

    import numpy as np

    path = Path(path)
    data = read_limited(path, max_bytes=max_bytes, error=error)
    try:
        with zipfile.ZipFile(_io.BytesIO(data)) as zf:
            inflated = sum(info.file_size for info in zf.infolist())
        if inflated > max_bytes:
            raise detailed(
                error, path, f"its arrays inflate to {inflated:,} bytes, more than the {max_bytes:,} allowed"
            )
        with np.load(_io.BytesIO(data), allow_pickle=False) as npz:
            return {name: npz[name] for name in npz.files}
    except (VlmproprioError, MemoryError):
        raise
    except Exception as exc:
        # whatever damaged bytes make zipfile or numpy raise (an "encrypted" member is a RuntimeError, an unknown
        # zip version a NotImplementedError); their messages name the member, so the line names the file first
        raise detailed(error, path, f"{type(exc).__name__}: {exc}") from exc
