"""diskcache stores that hold data only: the one way the package opens an on-disk key-value store.

diskcache pickles by default, and unpickling a file runs code. The response cache keeps JSON
(``JSON_VALUES``), the embedding cache raw float32 bytes (``BYTES_VALUES``); a row in any other form is
refused with the caller's error, never loaded. :func:`open_store` creates the folder, retries while another
process is setting the same database up, and turns a full or read-only disk into a one-line error.
"""

from __future__ import annotations

import functools
import sqlite3
import time
from pathlib import Path
from typing import Literal

from vlmproprio.errors import VlmproprioError
from vlmproprio.io import is_write_failure, write_error

JSON_VALUES = "json"
BYTES_VALUES = "bytes"
Values = Literal["json", "bytes"]


@functools.cache
def _json_only_disk(error: type[VlmproprioError]) -> type:
    """diskcache's JSONDisk, minus its pickle fallbacks."""
    import diskcache
    from diskcache.core import MODE_BINARY, MODE_RAW

    class JSONOnlyDisk(diskcache.JSONDisk):
        def get(self, key, raw):
            if not raw:  # JSONDisk stores keys as raw bytes; anything else was not written by us
                raise error("cache key is not raw JSON bytes (refusing to unpickle)")
            return super().get(key, raw)

        def fetch(self, mode, filename, value, read):
            if mode not in (MODE_RAW, MODE_BINARY):
                raise error(f"cache value has storage mode {mode} (refusing to unpickle)")
            return super().fetch(mode, filename, value, read)

    return JSONOnlyDisk


@functools.cache
def _bytes_only_disk(error: type[VlmproprioError]) -> type:
    """Keys are str, values are bytes."""
    import diskcache
    from diskcache.core import MODE_BINARY, MODE_RAW, UNKNOWN

    class BytesOnlyDisk(diskcache.Disk):
        def put(self, key):
            if type(key) is not str:
                raise error(f"cache keys are str, got {type(key).__name__}")
            return super().put(key)

        def get(self, key, raw):
            if not raw:
                raise error(f"{self._directory}: cache holds a non-raw key; delete the folder")
            return super().get(key, raw)

        def store(self, value, read, key=UNKNOWN):
            if type(value) is not bytes:
                raise error(f"cache values are bytes, got {type(value).__name__}")
            return super().store(value, read, key)

        def fetch(self, mode, filename, value, read):
            if mode not in (MODE_RAW, MODE_BINARY) or read:
                raise error(f"{self._directory}: cache row of mode {mode} refused; delete the folder")
            data = super().fetch(mode, filename, value, read)
            if type(data) is not bytes:
                raise error(f"{self._directory}: cache row is not bytes; delete the folder")
            return data

    return BytesOnlyDisk


def data_only_disk(values: Values, error: type[VlmproprioError]) -> type:
    """The diskcache Disk class for ``values``, raising ``error`` on anything else."""
    return (_json_only_disk if values == JSON_VALUES else _bytes_only_disk)(error)


def open_store(
    directory: Path | str,
    values: Values,
    *,
    error: type[VlmproprioError],
    what: str,
    corrupt: type[VlmproprioError] | None = None,
    timeout_s: float = 120.0,
    **settings,
):
    """A ``diskcache.Cache`` in ``directory`` that holds ``values`` only, never evicts, and is safe for many
    processes. Opening runs schema setup (PRAGMAs, CREATE TABLE) that can collide with another process doing
    the same: a locked database is retried until ``timeout_s``; any other failure is ``error`` naming ``what``.
    A row that is not ``values`` raises ``corrupt`` (default ``error``) when read."""
    import diskcache

    directory = Path(directory)
    try:
        directory.mkdir(parents=True, exist_ok=True)
    except OSError as exc:  # a file in the way, a read-only or full disk
        raise write_error(directory, exc, f"create {what} directory") from exc
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            return diskcache.Cache(
                str(directory),
                timeout=timeout_s,
                disk=data_only_disk(values, corrupt or error),
                eviction_policy="none",
                **settings,
            )
        except sqlite3.OperationalError as exc:
            if "locked" not in str(exc) or time.monotonic() > deadline:
                raise error(f"cannot open {what} {directory}: {exc}") from exc
            time.sleep(0.05)
        except (OSError, sqlite3.Error) as exc:  # a read-only or full folder, a broken database
            if is_write_failure(exc):
                raise write_error(directory, exc, f"open {what}") from exc
            raise error(f"cannot open {what} {directory}: {exc}") from exc
