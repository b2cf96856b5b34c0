"""Helpers for reliability tests that do not need the CLI's own process: the CLI called in this one, and
shorter retry waits for the openai backend.

A CLI subprocess costs ~1.5 CPU s of imports before it does anything; where the process boundary is not what a
test checks (no kill, no environment isolation, no fresh interpreter), ``cli_in_process`` runs the same
``vlmproprio.cli.main`` here and returns what ``reliability_support.cli`` would: exit code, stdout, stderr.
"""

from __future__ import annotations

import contextlib
import io
import subprocess
import threading
from collections.abc import Mapping, Sequence


def cli_in_process(args: Sequence[object], env: Mapping[str, str] | None = None) -> subprocess.CompletedProcess:
    """``vlmproprio ARGS`` through ``cli.main`` in this process, its output captured like a subprocess's;
    ``env``: environment variables set for the call only (e.g. ``VLMPROPRIO_CACHE``)."""
    import pytest

    from vlmproprio.cli import main

    argv = [str(a) for a in args]
    out, err = io.StringIO(), io.StringIO()
    with pytest.MonkeyPatch.context() as mp, contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        for name, value in (env or {}).items():
            mp.setenv(name, value)
        try:
            code = main(argv)
        except SystemExit as exc:  # argparse's usage errors and --help exit
            code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
    return subprocess.CompletedProcess(["vlmproprio", *argv], code, out.getvalue(), err.getvalue())


def scaled_retry_backoff(monkeypatch, factor: float) -> dict[str, int]:
    """Multiply the exponential backoff between retries by ``factor``, for the openai SDK's retries and for the
    backend's own (200s whose body is no completion); a server's Retry-After is still honoured as sent. Returns
    a live count of the SDK's retries (``"retries"``), which is what shows a failing run stopped early.

    The backoff lengths are the SDK's constants and the backend's default, not settings of the CLI; what the
    tests check (retried, answers kept, stops after one request's retries) does not depend on them, only the
    seconds spent waiting do (0.5, 1, 2 and 4 s before the 4 retries of a request: 7.5 s per failed run)."""
    import openai._base_client as sdk

    from vlmproprio.backends.openai import OpenAIBackend

    monkeypatch.setattr(sdk, "INITIAL_RETRY_DELAY", sdk.INITIAL_RETRY_DELAY * factor)
    monkeypatch.setattr(sdk, "MAX_RETRY_DELAY", sdk.MAX_RETRY_DELAY * factor)
    real_init, real_sleep = OpenAIBackend.__init__, sdk.SyncAPIClient._sleep_for_retry
    counts, lock = {"retries": 0}, threading.Lock()  # requests retry in several threads at once

    def init(self, *args, **kwargs) -> None:
        real_init(self, *args, **kwargs)
        self.backoff_s *= factor

    def sleep_for_retry(self, **kwargs) -> None:
        with lock:
            counts["retries"] += 1
        real_sleep(self, **kwargs)

    monkeypatch.setattr(OpenAIBackend, "__init__", init)
    monkeypatch.setattr(sdk.SyncAPIClient, "_sleep_for_retry", sleep_for_retry)
    return counts
